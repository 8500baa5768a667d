//! `HELP:`: the command list, one `HELP:` line each, then `HELP:`.

use super::{Cx, Reply};

const TEXT: &[&str] = &[
    "LIST:[mask]                 List variables (* = disabled, ~ = hidden).",
    "GET:<name|mask|%addr>       Get the value of variables.",
    "SET:<name|%addr>,<value>    Set a variable in the PLC.",
    "EN:[mask] [delta]           Enable variables for DIFF: messages.",
    "DI:[mask] [delta]           Disable variables.",
    "HIDE:<mask>                 Hide variables from the all-forms.",
    "UNHIDE:<mask>               Unhide variables.",
    "GETMEM:<name|%addr> <size>  Get a memory block from the PLC.",
    "GETFILE:<name>              Get a file from the PLC or PC.",
    "GETFILEINFO:<name>          Get information about a file.",
    "WRITEFILE:<name>[n]=data    Write a file into the PLC or PC.",
    "WRITEFILEINFO:<name>[n]=data Write file information.",
    "GETINFO:[name]              Information about the server.",
    "SETCONF:<name>,<value>      Change configuration (crlf, diff, ipaddr, ...).",
    "HELP:                       This help.",
];

pub fn run(cx: &mut Cx<'_>, out: &mut Vec<u8>) -> Reply {
    let eol = cx.client.eol;
    for line in TEXT {
        out.extend_from_slice(b"HELP:");
        out.extend_from_slice(line.as_bytes());
        out.extend_from_slice(eol);
    }
    out.extend_from_slice(b"HELP:");
    out.extend_from_slice(eol);
    Reply::Done
}
