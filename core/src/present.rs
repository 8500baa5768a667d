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

/// `YYYY-MM-DD` in ASCII digits: chrono's `%Y-%m-%d` also takes a signed
/// year and unpadded fields (`+23220-6-5`), which no face prints back.
fn is_iso_date(text: &[u8]) -> bool {
    text.len() == 10
        && text.iter().enumerate().all(|(at, &c)| match at {
            4 | 7 => c == b'-',
            _ => c.is_ascii_digit(),
        })
}

/// The protocol text a SET takes for a value of type `ty` given in the
/// user's terms (`input`, as [`Presented`] shows values): the reverse of
/// [`Presented::of`] for MQTT's `/set` and other faces that write.
///
/// DATE, DT, TOD and TIME take only their ISO 8601 forms (parsed strictly:
/// a DT needs its zone, `Z` or `+01:00`); an integer type also takes a
/// number without a fraction (`5.0`, `1e3`), as Home Assistant sends a
/// whole number; every other text goes to SET as it is, for SET's own
/// checks. An error names the form expected.
pub fn protocol_text<'a>(
    ty: IecType,
    input: &'a [u8],
    opts: &FormatOptions,
) -> Result<std::borrow::Cow<'a, [u8]>, &'static str> {
    use std::borrow::Cow;
    let text = std::str::from_utf8(input).ok().map(str::trim);
    let value = match ty {
        IecType::Dt => {
            let t = text
                .and_then(|t| DateTime::parse_from_rfc3339(t).ok())
                .ok_or(EXPECTED_DT)?;
            Value::Date(t.timestamp_millis() as f64 / 1000.0)
        }
        IecType::Date => {
            let d = text
                .filter(|t| is_iso_date(t.as_bytes()))
                .and_then(|t| chrono::NaiveDate::parse_from_str(t, "%Y-%m-%d").ok())
                .ok_or(EXPECTED_DATE)?;
            Value::Date(d.and_time(chrono::NaiveTime::MIN).and_utc().timestamp() as f64)
        }
        IecType::Tod => Value::Time(text.and_then(parse_time_of_day).ok_or(EXPECTED_TOD)?),
        IecType::Time => Value::Time(text.and_then(parse_duration).ok_or(EXPECTED_TIME)?),
        ty if is_integer(ty) => match text.map(whole_number) {
            Some(Some(n)) => return Ok(Cow::Owned(n.into_bytes())),
            _ => return Ok(Cow::Borrowed(input)),
        },
        _ => return Ok(Cow::Borrowed(input)),
    };
    let mut out = Vec::new();
    value.format(ty, opts, &mut out);
    Ok(Cow::Owned(out))
}

/// What [`protocol_text`] expects of each time type.
pub const EXPECTED_DT: &str =
    "expected a date and time in ISO 8601 with its zone, as 2026-11-25T10:15:00.123Z";
pub const EXPECTED_DATE: &str = "expected a date in ISO 8601, as 2026-11-25";
pub const EXPECTED_TOD: &str = "expected a time of day, as 10:15:00.123 (HH:MM[:SS[.mmm]])";
pub const EXPECTED_TIME: &str =
    "expected an ISO 8601 duration, as PT1H2M3.456S (P[nD]T[nH][nM][n[.mmm]S])";

fn is_integer(ty: IecType) -> bool {
    !matches!(
        ty,
        IecType::Bool
            | IecType::Real
            | IecType::Lreal
            | IecType::String(_)
            | IecType::Date
            | IecType::Dt
            | IecType::Tod
            | IecType::Time
    )
}

/// `5.0`, `1e3` as `5`, `1000`: a number in JSON's grammar whose value is
/// whole and within 64 bits; `None` for anything else (SET judges it).
fn whole_number(text: &str) -> Option<String> {
    if !text.contains(['.', 'e', 'E']) || text.starts_with('+') {
        return None;
    }
    let x: f64 = text.parse().ok()?;
    (x.is_finite() && x.fract() == 0.0 && x.abs() < 9.0e18).then(|| format!("{}", x as i64))
}

/// `HH:MM`, `HH:MM:SS` or `HH:MM:SS.f` (1 to 3 digits), before 24:00, as
/// milliseconds since midnight.
fn parse_time_of_day(text: &str) -> Option<u32> {
    let two = |s: &str, max: u32| -> Option<u32> {
        (s.len() == 2 && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse().ok())
            .flatten()
            .filter(|&n| n <= max)
    };
    let mut parts = text.splitn(3, ':');
    let h = two(parts.next()?, 23)?;
    let m = two(parts.next()?, 59)?;
    let ms = match parts.next() {
        None => 0,
        Some(rest) => {
            let (s, frac) = rest
                .split_once('.')
                .map_or((rest, None), |(s, f)| (s, Some(f)));
            two(s, 59)? * 1000 + frac.map_or(Some(0), millis)?
        }
    };
    Some((h * 60 + m) * 60_000 + ms)
}

/// 1 to 3 digits after a decimal point as milliseconds.
fn millis(frac: &str) -> Option<u32> {
    if frac.is_empty() || frac.len() > 3 || !frac.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(frac.parse::<u32>().ok()? * 10u32.pow(3 - frac.len() as u32))
}

