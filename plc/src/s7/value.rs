//! How S7's types lie in PLC memory (big-endian, as in a non-optimised
//! block) and become a client's value and back
//! ([`crate::value_codec::Codec::S7`] calls here).
//!
//! | S7 type | bytes | client type |
//! | --- | --- | --- |
//! | BYTE .. LREAL (every IEC number) | its size, big-endian | itself |
//! | `STRING[n]` | 2 + n: max length, actual length, characters | `STRING[n]` |
//! | `WSTRING[n]` | 4 + 2n: max, actual (16 bits each), UTF-16 | `STRING[n]` (cp1250; others become `?`) |
//! | DATE | 2: days since 1990-01-01 | DATE |
//! | TIME | 4: signed milliseconds (a negative one shows as 0) | TIME |
//! | TOD | 4: milliseconds since midnight | TOD |
//! | DATE_AND_TIME | 8, BCD: year (90-99: 1990s, 00-89: 2000s), month, day, hour, minute, second, milliseconds, weekday | DT |
//! | DTL | 12: year (16 bits), month, day, weekday, hour, minute, second, nanoseconds (32 bits) | DT |
//! | S5TIME | 2: time base (10 ms, 100 ms, 1 s, 10 s) and three BCD digits | TIME |
//!
//! A date or time read shows the PLC's clock as it is (no time zone is
//! applied), as a Tecomat PLC's DT does.

use plccoms_protocol::value::Value;
use plccoms_protocol::{cp1250, IecType};

use crate::time::{civil_from_days, days_from_civil};
use crate::value_codec::EncodeError;

/// An S7 type's layout in memory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// An IEC number (or TOD), big-endian.
    Plain(IecType),
    String(u16),
    WString(u16),
    Date,
    Time,
    DateAndTime,
    Dtl,
    S5Time,
}

/// 1990-01-01 in days since 1970.
const DAYS_1990: i64 = 7305;

/// Most characters an S7 STRING holds.
pub const MAX_STRING: u16 = 254;

impl Layout {
    /// The layout of a type as a tag file names it (`INT`, `STRING[20]`,
    /// `WSTRING[10]`, `DATE_AND_TIME`, `DTL`, `S5TIME`), or `None`.
    pub fn parse(text: &str) -> Option<Layout> {
        let upper = text.trim().to_ascii_uppercase();
        let sized = |prefix: &str| -> Option<Option<u16>> {
            let rest = upper.strip_prefix(prefix)?;
            if rest.is_empty() {
                return Some(None);
            }
            let n = rest.strip_prefix('[')?.strip_suffix(']')?.trim();
            Some(
                n.parse()
                    .ok()
                    .filter(|n| (1..=MAX_STRING).contains(n))
                    .or(Some(0)),
            )
        };
        if let Some(n) = sized("WSTRING") {
            return Layout::WString(n.unwrap_or(MAX_STRING)).checked();
        }
        if let Some(n) = sized("STRING") {
            return Layout::String(n.unwrap_or(MAX_STRING)).checked();
        }
        Some(match upper.as_str() {
            "DATE" => Layout::Date,
            "TIME" => Layout::Time,
            "DT" | "DATE_AND_TIME" => Layout::DateAndTime,
            "DTL" => Layout::Dtl,
            "S5TIME" => Layout::S5Time,
            "TOD" | "TIME_OF_DAY" => Layout::Plain(IecType::Tod),
            "CHAR" => Layout::Plain(IecType::Byte),
            other => match IecType::parse(other.as_bytes())? {
                IecType::String(_) | IecType::Date | IecType::Dt | IecType::Time => return None,
                ty => Layout::Plain(ty),
            },
        })
    }

    /// `None` for a string of no characters (a size that did not parse).
    fn checked(self) -> Option<Layout> {
        match self {
            Layout::String(0) | Layout::WString(0) => None,
            other => Some(other),
        }
    }

    /// Bytes in memory.
    pub fn len(self) -> u32 {
        match self {
            Layout::Plain(ty) => ty.size() as u32,
            Layout::String(n) => 2 + u32::from(n),
            Layout::WString(n) => 4 + 2 * u32::from(n),
            Layout::Date | Layout::S5Time => 2,
            Layout::Time => 4,
            Layout::DateAndTime => 8,
            Layout::Dtl => 12,
        }
    }

    pub fn is_empty(self) -> bool {
        false
    }

