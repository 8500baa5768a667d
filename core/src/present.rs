//! A value in the user's terms, for every face but the telnet port: MQTT,
//! Home Assistant, the web page, the JSON API and the exports. The telnet
//! port prints the vendor's forms (a DT as the 64 bits of its binary64
//! seconds, a REAL with six decimals); everywhere else a number is a number
//! as short as it round-trips, a BOOL is true or false, and times are
//! ISO 8601:
//!
//! | type | presented as | example |
//! |---|---|---|
//! | BOOL | boolean | `true` |
//! | integers | integer | `-12` |
//! | REAL, LREAL | number, shortest form that reads back the same (NaN and infinities as the strings `nan`, `inf`, `-inf`) | `22.3` |
//! | STRING | text (control bytes stay escaped as `\xHH`) | `"Hall 2"` |
//! | DATE | calendar date, UTC | `"2026-11-25"` |
//! | DT (and a Modbus TS48) | date and time, UTC, milliseconds | `"2026-11-25T10:15:00.123Z"` |
//! | TOD | time of day, milliseconds | `"10:15:00.123"` |
//! | TIME | ISO 8601 duration, milliseconds | `"PT1H2M3.456S"` |
//!
//! The input is the text the protocol prints (what the change stream holds),
//! read back with the section's number settings, so every face shows the
//! value the telnet port shows, in its own form.
//! [`protocol_text`] is the way back, for writes given in these forms.

use std::fmt::Write as _;

use chrono::{DateTime, Utc};
use plccoms_protocol::cp1250;
use plccoms_protocol::value::{FormatOptions, Value};
use plccoms_protocol::IecType;
use serde::{Serialize, Serializer};

/// A value as a user reads it.
#[derive(Debug, Clone, PartialEq)]
pub enum Presented {
    Bool(bool),
    Signed(i64),
    Unsigned(u64),
    /// REAL or LREAL; a REAL widened from its shortest decimal form, so
    /// 22.3f32 is 22.3, not 22.299999237060547.
    Number(f64),
    Text(String),
    /// DATE, `YYYY-MM-DD`.
    Date(String),
    /// DT, `YYYY-MM-DDTHH:MM:SS.mmmZ`.
    DateTime(String),
    /// TOD, `HH:MM:SS.mmm`.
    TimeOfDay(String),
    /// TIME, `PT..H..M..S`.
    Duration(String),
}

impl Presented {
    /// The value of a variable of type `ty` whose protocol text is `text`
    /// (printed with `opts`). A text that does not read back (it cannot
    /// happen for a text the server printed) is presented as text.
    pub fn of(ty: IecType, text: &[u8], opts: &FormatOptions) -> Presented {
        if let IecType::String(_) = ty {
            let inner = match text {
                [b'"', inner @ .., b'"'] => inner,
                other => other,
            };
            return Presented::Text(cp1250::decode(inner).into_owned());
        }
        match Value::parse(ty, text, opts) {
            Ok(value) => Presented::of_value(ty, &value),
            Err(_) => Presented::Text(cp1250::decode(text).into_owned()),
        }
    }

    /// A decoded value of type `ty`.
    pub fn of_value(ty: IecType, value: &Value) -> Presented {
        match (ty, value) {
            (IecType::Bool, v) => Presented::Bool(v.as_f64() != 0.0),
            (IecType::Real, Value::Real(x)) => Presented::Number(shortest_f32(*x)),
            (IecType::Real | IecType::Lreal, v) => Presented::Number(v.as_f64()),
            (IecType::Date, v) => Presented::Date(date(v.as_f64())),
            (IecType::Dt, v) => Presented::DateTime(date_time(v.as_f64())),
            (IecType::Tod, Value::Time(ms)) => Presented::TimeOfDay(time_of_day(*ms)),
            (IecType::Time, Value::Time(ms)) => Presented::Duration(duration(*ms)),
            (_, Value::Signed(n)) => Presented::Signed(*n),
            (_, Value::Unsigned(n)) => Presented::Unsigned(*n),
            (_, Value::Str(bytes)) => Presented::Text(cp1250::decode(bytes).into_owned()),
            (_, v) => Presented::Number(v.as_f64()),
        }
    }