/// `P[nD]T[nH][nM][n[.f]S]` (or `PnD`) as milliseconds, within TIME's 32
/// bits; at least one part, a fraction only on the seconds.
fn parse_duration(text: &str) -> Option<u32> {
    let rest = text.strip_prefix('P')?;
    let (days, time) = match rest.split_once('T') {
        Some((d, t)) => (d, Some(t)),
        None => (rest, None),
    };
    let mut total: u64 = 0;
    let mut parts = 0;
    let number = |s: &str| -> Option<u64> {
        (!s.is_empty() && s.len() <= 10 && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse().ok())
            .flatten()
    };
    if !days.is_empty() {
        total += number(days.strip_suffix('D')?)? * 86_400_000;
        parts += 1;
    }
    if let Some(mut time) = time {
        if time.is_empty() {
            return None;
        }
        for (unit, ms) in [('H', 3_600_000), ('M', 60_000)] {
            if let Some((n, after)) = time.split_once(unit) {
                total += number(n)? * ms;
                parts += 1;
                time = after;
            }
        }
        if !time.is_empty() {
            let s = time.strip_suffix('S')?;
            let (whole, frac) = s.split_once('.').map_or((s, None), |(w, f)| (w, Some(f)));
            total += number(whole)? * 1000 + u64::from(frac.map_or(Some(0), millis)?);
            parts += 1;
        }
    }
    (parts > 0).then_some(())?;
    u32::try_from(total).ok()
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

    #[test]
    fn user_forms_back_to_protocol_text() {
        let opts = FormatOptions::default();
        let back = |ty: IecType, input: &str| {
            protocol_text(ty, input.as_bytes(), &opts).map(|t| Presented::of(ty, &t, &opts).text())
        };
        // Every form Presented shows reads back to the same value.
        for (ty, shown) in [
            (IecType::Dt, "2026-11-25T10:15:00.123Z"),
            (IecType::Date, "2026-11-25"),
            (IecType::Tod, "10:15:00.123"),
            (IecType::Tod, "00:00:00.000"),
            (IecType::Time, "PT1H2M3.456S"),
            (IecType::Time, "PT0S"),
            (IecType::Time, "PT2H"),
            (IecType::Time, "PT2M0.5S"),
        ] {
            assert_eq!(back(ty, shown).as_deref(), Ok(shown), "{ty}");
        }
        // Other zones and shorter forms.
        assert_eq!(
            back(IecType::Dt, "2026-11-25T11:15:00+01:00").as_deref(),
            Ok("2026-11-25T10:15:00.000Z")
        );
        assert_eq!(back(IecType::Tod, "07:30").as_deref(), Ok("07:30:00.000"));
        assert_eq!(
            back(IecType::Time, "P1DT0.25S").as_deref(),
            Ok("PT24H0.25S")
        );
        // Strict: no zone, no time, out of range, the raw protocol text.
        for (ty, bad, expected) in [
            (IecType::Dt, "2026-11-25T10:15:00", EXPECTED_DT),
            (IecType::Dt, "2026-11-25", EXPECTED_DT),
            (IecType::Dt, "4745318240020496122", EXPECTED_DT),
            (IecType::Date, "2026-11-5", EXPECTED_DATE),
            (IecType::Date, "2026-02-30", EXPECTED_DATE),
            // Ten characters chrono's `%Y-%m-%d` takes (fuzzing found it).
            (IecType::Date, "+23220-6-5", EXPECTED_DATE),
            (IecType::Date, "2026-1-025", EXPECTED_DATE),
            (IecType::Tod, "24:00", EXPECTED_TOD),
            (IecType::Tod, "7:30", EXPECTED_TOD),
            (IecType::Tod, "10:15:00.1234", EXPECTED_TOD),
            (IecType::Time, "PT", EXPECTED_TIME),
            (IecType::Time, "P", EXPECTED_TIME),
            (IecType::Time, "PT1.5M", EXPECTED_TIME),
            (IecType::Time, "PT-1S", EXPECTED_TIME),
            (IecType::Time, "P50D", EXPECTED_TIME),
            (IecType::Time, "1000", EXPECTED_TIME),
            (IecType::Time, "PT\u{ff}S", EXPECTED_TIME),
        ] {
            assert_eq!(back(ty, bad), Err(expected), "{bad}");
        }
        assert_eq!(
            protocol_text(IecType::Time, b"\xffPT1S", &opts),
            Err(EXPECTED_TIME)
        );
        // Numbers: a whole number with a fraction part for an integer type;
        // the rest as it came, for SET to judge.
        let raw = |ty, input: &str| {
            protocol_text(ty, input.as_bytes(), &opts)
                .unwrap()
                .into_owned()
        };
        assert_eq!(raw(IecType::Int, "5.0"), b"5");
        assert_eq!(raw(IecType::Int, "-1e3"), b"-1000");
        assert_eq!(raw(IecType::Int, "5.5"), b"5.5");
        assert_eq!(raw(IecType::Int, "12"), b"12");
        assert_eq!(raw(IecType::Real, "22.3"), b"22.3");
        assert_eq!(raw(IecType::Bool, "true"), b"true");
        assert_eq!(raw(IecType::String(8), "PT1S"), b"PT1S");
    }
}
