//! Client requests: classifying an input line and the grammars of command
//! arguments.
//!
//! A request is `NAME:args`. Command names are case-insensitive, spaces and
//! tabs around the token and around the arguments are tolerated
//! (`SETCONF: pubfile, Test.pub`, `EN:NAME `). A line that is not a command
//! continues the previous command (manual 4.1: `GET:a` then `b` means `GET:b`).

use nom::bytes::complete::{tag, take_while1};
use nom::character::complete::{digit1, space0};
use nom::combinator::all_consuming;
use nom::{IResult, Parser};
use thiserror::Error;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Command {
    List,
    Get,
    Set,
    En,
    Di,
    Hide,
    Unhide,
    GetMem,
    GetFile,
    GetFileInfo,
    WriteFile,
    WriteFileInfo,
    GetInfo,
    SetConf,
    Help,
}

impl Command {
    pub const ALL: [Command; 15] = [
        Command::List,
        Command::Get,
        Command::Set,
        Command::En,
        Command::Di,
        Command::Hide,
        Command::Unhide,
        Command::GetMem,
        Command::GetFile,
        Command::GetFileInfo,
        Command::WriteFile,
        Command::WriteFileInfo,
        Command::GetInfo,
        Command::SetConf,
        Command::Help,
    ];

    /// The name as answers print it (upper case, without the `:`).
    pub fn name(self) -> &'static str {
        match self {
            Command::List => "LIST",
            Command::Get => "GET",
            Command::Set => "SET",
            Command::En => "EN",
            Command::Di => "DI",
            Command::Hide => "HIDE",
            Command::Unhide => "UNHIDE",
            Command::GetMem => "GETMEM",
            Command::GetFile => "GETFILE",
            Command::GetFileInfo => "GETFILEINFO",
            Command::WriteFile => "WRITEFILE",
            Command::WriteFileInfo => "WRITEFILEINFO",
            Command::GetInfo => "GETINFO",
            Command::SetConf => "SETCONF",
            Command::Help => "HELP",
        }
    }

    /// The command named by `token` (case-insensitive, without the `:`).
    pub fn from_token(token: &[u8]) -> Option<Command> {
        Command::ALL
            .into_iter()
            .find(|c| c.name().as_bytes().eq_ignore_ascii_case(token))
    }

    /// Whether a bare following line repeats this command on that line.
    pub fn accepts_continuation(self) -> bool {
        matches!(
            self,
            Command::List
                | Command::Get
                | Command::Set
                | Command::En
                | Command::Di
                | Command::Hide
                | Command::Unhide
                | Command::GetMem
        )
    }
}

/// What one input line (without its line end) is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Line<'a> {
    /// Nothing but spaces and tabs: ignored.
    Empty,
    /// `TOKEN:args`; `args` trimmed of spaces and tabs.
    Command { command: Command, args: &'a [u8] },
    /// `TOKEN:...` whose letters name no command (ERROR 32).
    UnknownCommand,
    /// Anything else, trimmed: the previous command applied to this line.
    Continuation(&'a [u8]),
}

/// Why arguments were refused: `Incomplete` answers ERROR 31, `Bad`
/// ERROR 30 (or 35 where the command's value is at fault).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum ArgError {
    #[error("incomplete client request")]
    Incomplete,
    #[error("bad client request")]
    Bad,
}

fn is_blank(b: u8) -> bool {
    b == b' ' || b == b'\t'
}

/// `text` without leading and trailing spaces and tabs.
pub fn trim(text: &[u8]) -> &[u8] {
    let start = text
        .iter()
        .position(|&b| !is_blank(b))
        .unwrap_or(text.len());
    let end = text
        .iter()
        .rposition(|&b| !is_blank(b))
        .map_or(start, |p| p + 1);
    &text[start..end]
}

/// `[blanks] letters [blanks] :` at the start of a line; the letters.
fn command_token(line: &[u8]) -> IResult<&[u8], &[u8]> {
    let (rest, (_, token, _, _)) = (
        space0,
        take_while1(|b: u8| b.is_ascii_alphabetic()),
        space0,
        tag(&b":"[..]),
    )
        .parse(line)?;
    Ok((rest, token))
}

