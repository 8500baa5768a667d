//! OPC UA values and the PLC's memory layout: a node's DataType as an IEC
//! type, a Variant as the bytes a variable of that type holds (the
//! Tecomat little-endian layout of [`plccoms_plc::value_codec::Codec::Native`]),
//! and those bytes back as the Variant the node takes.

use opcua::types::{DateTime, NodeId, UAString, Variant};
use plccoms_core::driver::PushedBytes;
use plccoms_protocol::value::Value;
use plccoms_protocol::{cp1250, IecType};

/// The built-in types a variable is served for (OPC 10000-6, 5.1.2), as
/// the node's DataType names them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Builtin {
    Boolean,
    SByte,
    Byte,
    Int16,
    UInt16,
    Int32,
    UInt32,
    Int64,
    UInt64,
    Float,
    Double,
    String,
    DateTime,
    /// Double milliseconds, shown as TIME.
    Duration,
    /// Read only: its text.
    LocalizedText,
}

/// Longest string a variable holds (the protocol's STRING limit).
pub const STRING_LEN: u16 = plccoms_protocol::types::MAX_STRING_LEN;

impl Builtin {
    /// The built-in type of a DataType node id: the standard ones and the
    /// standard subtypes that keep their base's encoding (UtcTime,
    /// Enumeration values as Int32, ...). `None`: a structure or a type of
    /// the server's own, skipped.
    pub fn of_data_type(data_type: &NodeId) -> Option<Builtin> {
        if data_type.namespace != 0 {
            return None;
        }
        let opcua::types::Identifier::Numeric(id) = data_type.identifier else {
            return None;
        };
        Some(match id {
            1 => Builtin::Boolean,
            2 => Builtin::SByte,
            3 => Builtin::Byte,
            4 => Builtin::Int16,
            5 => Builtin::UInt16,
            6 | 29 => Builtin::Int32,   // Int32, Enumeration
            7 | 289 => Builtin::UInt32, // UInt32, Counter
            8 => Builtin::Int64,
            9 => Builtin::UInt64,
            10 => Builtin::Float,
            11 => Builtin::Double,
            12 | 295 | 291 => Builtin::String, // String, LocaleId, NumericRange
            13 | 294 => Builtin::DateTime,     // DateTime, UtcTime
            290 => Builtin::Duration,
            21 => Builtin::LocalizedText,
            _ => return None,
        })
    }

    /// The IEC type clients see.
    pub fn iec(self) -> IecType {
        match self {
            Builtin::Boolean => IecType::Bool,
            Builtin::SByte => IecType::Sint,
            Builtin::Byte => IecType::Usint,
            Builtin::Int16 => IecType::Int,
            Builtin::UInt16 => IecType::Uint,
            Builtin::Int32 => IecType::Dint,
            Builtin::UInt32 => IecType::Udint,
            Builtin::Int64 => IecType::Lint,
            Builtin::UInt64 => IecType::Ulint,
            Builtin::Float => IecType::Real,
            Builtin::Double => IecType::Lreal,
            Builtin::String | Builtin::LocalizedText => IecType::String(STRING_LEN),
            Builtin::DateTime => IecType::Dt,
            Builtin::Duration => IecType::Time,
        }
    }

    /// The built-in type a value of `ty` is written as when the server does
    /// not say (a tag file's type for a node whose DataType is unknown).
    pub fn of_iec(ty: IecType) -> Builtin {
        match ty {
            IecType::Bool => Builtin::Boolean,
            IecType::Sint => Builtin::SByte,
            IecType::Byte | IecType::Usint => Builtin::Byte,
            IecType::Int => Builtin::Int16,
            IecType::Word | IecType::Uint => Builtin::UInt16,
            IecType::Dint => Builtin::Int32,
            IecType::Dword | IecType::Udint => Builtin::UInt32,
            IecType::Lint => Builtin::Int64,
            IecType::Lword | IecType::Ulint => Builtin::UInt64,
            IecType::Real => Builtin::Float,
            IecType::Lreal => Builtin::Double,
            IecType::String(_) => Builtin::String,
            IecType::Date | IecType::Dt => Builtin::DateTime,
            IecType::Time | IecType::Tod => Builtin::Duration,
        }
    }
}

