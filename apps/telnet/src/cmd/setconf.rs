//! `SETCONF:<name>,<value>`, with the names and values of the table of keys
//! (`config::setconf_key`). `crlf` and `diff` change this client only and
//! are answered by echoing the setting (`Yes`/`No`, `True`/`False`, `On`/`Off`
//! or `1`/`0`, as in the ini file). `ipaddr`, `epsaddr`, `epsport`,
//! `serial_device`, `serial_speed` and `pubfile` change the section for all
//! its clients: the link is re-established and the public file reloaded,
//! answered `WARNING:250 Changed public file: '<name>'` (or 251 when its
//! content is the same), and every other client of the section gets the same
//! warning. ERROR:10 when the PLC does not answer, ERROR:35 for a bad value,
//! ERROR:50 for an unknown name; a refused SETCONF changes nothing. With
//! READ_ONLY = Yes the section-wide keys answer ERROR:30 and change nothing,
//! and so does every name SETCONF_KEYS does not list. `trace` (this
//! server's own) switches the section's frame trace in the log, answered
//! like `crlf`.

use plccoms_protocol::answer::{write_error, write_warning, ErrorCode, WarningCode};
use plccoms_protocol::request::{parse_setconf, ArgError};

use super::{error, Cx, Effect, Reply};
use plccoms_core::changes::Notice;
use plccoms_core::config::{self, SetConfScope};
use plccoms_core::link::{ConfChange, ReconfError, ReconfReply};

pub struct ConfThen {
    context: Vec<u8>,
}

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let (name, value) = match parse_setconf(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(cx, ErrorCode::Incomplete, context, out),
        Err(ArgError::Bad) => return error(cx, ErrorCode::BadRequest, context, out),
    };
    let Some(key) = config::setconf_key(&String::from_utf8_lossy(name)) else {
        return error(cx, ErrorCode::SetConfUnknown, context, out);
    };
    let text = String::from_utf8_lossy(value);
    let state = cx.section.state();
    let name = key.setconf_name().unwrap_or_default();
    if let Some(allowed) = &state.config.setconf_keys {
        // SETCONF_KEYS: a site keeps these keys away from its clients.
        if !allowed.contains(&name) {
            return super::read_only(cx, context, out);
        }
    }
    if key.setconf_scope() == Some(SetConfScope::Client) {
        let Some(on) = config::parse_bool(&text) else {
            return error(cx, ErrorCode::WrongValue, context, out);
        };
        if name == "crlf" {
            cx.client.eol = if on { b"\r\n" } else { b"\n" };
        } else {
            cx.client.diff = on;
        }
        out.extend_from_slice(b"SETCONF:");
        out.extend_from_slice(name.to_ascii_uppercase().as_bytes());
        out.push(b',');
        out.extend_from_slice(if on { b"YES" } else { b"NO" });
        out.extend_from_slice(cx.client.eol);
        return Reply::Done;
    }
    if state.config.read_only {
        return super::read_only(cx, context, out);
    }
    if key.name == "TRACE" {
        // The section's frame trace: the log, not the PLC, changes.
        let Some(on) = config::parse_bool(&text) else {
            return error(cx, ErrorCode::WrongValue, context, out);
        };
        cx.section.trace().set(on);
        tracing::info!(
            section = %cx.section.name(),
            "SETCONF: trace {} (frames at trace level, target {})",
            if on { "on" } else { "off" },
            plccoms_core::trace::TARGET
        );
        out.extend_from_slice(b"SETCONF:TRACE,");
        out.extend_from_slice(if on { b"YES" } else { b"NO" });
        out.extend_from_slice(cx.client.eol);
        return Reply::Done;
    }
    // The value is parsed and range-checked as the ini key is; the link
    // gets the field it sets.
    let mut section = state.config.clone();
    if key.apply_setconf(&mut section, &text).is_err()
        || (key.name == "PUBFILE" && plccoms_core::link::tables::check_client_name(&text).is_err())
    {
        return error(cx, ErrorCode::WrongValue, context, out);
    }
    let change = match key.name {
        "IPADDR" => section.ipaddr.map(ConfChange::IpAddr),
        "EPSADDR" => section.epsaddr.map(ConfChange::EpsAddr),
        "EPSPORT" => Some(ConfChange::EpsPort(section.epsport)),
        "SERIAL_DEVICE" => section.serial_device.map(ConfChange::SerialDevice),
        "SERIAL_SPEED" => section.serial_speed.map(ConfChange::SerialSpeed),
        "PUBFILE" => section.pubfile.map(ConfChange::PubFile),
        _ => None,
    };
    let Some(change) = change else {
        return error(cx, ErrorCode::SetConfUnknown, context, out);
    };
    let then = ConfThen {
        context: context.to_vec(),
    };
    Reply::conf(cx.section.reconfigure(change), then)
}

/// The answer to a section-wide SETCONF. A public file it loaded is told by
/// the session (with the notices before it), so only errors are written here.
pub fn complete(cx: &mut Cx<'_>, then: ConfThen, reply: ReconfReply, out: &mut Vec<u8>) -> Effect {
    match reply {
        Ok(outcome) => return Effect::Reconfigured(outcome.notice),
        Err(ReconfError::Unreachable(_)) => write_error(out, ErrorCode::ConnectPlc, b""),
        Err(ReconfError::PubFile(_)) => write_error(out, ErrorCode::WrongValue, &then.context),
    }
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