/// Classifies one input line (without its line end).
pub fn classify(line: &[u8]) -> Line<'_> {
    match command_token(line) {
        Ok((rest, token)) => match Command::from_token(token) {
            Some(command) => Line::Command {
                command,
                args: trim(rest),
            },
            None => Line::UnknownCommand,
        },
        Err(_) => match trim(line) {
            [] => Line::Empty,
            trimmed => Line::Continuation(trimmed),
        },
    }
}

/// Splits at blanks into at most `N` non-empty fields; `None` if more.
fn fields<const N: usize>(args: &[u8]) -> Option<([&[u8]; N], usize)> {
    let mut out: [&[u8]; N] = [&[]; N];
    let mut count = 0;
    for field in args.split(|&b| is_blank(b)).filter(|f| !f.is_empty()) {
        *out.get_mut(count)? = field;
        count += 1;
    }
    Some((out, count))
}

/// `SET:name,value`: split at the first `,` (the value may hold `,` and
/// `:`), blanks around both trimmed. The value may be empty (an empty STRING).
pub fn parse_set(args: &[u8]) -> Result<(&[u8], &[u8]), ArgError> {
    let comma = args
        .iter()
        .position(|&b| b == b',')
        .ok_or(ArgError::Incomplete)?;
    let name = trim(&args[..comma]);
    if name.is_empty() {
        return Err(ArgError::Incomplete);
    }
    Ok((name, trim(&args[comma + 1..])))
}

/// `EN:[mask] [delta]` (also DI, and HIDE/UNHIDE/GET/LIST without delta):
/// the mask (empty means all) and the delta text, if any.
pub fn parse_mask_delta(args: &[u8]) -> Result<(&[u8], Option<&[u8]>), ArgError> {
    match fields::<2>(args) {
        Some(([mask, _], 1)) => Ok((mask, None)),
        Some(([mask, delta], 2)) => Ok((mask, Some(delta))),
        Some(_) => Ok((&[], None)),
        None => Err(ArgError::Bad),
    }
}

/// `GETMEM:<name|%addr> <size>`.
pub fn parse_getmem(args: &[u8]) -> Result<(&[u8], u32), ArgError> {
    match fields::<2>(args) {
        Some(([name, size], 2)) => {
            let size = decimal_u32(size).ok_or(ArgError::Bad)?;
            Ok((name, size))
        }
        Some(_) => Err(ArgError::Incomplete),
        None => Err(ArgError::Bad),
    }
}

/// `SETCONF:key,value`, blanks around both tolerated.
pub fn parse_setconf(args: &[u8]) -> Result<(&[u8], &[u8]), ArgError> {
    let comma = args
        .iter()
        .position(|&b| b == b',')
        .ok_or(ArgError::Incomplete)?;
    let key = trim(&args[..comma]);
    if key.is_empty() {
        return Err(ArgError::Incomplete);
    }
    Ok((key, trim(&args[comma + 1..])))
}

fn decimal_u32(text: &[u8]) -> Option<u32> {
    let (_, digits) = all_consuming(digit1::<_, nom::error::Error<&[u8]>>)
        .parse(text)
        .ok()?;
    digits.iter().try_fold(0u32, |n, d| {
        n.checked_mul(10)?.checked_add(u32::from(d - b'0'))
    })
}

/// `[<digits>]=` at the start of `text`: the length and the rest.
fn block_length(text: &[u8]) -> IResult<&[u8], &[u8]> {
    let (rest, (_, digits, _)) = (tag(&b"["[..]), digit1, tag(&b"]="[..])).parse(text)?;
    Ok((rest, digits))
}

/// Finds the first `[<digits>]=` in `text`: (start of `[`, length digits,
/// offset just past `=`).
pub(crate) fn find_block_length(text: &[u8]) -> Option<(usize, &[u8], usize)> {
    text.iter()
        .enumerate()
        .filter(|&(_, &b)| b == b'[')
        .find_map(|(i, _)| {
            let (rest, digits) = block_length(&text[i..]).ok()?;
            Some((i, digits, text.len() - rest.len()))
        })
}