    /// The value as plain text: numbers in their shortest form, times as
    /// ISO 8601, `true`/`false`.
    pub fn text(&self) -> String {
        match self {
            Presented::Bool(b) => b.to_string(),
            Presented::Signed(n) => n.to_string(),
            Presented::Unsigned(n) => n.to_string(),
            Presented::Number(x) => number_text(*x),
            Presented::Text(s)
            | Presented::Date(s)
            | Presented::DateTime(s)
            | Presented::TimeOfDay(s)
            | Presented::Duration(s) => s.clone(),
        }
    }

    /// The value as a number, where it is one (BOOL as 0 or 1): what a
    /// numeric column or a chart takes.
    pub fn as_number(&self) -> Option<f64> {
        match self {
            Presented::Bool(b) => Some(f64::from(u8::from(*b))),
            Presented::Signed(n) => Some(*n as f64),
            Presented::Unsigned(n) => Some(*n as f64),
            Presented::Number(x) if x.is_finite() => Some(*x),
            _ => None,
        }
    }
}

impl Serialize for Presented {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            Presented::Bool(b) => serializer.serialize_bool(*b),
            Presented::Signed(n) => serializer.serialize_i64(*n),
            Presented::Unsigned(n) => serializer.serialize_u64(*n),
            Presented::Number(x) if x.is_finite() => serializer.serialize_f64(*x),
            // JSON has no NaN or infinity.
            Presented::Number(x) => serializer.serialize_str(&number_text(*x)),
            Presented::Text(s)
            | Presented::Date(s)
            | Presented::DateTime(s)
            | Presented::TimeOfDay(s)
            | Presented::Duration(s) => serializer.serialize_str(s),
        }
    }
}

/// 22.3f32 as 22.3: the shortest decimal that reads back as the same f32,
/// widened.
fn shortest_f32(x: f32) -> f64 {
    if !x.is_finite() {
        return f64::from(x);
    }
    format!("{x}").parse().unwrap_or(f64::from(x))
}

fn number_text(x: f64) -> String {
    if x.is_nan() {
        "nan".into()
    } else if x.is_infinite() {
        if x > 0.0 { "inf" } else { "-inf" }.into()
    } else {
        format!("{x}")
    }
}

fn utc(seconds: f64) -> Option<DateTime<Utc>> {
    if !seconds.is_finite() {
        return None;
    }
    DateTime::<Utc>::from_timestamp_millis((seconds * 1000.0).round() as i64)
}

/// `YYYY-MM-DD` of seconds since 1970, UTC.
fn date(seconds: f64) -> String {
    utc(seconds).map_or_else(
        || number_text(seconds),
        |t| t.format("%Y-%m-%d").to_string(),
    )
}

/// `YYYY-MM-DDTHH:MM:SS.mmmZ` of seconds since 1970.
fn date_time(seconds: f64) -> String {
    utc(seconds).map_or_else(
        || number_text(seconds),
        |t| t.format("%Y-%m-%dT%H:%M:%S%.3fZ").to_string(),
    )
}

/// `HH:MM:SS.mmm` of milliseconds since midnight (a day and more wraps
/// as the PLC's clock would not; shown as hours past 24).
fn time_of_day(ms: u32) -> String {
    let (h, m, s, ms) = (ms / 3_600_000, ms / 60_000 % 60, ms / 1000 % 60, ms % 1000);
    format!("{h:02}:{m:02}:{s:02}.{ms:03}")
}

/// ISO 8601 duration of milliseconds: `PT1H2M3.456S`, `PT0S`.
fn duration(ms: u32) -> String {
    let (h, m, s, ms) = (ms / 3_600_000, ms / 60_000 % 60, ms / 1000 % 60, ms % 1000);
    let mut out = String::from("PT");
    if h > 0 {
        let _ = write!(out, "{h}H");
    }
    if m > 0 {
        let _ = write!(out, "{m}M");
    }
    if s > 0 || ms > 0 || (h == 0 && m == 0) {
        let _ = write!(out, "{s}");
        if ms > 0 {
            let _ = write!(out, ".{ms:03}");
            while out.ends_with('0') {
                out.pop();
            }
        }
        out.push('S');
    }
    out
}

