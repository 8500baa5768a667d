//! What the historian records: samples (a variable's value at the time of
//! the poll that read it, with its quality) and events (link loss and
//! return, data not recorded, captures), and values in the types SQLite
//! stores.

use plccoms_protocol::cp1250;
use plccoms_protocol::value::Value;
use plccoms_protocol::IecType;

use plccoms_core::changes::Quality;
use plccoms_core::vars::VarId;

/// One recorded value.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// UTC milliseconds of the poll that read the value.
    pub t: i64,
    pub var: VarId,
    pub value: Stored,
    pub quality: Quality,
    /// UTC milliseconds the PLC stamped (`HISTORY_STAMP`), if paired.
    pub plc_time: Option<i64>,
}

/// A value in the type SQLite stores it in: integers (BOOL, the integer
/// types, TIME and TOD in ms, DATE and DT in ms), reals (REAL, LREAL) and
/// text (STRING, in UTF-8). ULINT and LWORD values above `i64::MAX` are
/// stored as their two's complement (the variable's type tells).
#[derive(Debug, Clone, PartialEq)]
pub enum Stored {
    Int(i64),
    Real(f64),
    Text(String),
    /// SQLite stores a NaN as NULL: a REAL or LREAL that reads back NULL was
    /// NaN.
    Null,
}

impl Stored {
    pub fn from_value(value: &Value) -> Stored {
        match value {
            Value::Bool(b) => Stored::Int(i64::from(*b)),
            Value::Unsigned(u) => Stored::Int(*u as i64),
            Value::Signed(i) => Stored::Int(*i),
            Value::Real(f) if f.is_nan() => Stored::Null,
            Value::Real(f) => Stored::Real(f64::from(*f)),
            Value::LReal(f) if f.is_nan() => Stored::Null,
            Value::LReal(f) => Stored::Real(*f),
            Value::Time(ms) => Stored::Int(i64::from(*ms)),
            Value::Date(seconds) => date_ms(*seconds),
            Value::Str(bytes) => Stored::Text(cp1250::decode(bytes).into_owned()),
        }
    }

    /// The value as a number of milliseconds, for PLC time stamps: DATE and
    /// DT (stored in ms), and integers holding ms since 1970.
    pub fn as_ms(&self) -> Option<i64> {
        match self {
            Stored::Int(ms) => Some(*ms),
            Stored::Real(ms) if ms.is_finite() => Some(ms.round() as i64),
            _ => None,
        }
    }
}

/// DATE and DT hold seconds since 1970 as a real: stored as integer ms when
/// that is exact (always, for the PLC's whole seconds), else as real ms.
fn date_ms(seconds: f64) -> Stored {
    let ms = seconds * 1000.0;
    if ms.is_finite() && ms.fract() == 0.0 && ms.abs() < 9.0e15 {
        Stored::Int(ms as i64)
    } else {
        Stored::Real(ms)
    }
}

/// Whether a variable of type `ty` can hold a PLC time stamp: DATE/DT, or
/// milliseconds since 1970 in a 64-bit integer (a TS48 fits).
pub fn is_stamp_type(ty: IecType) -> bool {
    matches!(
        ty,
        IecType::Dt | IecType::Date | IecType::Lint | IecType::Ulint | IecType::Lword
    )
}

/// Something that happened to the recording, kept beside the samples.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Event {
    /// UTC milliseconds.
    pub t: i64,
    pub kind: EventKind,
    pub detail: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EventKind {
    /// Recording started (server start).
    Start,
    /// Recording stopped (server stop).
    Stop,
    /// The link to the PLC was lost: every recorded variable got a
    /// `link_lost` sample at this time.
    LinkLost,
    /// The link is back: every recorded variable got a sample.
    LinkRestored,
    /// A new public file: variables were resolved again.
    Table,
    /// The recorder did not see some publishes (it was late): changes in
    /// between may be missing.
    Missed,
    /// Samples were dropped (queue full, disk full or size limit).
    Dropped,
    /// A trigger's rising edge: a capture from PRE cycles before.
    Capture,
}

impl EventKind {
    pub fn as_str(self) -> &'static str {
        match self {
            EventKind::Start => "start",
            EventKind::Stop => "stop",
            EventKind::LinkLost => "link_lost",
            EventKind::LinkRestored => "link_restored",
            EventKind::Table => "table",
            EventKind::Missed => "missed",
            EventKind::Dropped => "dropped",
            EventKind::Capture => "capture",
        }
    }
}

/// Quality as stored: 0 good, 1 stale, 2 link lost.
pub fn quality_code(quality: Quality) -> i64 {
    match quality {
        Quality::Good => 0,
        Quality::Stale => 1,
        Quality::LinkLost => 2,
    }
}

pub fn quality_from_code(code: i64) -> Quality {
    match code {
        0 => Quality::Good,
        1 => Quality::Stale,
        _ => Quality::LinkLost,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_in_their_own_type() {
        let cases = [
            (Value::Bool(true), IecType::Bool, Stored::Int(1)),
            (
                Value::Unsigned(u64::MAX),
                IecType::Ulint,
                Stored::Int(-1), // the type tells
            ),
            (Value::Signed(-5), IecType::Int, Stored::Int(-5)),
            (
                Value::Real(0.1),
                IecType::Real,
                Stored::Real(f64::from(0.1f32)),
            ),
            (Value::LReal(f64::NAN), IecType::Lreal, Stored::Null),
            (Value::Real(f32::NAN), IecType::Real, Stored::Null),
            (Value::Time(1234), IecType::Time, Stored::Int(1234)),
            (
                Value::Date(1_700_000_000.0),
                IecType::Dt,
                Stored::Int(1_700_000_000_000),
            ),
            (
                Value::Date(1.0005),
                IecType::Dt,
                Stored::Real(1.0005 * 1000.0),
            ),
            (
                Value::Str(b"P\xF8\xEDli\x9A".to_vec()),
                IecType::String(16),
                Stored::Text("Příliš".into()),
            ),
        ];
        for (value, _ty, stored) in cases {
            assert_eq!(Stored::from_value(&value), stored, "{value:?}");
        }
    }
}
