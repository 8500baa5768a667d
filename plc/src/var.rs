//! A variable: its name, its place in PLC memory, its type and how its
//! bytes become a client's value and back. The one struct the server's
//! variable tables, the simulated PLC's program and the public file parser
//! use ([`VarDef`], a public file's line), also made from a Modbus tag
//! ([`crate::modbus::tags::Tag::var`]).

use plccoms_protocol::value::{FormatOptions, Value};
use plccoms_protocol::{Area, IecType};

use crate::memory::WriteData;
use crate::value_codec::{Codec, EncodeError};

#[derive(Debug, Clone, PartialEq)]
pub struct Var {
    /// cp1250 bytes: as written in its file; upper case in a server's table,
    /// as the server prints it.
    pub name: Box<[u8]>,
    pub area: Area,
    /// Byte offset in the area.
    pub offset: u32,
    /// Bit in the byte at `offset`, for a BOOL.
    pub bit: Option<u8>,
    pub ty: IecType,
    /// How its bytes become the client's value (`ty`) and back (Native for
    /// a public file's variables).
    pub codec: Codec,
    /// Whether a SET may write it (a Modbus tag may be read-only).
    pub writable: bool,
    /// What a tag file says of it beyond its place (`None` for a public
    /// file's variables): boxed, so a table of 100,000 variables without
    /// it pays a pointer each.
    pub info: Option<Box<VarInfo>>,
}

/// What a tag file tells of a variable for people: its unit, description,
/// range and decimals. The telnet port shows none of it; the other faces
/// (MQTT, Home Assistant, the web page) do.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct VarInfo {
    /// As written (`°C`, `kWh`); empty when not given.
    pub unit: String,
    pub description: String,
    /// The range a writer may set, when the file gives one.
    pub min: Option<f64>,
    pub max: Option<f64>,
    /// Decimals to print the value with, when the file gives them.
    pub decimals: Option<u8>,
}

impl VarInfo {
    /// `None` when nothing is said.
    pub fn boxed(self) -> Option<Box<VarInfo>> {
        (self != VarInfo::default()).then(|| Box::new(self))
    }
}

impl Var {
    /// The value held by `bytes` as read for this variable (a BOOL's bit is
    /// picked out of its byte).
    pub fn decode(&self, bytes: &[u8]) -> Value {
        match self.bit {
            Some(bit) => Value::Bool(bytes.first().is_some_and(|b| b & (1 << bit) != 0)),
            None => self.codec.decode(self.ty, bytes),
        }
    }

    /// What to write so the variable holds `value` (a BOOL as its bit only),
    /// or why it cannot hold it (the raw value of a scaled tag out of range).
    pub fn encode(&self, value: &Value) -> Result<WriteData, EncodeError> {
        match (self.bit, value) {
            (Some(bit), Value::Bool(on)) => Ok(WriteData::Bit { bit, value: *on }),
            _ => self.codec.encode(self.ty, value).map(WriteData::Bytes),
        }
    }

    /// Appends the text GET and DIFF print for `value`: the vendor's form,
    /// or what the tag file's decimals and scale make it
    /// ([`Codec::format`]). Every face prints through here, so the telnet
    /// port, MQTT and the web page show the same value.
    pub fn format(&self, value: &Value, opts: &FormatOptions, out: &mut Vec<u8>) {
        let decimals = self.info.as_ref().and_then(|info| info.decimals);
        self.codec.format(self.ty, decimals, value, opts, out);
    }

    /// Bytes read from PLC memory for this variable.
    pub fn byte_len(&self) -> u32 {
        self.codec.byte_len(self.ty)
    }
}

/// A variable as its file defines it (name as written), with its 1-based
/// line for messages.
#[derive(Debug, Clone, PartialEq)]
pub struct VarDef {
    pub var: Var,
    pub line: usize,
}
