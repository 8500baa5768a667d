//! `SET:<name|%addr>,<value>`: writes the value (a BOOL as its bit only) and
//! answers `DIFF:<NAME>,<value>` with the value read back from the PLC, unless
//! DIFF lines are off for this client. An invalid value, or one the
//! variable's raw type cannot hold (a scaled Modbus tag), is ERROR:35 and
//! nothing is written; a SET of a read-only variable (a Modbus input, or a
//! tag with `access = ro`) is ERROR:30 with the request, as on a `READ_ONLY`
//! section.
//!
//! [`plan`] and [`write`] are the same validation and errors for in-process
//! writers (MQTT, the web page): a write is confirmed with the value read
//! back, or refused with the error a client would get.

use std::sync::Arc;

use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::cp1250;
use plccoms_protocol::request::{parse_set, ArgError};
use plccoms_protocol::value::{FormatOptions, Value};

use super::{error, link_error, Cx, Reply};
use crate::backend::{self, ReadRequest, WriteRequest};
use crate::link::{LinkError, SetItem, SetReply};
use crate::section::Section;
use crate::vars::{Codec, Var, VarId, VarTable};

pub struct SetThen {
    table: Arc<VarTable>,
    id: Option<VarId>,
    /// The variable written (a direct address as a variable of its own):
    /// its name as printed, and how to read its answer.
    var: Var,
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
    /// Not a value of the variable's type, or not one its raw type holds
    /// (ERROR:35, with the request).
    BadValue,
    /// The variable cannot be written (ERROR:30, with the request).
    ReadOnly,
}

impl Refusal {
    pub fn code(self) -> ErrorCode {
        match self {
            Refusal::BadAddress => ErrorCode::MemSet,
            Refusal::UnknownVariable => ErrorCode::UnknownVariable,
            Refusal::BadValue => ErrorCode::WrongValue,
            Refusal::ReadOnly => ErrorCode::BadRequest,
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
    let (var, id) = if name.first() == Some(&b'%') {
        let address = parse_direct(name).ok_or(Refusal::BadAddress)?;
        let var = Var {
            name: cp1250::to_upper(name).into_boxed_slice(),
            area: address.area,
            offset: address.offset,
            bit: address.bit,
            ty: address.ty,
            codec: Codec::Native,
            writable: true,
        };
        (var, None)
    } else {
        let id = table.lookup(name).ok_or(Refusal::UnknownVariable)?;
        (table.var(id).clone(), Some(id))
    };
    if !var.writable {
        return Err(Refusal::ReadOnly);
    }
    let value = Value::parse(var.ty, text, format).map_err(|_| Refusal::BadValue)?;
    let data = var.encode(&value).map_err(|_| Refusal::BadValue)?;
    Ok(Planned {
        item: SetItem {
            write: WriteRequest {
                area: var.area,
                offset: var.offset,
                data,
            },
            readback: ReadRequest {
                area: var.area,
                offset: var.offset,
                len: var.byte_len(),
            },
            var: id.map(|id| (table.clone(), id)),
        },
        then: SetThen {
            table: table.clone(),
            id,
            var,
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

/// The value a SET read back, or the error its sender gets (the context
/// of its line).
fn confirm(then: &SetThen, reply: SetReply) -> Result<(Value, u64), (ErrorCode, Vec<u8>)> {
    let outcome = match reply {
        Ok(outcome) => outcome,
        Err(LinkError::Offline) => return Err((ErrorCode::ConnectPlc, Vec::new())),
        Err(_) => return Err((ErrorCode::SendData, Vec::new())),
    };
    let bytes = match outcome.answer {
        Ok(bytes) => bytes,
        Err(backend::Refusal::Modbus(code)) => {
            // The device's exception, named in the context: a value it
            // refuses is a wrong value, anything else the address's fault.
            let errcode = if code == plccoms_plc::modbus::ExceptionCode::ILLEGAL_DATA_VALUE {
                ErrorCode::WrongValue
            } else {
                ErrorCode::MemSet
            };
            return Err((errcode, exception_context(&then.var.name, code)));
        }
        Err(_) if then.id.is_some() => return Err((ErrorCode::SendData, Vec::new())),
        Err(_) => return Err((ErrorCode::MemSet, then.var.name.to_vec())),
    };
    Ok((then.var.decode(&bytes), outcome.seq))
}

/// `NAME: Modbus exception 2 (illegal data address)`, an error's context.
pub fn exception_context(name: &[u8], code: plccoms_plc::modbus::ExceptionCode) -> Vec<u8> {
    let mut context = name.to_vec();
    context.extend_from_slice(format!(": {code}").as_bytes());
    context
}

pub fn complete(cx: &mut Cx<'_>, then: SetThen, reply: SetReply, out: &mut Vec<u8>) {
    let eol = cx.client.eol;
    let (value, seq) = match confirm(&then, reply) {
        Ok(confirmed) => confirmed,
        Err((ErrorCode::ConnectPlc, _)) => {
            return link_error(LinkError::Offline, ErrorCode::SendData, eol, out)
        }
        Err((code, context)) => {
            write_error(out, code, &context);
            out.extend_from_slice(eol);
            return;
        }
    };
    if cx.client.diff {
        out.extend_from_slice(b"DIFF:");
        out.extend_from_slice(&then.var.name);
        out.push(b',');
        value.format(then.var.ty, &cx.section.format, out);
        out.extend_from_slice(eol);
    }
    // The table may have changed while the SET was under way.
    if let (Some(id), true) = (then.id, Arc::ptr_eq(&then.table, cx.client.vars.table())) {
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
            value.format(then.var.ty, &section.format, &mut text);
            Ok(Confirmed {
                name: then.var.name.to_vec(),
                value,
                text,
            })
        }
        Err((code, context)) => Err(WriteError::new(code, &context)),
    }
}
