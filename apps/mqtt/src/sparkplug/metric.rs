//! From a variable to a Sparkplug metric and back: the datatype of each
//! PLC type (spec 3.0, 6.4.16), its value in the payload, the properties
//! (unit, description, quality) and a command's value as SET takes it.
//!
//! | PLC type | datatype | value field |
//! |---|---|---|
//! | BOOL | Boolean (11) | `boolean_value` |
//! | SINT, INT, DINT | Int8, Int16, Int32 (1-3) | `int_value`, two's complement in the type's width |
//! | USINT/BYTE, UINT/WORD, UDINT/DWORD | UInt8, UInt16, UInt32 (5-7) | `int_value` |
//! | LINT, ULINT/LWORD | Int64, UInt64 (4, 8) | `long_value` |
//! | REAL, LREAL | Float, Double (9, 10) | `float_value`, `double_value` |
//! | STRING | String (12) | `string_value` |
//! | DT, DATE (and a Modbus TS48) | DateTime (13) | `long_value`, ms since 1970 UTC |
//! | TOD, TIME | String (12) | ISO 8601: `10:15:00.123`, `PT1H2M3.456S` |
//!
//! Signed values narrower than 64 bits go in their own width (Int8 -1 is
//! 255), as pysparkplug and Tahu's Python client read them; a command's
//! value sign-extended to 32 bits (Tahu's Java client) is taken too.

use chrono::{DateTime, NaiveDate};
use plccoms_core::changes::Quality;
use plccoms_core::present::Presented;
use plccoms_core::vars::Var;
use plccoms_protocol::IecType;

use super::proto::{Metric, MetricValue, PropertyScalar, PropertySet, PropertyValue};

/// Sparkplug datatypes (spec 3.0, 6.4.16).
pub mod datatype {
    pub const INT8: u32 = 1;
    pub const INT16: u32 = 2;
    pub const INT32: u32 = 3;
    pub const INT64: u32 = 4;
    pub const UINT8: u32 = 5;
    pub const UINT16: u32 = 6;
    pub const UINT32: u32 = 7;
    pub const UINT64: u32 = 8;
    pub const FLOAT: u32 = 9;
    pub const DOUBLE: u32 = 10;
    pub const BOOLEAN: u32 = 11;
    pub const STRING: u32 = 12;
    pub const DATETIME: u32 = 13;
}

/// The property that tells a metric's quality: `good`, `stale` or
/// `link_lost` (a String property, in births and in every data message
/// whose quality is not good, and when it becomes good again).
pub const QUALITY: &str = "Quality";
/// Tahu and Ignition's own property for the unit.
pub const UNIT: &str = "engUnit";
pub const DESCRIPTION: &str = "Description";

/// The datatype of a variable of type `ty`.
pub fn datatype(ty: IecType) -> u32 {
    use datatype::*;
    match ty {
        IecType::Bool => BOOLEAN,
        IecType::Sint => INT8,
        IecType::Int => INT16,
        IecType::Dint => INT32,
        IecType::Lint => INT64,
        IecType::Usint | IecType::Byte => UINT8,
        IecType::Uint | IecType::Word => UINT16,
        IecType::Udint | IecType::Dword => UINT32,
        IecType::Ulint | IecType::Lword => UINT64,
        IecType::Real => FLOAT,
        IecType::Lreal => DOUBLE,
        IecType::Date | IecType::Dt => DATETIME,
        IecType::String(_) | IecType::Tod | IecType::Time => STRING,
    }
}

/// The payload value of `shown` as a metric of `datatype`; `None` when it
/// has no such form (then the metric is sent with `is_null`).
pub fn value(datatype: u32, shown: &Presented) -> Option<MetricValue> {
    use datatype::*;
    let signed = |bits: u32| -> Option<MetricValue> {
        let n = match shown {
            Presented::Signed(n) => *n,
            Presented::Unsigned(n) => i64::try_from(*n).ok()?,
            _ => return None,
        };
        let mask = (1u64 << bits) - 1;
        Some(MetricValue::IntValue((n as u64 & mask) as u32))
    };
    let unsigned = || -> Option<u64> {
        match shown {
            Presented::Unsigned(n) => Some(*n),
            Presented::Signed(n) => u64::try_from(*n).ok(),
            _ => None,
        }
    };
    Some(match datatype {
        INT8 => signed(8)?,
        INT16 => signed(16)?,
        INT32 => signed(32)?,
        INT64 => match shown {
            Presented::Signed(n) => MetricValue::LongValue(*n as u64),
            _ => MetricValue::LongValue(unsigned()?),
        },
        UINT8 | UINT16 | UINT32 => MetricValue::IntValue(u32::try_from(unsigned()?).ok()?),
        UINT64 => MetricValue::LongValue(unsigned()?),
        FLOAT => MetricValue::FloatValue(shown.as_number_or_nan()? as f32),
        DOUBLE => MetricValue::DoubleValue(shown.as_number_or_nan()?),
        BOOLEAN => match shown {
            Presented::Bool(b) => MetricValue::BooleanValue(*b),
            _ => return None,
        },
        DATETIME => MetricValue::LongValue(unix_ms(shown)? as u64),
        _ => MetricValue::StringValue(shown.text()),
    })
}

