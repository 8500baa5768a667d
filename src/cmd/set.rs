//! `SET:<name|%addr>,<value>`: writes the value (a BOOL as its bit only) and
//! answers `DIFF:<NAME>,<value>` with the value read back from the PLC, unless
//! DIFF lines are off for this client. An invalid value is ERROR:35 and
//! nothing is written.
//!
//! [`plan`] and [`write`] are the same validation and errors for in-process
//! writers (MQTT, the web page): a write is confirmed with the value read
//! back, or refused with the error a client would get.

use std::sync::Arc;

use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::request::{parse_set, ArgError};
use plccoms_protocol::value::{FormatOptions, Value};
use plccoms_protocol::{cp1250, IecType};

use super::{error, link_error, Cx, Reply};
use crate::backend::{ReadRequest, WriteData, WriteRequest};
use crate::link::{LinkError, SetItem, SetReply};
use crate::section::Section;
use crate::vars::{VarId, VarTable};

pub struct SetThen {
    name: Vec<u8>,
    table: Arc<VarTable>,
    var: Option<VarId>,
    ty: IecType,
    bit: Option<u8>,
}

/// A validated SET: what the link writes, and how its answer is read.
pub struct Planned {
    pub item: SetItem,
    pub then: SetThen,
}

/// Why a SET is refused before anything is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// Not a direct address this server understands (ERROR:81, with the name).
    BadAddress,
    /// No such variable (ERROR:33, with the request).
    UnknownVariable,
    /// Not a value of the variable's type (ERROR:35, with the request).
    BadValue,
}

impl Refusal {
    pub fn code(self) -> ErrorCode {
        match self {
            Refusal::BadAddress => ErrorCode::MemSet,
            Refusal::UnknownVariable => ErrorCode::UnknownVariable,
            Refusal::BadValue => ErrorCode::WrongValue,
        }
    }
}

/// Validates a SET of `name` (a variable of `table` or a `%` address) to the
/// value written as `text`, exactly as the command does.
pub fn plan(
    table: &Arc<VarTable>,
    format: &FormatOptions,
    name: &[u8],
    text: &[u8],
) -> Result<Planned, Refusal> {
    let (area, offset, ty, bit, var, printed) = if name.first() == Some(&b'%') {
        let address = parse_direct(name).ok_or(Refusal::BadAddress)?;
        (
            address.area,
            address.offset,
            address.ty,
            address.bit,
            None,
            cp1250::to_upper(name),
        )
    } else {
        let id = table.lookup(name).ok_or(Refusal::UnknownVariable)?;
        let v = table.var(id);
        (v.area, v.offset, v.ty, v.bit, Some(id), v.name.to_vec())
    };
    let value = Value::parse(ty, text, format).map_err(|_| Refusal::BadValue)?;
    let data = match (bit, &value) {
        (Some(bit), Value::Bool(on)) => WriteData::Bit { bit, value: *on },
        _ => {
            let mut bytes = Vec::with_capacity(ty.size());
            value.encode(ty, &mut bytes);
            WriteData::Bytes(bytes)
        }
    };
    Ok(Planned {
        item: SetItem {
            write: WriteRequest { area, offset, data },
            readback: ReadRequest {
                area,
                offset,
                len: ty.size() as u32,
            },
            var: var.map(|id| (table.clone(), id)),
        },
        then: SetThen {
            name: printed,
            table: table.clone(),
            var,
            ty,
            bit,
        },
    })
}

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let (name, text) = match parse_set(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(cx, ErrorCode::Incomplete, context, out),
        Err(ArgError::Bad) => return error(cx, ErrorCode::BadRequest, context, out),
    };
    let table = cx.client.vars.table().clone();
    match plan(&table, &cx.section.format, name, text) {
        Ok(planned) => Reply::set(cx.section.link.set(planned.item), planned.then),
        Err(Refusal::BadAddress) => error(cx, ErrorCode::MemSet, name, out),
        Err(refusal) => error(cx, refusal.code(), context, out),
    }
}

