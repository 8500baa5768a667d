//! Message payloads, UTF-8, with values in the user's terms
//! ([`Presented`]: what the web page and the exports show too, never the
//! telnet port's vendor forms).
//!
//! | type | `plain` | `json` `value` |
//! |---|---|---|
//! | BOOL | `true` / `false` | `true` / `false` |
//! | integers | `-12` | `-12` |
//! | REAL, LREAL | `22.3` (shortest form that reads back the same; `nan`, `inf`, `-inf`) | `22.3` (`"nan"`, `"inf"`, `"-inf"`) |
//! | STRING | the text, without quotes (`\xHH` for control bytes) | `"the text"` |
//! | DATE | `2026-11-25` | `"2026-11-25"` |
//! | DT (and a Modbus TS48) | `2026-11-25T10:15:00.123Z` (UTC) | `"2026-11-25T10:15:00.123Z"` |
//! | TOD | `10:15:00.123` | `"10:15:00.123"` |
//! | TIME | `PT1H2M3.456S` (ISO 8601 duration) | `"PT1H2M3.456S"` |
//!
//! In the `json` format a value is
//!
//! ```json
//! {"value": 21.5, "ts": "2026-11-22T10:15:00.100Z", "quality": "good"}
//! ```
//!
//! `ts` is the time of the poll that read the value (UTC, milliseconds);
//! `quality` is `good`, `stale` or `link_lost` (see `changes::Quality`).
//! A `plain` empty STRING is an empty message, which a broker takes as
//! clearing the retained one: `json` tells an empty text from no value.
//!
//! A refused write's `error` payload is the ERROR line a client's SET would
//! have got (plain), or `{"error": "<that line>", "code": 35, "ts": ".."}`.

use chrono::{DateTime, SecondsFormat, Utc};
use serde_json::json;

use plccoms_core::changes::Quality;
use plccoms_core::config::MqttFormat;
use plccoms_core::present::Presented;

/// `2026-11-22T10:15:00.100Z`.
pub fn iso_ms(unix_ms: i64) -> String {
    DateTime::<Utc>::from_timestamp_millis(unix_ms)
        .unwrap_or_default()
        .to_rfc3339_opts(SecondsFormat::Millis, true)
}

/// The payload of `value`, read at `unix_ms` with `quality`.
pub fn value(format: MqttFormat, value: &Presented, unix_ms: i64, quality: Quality) -> Vec<u8> {
    match format {
        MqttFormat::Plain => value.text().into_bytes(),
        MqttFormat::Json => json!({
            "value": value,
            "ts": iso_ms(unix_ms),
            "quality": quality.as_str(),
        })
        .to_string()
        .into_bytes(),
    }
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
    use plccoms_protocol::value::{FormatOptions, Value};
    use plccoms_protocol::IecType;

    /// The payloads of a value of `ty` as the protocol printed it.
    fn payloads(ty: IecType, value: Value) -> (String, serde_json::Value) {
        let opts = FormatOptions::default();
        let mut text = Vec::new();
        value.format(ty, &opts, &mut text);
        let shown = Presented::of(ty, &text, &opts);
        let plain = super::value(MqttFormat::Plain, &shown, 0, Quality::Good);
        let json = super::value(MqttFormat::Json, &shown, 1_763_806_500_100, Quality::Good);
        (
            String::from_utf8(plain).unwrap(),
            serde_json::from_slice(&json).unwrap(),
        )
    }

    #[test]
    fn values_in_the_user_s_terms_in_both_formats() {
        let cases = [
            (IecType::Bool, Value::Bool(true), "true", json!(true)),
            (IecType::Int, Value::Signed(-12), "-12", json!(-12)),
            (IecType::Real, Value::Real(22.3), "22.3", json!(22.3)),
            (
                IecType::Ulint,
                Value::Unsigned(u64::MAX),
                "18446744073709551615",
                json!(u64::MAX),
            ),
            (IecType::Lreal, Value::LReal(f64::NAN), "nan", json!("nan")),
            (
                IecType::String(20),
                Value::Str(b"Dobr\xfd den".to_vec()),
                "Dobrý den",
                json!("Dobrý den"),
            ),
            (IecType::String(20), Value::Str(Vec::new()), "", json!("")),
            (
                IecType::Dt,
                Value::Date(1_795_601_700.123),
                "2026-11-25T10:15:00.123Z",
                json!("2026-11-25T10:15:00.123Z"),
            ),
            (
                IecType::Date,
                Value::Date(1_795_564_800.0),
                "2026-11-25",
                json!("2026-11-25"),
            ),
            (
                IecType::Tod,
                Value::Time(36_900_123),
                "10:15:00.123",
                json!("10:15:00.123"),
            ),
            (
                IecType::Time,
                Value::Time(3_723_456),
                "PT1H2M3.456S",
                json!("PT1H2M3.456S"),
            ),
        ];
        for (ty, v, plain, value) in cases {
            let (p, j) = payloads(ty, v);
            assert_eq!((p.as_str(), &j["value"]), (plain, &value), "{ty}");
            assert_eq!(j["ts"], "2025-11-22T10:15:00.100Z");
            assert_eq!(j["quality"], "good");
        }
        let stale = value(
            MqttFormat::Json,
            &Presented::Signed(1),
            0,
            Quality::LinkLost,
        );
        let stale: serde_json::Value = serde_json::from_slice(&stale).unwrap();
        assert_eq!(stale["quality"], "link_lost");
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
