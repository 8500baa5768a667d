//! `SETCONF:<name>,<value>`. `crlf` and `diff` change this client only and
//! are answered by echoing the setting. `ipaddr`, `epsaddr`, `epsport`,
//! `serial_device`, `serial_speed` and `pubfile` change the section for all
//! its clients: the link is re-established and the public file reloaded,
//! answered `WARNING:250 Changed public file: '<name>'` (or 251 when its
//! content is the same), and every other client of the section gets the same
//! warning. ERROR:10 when the PLC does not answer, ERROR:35 for a bad value,
//! ERROR:50 for an unknown name. With READ_ONLY = Yes the section-wide keys
//! answer ERROR:30 and change nothing.

use plccoms_protocol::answer::{write_error, write_warning, ErrorCode, WarningCode};
use plccoms_protocol::request::{parse_setconf, ArgError};

use super::{error, Cx, Effect, Reply};
use crate::changes::Notice;
use crate::config::parse_ipv4;
use crate::link::{ConfChange, ReconfError, ReconfReply};

pub struct ConfThen {
    context: Vec<u8>,
}

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let (name, value) = match parse_setconf(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(cx, ErrorCode::Incomplete, context, out),
        Err(ArgError::Bad) => return error(cx, ErrorCode::BadRequest, context, out),
    };
    let key = String::from_utf8_lossy(name).to_ascii_lowercase();
    let text = String::from_utf8_lossy(value).into_owned();
    let section_wide = matches!(
        key.as_str(),
        "ipaddr" | "epsaddr" | "epsport" | "serial_device" | "serial_speed" | "pubfile"
    );
    if section_wide && cx.section.read_only() {
        return super::read_only(cx, context, out);
    }
    let change = match key.as_str() {
        "crlf" | "diff" => {
            let Some(on) = yes_no(value) else {
                return error(cx, ErrorCode::WrongValue, context, out);
            };
            if key == "crlf" {
                cx.client.eol = if on { b"\r\n" } else { b"\n" };
            } else {
                cx.client.diff = on;
            }
            out.extend_from_slice(b"SETCONF:");
            out.extend_from_slice(key.to_ascii_uppercase().as_bytes());
            out.push(b',');
            out.extend_from_slice(if on { b"YES" } else { b"NO" });
            out.extend_from_slice(cx.client.eol);
            return Reply::Done;
        }
        "ipaddr" => parse_ipv4(&text).map(ConfChange::IpAddr),
        "epsaddr" => text
            .parse()
            .ok()
            .filter(|a| (1..=126).contains(a))
            .map(ConfChange::EpsAddr),
        "epsport" => text
            .parse()
            .ok()
            .filter(|&p| p > 0)
            .map(ConfChange::EpsPort),
        "serial_device" => (!text.is_empty()).then(|| ConfChange::SerialDevice(text.clone())),
        "serial_speed" => text
            .parse()
            .ok()
            .filter(|&s| s > 0)
            .map(ConfChange::SerialSpeed),
        "pubfile" => (!text.is_empty()).then(|| ConfChange::PubFile(text.clone())),
        _ => return error(cx, ErrorCode::SetConfUnknown, context, out),
    };
    let Some(change) = change else {
        return error(cx, ErrorCode::WrongValue, context, out);
    };
    let then = ConfThen {
        context: context.to_vec(),
    };
    Reply::conf(cx.section.link.reconfigure(change), then)
}

/// The answer to a section-wide SETCONF. A public file it loaded is told by
/// the session (with the notices before it), so only errors are written here.
pub fn complete(cx: &mut Cx<'_>, then: ConfThen, reply: ReconfReply, out: &mut Vec<u8>) -> Effect {
    let code = match reply {
        Ok(outcome) => return Effect::Reconfigured(outcome.notice),
        Err(ReconfError::Unreachable(_)) => {
            write_error(out, ErrorCode::ConnectPlc, b"");
            out.extend_from_slice(cx.client.eol);
            return Effect::None;
        }
        Err(ReconfError::PubFile(_)) => ErrorCode::WrongValue,
    };
    write_error(out, code, &then.context);
    out.extend_from_slice(cx.client.eol);
    Effect::None
}

/// `WARNING:250 Changed public file: '<name>'` or 251, without line end.
pub fn write_notice(notice: &Notice, out: &mut Vec<u8>) {
    let code = if notice.changed {
        WarningCode::PubfileChanged
    } else {
        WarningCode::PubfileSame
    };
    write_warning(out, code, notice.name.as_bytes());
}

/// `yes`/`no` (also `1`/`0`, `true`/`false`), any case.
pub fn yes_no(value: &[u8]) -> Option<bool> {
    match String::from_utf8_lossy(value).to_ascii_lowercase().as_str() {
        "yes" | "1" | "true" => Some(true),
        "no" | "0" | "false" => Some(false),
        _ => None,
    }
}
