//! The one write path: a value written as text to a variable (or a `%`
//! address), validated, sent through the link and confirmed with the value
//! read back, or refused with a [`WriteRefusal`] that each app renders its
//! own way (the line protocol's `ERROR:` lines: [`WriteRefusal::code`] and
//! [`WriteRefusal::context`]).

use std::sync::Arc;

use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::cp1250;
use plccoms_protocol::value::{FormatOptions, Value};
use tokio::sync::oneshot;

use super::Section;
use crate::driver::{self, ReadRequest, WriteRequest};
use crate::link::{LinkError, SetItem, SetReply};
use crate::vars::{Codec, Var, VarId, VarTable};

/// Why a write was refused, before or after it reached the PLC.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WriteRefusal {
    /// Not a direct address this server understands.
    BadAddress,
    /// No such variable.
    UnknownVariable,
    /// The section is READ_ONLY, or the variable cannot be written (a
    /// Modbus input, a tag with `access = ro`).
    ReadOnly,
    /// Not a value of the variable's type, or not one its raw type holds:
    /// the parser's message. Nothing was written.
    BadValue(String),
    /// No link to the PLC: refused at once, never written later.
    Unreachable,
    /// The link failed during the write.
    Failed,
    /// The write waited past EPSTOUT to be sent: it never will be.
    TimedOut,
    /// The device refused the write or its read-back.
    Refused {
        /// The variable's name as the protocol prints it.
        name: Vec<u8>,
        refusal: driver::Refusal,
        /// A `%` address rather than a table variable.
        direct: bool,
    },
}

impl WriteRefusal {
    /// The line protocol's error code for it.
    pub fn code(&self) -> ErrorCode {
        match self {
            WriteRefusal::BadAddress => ErrorCode::MemSet,
            WriteRefusal::UnknownVariable => ErrorCode::UnknownVariable,
            WriteRefusal::ReadOnly => ErrorCode::BadRequest,
            WriteRefusal::BadValue(_) => ErrorCode::WrongValue,
            WriteRefusal::Unreachable => ErrorCode::ConnectPlc,
            WriteRefusal::Failed | WriteRefusal::TimedOut => ErrorCode::SendData,
            // A value the device refuses is a wrong value, anything else
            // the address's fault.
            WriteRefusal::Refused {
                refusal: driver::Refusal::Modbus(code),
                ..
            } if *code == plccoms_plc::modbus::ExceptionCode::ILLEGAL_DATA_VALUE => {
                ErrorCode::WrongValue
            }
            WriteRefusal::Refused {
                refusal: driver::Refusal::Modbus(_) | driver::Refusal::S7(_),
                ..
            } => ErrorCode::MemSet,
            // ADS: invalid data or parameter value (0x706, 0x70B).
            WriteRefusal::Refused {
                refusal: driver::Refusal::Ads(code),
                ..
            } if matches!(code.0, 0x706 | 0x70B) => ErrorCode::WrongValue,
            WriteRefusal::Refused {
                refusal: driver::Refusal::Ads(_),
                ..
            } => ErrorCode::MemSet,
            // An OPC UA server's BadTypeMismatch, BadOutOfRange: the value.
            WriteRefusal::Refused {
                refusal: driver::Refusal::Opcua(code),
                ..
            } if matches!(code & 0xFFFF_0000, 0x8074_0000 | 0x803C_0000) => ErrorCode::WrongValue,
            WriteRefusal::Refused {
                refusal: driver::Refusal::Opcua(_),
                ..
            } => ErrorCode::MemSet,
            WriteRefusal::Refused { direct: false, .. } => ErrorCode::SendData,
            WriteRefusal::Refused { direct: true, .. } => ErrorCode::MemSet,
        }
    }