/// A value as a user writes it (the forms [`Presented`] shows) as the text
/// the protocol reads, for `Section::write`: a DATE as `2026-11-25`, a DT
/// as RFC 3339 (`2026-11-25T10:15:00.123Z`; without an offset, UTC), a TOD
/// as `10:15:00.123`, a TIME as an ISO 8601 duration (`PT1H2M3.456S`,
/// `P1DT2H`). Anything else, and a time type's protocol form (digits),
/// passes unchanged: the protocol's parser judges it, as it does a SET's.
pub fn protocol_text(ty: IecType, text: &str, opts: &FormatOptions) -> Result<Vec<u8>, String> {
    let text = text.trim();
    let protocol_form = !text.is_empty()
        && text
            .bytes()
            .all(|b| b.is_ascii_digit() || (opts.date_time_decimal && b == b'.'));
    let value = match ty {
        IecType::Date | IecType::Dt if !protocol_form => {
            let ms = parse_date_time(text).ok_or_else(|| {
                format!("'{text}' is not a date and time (e.g. 2026-11-25T10:15:00Z)")
            })?;
            // A DATE holds the day's midnight.
            let ms = if ty == IecType::Date {
                ms.div_euclid(86_400_000) * 86_400_000
            } else {
                ms
            };
            Value::Date(ms as f64 / 1000.0)
        }
        IecType::Tod if !protocol_form => Value::Time(
            parse_time_of_day(text)
                .ok_or_else(|| format!("'{text}' is not a time of day (e.g. 10:15:00.123)"))?,
        ),
        IecType::Time if !protocol_form => Value::Time(
            parse_duration(text)
                .ok_or_else(|| format!("'{text}' is not a duration (e.g. PT1H2M3.5S)"))?,
        ),
        _ => return Ok(cp1250::encode(text).into_owned()),
    };
    let mut out = Vec::new();
    value.format(ty, opts, &mut out);
    Ok(out)
}

/// UTC milliseconds of an RFC 3339 time, a date and time without an offset
/// (UTC), or a date (its midnight, UTC).
fn parse_date_time(text: &str) -> Option<i64> {
    if let Ok(t) = DateTime::parse_from_rfc3339(text) {
        return Some(t.timestamp_millis());
    }
    for format in [
        "%Y-%m-%dT%H:%M:%S%.f",
        "%Y-%m-%d %H:%M:%S%.f",
        "%Y-%m-%dT%H:%M",
    ] {
        if let Ok(t) = chrono::NaiveDateTime::parse_from_str(text, format) {
            return Some(t.and_utc().timestamp_millis());
        }
    }
    let day = chrono::NaiveDate::parse_from_str(text, "%Y-%m-%d").ok()?;
    Some(day.and_hms_opt(0, 0, 0)?.and_utc().timestamp_millis())
}

/// Milliseconds since midnight of `HH:MM`, `HH:MM:SS` or `HH:MM:SS.fff`.
fn parse_time_of_day(text: &str) -> Option<u32> {
    let mut parts = text.split(':');
    let (h, m) = (parts.next()?, parts.next()?);
    let s = parts.next().unwrap_or("0");
    if parts.next().is_some() {
        return None;
    }
    let whole = |t: &str, max: u32| -> Option<u32> {
        (!t.is_empty() && t.len() <= 2 && t.bytes().all(|b| b.is_ascii_digit()))
            .then(|| t.parse().ok())
            .flatten()
            .filter(|n| *n <= max)
    };
    let (h, m) = (whole(h, 23)?, whole(m, 59)?);
    let (s, frac) = s.split_once('.').unwrap_or((s, ""));
    let ms = milliseconds(frac)?;
    Some(h * 3_600_000 + m * 60_000 + whole(s, 59)? * 1000 + ms)
}

/// Milliseconds of a fraction's digits (`5` is 500, `123` 123; more
/// digits are rounded off); `""` is 0.
fn milliseconds(digits: &str) -> Option<u32> {
    if !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let mut padded: String = digits.chars().take(4).collect();
    while padded.len() < 4 {
        padded.push('0');
    }
    let tenths_of_ms: u32 = padded.parse().ok()?;
    Some((tenths_of_ms + 5) / 10)
}

