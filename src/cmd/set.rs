//! `SET:<name|%addr>,<value>`: writes the value (a BOOL as its bit only) and
//! answers `DIFF:<NAME>,<value>` with the value read back from the PLC, unless
//! DIFF lines are off for this client. An invalid value is ERROR:35 and
//! nothing is written.

use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::request::{parse_set, ArgError};
use plccoms_protocol::value::Value;
use plccoms_protocol::{cp1250, IecType};

use super::error;
use super::get::link_error;
use crate::backend::{ReadRequest, WriteData, WriteRequest};
use crate::poller::{SetItem, SetReply};
use crate::session::{Pending, Session};
use crate::vars::{VarId, VarTable};
use std::sync::Arc;

pub struct SetThen {
    name: Vec<u8>,
    table: Arc<VarTable>,
    var: Option<VarId>,
    ty: IecType,
    bit: Option<u8>,
}

pub async fn apply(session: &mut Session, args: &[u8], context: &[u8]) {
    let (name, text) = match parse_set(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(session, ErrorCode::Incomplete, context),
        Err(ArgError::Bad) => return error(session, ErrorCode::BadRequest, context),
    };
    let (area, offset, ty, bit, var, printed) = if name.first() == Some(&b'%') {
        let Some(address) = parse_direct(name) else {
            return error(session, ErrorCode::MemSet, name);
        };
        (
            address.area,
            address.offset,
            address.ty,
            address.bit,
            None,
            cp1250::to_upper(name),
        )
    } else {
        let Some(id) = session.vars.table().lookup(name) else {
            return error(session, ErrorCode::UnknownVariable, context);
        };
        let v = session.vars.table().var(id);
        (v.area, v.offset, v.ty, v.bit, Some(id), v.name.to_vec())
    };
    let value = match Value::parse(ty, text, &session.shared.format) {
        Ok(value) => value,
        Err(_) => return error(session, ErrorCode::WrongValue, context),
    };
    let data = match (bit, &value) {
        (Some(bit), Value::Bool(on)) => WriteData::Bit { bit, value: *on },
        _ => {
            let mut bytes = Vec::with_capacity(ty.size());
            value.encode(ty, &mut bytes);
            WriteData::Bytes(bytes)
        }
    };
    let item = SetItem {
        write: WriteRequest { area, offset, data },
        readback: ReadRequest {
            area,
            offset,
            len: ty.size() as u32,
        },
        var: var.map(|id| (session.vars.table().clone(), id)),
    };
    let rx = session.shared.poller.set(item).await;
    let then = SetThen {
        name: printed,
        table: session.vars.table().clone(),
        var,
        ty,
        bit,
    };
    session.pending.push_back(Pending::Set { rx, then });
}

pub fn complete(session: &mut Session, then: SetThen, reply: SetReply, out: &mut Vec<u8>) {
    let eol = session.conn.eol;
    let outcome = match reply {
        Ok(outcome) => outcome,
        Err(err) => return link_error(err, ErrorCode::SendData, eol, out),
    };
    let bytes = match outcome.answer {
        Ok(bytes) => bytes,
        Err(_) => {
            if then.var.is_some() {
                write_error(out, ErrorCode::SendData, b"");
            } else {
                write_error(out, ErrorCode::MemSet, &then.name);
            }
            out.extend_from_slice(eol);
            return;
        }
    };
    let value = match then.bit {
        Some(bit) => Value::Bool(bytes.first().is_some_and(|b| b & (1 << bit) != 0)),
        None => Value::decode(then.ty, &bytes),
    };
    if session.diff {
        out.extend_from_slice(b"DIFF:");
        out.extend_from_slice(&then.name);
        out.push(b',');
        value.format(then.ty, &session.shared.format, out);
        out.extend_from_slice(eol);
    }
    // The table may have changed while the SET was under way.
    if let (Some(id), true) = (then.var, Arc::ptr_eq(&then.table, session.vars.table())) {
        session.vars.mark_sent(id, outcome.seq, Some(value));
    }
}