/// The protocol value of `variant` for a variable of type `ty`; `None` for
/// a Variant that is no scalar of a served type (an array, a structure).
pub fn value_of(variant: &Variant, ty: IecType) -> Option<Value> {
    let number = |v: f64| -> Value {
        match ty {
            IecType::Real => Value::Real(v as f32),
            IecType::Lreal => Value::LReal(v),
            _ if is_signed(ty) => Value::Signed(v as i64),
            _ => Value::Unsigned(v as u64),
        }
    };
    let integer = |signed: i64| -> Value {
        match ty {
            IecType::Real => Value::Real(signed as f32),
            IecType::Lreal => Value::LReal(signed as f64),
            IecType::Bool => Value::Bool(signed != 0),
            _ if is_signed(ty) => Value::Signed(signed),
            _ => Value::Unsigned(signed as u64),
        }
    };
    Some(match variant {
        Variant::Boolean(b) => integer(i64::from(*b)),
        Variant::SByte(v) => integer(i64::from(*v)),
        Variant::Byte(v) => integer(i64::from(*v)),
        Variant::Int16(v) => integer(i64::from(*v)),
        Variant::UInt16(v) => integer(i64::from(*v)),
        Variant::Int32(v) => integer(i64::from(*v)),
        Variant::UInt32(v) => integer(i64::from(*v)),
        Variant::Int64(v) => integer(*v),
        Variant::UInt64(v) if is_signed(ty) => Value::Signed(*v as i64),
        Variant::UInt64(v) => match ty {
            IecType::Real | IecType::Lreal => number(*v as f64),
            _ => Value::Unsigned(*v),
        },
        Variant::Float(v) => match ty {
            IecType::Real => Value::Real(*v),
            _ => number(f64::from(*v)),
        },
        Variant::Double(v) => match ty {
            IecType::Time | IecType::Tod => Value::Time(v.clamp(0.0, f64::from(u32::MAX)) as u32),
            _ => number(*v),
        },
        Variant::String(s) => Value::Str(text_bytes(s.value().as_deref().unwrap_or(""))),
        Variant::LocalizedText(t) => {
            Value::Str(text_bytes(t.text.value().as_deref().unwrap_or("")))
        }
        Variant::DateTime(t) => Value::Date(t.as_chrono().timestamp_millis() as f64 / 1000.0),
        _ => return None,
    })
}

fn text_bytes(text: &str) -> Vec<u8> {
    let mut bytes = cp1250::encode(text).into_owned();
    bytes.truncate(usize::from(STRING_LEN));
    bytes
}

fn is_signed(ty: IecType) -> bool {
    matches!(
        ty,
        IecType::Sint | IecType::Int | IecType::Dint | IecType::Lint
    )
}

/// The bytes a variable of type `ty` holds for `variant`.
pub fn bytes_of(variant: &Variant, ty: IecType) -> Option<PushedBytes> {
    let value = value_of(variant, ty)?;
    let mut out = PushedBytes::new();
    value.encode_with(ty, |bytes| out.extend_from_slice(bytes));
    Some(out)
}

