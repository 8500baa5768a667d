//! `SETCONF:<name>,<value>`. `crlf` and `diff` change this client only and
//! are answered by echoing the setting; an unknown name is ERROR:50, a bad
//! value ERROR:35.

use plccoms_protocol::answer::ErrorCode;
use plccoms_protocol::request::{parse_setconf, ArgError};

use super::error;
use crate::session::Session;

pub fn apply(session: &mut Session, args: &[u8], context: &[u8]) {
    let (name, value) = match parse_setconf(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(session, ErrorCode::Incomplete, context),
        Err(ArgError::Bad) => return error(session, ErrorCode::BadRequest, context),
    };
    let key = String::from_utf8_lossy(name).to_ascii_lowercase();
    match key.as_str() {
        "crlf" | "diff" => {
            let Some(on) = yes_no(value) else {
                return error(session, ErrorCode::WrongValue, context);
            };
            if key == "crlf" {
                session.conn.set_crlf(on);
            } else {
                session.diff = on;
            }
            let mut line = b"SETCONF:".to_vec();
            line.extend_from_slice(key.to_ascii_uppercase().as_bytes());
            line.push(b',');
            line.extend_from_slice(if on { b"YES" } else { b"NO" });
            session.answer_line(line);
        }
        _ => error(session, ErrorCode::SetConfUnknown, context),
    }
}

/// `yes`/`no` (also `1`/`0`, `true`/`false`), any case.
pub fn yes_no(value: &[u8]) -> Option<bool> {
    match String::from_utf8_lossy(value).to_ascii_lowercase().as_str() {
        "yes" | "1" | "true" => Some(true),
        "no" | "0" | "false" => Some(false),
        _ => None,
    }
}