    /// The type clients see.
    pub fn client_type(self) -> IecType {
        match self {
            Layout::Plain(ty) => ty,
            Layout::String(n) | Layout::WString(n) => IecType::String(n),
            Layout::Date => IecType::Date,
            Layout::Time | Layout::S5Time => IecType::Time,
            Layout::DateAndTime | Layout::Dtl => IecType::Dt,
        }
    }

    /// The client's value of the bytes read (missing ones count as 0).
    pub fn decode(self, bytes: &[u8]) -> Value {
        let mut b = bytes.to_vec();
        b.resize(self.len() as usize, 0);
        match self {
            Layout::Plain(ty) => {
                b.reverse();
                Value::decode(ty, &b)
            }
            Layout::String(n) => {
                let len = usize::from(b[1].min(b[0]).min(n as u8));
                Value::Str(b[2..2 + len].to_vec())
            }
            Layout::WString(n) => {
                let word = |i: usize| u16::from_be_bytes([b[i], b[i + 1]]);
                let len = usize::from(word(2).min(word(0)).min(n));
                let units = (0..len).map(|i| word(4 + 2 * i));
                let text: String = char::decode_utf16(units)
                    .map(|c| c.unwrap_or('?'))
                    .map(|c| {
                        if cp1250::try_encode(c.encode_utf8(&mut [0; 4])).is_some() {
                            c
                        } else {
                            '?'
                        }
                    })
                    .collect();
                Value::Str(cp1250::encode(&text).into_owned())
            }
            Layout::Date => {
                let days = i64::from(u16::from_be_bytes([b[0], b[1]])) + DAYS_1990;
                Value::Date((days * 86_400) as f64)
            }
            Layout::Time => Value::Time(i32::from_be_bytes([b[0], b[1], b[2], b[3]]).max(0) as u32),
            Layout::DateAndTime => {
                let year = i64::from(bcd(b[0]));
                let year = if year < 90 { 2000 + year } else { 1900 + year };
                let ms = u32::from(bcd(b[6])) * 10 + u32::from(b[7] >> 4);
                let f = |i: usize| bcd(b[i]);
                Value::Date(seconds(year, f(1), f(2), f(3), f(4), f(5)) + f64::from(ms) / 1000.0)
            }
            Layout::Dtl => {
                let year = i64::from(u16::from_be_bytes([b[0], b[1]]));
                let ns = u32::from_be_bytes([b[8], b[9], b[10], b[11]]).min(999_999_999);
                let ms = ns / 1_000_000;
                Value::Date(seconds(year, b[2], b[3], b[5], b[6], b[7]) + f64::from(ms) / 1000.0)
            }
            Layout::S5Time => {
                let word = u16::from_be_bytes([b[0], b[1]]);
                let base = [10, 100, 1000, 10_000][usize::from(word >> 12 & 3)];
                let count =
                    u32::from(bcd((word >> 8 & 0x0F) as u8)) * 100 + u32::from(bcd(word as u8));
                Value::Time(count * base)
            }
        }
    }