trait NumberOrNan {
    fn as_number_or_nan(&self) -> Option<f64>;
}

impl NumberOrNan for Presented {
    /// Numbers with NaN and infinities (a Float carries them).
    fn as_number_or_nan(&self) -> Option<f64> {
        match self {
            Presented::Number(x) => Some(*x),
            other => other.as_number(),
        }
    }
}

/// Milliseconds since 1970 of a DT or DATE as presented.
fn unix_ms(shown: &Presented) -> Option<i64> {
    match shown {
        Presented::DateTime(text) => DateTime::parse_from_rfc3339(text)
            .ok()
            .map(|t| t.timestamp_millis()),
        Presented::Date(text) => NaiveDate::parse_from_str(text, "%Y-%m-%d").ok().map(|d| {
            d.and_time(chrono::NaiveTime::MIN)
                .and_utc()
                .timestamp_millis()
        }),
        _ => None,
    }
}

fn string_property(text: &str) -> PropertyValue {
    PropertyValue {
        r#type: Some(datatype::STRING),
        is_null: None,
        value: Some(PropertyScalar::StringValue(text.to_string())),
    }
}

/// The properties of a metric: its quality, and in a birth the unit and
/// description the tag file gives.
pub fn properties(var: Option<&Var>, quality: Quality) -> PropertySet {
    let mut set = PropertySet {
        keys: vec![QUALITY.to_string()],
        values: vec![string_property(quality.as_str())],
    };
    if let Some(info) = var.and_then(|v| v.info.as_deref()) {
        for (key, text) in [(UNIT, &info.unit), (DESCRIPTION, &info.description)] {
            if !text.is_empty() {
                set.keys.push(key.to_string());
                set.values.push(string_property(text));
            }
        }
    }
    set
}

/// A metric of the node's own (bdSeq, Node Control/Rebirth, counters).
pub fn node_metric(name: &str, alias: u64, value: MetricValue, datatype: u32) -> Metric {
    Metric {
        name: Some(name.to_string()),
        alias: Some(alias),
        datatype: Some(datatype),
        value: Some(value),
        ..Metric::default()
    }
}

/// Why a command's value cannot be written.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CommandValueError {
    #[error("no value (is_null or none given)")]
    Missing,
    #[error("a value of the wrong kind for a {0} metric")]
    WrongKind(&'static str),
    #[error("{0} is out of the range of a {1} metric")]
    OutOfRange(i128, &'static str),
}

fn name_of(datatype: u32) -> &'static str {
    use datatype::*;
    match datatype {
        INT8 => "Int8",
        INT16 => "Int16",
        INT32 => "Int32",
        INT64 => "Int64",
        UINT8 => "UInt8",
        UINT16 => "UInt16",
        UINT32 => "UInt32",
        UINT64 => "UInt64",
        FLOAT => "Float",
        DOUBLE => "Double",
        BOOLEAN => "Boolean",
        DATETIME => "DateTime",
        _ => "String",
    }
}