    /// The context of its `ERROR:` line: `request` (the SET as written) for
    /// a refusal before the link, else what the link's answer names.
    pub fn context(&self, name: &[u8], request: &[u8]) -> Vec<u8> {
        match self {
            WriteRefusal::BadAddress => name.to_vec(),
            WriteRefusal::UnknownVariable | WriteRefusal::ReadOnly | WriteRefusal::BadValue(_) => {
                request.to_vec()
            }
            WriteRefusal::Unreachable | WriteRefusal::Failed | WriteRefusal::TimedOut => Vec::new(),
            WriteRefusal::Refused {
                name,
                refusal: driver::Refusal::Modbus(code),
                ..
            } => exception_context(name, *code),
            WriteRefusal::Refused {
                name,
                refusal: driver::Refusal::S7(code),
                ..
            } => exception_context(name, *code),
            WriteRefusal::Refused {
                name,
                refusal: refusal @ driver::Refusal::Ads(_),
                ..
            } => refusal_context(name, refusal),
            WriteRefusal::Refused {
                name,
                refusal: refusal @ driver::Refusal::Opcua(_),
                ..
            } => exception_context(name, refusal),
            WriteRefusal::Refused { direct: false, .. } => Vec::new(),
            WriteRefusal::Refused { name, .. } => name.clone(),
        }
    }

    /// `ERROR:<code> <text> '<context>'` (no line end) for a write of
    /// `text` to `name` made as `SET:<name>,<text>`.
    pub fn line(&self, name: &[u8], text: &[u8]) -> String {
        let mut request = b"SET:".to_vec();
        request.extend_from_slice(name);
        request.push(b',');
        request.extend_from_slice(text);
        let mut line = Vec::new();
        write_error(&mut line, self.code(), &self.context(name, &request));
        cp1250::decode(&line).into_owned()
    }
}

/// `NAME: Modbus exception 2 (illegal data address)` (or an S7 return
/// code's text, or an OPC UA server's `NAME: OPC UA BadNotWritable
/// (0x803B0000)`), an error's context.
pub fn exception_context(name: &[u8], code: impl std::fmt::Display) -> Vec<u8> {
    let mut context = name.to_vec();
    context.extend_from_slice(format!(": {code}").as_bytes());
    context
}

/// `NAME: ADS error 0x710 (symbol not found)`: a device's named refusal
/// as an error's context.
pub fn refusal_context(name: &[u8], refusal: &driver::Refusal) -> Vec<u8> {
    let mut context = name.to_vec();
    context.extend_from_slice(format!(": {refusal}").as_bytes());
    context
}

/// A write confirmed by the PLC.
#[derive(Debug, Clone)]
pub struct Written {
    /// The variable's name as the protocol prints it (cp1250, upper case).
    pub name: Vec<u8>,
    /// The value read back.
    pub value: Value,
    /// The value as the protocol prints it (`DIFF:` line text).
    pub text: Vec<u8>,
    /// The change stream's sequence that carries the value read back.
    pub seq: u64,
    /// The table variable written (none for a `%` address).
    pub var: Option<(Arc<VarTable>, VarId)>,
}

/// A write sent to the link: [`PendingWrite::confirm`] its answer.
pub struct PendingWrite {
    pub reply: oneshot::Receiver<SetReply>,
    pub target: WriteTarget,
}

/// The variable written (a direct address as a variable of its own), and
/// how to read its answer.
pub struct WriteTarget {
    table: Arc<VarTable>,
    id: Option<VarId>,
    var: Var,
    format: FormatOptions,
}

impl WriteTarget {
    /// The value read back, or why the write failed.
    pub fn confirm(&self, reply: SetReply) -> Result<Written, WriteRefusal> {
        let outcome = match reply {
            Ok(outcome) => outcome,
            Err(LinkError::Offline) => return Err(WriteRefusal::Unreachable),
            Err(LinkError::Late) => return Err(WriteRefusal::TimedOut),
            Err(LinkError::Plc(_)) => return Err(WriteRefusal::Failed),
        };
        let bytes = outcome.answer.map_err(|refusal| WriteRefusal::Refused {
            name: self.var.name.to_vec(),
            refusal,
            direct: self.id.is_none(),
        })?;
        let value = self.var.decode(&bytes);
        let mut text = Vec::new();
        self.var.format(&value, &self.format, &mut text);
        Ok(Written {
            name: self.var.name.to_vec(),
            value,
            text,
            seq: outcome.seq,
            var: self.id.map(|id| (self.table.clone(), id)),
        })
    }
}