    /// The bytes that make the variable hold `value`, or why it cannot.
    pub fn encode(self, value: &Value) -> Result<Vec<u8>, EncodeError> {
        let mut out = Vec::with_capacity(self.len() as usize);
        match self {
            Layout::Plain(ty) => {
                value.encode(ty, &mut out);
                out.reverse();
            }
            Layout::String(n) => {
                let text = string_of(value, usize::from(n));
                out.extend_from_slice(&[n as u8, text.len() as u8]);
                out.extend_from_slice(&text);
                out.resize(self.len() as usize, 0);
            }
            Layout::WString(n) => {
                let text = string_of(value, usize::from(n));
                let units: Vec<u16> = cp1250::decode(&text)
                    .encode_utf16()
                    .take(usize::from(n))
                    .collect();
                out.extend_from_slice(&n.to_be_bytes());
                out.extend_from_slice(&(units.len() as u16).to_be_bytes());
                units
                    .iter()
                    .for_each(|u| out.extend_from_slice(&u.to_be_bytes()));
                out.resize(self.len() as usize, 0);
            }
            Layout::Date => {
                let days = (value.as_f64() / 86_400.0).floor() as i64 - DAYS_1990;
                let days = u16::try_from(days).map_err(|_| {
                    EncodeError("an S7 DATE holds 1990-01-01 to 2169-06-06".to_string())
                })?;
                out.extend_from_slice(&days.to_be_bytes());
            }
            Layout::Time => {
                let ms = i32::try_from(millis(value)).map_err(|_| {
                    EncodeError("an S7 TIME holds at most 24d20h31m23s647ms".to_string())
                })?;
                out.extend_from_slice(&ms.to_be_bytes());
            }
            Layout::DateAndTime => {
                let (year, rest) = civil(value.as_f64());
                if !(1990..=2089).contains(&year) {
                    return Err(EncodeError(format!(
                        "DATE_AND_TIME holds the years 1990 to 2089, not {year}"
                    )));
                }
                let [month, day, hour, minute, second, weekday] = rest.fields;
                out.extend([(year % 100) as u8, month, day, hour, minute, second].map(to_bcd));
                out.push(to_bcd((rest.ms / 10) as u8));
                out.push(((rest.ms % 10) as u8) << 4 | (weekday % 7 + 1));
            }
            Layout::Dtl => {
                let (year, rest) = civil(value.as_f64());
                if !(1970..=2262).contains(&year) {
                    return Err(EncodeError(format!(
                        "DTL holds the years 1970 to 2262, not {year}"
                    )));
                }
                let [month, day, hour, minute, second, weekday] = rest.fields;
                out.extend_from_slice(&(year as u16).to_be_bytes());
                out.extend_from_slice(&[month, day, weekday % 7 + 1, hour, minute, second]);
                out.extend_from_slice(&(rest.ms * 1_000_000).to_be_bytes());
            }
            Layout::S5Time => {
                let ms = millis(value);
                let Some((code, base)) = [10u64, 100, 1000, 10_000]
                    .into_iter()
                    .enumerate()
                    .find(|&(_, base)| ms / base <= 999)
                else {
                    return Err(EncodeError("an S5TIME holds at most 2h46m30s".to_string()));
                };
                let count = ms / base;
                let digits = ((count / 100) << 8) | ((count / 10 % 10) << 4) | (count % 10);
                out.extend_from_slice(&(((code as u64) << 12 | digits) as u16).to_be_bytes());
            }
        }
        Ok(out)
    }
}

/// A duration value in milliseconds (TIME is a count of them).
fn millis(value: &Value) -> u64 {
    match value {
        Value::Time(t) => u64::from(*t),
        other => other.as_f64().max(0.0) as u64,
    }
}

fn bcd(b: u8) -> u8 {
    (b >> 4).min(9) * 10 + (b & 0x0F).min(9)
}

fn to_bcd(n: u8) -> u8 {
    ((n / 10 % 10) << 4) | (n % 10)
}

/// A string value's cp1250 bytes, cut to `n`.
fn string_of(value: &Value, n: usize) -> Vec<u8> {
    let mut text = match value {
        Value::Str(s) => s.clone(),
        other => {
            let mut out = Vec::new();
            other.encode(IecType::String(n as u16), &mut out);
            out.retain(|&b| b != 0);
            out
        }
    };
    text.truncate(n);
    text
}

/// Seconds since 1970 of a wall-clock date and time (fields out of range
/// are clamped: a broken clock shows as a date, never a panic).
fn seconds(year: i64, month: u8, day: u8, hour: u8, minute: u8, second: u8) -> f64 {
    let days = days_from_civil(
        year,
        u32::from(month.clamp(1, 12)),
        u32::from(day.clamp(1, 31)),
    );
    (days * 86_400
        + i64::from(hour.min(23)) * 3600
        + i64::from(minute.min(59)) * 60
        + i64::from(second.min(59))) as f64
}

struct Civil {
    /// Month, day, hour, minute, second, weekday (0 = Sunday).
    fields: [u8; 6],
    ms: u32,
}

