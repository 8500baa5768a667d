//! `SETCONF:<name>,<value>`, with the names and values of the table of keys
//! (`config::setconf_key`). `crlf` and `diff` change this client only and
//! are answered by echoing the setting (`Yes`/`No`, `True`/`False`, `On`/`Off`
//! or `1`/`0`, as in the ini file). `ipaddr`, `epsaddr`, `epsport`,
//! `serial_device`, `serial_speed` and `pubfile` change the section for all
//! its clients: the link is re-established and the public file reloaded,
//! answered `WARNING:250 Changed public file: '<name>'` (or 251 when its
//! content is the same), and every other client of the section gets the same
//! warning. ERROR:10 when the PLC does not answer, ERROR:35 for a bad value,
//! ERROR:50 for an unknown name. With READ_ONLY = Yes the section-wide keys
//! answer ERROR:30 and change nothing.

use plccoms_protocol::answer::{write_error, write_warning, ErrorCode, WarningCode};
use plccoms_protocol::request::{parse_setconf, ArgError};

use super::error;
use crate::config::{self, SetConfScope};
use crate::fanout::Notice;
use crate::poller::{ConfChange, ReconfError, ReconfReply};
use crate::session::{Pending, Session};

pub struct ConfThen {
    context: Vec<u8>,
}

pub async fn apply(session: &mut Session, args: &[u8], context: &[u8]) {
    let (name, value) = match parse_setconf(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(session, ErrorCode::Incomplete, context),
        Err(ArgError::Bad) => return error(session, ErrorCode::BadRequest, context),
    };
    let Some(key) = config::setconf_key(&String::from_utf8_lossy(name)) else {
        return error(session, ErrorCode::SetConfUnknown, context);
    };
    let text = String::from_utf8_lossy(value);
    if key.setconf_scope() == Some(SetConfScope::Client) {
        let Some(on) = config::parse_bool(&text) else {
            return error(session, ErrorCode::WrongValue, context);
        };
        let name = key.setconf_name().unwrap_or_default();
        if name == "crlf" {
            session.conn.set_crlf(on);
        } else {
            session.diff = on;
        }
        let mut line = b"SETCONF:".to_vec();
        line.extend_from_slice(name.to_ascii_uppercase().as_bytes());
        line.push(b',');
        line.extend_from_slice(if on { b"YES" } else { b"NO" });
        return session.answer_line(line);
    }
    if session.shared.config.read_only {
        return super::read_only(session, context);
    }
    // The value is parsed and range-checked as the ini key is; the poller
    // gets the field it sets.
    let mut section = session.shared.config.clone();
    if key.apply_setconf(&mut section, &text).is_err() {
        return error(session, ErrorCode::WrongValue, context);
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
        return error(session, ErrorCode::SetConfUnknown, context);
    };
    let rx = session.shared.poller.reconfigure(change).await;
    let then = ConfThen {
        context: context.to_vec(),
    };
    session.pending.push_back(Pending::Conf { rx, then });
}

pub fn complete(session: &mut Session, then: ConfThen, reply: ReconfReply, out: &mut Vec<u8>) {
    match reply {
        Ok(outcome) => {
            // The poller published the reload before answering: from the
            // next request on, this client uses the new table.
            session.latest_snapshot();
            // Reloads before this one that the client has not heard of yet,
            // then this one, told by this answer only.
            session.notices_up_to(outcome.notice.seq - 1, out);
            session.notice_seen = session.notice_seen.max(outcome.notice.seq);
            write_notice(&outcome.notice, out);
        }
        Err(ReconfError::Unreachable(_)) => write_error(out, ErrorCode::ConnectPlc, b""),
        Err(ReconfError::PubFile(_)) => write_error(out, ErrorCode::WrongValue, &then.context),
    }
    out.extend_from_slice(session.conn.eol);
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
