//! `SET:<name|%addr>,<value>`: writes the value (a BOOL as its bit only) and
//! answers `DIFF:<NAME>,<value>` with the value read back from the PLC, unless
//! DIFF lines are off for this client. An invalid value is ERROR:35 and
//! nothing is written.

use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::request::{parse_set, ArgError};
use plccoms_protocol::value::Value;
use plccoms_protocol::{cp1250, IecType};

use std::sync::Arc;

use super::{error, link_error, Cx, Reply};
use crate::backend::{ReadRequest, WriteData, WriteRequest};
use crate::link::{SetItem, SetReply};
use crate::vars::{VarId, VarTable};

pub struct SetThen {
    name: Vec<u8>,
    table: Arc<VarTable>,
    var: Option<VarId>,
    ty: IecType,
    bit: Option<u8>,
}

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let (name, text) = match parse_set(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(cx, ErrorCode::Incomplete, context, out),
        Err(ArgError::Bad) => return error(cx, ErrorCode::BadRequest, context, out),
    };
    let table = cx.client.vars.table().clone();
    let (area, offset, ty, bit, var, printed) = if name.first() == Some(&b'%') {
        let Some(address) = parse_direct(name) else {
            return error(cx, ErrorCode::MemSet, name, out);
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
        let Some(id) = table.lookup(name) else {
            return error(cx, ErrorCode::UnknownVariable, context, out);
        };
        let v = table.var(id);
        (v.area, v.offset, v.ty, v.bit, Some(id), v.name.to_vec())
    };
    let value = match Value::parse(ty, text, &cx.section.format) {
        Ok(value) => value,
        Err(_) => return error(cx, ErrorCode::WrongValue, context, out),
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
        var: var.map(|id| (table.clone(), id)),
    };
    let then = SetThen {
        name: printed,
        table,
        var,
        ty,
        bit,
    };
    Reply::set(cx.section.link.set(item), then)
}

pub fn complete(cx: &mut Cx<'_>, then: SetThen, reply: SetReply, out: &mut Vec<u8>) {
    let eol = cx.client.eol;
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
    if cx.client.diff {
        out.extend_from_slice(b"DIFF:");
        out.extend_from_slice(&then.name);
        out.push(b',');
        value.format(then.ty, &cx.section.format, out);
        out.extend_from_slice(eol);
    }
    // The table may have changed while the SET was under way.
    if let (Some(id), true) = (then.var, Arc::ptr_eq(&then.table, cx.client.vars.table())) {
        cx.client.vars.mark_sent(id, outcome.seq, Some(value));
    }
}