/// Parses a decimal block length, `None` on overflow of `usize`.
pub(crate) fn block_len_value(digits: &[u8]) -> Option<usize> {
    digits.iter().try_fold(0usize, |n, d| {
        n.checked_mul(10)?.checked_add(usize::from(d - b'0'))
    })
}

/// `name[n]=data`, the framing of WRITEFILE, WRITEFILEINFO and GETFILE
/// blocks: the name, `n` and everything after `]=`. The first `[<digits>]=`
/// ends the name. The caller checks `data.len()` against `n` where the data
/// did not come from a decoder [`Block`](crate::decoder::Frame::Block),
/// which guarantees it.
///
/// No `[<digits>]=` is `Incomplete`; an empty name or a length that does not
/// fit in `usize` is `Bad`.
pub fn parse_block(args: &[u8]) -> Result<(&[u8], usize, &[u8]), ArgError> {
    let (open, digits, data_start) = find_block_length(args).ok_or(ArgError::Incomplete)?;
    let name = trim(&args[..open]);
    if name.is_empty() {
        return Err(ArgError::Bad);
    }
    let len = block_len_value(digits).ok_or(ArgError::Bad)?;
    Ok((name, len, &args[data_start..]))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cmd(command: Command, args: &[u8]) -> Line<'_> {
        Line::Command { command, args }
    }

    #[test]
    fn command_names() {
        for c in Command::ALL {
            assert_eq!(Command::from_token(c.name().as_bytes()), Some(c));
            assert_eq!(
                Command::from_token(c.name().to_lowercase().as_bytes()),
                Some(c)
            );
        }
        assert_eq!(
            Command::from_token(b"GetFileInfo"),
            Some(Command::GetFileInfo)
        );
        assert_eq!(Command::from_token(b"GETX"), None);
        assert_eq!(Command::from_token(b""), None);
        assert!(Command::GetMem.accepts_continuation());
        assert!(!Command::GetInfo.accepts_continuation());
        assert!(!Command::WriteFile.accepts_continuation());
    }

    #[test]
    fn classify_commands() {
        assert_eq!(classify(b"GET:test_*"), cmd(Command::Get, b"test_*"));
        assert_eq!(classify(b"get:x"), cmd(Command::Get, b"x"));
        assert_eq!(classify(b"Get:X"), cmd(Command::Get, b"X"));
        assert_eq!(
            classify(b"SETCONF: pubfile, Test.pub"),
            cmd(Command::SetConf, b"pubfile, Test.pub")
        );
        assert_eq!(classify(b"EN:NAME "), cmd(Command::En, b"NAME"));
        assert_eq!(
            classify(b"  \tEN :\tNAME 0.5\t"),
            cmd(Command::En, b"NAME 0.5")
        );
        assert_eq!(classify(b"EN:"), cmd(Command::En, b""));
        assert_eq!(classify(b"LIST:"), cmd(Command::List, b""));
        assert_eq!(
            classify(b"SET:text,\"a: b, c\""),
            cmd(Command::Set, b"text,\"a: b, c\"")
        );
        assert_eq!(classify(b"FOO:bar"), Line::UnknownCommand);
        assert_eq!(classify(b"x:"), Line::UnknownCommand);
    }

    #[test]
    fn classify_other_lines() {
        assert_eq!(classify(b""), Line::Empty);
        assert_eq!(classify(b"   "), Line::Empty);
        assert_eq!(classify(b" \t "), Line::Empty);
        assert_eq!(classify(b"test_2"), Line::Continuation(b"test_2"));
        assert_eq!(classify(b"  test_2  "), Line::Continuation(b"test_2"));
        assert_eq!(classify(b"b,5"), Line::Continuation(b"b,5"));
        assert_eq!(
            classify(b"T_ZONES[0].X"),
            Line::Continuation(b"T_ZONES[0].X")
        );
        assert_eq!(classify(b"1GET:x"), Line::Continuation(b"1GET:x"));
        assert_eq!(classify(b"GET"), Line::Continuation(b"GET"));
        assert_eq!(classify(b":x"), Line::Continuation(b":x"));
        assert_eq!(classify(b"GET_X:y"), Line::Continuation(b"GET_X:y"));
    }

    #[test]
    fn set_args() {
        assert_eq!(parse_set(b"test_1,123"), Ok((&b"test_1"[..], &b"123"[..])));
        assert_eq!(parse_set(b"t , 1 "), Ok((&b"t"[..], &b"1"[..])));
        assert_eq!(
            parse_set(b"s,\"a,b:c\""),
            Ok((&b"s"[..], &b"\"a,b:c\""[..]))
        );
        assert_eq!(parse_set(b"s,"), Ok((&b"s"[..], &b""[..])));
        assert_eq!(parse_set(b"test_1"), Err(ArgError::Incomplete));
        assert_eq!(parse_set(b" ,1"), Err(ArgError::Incomplete));
        assert_eq!(parse_set(b""), Err(ArgError::Incomplete));
    }

    #[test]
    fn mask_delta_args() {
        assert_eq!(parse_mask_delta(b""), Ok((&b""[..], None)));
        assert_eq!(parse_mask_delta(b"temp*"), Ok((&b"temp*"[..], None)));
        assert_eq!(
            parse_mask_delta(b"temperature 0.5"),
            Ok((&b"temperature"[..], Some(&b"0.5"[..])))
        );
        assert_eq!(
            parse_mask_delta(b"temp \t a"),
            Ok((&b"temp"[..], Some(&b"a"[..])))
        );
        assert_eq!(parse_mask_delta(b"a b c"), Err(ArgError::Bad));
        // `EN:temp a`: the fields parse; the delta text fails later (ERROR 35).
        let (_, delta) = parse_mask_delta(b"temp a").unwrap();
        assert!(crate::value::Delta::parse(delta.unwrap()).is_err());
    }

    #[test]
    fn getmem_args() {
        assert_eq!(parse_getmem(b"test_string 6"), Ok((&b"test_string"[..], 6)));
        assert_eq!(parse_getmem(b"%R100  16"), Ok((&b"%R100"[..], 16)));
        assert_eq!(parse_getmem(b"test_string"), Err(ArgError::Incomplete));
        assert_eq!(parse_getmem(b""), Err(ArgError::Incomplete));
        assert_eq!(parse_getmem(b"x six"), Err(ArgError::Bad));
        assert_eq!(parse_getmem(b"x -1"), Err(ArgError::Bad));
        assert_eq!(parse_getmem(b"x 4294967296"), Err(ArgError::Bad));
        assert_eq!(parse_getmem(b"x 1 2"), Err(ArgError::Bad));
    }

    #[test]
    fn setconf_args() {
        assert_eq!(
            parse_setconf(b"pubfile, Test.pub"),
            Ok((&b"pubfile"[..], &b"Test.pub"[..]))
        );
        assert_eq!(parse_setconf(b"crlf ,no"), Ok((&b"crlf"[..], &b"no"[..])));
        assert_eq!(parse_setconf(b"crlf"), Err(ArgError::Incomplete));
        assert_eq!(parse_setconf(b",x"), Err(ArgError::Incomplete));
    }

    #[test]
    fn block_args() {
        assert_eq!(
            parse_block(b"test.txt[22]=This is test string 1."),
            Ok((&b"test.txt"[..], 22, &b"This is test string 1."[..]))
        );
        assert_eq!(
            parse_block(b"test.txt[0]="),
            Ok((&b"test.txt"[..], 0, &b""[..]))
        );
        assert_eq!(
            parse_block(b"a[x].txt[3]=[1]=!"),
            Ok((&b"a[x].txt"[..], 3, &b"[1]=!"[..]))
        );
        assert_eq!(parse_block(b"test.txt"), Err(ArgError::Incomplete));
        assert_eq!(parse_block(b"test.txt[]="), Err(ArgError::Incomplete));
        assert_eq!(parse_block(b"test.txt[5]"), Err(ArgError::Incomplete));
        assert_eq!(parse_block(b"[5]=abcde"), Err(ArgError::Bad));
        assert_eq!(
            parse_block(b"t[99999999999999999999999]="),
            Err(ArgError::Bad)
        );
    }
}
