//! Values between the change stream and OPC UA: a variable's IEC type as
//! the OPC UA data type a client expects, a decoded value as a Variant (the
//! user's forms of [`Presented`], times as OPC UA times), a quality as a
//! StatusCode, and a written Variant back to the text SET takes
//! ([`present::protocol_text`] for the time types).

use opcua::types::{DataTypeId, DateTime, StatusCode, Variant};
use plccoms_core::changes::Quality;
use plccoms_core::present::{self, Presented};
use plccoms_core::section::write::WriteRefusal;
use plccoms_protocol::cp1250;
use plccoms_protocol::value::{FormatOptions, Value};
use plccoms_protocol::IecType;

/// The OPC UA data type of a variable of type `ty` (the table:
/// TIME as a Duration in ms; TOD, which OPC UA has no type for, as its
/// ISO text).
pub fn data_type(ty: IecType) -> DataTypeId {
    match ty {
        IecType::Bool => DataTypeId::Boolean,
        IecType::Sint => DataTypeId::SByte,
        IecType::Usint | IecType::Byte => DataTypeId::Byte,
        IecType::Int => DataTypeId::Int16,
        IecType::Uint | IecType::Word => DataTypeId::UInt16,
        IecType::Dint => DataTypeId::Int32,
        IecType::Udint | IecType::Dword => DataTypeId::UInt32,
        IecType::Lint => DataTypeId::Int64,
        IecType::Ulint | IecType::Lword => DataTypeId::UInt64,
        IecType::Real => DataTypeId::Float,
        IecType::Lreal => DataTypeId::Double,
        IecType::String(_) | IecType::Tod => DataTypeId::String,
        IecType::Date | IecType::Dt => DataTypeId::DateTime,
        IecType::Time => DataTypeId::Duration,
    }
}

/// The Variant of a decoded value of type `ty`; `None` where the value does
/// not fit the OPC UA type (it cannot, for a value the codec decoded).
pub fn variant(ty: IecType, value: &Value) -> Option<Variant> {
    let presented = Presented::of_value(ty, value);
    Some(match ty {
        IecType::Date | IecType::Dt => {
            let ms = (value.as_f64() * 1000.0).round();
            if !ms.is_finite() {
                return None;
            }
            let utc = chrono::DateTime::from_timestamp_millis(ms as i64)?;
            Variant::DateTime(Box::new(DateTime::from(utc)))
        }
        IecType::Time => match value {
            Value::Time(ms) => Variant::Double(f64::from(*ms)),
            _ => return None,
        },
        IecType::Tod | IecType::String(_) => Variant::String(presented.text().into()),
        IecType::Bool => Variant::Boolean(matches!(presented, Presented::Bool(true))),
        IecType::Real => Variant::Float(presented.as_number().unwrap_or(value.as_f64()) as f32),
        IecType::Lreal => Variant::Double(value.as_f64()),
        _ => integer(data_type(ty), &presented)?,
    })
}

fn integer(ty: DataTypeId, presented: &Presented) -> Option<Variant> {
    let n: i128 = match presented {
        Presented::Signed(n) => i128::from(*n),
        Presented::Unsigned(n) => i128::from(*n),
        // A scaled tag of an integer type presents a whole number.
        Presented::Number(x) if x.fract() == 0.0 && x.is_finite() => *x as i128,
        _ => return None,
    };
    Some(match ty {
        DataTypeId::SByte => Variant::SByte(i8::try_from(n).ok()?),
        DataTypeId::Byte => Variant::Byte(u8::try_from(n).ok()?),
        DataTypeId::Int16 => Variant::Int16(i16::try_from(n).ok()?),
        DataTypeId::UInt16 => Variant::UInt16(u16::try_from(n).ok()?),
        DataTypeId::Int32 => Variant::Int32(i32::try_from(n).ok()?),
        DataTypeId::UInt32 => Variant::UInt32(u32::try_from(n).ok()?),
        DataTypeId::Int64 => Variant::Int64(i64::try_from(n).ok()?),
        DataTypeId::UInt64 => Variant::UInt64(u64::try_from(n).ok()?),
        _ => return None,
    })
}