/// A command's value for a variable of type `ty`, in the user's terms
/// (what [`plccoms_core::present::protocol_text`] takes). A value is read
/// by its field, whatever datatype the command claims: hosts differ there.
pub fn command_text(ty: IecType, value: Option<&MetricValue>) -> Result<String, CommandValueError> {
    use datatype::*;
    let dt = datatype(ty);
    let kind = name_of(dt);
    let value = value.ok_or(CommandValueError::Missing)?;
    let wrong = || CommandValueError::WrongKind(kind);
    let integer = |n: i128| -> Result<String, CommandValueError> {
        let (lo, hi): (i128, i128) = match dt {
            INT8 => (-128, 127),
            INT16 => (-32768, 32767),
            INT32 => (i32::MIN.into(), i32::MAX.into()),
            INT64 => (i64::MIN.into(), i64::MAX.into()),
            UINT8 => (0, 255),
            UINT16 => (0, 65535),
            UINT32 => (0, u32::MAX.into()),
            _ => (0, u64::MAX.into()),
        };
        if n < lo || n > hi {
            return Err(CommandValueError::OutOfRange(n, kind));
        }
        Ok(n.to_string())
    };
    match (dt, value) {
        (BOOLEAN, MetricValue::BooleanValue(b)) => Ok(b.to_string()),
        (BOOLEAN, MetricValue::IntValue(n)) => Ok((*n != 0).to_string()),
        (INT8 | INT16 | INT32, MetricValue::IntValue(n)) => {
            let bits = match dt {
                INT8 => 8,
                INT16 => 16,
                _ => 32,
            };
            // In the type's width, or sign-extended to 32 bits.
            let n = i128::from(*n);
            let wide = if n >= 1 << 31 { n - (1 << 32) } else { n };
            let narrow = if n < (1 << bits) && n >= 1 << (bits - 1) {
                n - (1 << bits)
            } else {
                wide
            };
            integer(narrow)
        }
        (UINT8 | UINT16 | UINT32 | UINT64, MetricValue::IntValue(n)) => integer((*n).into()),
        (UINT64, MetricValue::LongValue(n)) => integer((*n).into()),
        (INT64, MetricValue::LongValue(n)) => integer((*n as i64).into()),
        (INT64, MetricValue::IntValue(n)) => integer((*n).into()),
        (FLOAT | DOUBLE, MetricValue::FloatValue(x)) => Ok(Presented::Number(f64::from(*x)).text()),
        (FLOAT | DOUBLE, MetricValue::DoubleValue(x)) => Ok(Presented::Number(*x).text()),
        (DATETIME, MetricValue::LongValue(ms)) => {
            let ms = i64::try_from(*ms).map_err(|_| wrong())?;
            let t = DateTime::from_timestamp_millis(ms).ok_or_else(wrong)?;
            Ok(if ty == IecType::Date {
                t.format("%Y-%m-%d").to_string()
            } else {
                t.to_rfc3339_opts(chrono::SecondsFormat::Millis, true)
            })
        }
        (STRING, MetricValue::StringValue(s)) => Ok(s.clone()),
        _ => Err(wrong()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_protocol::value::{FormatOptions, Value};

    fn shown(ty: IecType, v: Value) -> Presented {
        let mut text = Vec::new();
        v.format(ty, &FormatOptions::default(), &mut text);
        Presented::of(ty, &text, &FormatOptions::default())
    }

    #[test]
    fn datatypes_and_values_as_spec_3_0_maps_them() {
        // [tck-id-payloads-metric-datatype-value-type] and 6.4.16.
        let cases = [
            (
                IecType::Bool,
                Value::Bool(true),
                11,
                MetricValue::BooleanValue(true),
            ),
            (
                IecType::Sint,
                Value::Signed(-1),
                1,
                MetricValue::IntValue(255),
            ),
            (
                IecType::Int,
                Value::Signed(-2),
                2,
                MetricValue::IntValue(0xfffe),
            ),
            (
                IecType::Dint,
                Value::Signed(-3),
                3,
                MetricValue::IntValue(0xffff_fffd),
            ),
            (
                IecType::Lint,
                Value::Signed(-4),
                4,
                MetricValue::LongValue(u64::MAX - 3),
            ),
            (
                IecType::Byte,
                Value::Unsigned(200),
                5,
                MetricValue::IntValue(200),
            ),
            (
                IecType::Uint,
                Value::Unsigned(60000),
                6,
                MetricValue::IntValue(60000),
            ),
            (
                IecType::Dword,
                Value::Unsigned(4e9 as u64),
                7,
                MetricValue::IntValue(4_000_000_000),
            ),
            (
                IecType::Ulint,
                Value::Unsigned(u64::MAX),
                8,
                MetricValue::LongValue(u64::MAX),
            ),
            (
                IecType::Real,
                Value::Real(22.5),
                9,
                MetricValue::FloatValue(22.5),
            ),
            (
                IecType::Lreal,
                Value::LReal(-0.125),
                10,
                MetricValue::DoubleValue(-0.125),
            ),
            (
                IecType::String(10),
                Value::Str(b"Dobr\xfd".to_vec()),
                12,
                MetricValue::StringValue("Dobrý".into()),
            ),
            (
                IecType::Dt,
                Value::Date(1_795_601_700.123),
                13,
                MetricValue::LongValue(1_795_601_700_123),
            ),
            (
                IecType::Date,
                Value::Date(1_795_564_800.0),
                13,
                MetricValue::LongValue(1_795_564_800_000),
            ),
            (
                IecType::Time,
                Value::Time(3_723_456),
                12,
                MetricValue::StringValue("PT1H2M3.456S".into()),
            ),
            (
                IecType::Tod,
                Value::Time(36_900_123),
                12,
                MetricValue::StringValue("10:15:00.123".into()),
            ),
        ];
        for (ty, v, dt, want) in cases {
            assert_eq!(datatype(ty), dt, "{ty}");
            let got = value(dt, &shown(ty, v)).unwrap();
            assert_eq!(got, want, "{ty}");
            // And back, as a command carrying the same value.
            let text = command_text(ty, Some(&got)).unwrap();
            let back = plccoms_core::present::protocol_text(
                ty,
                text.as_bytes(),
                &FormatOptions::default(),
            );
            assert!(back.is_ok(), "{ty}: {text}");
        }
    }

    #[test]
    fn command_values_checked_against_the_metric_s_type() {
        assert_eq!(
            command_text(IecType::Sint, Some(&MetricValue::IntValue(255))).unwrap(),
            "-1"
        );
        // Sign-extended to 32 bits, as Tahu's Java client sends it.
        assert_eq!(
            command_text(IecType::Sint, Some(&MetricValue::IntValue(0xffff_fffe))).unwrap(),
            "-2"
        );
        assert_eq!(
            command_text(IecType::Int, Some(&MetricValue::IntValue(1234))).unwrap(),
            "1234"
        );
        assert_eq!(
            command_text(IecType::Usint, Some(&MetricValue::IntValue(256))),
            Err(CommandValueError::OutOfRange(256, "UInt8"))
        );
        assert_eq!(
            command_text(IecType::Bool, Some(&MetricValue::BooleanValue(true))).unwrap(),
            "true"
        );
        assert_eq!(
            command_text(IecType::Bool, Some(&MetricValue::StringValue("x".into()))),
            Err(CommandValueError::WrongKind("Boolean"))
        );
        assert_eq!(
            command_text(IecType::Real, Some(&MetricValue::FloatValue(21.5))).unwrap(),
            "21.5"
        );
        assert_eq!(
            command_text(IecType::Real, None),
            Err(CommandValueError::Missing)
        );
        assert_eq!(
            command_text(
                IecType::Dt,
                Some(&MetricValue::LongValue(1_795_601_700_123))
            )
            .unwrap(),
            "2026-11-25T10:15:00.123Z"
        );
        assert_eq!(
            command_text(
                IecType::Date,
                Some(&MetricValue::LongValue(1_795_564_800_000))
            )
            .unwrap(),
            "2026-11-25"
        );
    }

    #[test]
    fn quality_unit_and_description_properties() {
        let props = properties(None, Quality::LinkLost);
        assert_eq!(props.keys, ["Quality"]);
        assert_eq!(
            props.values[0].value,
            Some(PropertyScalar::StringValue("link_lost".into()))
        );
        let var = Var {
            name: b"T".to_vec().into(),
            area: plccoms_protocol::Area::R,
            offset: 0,
            bit: None,
            ty: IecType::Real,
            codec: Default::default(),
            writable: true,
            info: plccoms_core::vars::VarInfo {
                unit: "°C".into(),
                description: "Teplota v hale".into(),
                ..Default::default()
            }
            .boxed(),
        };
        let props = properties(Some(&var), Quality::Good);
        assert_eq!(props.keys, ["Quality", "engUnit", "Description"]);
        let texts: Vec<_> = props
            .values
            .iter()
            .map(|v| (v.r#type, v.value.clone()))
            .collect();
        assert_eq!(
            texts,
            [
                (Some(12), Some(PropertyScalar::StringValue("good".into()))),
                (Some(12), Some(PropertyScalar::StringValue("°C".into()))),
                (
                    Some(12),
                    Some(PropertyScalar::StringValue("Teplota v hale".into()))
                ),
            ]
        );
    }
}