fn civil(secs: f64) -> (i64, Civil) {
    let total_ms = (secs * 1000.0).round() as i64;
    let days = total_ms.div_euclid(86_400_000);
    let in_day = total_ms.rem_euclid(86_400_000);
    let (year, month, day) = civil_from_days(days);
    let s = in_day / 1000;
    let weekday = crate::time::weekday(days) % 7;
    (
        year,
        Civil {
            fields: [
                month as u8,
                day as u8,
                (s / 3600) as u8,
                (s / 60 % 60) as u8,
                (s % 60) as u8,
                weekday,
            ],
            ms: (in_day % 1000) as u32,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(layout: Layout, value: Value, wire: &[u8]) {
        assert_eq!(layout.encode(&value).unwrap(), wire, "{layout:?}");
        assert_eq!(layout.decode(wire), value, "{layout:?}");
        assert_eq!(wire.len() as u32, layout.len());
    }

    #[test]
    fn numbers_are_big_endian() {
        round_trip(
            Layout::Plain(IecType::Int),
            Value::Signed(-2),
            &[0xFF, 0xFE],
        );
        round_trip(
            Layout::Plain(IecType::Udint),
            Value::Unsigned(0x11223344),
            &[0x11, 0x22, 0x33, 0x44],
        );
        round_trip(
            Layout::Plain(IecType::Real),
            Value::Real(1.5),
            &[0x3F, 0xC0, 0, 0],
        );
        round_trip(
            Layout::Plain(IecType::Lreal),
            Value::LReal(-2.0),
            &[0xC0, 0, 0, 0, 0, 0, 0, 0],
        );
        round_trip(Layout::Plain(IecType::Byte), Value::Unsigned(7), &[7]);
    }

    #[test]
    fn strings_carry_their_lengths() {
        round_trip(
            Layout::String(4),
            Value::Str(b"ab".to_vec()),
            &[4, 2, b'a', b'b', 0, 0],
        );
        // An actual length past the maximum is cut to it.
        assert_eq!(
            Layout::String(2).decode(&[2, 9, b'x', b'y']),
            Value::Str(b"xy".to_vec())
        );
        assert_eq!(
            Layout::String(3)
                .encode(&Value::Str(b"long".to_vec()))
                .unwrap(),
            [3, 3, b'l', b'o', b'n']
        );
        round_trip(
            Layout::WString(2),
            Value::Str(vec![0x8A]),
            &[0, 2, 0, 1, 0x01, 0x60, 0, 0],
        );
    }

    #[test]
    fn dates_and_times() {
        // 2024-02-29 13:45:56.789, a Thursday.
        let secs =
            days_from_civil(2024, 2, 29) as f64 * 86_400.0 + 13.0 * 3600.0 + 45.0 * 60.0 + 56.789;
        let dt = Layout::DateAndTime.encode(&Value::Date(secs)).unwrap();
        assert_eq!(dt, [0x24, 0x02, 0x29, 0x13, 0x45, 0x56, 0x78, 0x95]);
        match Layout::DateAndTime.decode(&dt) {
            Value::Date(back) => assert!((back - secs).abs() < 0.0005),
            other => panic!("{other:?}"),
        }
        let dtl = Layout::Dtl.encode(&Value::Date(secs)).unwrap();
        assert_eq!(&dtl[..8], [0x07, 0xE8, 2, 29, 5, 13, 45, 56]);
        round_trip(
            Layout::Date,
            Value::Date(days_from_civil(1990, 1, 2) as f64 * 86_400.0),
            &[0, 1],
        );
        round_trip(Layout::Time, Value::Time(1500), &[0, 0, 0x05, 0xDC]);
        assert_eq!(
            Layout::Time.decode(&[0xFF, 0xFF, 0xFF, 0xFF]),
            Value::Time(0)
        );
        round_trip(Layout::S5Time, Value::Time(2_500), &[0x02, 0x50]);
        assert_eq!(Layout::S5Time.decode(&[0x12, 0x50]), Value::Time(25_000));
        round_trip(Layout::S5Time, Value::Time(9_990_000), &[0x39, 0x99]);
        assert!(Layout::S5Time.encode(&Value::Time(10_000_000)).is_err());
        assert!(Layout::DateAndTime.encode(&Value::Date(0.0)).is_err());
    }

    #[test]
    fn type_names() {
        assert_eq!(Layout::parse("string[20]"), Some(Layout::String(20)));
        assert_eq!(Layout::parse("STRING"), Some(Layout::String(254)));
        assert_eq!(Layout::parse("STRING[255]"), None);
        assert_eq!(Layout::parse("WSTRING[8]"), Some(Layout::WString(8)));
        assert_eq!(Layout::parse("Date_And_Time"), Some(Layout::DateAndTime));
        assert_eq!(Layout::parse("DTL"), Some(Layout::Dtl));
        assert_eq!(Layout::parse("lreal"), Some(Layout::Plain(IecType::Lreal)));
        assert_eq!(Layout::parse("FOO"), None);
    }
}