/// The Variant of a variable whose protocol text (as the change stream
/// holds it) is `text`.
pub fn variant_of_text(ty: IecType, text: &[u8], opts: &FormatOptions) -> Option<Variant> {
    if let IecType::String(_) = ty {
        return Some(Variant::String(Presented::of(ty, text, opts).text().into()));
    }
    variant(ty, &Value::parse(ty, text, opts).ok()?)
}

/// A value's StatusCode: good; stale as Uncertain (the last usable value);
/// link lost as Bad (no communication), the last value kept.
pub fn status(quality: Quality) -> StatusCode {
    match quality {
        Quality::Good => StatusCode::Good,
        Quality::Stale => StatusCode::UncertainLastUsableValue,
        Quality::LinkLost => StatusCode::BadNoCommunication,
    }
}

/// The text SET takes for `value` written to a variable of type `ty`, or
/// the StatusCode that refuses it. The stack checked the Variant's type
/// against the node's data type already; a mismatch here is refused the
/// same way.
pub fn write_text(
    ty: IecType,
    value: &Variant,
    opts: &FormatOptions,
) -> Result<Vec<u8>, StatusCode> {
    let user: String = match (ty, value) {
        (IecType::Bool, Variant::Boolean(b)) => b.to_string(),
        (IecType::Real, Variant::Float(x)) => finite(f64::from(*x))?,
        (IecType::Lreal, Variant::Double(x)) => finite(*x)?,
        (IecType::Date | IecType::Dt, Variant::DateTime(t)) => {
            let utc = t.as_chrono();
            if ty == IecType::Date {
                utc.format("%Y-%m-%d").to_string()
            } else {
                utc.to_rfc3339_opts(chrono::SecondsFormat::Millis, true)
            }
        }
        (IecType::Time, Variant::Double(ms)) => {
            if !ms.is_finite() || *ms < 0.0 || *ms > f64::from(u32::MAX) {
                return Err(StatusCode::BadOutOfRange);
            }
            format!("PT{}S", (ms.round() / 1000.0))
        }
        (IecType::String(_) | IecType::Tod, Variant::String(s)) => {
            return protocol(ty, cp1250::encode(s.as_ref()).as_ref(), opts);
        }
        (ty, v) => match (data_type(ty), v) {
            (DataTypeId::SByte, Variant::SByte(n)) => n.to_string(),
            (DataTypeId::Byte, Variant::Byte(n)) => n.to_string(),
            (DataTypeId::Int16, Variant::Int16(n)) => n.to_string(),
            (DataTypeId::UInt16, Variant::UInt16(n)) => n.to_string(),
            (DataTypeId::Int32, Variant::Int32(n)) => n.to_string(),
            (DataTypeId::UInt32, Variant::UInt32(n)) => n.to_string(),
            (DataTypeId::Int64, Variant::Int64(n)) => n.to_string(),
            (DataTypeId::UInt64, Variant::UInt64(n)) => n.to_string(),
            _ => return Err(StatusCode::BadTypeMismatch),
        },
    };
    protocol(ty, user.as_bytes(), opts)
}

fn finite(x: f64) -> Result<String, StatusCode> {
    if x.is_finite() {
        Ok(x.to_string())
    } else {
        Err(StatusCode::BadOutOfRange)
    }
}

fn protocol(ty: IecType, user: &[u8], opts: &FormatOptions) -> Result<Vec<u8>, StatusCode> {
    present::protocol_text(ty, user, opts)
        .map(|text| text.into_owned())
        .map_err(|_| StatusCode::BadOutOfRange)
}

/// A refusal of the core's write path as the StatusCode that says why.
pub fn refusal(refusal: &WriteRefusal) -> StatusCode {
    use plccoms_protocol::answer::ErrorCode;
    match refusal {
        WriteRefusal::BadAddress | WriteRefusal::UnknownVariable => StatusCode::BadNodeIdUnknown,
        WriteRefusal::ReadOnly => StatusCode::BadNotWritable,
        WriteRefusal::BadValue(_) => StatusCode::BadOutOfRange,
        WriteRefusal::Unreachable | WriteRefusal::Failed | WriteRefusal::TimedOut => {
            StatusCode::BadCommunicationError
        }
        // The device refused the value (a Modbus "illegal data value"), or
        // the address.
        WriteRefusal::Refused { .. } if refusal.code() == ErrorCode::WrongValue => {
            StatusCode::BadOutOfRange
        }
        WriteRefusal::Refused { .. } => StatusCode::BadNotWritable,
    }
}