/// The value a SET read back, or the error its sender gets.
fn confirm(then: &SetThen, reply: SetReply) -> Result<(Value, u64), (ErrorCode, &[u8])> {
    let outcome = match reply {
        Ok(outcome) => outcome,
        Err(LinkError::Offline) => return Err((ErrorCode::ConnectPlc, b"")),
        Err(_) => return Err((ErrorCode::SendData, b"")),
    };
    let bytes = match outcome.answer {
        Ok(bytes) => bytes,
        Err(_) if then.var.is_some() => return Err((ErrorCode::SendData, b"")),
        Err(_) => return Err((ErrorCode::MemSet, &then.name)),
    };
    let value = match then.bit {
        Some(bit) => Value::Bool(bytes.first().is_some_and(|b| b & (1 << bit) != 0)),
        None => Value::decode(then.ty, &bytes),
    };
    Ok((value, outcome.seq))
}

pub fn complete(cx: &mut Cx<'_>, then: SetThen, reply: SetReply, out: &mut Vec<u8>) {
    let eol = cx.client.eol;
    let (value, seq) = match confirm(&then, reply) {
        Ok(confirmed) => confirmed,
        Err((ErrorCode::ConnectPlc, _)) => {
            return link_error(LinkError::Offline, ErrorCode::SendData, eol, out)
        }
        Err((code, context)) => {
            write_error(out, code, context);
            out.extend_from_slice(eol);
            return;
        }
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
        cx.client.vars.mark_sent(id, seq, Some(value));
    }
}

/// A write confirmed by the PLC.
#[derive(Debug, Clone, PartialEq)]
pub struct Confirmed {
    /// The variable's name as the protocol prints it (cp1250, upper case).
    pub name: Vec<u8>,
    pub value: Value,
    /// The value as the protocol prints it (`DIFF:` line text).
    pub text: Vec<u8>,
}

/// A refused write: the error line a client's SET would have got.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WriteError {
    pub code: ErrorCode,
    /// `ERROR:<code> <text> '<context>'`, without line end.
    pub line: String,
}

impl WriteError {
    fn new(code: ErrorCode, context: &[u8]) -> WriteError {
        let mut line = Vec::new();
        write_error(&mut line, code, context);
        WriteError {
            code,
            line: cp1250::decode(&line).into_owned(),
        }
    }
}

impl std::fmt::Display for WriteError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.line)
    }
}

/// Writes `text` to `name` from inside the server (MQTT, the web page), with
/// SET's validation and errors (READ_ONLY included): confirmed with the value
/// read back, published to every client; or refused, and then never applied
/// later.
pub async fn write(section: &Section, name: &[u8], text: &[u8]) -> Result<Confirmed, WriteError> {
    let mut context = b"SET:".to_vec();
    context.extend_from_slice(name);
    context.push(b',');
    context.extend_from_slice(text);
    if section.read_only() {
        return Err(WriteError::new(ErrorCode::BadRequest, &context));
    }
    let table = section.changes.latest().table.clone();
    let planned = match plan(&table, &section.format, name, text) {
        Ok(planned) => planned,
        Err(Refusal::BadAddress) => return Err(WriteError::new(ErrorCode::MemSet, name)),
        Err(refusal) => return Err(WriteError::new(refusal.code(), &context)),
    };
    let reply = section
        .link
        .set(planned.item)
        .await
        .unwrap_or(Err(LinkError::Offline));
    let then = planned.then;
    match confirm(&then, reply) {
        Ok((value, _)) => {
            let mut text = Vec::new();
            value.format(then.ty, &section.format, &mut text);
            Ok(Confirmed {
                name: then.name,
                value,
                text,
            })
        }
        Err((code, context)) => Err(WriteError::new(code, context)),
    }
}
