//! `LIST:[mask]`: `LIST:<NAME>,<TYPE>` per variable, `*` when disabled for
//! this client, `~` when hidden, then `LIST:`.

use std::io::Write;

use plccoms_protocol::mask::Mask;

use super::{Cx, Reply};

pub fn run(cx: &mut Cx<'_>, args: &[u8], out: &mut Vec<u8>) -> Reply {
    let mask = Mask::new(args);
    let all = mask.is_all();
    let none = mask.min_len() > cx.client.vars.table().max_name_len();
    let eol = cx.client.eol;
    let vars = &cx.client.vars;
    let table = vars.table();
    out.reserve(if all { table.len() * 32 } else { 256 });
    let vars_listed = if none { &[][..] } else { table.vars() };
    for (id, var) in vars_listed.iter().enumerate() {
        if !all && !mask.matches(&var.name) {
            continue;
        }
        let id = id as u32;
        out.extend_from_slice(b"LIST:");
        out.extend_from_slice(&var.name);
        let _ = write!(out, ",{}", var.ty);
        if !vars.is_enabled(id) {
            out.push(b'*');
        }
        if vars.is_hidden(id) {
            out.push(b'~');
        }
        out.extend_from_slice(eol);
    }
    out.extend_from_slice(b"LIST:");
    out.extend_from_slice(eol);
    Reply::Done
}