/// The Variant of built-in type `builtin` for the bytes a client's SET
/// made for a variable of type `ty`. `None` when it cannot be written
/// (LocalizedText).
pub fn variant_of(bytes: &[u8], ty: IecType, builtin: Builtin) -> Option<Variant> {
    let value = Value::decode(ty, bytes);
    let (signed, unsigned) = integers(&value);
    Some(match builtin {
        Builtin::Boolean => Variant::Boolean(unsigned != 0),
        Builtin::SByte => Variant::SByte(signed as i8),
        Builtin::Byte => Variant::Byte(unsigned as u8),
        Builtin::Int16 => Variant::Int16(signed as i16),
        Builtin::UInt16 => Variant::UInt16(unsigned as u16),
        Builtin::Int32 => Variant::Int32(signed as i32),
        Builtin::UInt32 => Variant::UInt32(unsigned as u32),
        Builtin::Int64 => Variant::Int64(signed),
        Builtin::UInt64 => Variant::UInt64(unsigned),
        Builtin::Float => Variant::Float(value.as_f64() as f32),
        Builtin::Double => Variant::Double(value.as_f64()),
        Builtin::Duration => match value {
            Value::Time(ms) => Variant::Double(f64::from(ms)),
            other => Variant::Double(other.as_f64()),
        },
        Builtin::String => match value {
            Value::Str(text) => Variant::String(UAString::from(cp1250::decode(&text).as_ref())),
            _ => return None,
        },
        Builtin::DateTime => {
            let ms = (value.as_f64() * 1000.0).round() as i64;
            let time = chrono_of(ms)?;
            Variant::DateTime(Box::new(DateTime::from(time)))
        }
        Builtin::LocalizedText => return None,
    })
}

/// A value as a signed and an unsigned integer (casts, as `as` does).
fn integers(value: &Value) -> (i64, u64) {
    match value {
        Value::Bool(b) => (i64::from(*b), u64::from(*b)),
        Value::Unsigned(u) => (*u as i64, *u),
        Value::Signed(i) => (*i, *i as u64),
        Value::Time(t) => (i64::from(*t), u64::from(*t)),
        other => {
            let f = other.as_f64();
            (f as i64, f as u64)
        }
    }
}

fn chrono_of(ms: i64) -> Option<chrono::DateTime<chrono::Utc>> {
    chrono::DateTime::from_timestamp_millis(ms)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_served_type_goes_both_ways() {
        let cases = [
            (Variant::Boolean(true), Builtin::Boolean),
            (Variant::SByte(-5), Builtin::SByte),
            (Variant::Byte(200), Builtin::Byte),
            (Variant::Int16(-300), Builtin::Int16),
            (Variant::UInt16(60000), Builtin::UInt16),
            (Variant::Int32(-70000), Builtin::Int32),
            (Variant::UInt32(4_000_000_000), Builtin::UInt32),
            (Variant::Int64(-5_000_000_000), Builtin::Int64),
            (Variant::UInt64(u64::MAX), Builtin::UInt64),
            (Variant::Float(1.5), Builtin::Float),
            (Variant::Double(-2.25), Builtin::Double),
            (Variant::Double(1500.0), Builtin::Duration),
            (
                Variant::String(UAString::from("Žluťoučký")),
                Builtin::String,
            ),
        ];
        for (variant, builtin) in cases {
            let ty = builtin.iec();
            let bytes = bytes_of(&variant, ty).unwrap();
            assert_eq!(bytes.len(), ty.size());
            assert_eq!(
                variant_of(&bytes, ty, builtin),
                Some(variant),
                "{builtin:?}"
            );
        }
        let time = DateTime::from(chrono_of(1_700_000_000_123).unwrap());
        let bytes = bytes_of(&Variant::DateTime(Box::new(time)), IecType::Dt).unwrap();
        assert_eq!(
            variant_of(&bytes, IecType::Dt, Builtin::DateTime),
            Some(Variant::DateTime(Box::new(time)))
        );
    }

    #[test]
    fn what_is_not_served() {
        assert_eq!(bytes_of(&Variant::Empty, IecType::Int), None);
        assert_eq!(Builtin::of_data_type(&NodeId::new(3, 3001u32)), None);
        assert_eq!(Builtin::of_data_type(&NodeId::new(0, 22u32)), None);
        assert_eq!(
            Builtin::of_data_type(&NodeId::new(0, 294u32)),
            Some(Builtin::DateTime)
        );
    }
}