impl Section {
    /// Writes `text` to `name` (a variable or a `%` address): confirmed with
    /// the value read back, published to every client; or refused, and then
    /// never applied later. The write path of every app.
    pub async fn write(&self, name: &[u8], text: &[u8]) -> Result<Written, WriteRefusal> {
        let table = self.latest().table.clone();
        let pending = self.start_write(&table, name, text)?;
        let reply = pending.reply.await.unwrap_or(Err(LinkError::Offline));
        pending.target.confirm(reply)
    }

    /// Validates a write of `text` to `name` as a variable of `table` and
    /// sends it to the link, for an app that waits for its answer itself.
    pub fn start_write(
        &self,
        table: &Arc<VarTable>,
        name: &[u8],
        text: &[u8],
    ) -> Result<PendingWrite, WriteRefusal> {
        if self.read_only() {
            return Err(WriteRefusal::ReadOnly);
        }
        let (var, id) = if name.first() == Some(&b'%') {
            let address = parse_direct(name).ok_or(WriteRefusal::BadAddress)?;
            let var = Var {
                name: cp1250::to_upper(name).into_boxed_slice(),
                area: address.area,
                offset: address.offset,
                bit: address.bit,
                ty: address.ty,
                codec: Codec::Native,
                writable: true,
                info: None,
            };
            (var, None)
        } else {
            let id = table.lookup(name).ok_or(WriteRefusal::UnknownVariable)?;
            (table.var(id).clone(), Some(id))
        };
        if !var.writable {
            return Err(WriteRefusal::ReadOnly);
        }
        let bad = |e: &dyn std::fmt::Display| WriteRefusal::BadValue(e.to_string());
        let value = Value::parse(var.ty, text, &self.format).map_err(|e| bad(&e))?;
        let data = var.encode(&value).map_err(|e| bad(&e))?;
        let item = SetItem {
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
        };
        Ok(PendingWrite {
            reply: self.link.set(item),
            target: WriteTarget {
                table: table.clone(),
                id,
                var,
                format: self.format,
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_plc::modbus::ExceptionCode;

    #[test]
    fn refusals_render_as_set_error_lines() {
        let line = |r: WriteRefusal| r.line(b"counter", b"abc");
        assert_eq!(
            line(WriteRefusal::BadValue("not a number".into())),
            "ERROR:35 Wrong parameter value in request: 'SET:counter,abc'"
        );
        assert_eq!(
            line(WriteRefusal::ReadOnly),
            "ERROR:30 Bad client request: 'SET:counter,abc'"
        );
        assert_eq!(WriteRefusal::Unreachable.code(), ErrorCode::ConnectPlc);
        assert_eq!(WriteRefusal::TimedOut.context(b"X", b"SET:X,1"), b"");
        let refused = |refusal, direct| WriteRefusal::Refused {
            name: b"%R10".to_vec(),
            refusal,
            direct,
        };
        let value = refused(
            driver::Refusal::Modbus(ExceptionCode::ILLEGAL_DATA_VALUE),
            false,
        );
        assert_eq!(value.code(), ErrorCode::WrongValue);
        assert!(value.context(b"", b"").starts_with(b"%R10: "));
        let device = refused(driver::Refusal::BAD_PARAMETERS, false);
        assert_eq!(
            (device.code(), device.context(b"", b"")),
            (ErrorCode::SendData, vec![])
        );
        let direct = refused(driver::Refusal::BAD_PARAMETERS, true);
        assert_eq!(
            (direct.code(), direct.context(b"", b"")),
            (ErrorCode::MemSet, b"%R10".to_vec())
        );
        assert_eq!(
            WriteRefusal::BadAddress.context(b"%ZZ", b"SET:%ZZ,1"),
            b"%ZZ"
        );
    }
}
