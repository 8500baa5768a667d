//! `GET:<name|mask|%addr>`: `GET:<NAME>,<value>` per variable; a mask's
//! answer ends with `GET:`. Values of polled variables come from the latest
//! poll; the others (and any GET behind an unanswered SET of this client) are
//! read from the PLC, batched with other clients' reads.

use plccoms_protocol::address::{parse_direct, DirectAddress};
use plccoms_protocol::answer::ErrorCode;
use plccoms_protocol::cp1250;
use plccoms_protocol::value::Value;

use super::{error, select, Selection};
use crate::backend::ReadRequest;
use crate::poller::{LinkError, ReadReply};
use crate::session::{Pending, Session};
use crate::vars::{VarId, VarTable};
use std::sync::Arc;

/// What to do with the PLC's answer.
pub enum ReadThen {
    Vars {
        table: Arc<VarTable>,
        ids: Vec<VarId>,
        /// Per id: the value from the latest poll, or `None` when it is in
        /// the PLC's answer (in order).
        cached: Vec<Option<Arc<[u8]>>>,
        single: bool,
    },
    Direct {
        name: Vec<u8>,
        address: DirectAddress,
    },
    /// A GETMEM block.
    Mem { name: Vec<u8> },
}

pub async fn apply(session: &mut Session, args: &[u8], context: &[u8]) {
    if args.first() == Some(&b'%') {
        return direct(session, args).await;
    }
    let selection = select(session.vars.table(), args, |id| session.vars.is_hidden(id));
    if let Selection::One(id) = selection {
        if answer_from_poll(session, id) {
            return;
        }
    }
    let single = matches!(selection, Selection::One(_));
    if let Selection::Unknown = selection {
        return error(session, ErrorCode::UnknownVariable, context);
    }
    let ids = selection.ids();
    let snapshot = session.latest_snapshot();
    let table = session.vars.table().clone();
    // Behind an unanswered SET, or across a public-file change, only the PLC
    // knows.
    let cache_ok = !session.set_outstanding() && Arc::ptr_eq(&snapshot.table, &table);
    let mut requests = Vec::new();
    let cached: Vec<Option<Arc<[u8]>>> = ids
        .iter()
        .map(|&id| {
            if cache_ok {
                if let Some(text) = snapshot.current(id).and_then(|slot| slot.shared_text()) {
                    return Some(text);
                }
            }
            let var = table.var(id);
            requests.push(ReadRequest {
                area: var.area,
                offset: var.offset,
                len: var.byte_len(),
            });
            None
        })
        .collect();
    let then = ReadThen::Vars {
        table,
        ids,
        cached,
        single,
    };
    if requests.is_empty() {
        let mut out = Vec::new();
        complete(session, then, Ok(Vec::new()), &mut out);
        return session.answer(out);
    }
    let rx = session.shared.poller.read(requests).await;
    session.pending.push_back(Pending::Read { rx, then });
}

/// One variable whose polled value is current, and no SET of this client
/// unanswered: the answer comes straight from the newest snapshot, without
/// allocating (the bulk of what SCADA and home-automation clients send).
fn answer_from_poll(session: &mut Session, id: VarId) -> bool {
    if session.set_outstanding() {
        return false;
    }
    session.refresh_newest();
    let snapshot = &session.newest;
    if !Arc::ptr_eq(&snapshot.table, session.vars.table()) {
        return false;
    }
    let Some(text) = snapshot.current(id).and_then(|slot| slot.text()) else {
        return false;
    };
    let name = &snapshot.table.var(id).name;
    let eol = session.conn.eol;
    let parts: [&[u8]; 5] = [b"GET:", name, b",", text, eol];
    if session.pending.is_empty() {
        for part in parts {
            session.conn.extend(part);
        }
    } else {
        let answer = parts.concat();
        session.answer(answer);
    }
    true
}

async fn direct(session: &mut Session, args: &[u8]) {
    let Some(address) = parse_direct(args) else {
        return error(session, ErrorCode::MemGet, args);
    };
    let request = ReadRequest {
        area: address.area,
        offset: address.offset,
        len: address.ty.size() as u32,
    };
    let rx = session.shared.poller.read(vec![request]).await;
    let then = ReadThen::Direct {
        name: cp1250::to_upper(args),
        address,
    };
    session.pending.push_back(Pending::Read { rx, then });
}

/// Writes the answer once the PLC answered.
pub fn complete(session: &mut Session, then: ReadThen, reply: ReadReply, out: &mut Vec<u8>) {
    if let ReadThen::Mem { name } = &then {
        return super::getmem::complete(session, name, reply, out);
    }
    let eol = session.conn.eol;
    let format = &session.shared.format;
    let answers = match reply {
        Ok(answers) => answers,
        Err(err) => return link_error(err, ErrorCode::GetData, eol, out),
    };
    match then {
        ReadThen::Mem { .. } => unreachable!("handled above"),
        ReadThen::Direct { name, address } => match answers.into_iter().next() {
            Some(Ok(bytes)) => {
                let value = match address.bit {
                    Some(bit) => Value::Bool(bytes.first().is_some_and(|b| b & (1 << bit) != 0)),
                    None => Value::decode(address.ty, &bytes),
                };
                out.extend_from_slice(b"GET:");
                out.extend_from_slice(&name);
                out.push(b',');
                value.format(address.ty, format, out);
                out.extend_from_slice(eol);
            }
            _ => {
                plccoms_protocol::answer::write_error(out, ErrorCode::MemGet, &name);
                out.extend_from_slice(eol);
            }
        },
        ReadThen::Vars {
            table,
            ids,
            cached,
            single,
        } => {
            let mut answers = answers.into_iter();
            let start = out.len();
            for (&id, cached) in ids.iter().zip(&cached) {
                let var = table.var(id);
                out.extend_from_slice(b"GET:");
                out.extend_from_slice(&var.name);
                out.push(b',');
                if let Some(text) = cached {
                    out.extend_from_slice(text);
                } else {
                    match answers.next() {
                        Some(Ok(bytes)) => var.decode(&bytes).format(var.ty, format, out),
                        _ => {
                            out.truncate(start);
                            plccoms_protocol::answer::write_error(out, ErrorCode::GetData, b"");
                            out.extend_from_slice(eol);
                            return;
                        }
                    }
                }
                out.extend_from_slice(eol);
            }
            if !single {
                out.extend_from_slice(b"GET:");
                out.extend_from_slice(eol);
            }
        }
    }
}

/// ERROR:10 when there is no link, `code` when the PLC failed the request.
pub fn link_error(err: LinkError, code: ErrorCode, eol: &[u8], out: &mut Vec<u8>) {
    let code = match err {
        LinkError::Offline => ErrorCode::ConnectPlc,
        LinkError::Plc(_) => code,
    };
    plccoms_protocol::answer::write_error(out, code, b"");
    out.extend_from_slice(eol);
}
