//! `GET:<name|mask|%addr>`: `GET:<NAME>,<value>` per variable; a mask's
//! answer ends with `GET:`. Values of polled variables come from the latest
//! poll while it is fresh (see `link::fresh_for`); the others (and any GET
//! behind an unanswered SET of this client) are read from the PLC, batched
//! with other clients' reads. A Modbus device's exception is ERROR:80 with
//! the variable and the exception (`'NAME: Modbus exception 2 (illegal data
//! address)'`); other refusals ERROR:20, as from a Tecomat PLC.

use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::ErrorCode;
use plccoms_protocol::cp1250;
use plccoms_protocol::value::Value;

use std::sync::Arc;

use tokio::time::Instant;

use super::{error, link_error, select, Cx, ReadThen, Reply, Selection};
use plccoms_core::driver::{ReadRequest, Refusal};
use plccoms_core::link::ReadReply;
use plccoms_core::vars::VarId;

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    if args.first() == Some(&b'%') {
        return direct(cx, args, out);
    }
    let vars = &cx.client.vars;
    let selection = select(vars.table(), args, |id| vars.is_hidden(id));
    let now = cx.now;
    if let Selection::One(id) = selection {
        if answer_from_poll(cx, id, now, out) {
            return Reply::Done;
        }
    }
    let single = matches!(selection, Selection::One(_));
    if let Selection::Unknown = selection {
        return error(cx, ErrorCode::UnknownVariable, context, out);
    }
    let ids = selection.ids();
    let snapshot = cx.newest;
    let table = cx.client.vars.table().clone();
    // Behind an unanswered SET, or across a public-file change, only the PLC
    // knows.
    let cache_ok = !cx.behind_set && Arc::ptr_eq(&snapshot.table, &table);
    let mut requests = Vec::new();
    let cached: Vec<Option<Arc<[u8]>>> = ids
        .iter()
        .map(|&id| {
            if cache_ok {
                if let Some(text) = snapshot.fresh(id, now).and_then(|slot| slot.shared_text()) {
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
        complete(cx, then, Ok(Vec::new()), out);
        return Reply::Done;
    }
    Reply::read(cx.section.read(requests), then)
}

/// One variable whose polled value is fresh, and no SET of this client
/// unanswered: the answer comes straight from the newest snapshot, without
/// allocating (the bulk of what SCADA and home-automation clients send).
fn answer_from_poll(cx: &Cx<'_>, id: VarId, now: Instant, out: &mut Vec<u8>) -> bool {
    if cx.behind_set {
        return false;
    }
    let snapshot = cx.newest;
    if !Arc::ptr_eq(&snapshot.table, cx.client.vars.table()) {
        return false;
    }
    let Some(text) = snapshot.fresh(id, now).and_then(|slot| slot.text()) else {
        return false;
    };
    let name = &snapshot.table.var(id).name;
    for part in [b"GET:", &name[..], b",", text, cx.client.eol] {
        out.extend_from_slice(part);
    }
    true
}

fn direct(cx: &mut Cx<'_>, args: &[u8], out: &mut Vec<u8>) -> Reply {
    let Some(address) = parse_direct(args) else {
        return error(cx, ErrorCode::MemGet, args, out);
    };
    let request = ReadRequest {
        area: address.area,
        offset: address.offset,
        len: address.ty.size() as u32,
    };
    let then = ReadThen::Direct {
        name: cp1250::to_upper(args),
        address,
    };
    Reply::read(cx.section.read(vec![request]), then)
}

/// Writes a GET's answer once the PLC answered.
pub fn complete(cx: &mut Cx<'_>, then: ReadThen, reply: ReadReply, out: &mut Vec<u8>) {
    let eol = cx.client.eol;
    let format = cx.section.format();
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
                        Some(Ok(bytes)) => var.format(&var.decode(&bytes), format, out),
                        Some(Err(
                            refusal @ (Refusal::Modbus(_) | Refusal::S7(_) | Refusal::Opcua(_)),
                        )) => {
                            // The device's exception, named in the context.
                            out.truncate(start);
                            let context =
                                plccoms_core::section::write::exception_context(&var.name, refusal);
                            plccoms_protocol::answer::write_error(out, ErrorCode::MemGet, &context);
                            out.extend_from_slice(eol);
                            return;
                        }
                        Some(Err(refusal @ Refusal::Ads(_))) => {
                            // The ADS error, named in the context.
                            out.truncate(start);
                            let context =
                                plccoms_core::section::write::refusal_context(&var.name, &refusal);
                            plccoms_protocol::answer::write_error(out, ErrorCode::MemGet, &context);
                            out.extend_from_slice(eol);
                            return;
                        }
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
