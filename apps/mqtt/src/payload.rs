//! Message payloads, UTF-8.
//!
//! A value in the `plain` format is the text GET and DIFF print for it
//! (cp1250 turned into UTF-8; a STRING keeps its quotes). In the `json`
//! format it is
//!
//! ```json
//! {"value": 21.5, "ts": "2026-11-22T10:15:00.100Z", "quality": "good"}
//! ```
//!
//! `value` is a JSON number when the printed text is one (every integer,
//! REAL and LREAL, BOOL as 0 or 1, DATE and DT as printed), else a string
//! (a STRING's text without the quotes, `nan`, `inf`); `ts` is the time of
//! the poll that read the value (UTC, milliseconds); `quality` is `good`,
//! `stale` or `link_lost` (see `changes::Quality`).
//!
//! A refused write's `error` payload is the ERROR line a client's SET would
//! have got (plain), or `{"error": "<that line>", "code": 35, "ts": ".."}`.

use chrono::{DateTime, SecondsFormat, Utc};
use plccoms_protocol::cp1250;
use serde_json::json;

use plccoms_core::changes::Quality;
use plccoms_core::config::MqttFormat;

/// `2026-11-22T10:15:00.100Z`.
pub fn iso_ms(unix_ms: i64) -> String {
    DateTime::<Utc>::from_timestamp_millis(unix_ms)
        .unwrap_or_default()
        .to_rfc3339_opts(SecondsFormat::Millis, true)
}

/// The payload of a value printed as `text` (cp1250, as the protocol
/// prints it), read at `unix_ms` with `quality`.
pub fn value(format: MqttFormat, text: &[u8], unix_ms: i64, quality: Quality) -> Vec<u8> {
    match format {
        MqttFormat::Plain => cp1250::decode(text).into_owned().into_bytes(),
        MqttFormat::Json => {
            let value = json_value(text);
            let mut out = Vec::with_capacity(text.len() + 64);
            out.extend_from_slice(b"{\"value\":");
            // Writing a Value to a Vec cannot fail.
            let _ = serde_json::to_writer(&mut out, &value);
            out.extend_from_slice(b",\"ts\":\"");
            out.extend_from_slice(iso_ms(unix_ms).as_bytes());
            out.extend_from_slice(b"\",\"quality\":\"");
            out.extend_from_slice(quality.as_str().as_bytes());
            out.extend_from_slice(b"\"}");
            out
        }
    }
}

/// The JSON form of a printed value: a number if the text is one, else the
/// text (a STRING without its quotes).
fn json_value(text: &[u8]) -> serde_json::Value {
    if let [b'"', inner @ .., b'"'] = text {
        return serde_json::Value::String(cp1250::decode(inner).into_owned());
    }
    let decoded = cp1250::decode(text);
    if is_json_number(&decoded) {
        if let Ok(number) = serde_json::from_str::<serde_json::Number>(&decoded) {
            return serde_json::Value::Number(number);
        }
    }
    serde_json::Value::String(decoded.into_owned())
}

/// JSON's number grammar: `-?(0|[1-9]\d*)(\.\d+)?([eE][+-]?\d+)?`. Checked
/// here so that serde_json never rounds text it would also accept otherwise.
fn is_json_number(text: &str) -> bool {
    let b = text.as_bytes();
    let mut i = usize::from(b.first() == Some(&b'-'));
    let digits = |i: &mut usize| {
        let start = *i;
        while *i < b.len() && b[*i].is_ascii_digit() {
            *i += 1;
        }
        *i - start
    };
    let int_start = i;
    let n = digits(&mut i);
    if n == 0 || (n > 1 && b[int_start] == b'0') {
        return false;
    }
    if b.get(i) == Some(&b'.') {
        i += 1;
        if digits(&mut i) == 0 {
            return false;
        }
    }
    if matches!(b.get(i), Some(b'e' | b'E')) {
        i += 1;
        if matches!(b.get(i), Some(b'+' | b'-')) {
            i += 1;
        }
        if digits(&mut i) == 0 {
            return false;
        }
    }
    i == b.len()
}

/// The payload of a refused write: `line` is the ERROR line (UTF-8).
pub fn error(format: MqttFormat, code: u16, line: &str, unix_ms: i64) -> Vec<u8> {
    match format {
        MqttFormat::Plain => line.as_bytes().to_vec(),
        MqttFormat::Json => json!({"error": line, "code": code, "ts": iso_ms(unix_ms)})
            .to_string()
            .into_bytes(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn json(text: &[u8]) -> serde_json::Value {
        let payload = value(MqttFormat::Json, text, 1_763_806_500_100, Quality::Good);
        serde_json::from_slice(&payload).unwrap()
    }

    #[test]
    fn plain_is_the_protocol_text_in_utf8() {
        let t = value(MqttFormat::Plain, b"\"Dobr\xfd den\"", 0, Quality::Good);
        assert_eq!(String::from_utf8(t).unwrap(), "\"Dobrý den\"");
        assert_eq!(value(MqttFormat::Plain, b"-12", 0, Quality::Stale), b"-12");
    }

    #[test]
    fn json_numbers_strings_time_and_quality() {
        let v = json(b"21.500000");
        assert_eq!(v["value"], serde_json::json!(21.5));
        assert_eq!(v["ts"], "2025-11-22T10:15:00.100Z");
        assert_eq!(v["quality"], "good");
        assert_eq!(
            json(b"18446744073709551615")["value"].to_string(),
            "18446744073709551615"
        );
        assert_eq!(
            json(b"-9223372036854775808")["value"].to_string(),
            "-9223372036854775808"
        );
        assert_eq!(json(b"1.234560e+03")["value"], serde_json::json!(1234.56));
        assert_eq!(json(b"1")["value"], serde_json::json!(1));
        assert_eq!(json(b"\"a \\\"b\\\"\"")["value"], "a \\\"b\\\"");
        assert_eq!(json(b"\"\"")["value"], "");
        assert_eq!(json(b"nan")["value"], "nan");
        assert_eq!(json(b"-inf")["value"], "-inf");
        assert_eq!(json(b"007")["value"], "007");
        let stale = value(MqttFormat::Json, b"1", 0, Quality::LinkLost);
        assert!(String::from_utf8(stale)
            .unwrap()
            .ends_with("\"quality\":\"link_lost\"}"));
    }

    #[test]
    fn json_number_grammar() {
        for yes in ["0", "-0", "12", "1.5", "1e5", "1.5E-07", "-3.25e+10"] {
            assert!(is_json_number(yes), "{yes}");
        }
        for no in ["", "-", "01", "1.", ".5", "1e", "1e+", "+1", "inf", "1 "] {
            assert!(!is_json_number(no), "{no}");
        }
    }

    #[test]
    fn error_payloads() {
        let line = "ERROR:35 Wrong parameter value in request: 'SET:X,a'";
        assert_eq!(error(MqttFormat::Plain, 35, line, 0), line.as_bytes());
        let v: serde_json::Value =
            serde_json::from_slice(&error(MqttFormat::Json, 35, line, 0)).unwrap();
        assert_eq!(
            (v["error"].as_str(), v["code"].as_u64()),
            (Some(line), Some(35))
        );
        assert_eq!(v["ts"], "1970-01-01T00:00:00.000Z");
    }
}