/// Milliseconds of an ISO 8601 duration of days, hours, minutes and
/// seconds (`P1DT2H`, `PT1H2M3.456S`, `PT0S`); `None` past a TIME's range.
fn parse_duration(text: &str) -> Option<u32> {
    let upper = text.to_ascii_uppercase();
    let rest = upper.strip_prefix('P')?;
    let (days, time) = match rest.split_once('T') {
        Some((days, time)) => (days, Some(time)),
        None => (rest, None),
    };
    let mut total: u64 = 0;
    let mut any = false;
    if !days.is_empty() {
        let n: u64 = days.strip_suffix('D')?.parse().ok()?;
        total = n.checked_mul(86_400_000)?;
        any = true;
    }
    if let Some(mut time) = time {
        for (unit, scale) in [('H', 3_600_000u64), ('M', 60_000)] {
            if let Some((n, after)) = time.split_once(unit) {
                if n.is_empty() || !n.bytes().all(|b| b.is_ascii_digit()) {
                    return None;
                }
                total = total.checked_add(n.parse::<u64>().ok()?.checked_mul(scale)?)?;
                time = after;
                any = true;
            }
        }
        if !time.is_empty() {
            let seconds = time.strip_suffix('S')?;
            let (whole, frac) = seconds.split_once('.').unwrap_or((seconds, ""));
            if whole.is_empty() || !whole.bytes().all(|b| b.is_ascii_digit()) {
                return None;
            }
            let ms = whole.parse::<u64>().ok()?.checked_mul(1000)?;
            total = total
                .checked_add(ms)?
                .checked_add(u64::from(milliseconds(frac)?))?;
            any = true;
        }
    }
    if !any {
        return None;
    }
    u32::try_from(total).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn printed(ty: IecType, value: Value) -> Vec<u8> {
        let mut out = Vec::new();
        value.format(ty, &FormatOptions::default(), &mut out);
        out
    }

    fn of(ty: IecType, value: Value) -> Presented {
        Presented::of(ty, &printed(ty, value), &FormatOptions::default())
    }

    #[test]
    fn times_are_iso_8601() {
        // 2026-11-25T10:15:00.123Z
        let t = 1_795_601_700.123;
        let dt = printed(IecType::Dt, Value::Date(t));
        assert!(dt.iter().all(u8::is_ascii_digit), "telnet keeps the bits");
        assert_eq!(
            of(IecType::Dt, Value::Date(t)),
            Presented::DateTime("2026-11-25T10:15:00.123Z".into())
        );
        assert_eq!(
            of(IecType::Date, Value::Date(1_795_564_800.0)),
            Presented::Date("2026-11-25".into())
        );
        assert_eq!(
            of(IecType::Tod, Value::Time(36_900_123)),
            Presented::TimeOfDay("10:15:00.123".into())
        );
        assert_eq!(
            of(IecType::Time, Value::Time(3_723_456)),
            Presented::Duration("PT1H2M3.456S".into())
        );
        assert_eq!(of(IecType::Time, Value::Time(0)).text(), "PT0S");
        assert_eq!(of(IecType::Time, Value::Time(120_500)).text(), "PT2M0.5S");
        assert_eq!(of(IecType::Time, Value::Time(7_200_000)).text(), "PT2H");
    }

    #[test]
    fn with_date_time_decimal_the_seconds_read_back_too() {
        let opts = FormatOptions {
            date_time_decimal: true,
            ..FormatOptions::default()
        };
        let mut text = Vec::new();
        Value::Date(1_795_601_700.5).format(IecType::Dt, &opts, &mut text);
        assert_eq!(
            Presented::of(IecType::Dt, &text, &opts),
            Presented::DateTime("2026-11-25T10:15:00.500Z".into())
        );
    }

    #[test]
    fn numbers_are_numbers_in_their_shortest_form() {
        assert_eq!(printed(IecType::Real, Value::Real(22.3)), b"22.299999");
        let real = of(IecType::Real, Value::Real(22.3));
        assert_eq!(real, Presented::Number(22.3));
        assert_eq!(serde_json::to_string(&real).unwrap(), "22.3");
        assert_eq!(real.text(), "22.3");
        assert_eq!(
            serde_json::to_string(&of(IecType::Int, Value::Signed(-12))).unwrap(),
            "-12"
        );
        assert_eq!(
            serde_json::to_string(&of(IecType::Ulint, Value::Unsigned(u64::MAX))).unwrap(),
            "18446744073709551615"
        );
        assert_eq!(of(IecType::Bool, Value::Bool(true)), Presented::Bool(true));
        assert_eq!(of(IecType::Bool, Value::Bool(true)).as_number(), Some(1.0));
        let nan = of(IecType::Lreal, Value::LReal(f64::NAN));
        assert_eq!(serde_json::to_string(&nan).unwrap(), "\"nan\"");
        assert_eq!(nan.as_number(), None);
    }

    /// A Modbus tag's text (a scaled value in its shortest form, a REAL with
    /// the tag file's decimals) reads back as the value meant.
    #[test]
    fn a_tag_files_printed_values_read_back() {
        let file = plccoms_plc::modbus::tags::parse(
            b"name,type,table,address,scale,decimals\n\
              tenths,INT,holding,0,0.1\n\
              two,INT,holding,1,0.1,2\n\
              real,REAL,holding,2,,1\n",
        );
        let opts = FormatOptions::default();
        let cases: [(usize, &[u8], &str, f64); 4] = [
            (0, &223i16.to_be_bytes(), "22.3", 22.3),
            (0, &250i16.to_be_bytes(), "25", 25.0),
            (1, &223i16.to_be_bytes(), "22.30", 22.3),
            (2, &22.3f32.to_be_bytes(), "22.3", 22.3),
        ];
        for (index, bytes, text, number) in cases {
            let var = file.tags[index].var();
            let mut printed = Vec::new();
            var.format(&var.decode(bytes), &opts, &mut printed);
            assert_eq!(printed, text.as_bytes());
            assert_eq!(
                Presented::of(var.ty, &printed, &opts),
                Presented::Number(number),
                "{text}"
            );
        }
    }

    #[test]
    fn strings_lose_their_quotes_and_keep_their_escapes() {
        let ty = IecType::String(16);
        let text = printed(ty, Value::Str(b"Hall \x01\x9a".to_vec()));
        assert_eq!(
            Presented::of(ty, &text, &FormatOptions::default()),
            Presented::Text("Hall \\x01š".into())
        );
    }

    #[test]
    fn a_text_that_does_not_read_back_is_text() {
        assert_eq!(
            Presented::of(IecType::Int, b"abc", &FormatOptions::default()),
            Presented::Text("abc".into())
        );
    }

    fn back(ty: IecType, text: &str) -> Result<Vec<u8>, String> {
        protocol_text(ty, text, &FormatOptions::default())
    }

    #[test]
    fn iso_times_go_back_to_the_protocols_text() {
        let opts = FormatOptions::default();
        for (ty, user) in [
            (IecType::Dt, "2026-11-25T10:15:00.123Z"),
            (IecType::Date, "2026-11-25"),
            (IecType::Tod, "10:15:00.123"),
            (IecType::Time, "PT1H2M3.456S"),
            (IecType::Time, "PT0S"),
            (IecType::Time, "PT2M0.5S"),
        ] {
            let text = back(ty, user).unwrap();
            assert_eq!(Presented::of(ty, &text, &opts).text(), user, "{ty}");
        }
        // Other offsets, no offset, a bare date; days in a duration.
        let dt = |t: &str| Presented::of(IecType::Dt, &back(IecType::Dt, t).unwrap(), &opts);
        assert_eq!(
            dt("2026-11-25T11:15:00+01:00").text(),
            "2026-11-25T10:15:00.000Z"
        );
        assert_eq!(dt("2026-11-25 10:15:00").text(), "2026-11-25T10:15:00.000Z");
        assert_eq!(dt("2026-11-25").text(), "2026-11-25T00:00:00.000Z");
        let date = back(IecType::Date, "2026-11-25T23:59:59Z").unwrap();
        assert_eq!(
            Presented::of(IecType::Date, &date, &opts).text(),
            "2026-11-25"
        );
        assert_eq!(back(IecType::Time, "P1DT2H").unwrap(), b"93600000");
        assert_eq!(back(IecType::Tod, "10:15").unwrap(), b"36900000");
    }

    #[test]
    fn other_text_passes_and_bad_times_are_named() {
        // The protocol's own forms, and every other type, pass unchanged.
        assert_eq!(
            back(IecType::Dt, "4745317952616660992").unwrap(),
            b"4745317952616660992"
        );
        assert_eq!(back(IecType::Time, "1500").unwrap(), b"1500");
        assert_eq!(back(IecType::Real, "20.5").unwrap(), b"20.5");
        assert_eq!(back(IecType::Bool, "true").unwrap(), b"true");
        for (ty, bad) in [
            (IecType::Dt, "yesterday"),
            (IecType::Date, "2026-13-01"),
            (IecType::Tod, "24:00:00"),
            (IecType::Tod, "10:15:00:00"),
            (IecType::Time, "PT"),
            (IecType::Time, "P1H"),
            (IecType::Time, "PT-1S"),
            (IecType::Time, "P50D"),
            (IecType::Dt, ""),
        ] {
            let error = back(ty, bad).unwrap_err();
            assert!(error.contains(&format!("'{bad}'")), "{ty} {bad}: {error}");
        }
    }
}
