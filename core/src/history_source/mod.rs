//! Recorded history as the apps read it: the web page's `/api/history` and
//! chart ask a [`HistorySource`], the historian implements it, start-up
//! wires the one to the other. Here, below both, so that neither app
//! imports the other; so are the times both take, the CSV formula guard
//! and the one row shape both write ([`csv_row`], [`json_row`]: README,
//! "Reading it back").

pub mod time;

use std::io::Write as _;
use std::sync::Arc;

use futures::stream::BoxStream;

use crate::changes::Quality;
use crate::present::Presented;

/// One row of a history read: a sample of a variable, or a marker row
/// (`__LINK`, `__SERVER`, `__DAMAGED`, `__ERROR`) that a reader must take
/// for a gap.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// UTC milliseconds: the PLC's stamp where it stamped the sample, else
    /// the time of the poll that read it.
    pub unix_ms: i64,
    /// The variable's name, or a marker's.
    pub name: Arc<str>,
    /// `None` where the row has no value (a marker row).
    pub value: Option<Presented>,
    pub quality: RowQuality,
}

/// A row's `quality`: a sample's, or a marker's. Anything but `Good` is a
/// gap for a reader who forward-fills.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum RowQuality {
    Good,
    Stale,
    LinkLost,
    /// The server (and so the recording) was stopped: `__SERVER` rows.
    Stopped,
    /// Samples of a damaged packed block are left out: `__DAMAGED` rows.
    Damaged,
    /// The recorder missed changes (it lagged past its bound) or dropped
    /// samples (queue or disk full): `__RECORDER` rows.
    Missed,
    /// The read failed or was cut off here: an `__ERROR` row, the last.
    Error,
}

impl RowQuality {
    pub fn as_str(self) -> &'static str {
        match self {
            RowQuality::Good => "good",
            RowQuality::Stale => "stale",
            RowQuality::LinkLost => "link_lost",
            RowQuality::Stopped => "stopped",
            RowQuality::Damaged => "damaged",
            RowQuality::Missed => "missed",
            RowQuality::Error => "error",
        }
    }
}

impl From<Quality> for RowQuality {
    fn from(quality: Quality) -> RowQuality {
        match quality {
            Quality::Good => RowQuality::Good,
            Quality::Stale => RowQuality::Stale,
            Quality::LinkLost => RowQuality::LinkLost,
        }
    }
}

/// Marker rows' names.
pub const LINK: &str = "__LINK";
pub const SERVER: &str = "__SERVER";
pub const DAMAGED: &str = "__DAMAGED";
pub const RECORDER: &str = "__RECORDER";
pub const ERROR: &str = "__ERROR";

/// What is asked of the historian.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HistoryQuery {
    pub section: String,
    /// Variable masks (`*` wildcards, any case), as EN: takes them.
    pub masks: Vec<String>,
    /// UTC milliseconds, both ends included.
    pub from_ms: i64,
    pub to_ms: i64,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HistoryError {
    /// The section is not recorded (404).
    #[error("section '{0}' is not recorded by the historian")]
    UnknownSection(String),
    /// Reading the records failed (500, or the end of a started body).
    #[error("{0}")]
    Failed(String),
}

pub type SampleStream = BoxStream<'static, Result<Sample, HistoryError>>;

/// The historian, as the web server reads it.
pub trait HistorySource: Send + Sync {
    /// The rows of `query.section`'s variables matching `query.masks` from
    /// `from_ms` to `to_ms`, marker rows included, oldest first, streamed
    /// as they are read.
    fn samples(&self, query: HistoryQuery) -> Result<SampleStream, HistoryError>;
}

/// Whether a spreadsheet would take a text cell for a formula (OWASP "CSV
/// injection"): it begins with `=`, `+`, `-`, `@`, a tab or a carriage
/// return and does not read as a number. Such a cell is written with a `'`
/// before it, which spreadsheets show as text; numbers (negative ones
/// included) are never changed.
pub fn runs_as_formula(text: &[u8]) -> bool {
    matches!(
        text.first(),
        Some(b'=' | b'+' | b'-' | b'@' | b'\t' | b'\r')
    ) && !std::str::from_utf8(text).is_ok_and(|t| t.parse::<f64>().is_ok())
}

// ---------------------------------------------------------------------------
// The row shape: `time,name,value,text,quality`.

/// A value split into the row's two columns.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Split<'a> {
    /// For `value`: a finite number (BOOL as 0/1), in [`Presented`]'s form.
    Number(&'a Presented),
    /// For `text`: a string, DATE, DT, TOD or TIME in [`Presented`]'s form,
    /// or a NaN or infinity (`nan`, `inf`, `-inf`: no JSON number holds them).
    Text(&'a Presented),
}

pub fn split(value: &Presented) -> Split<'_> {
    match value {
        Presented::Bool(_) | Presented::Signed(_) | Presented::Unsigned(_) => Split::Number(value),
        Presented::Number(x) if x.is_finite() => Split::Number(value),
        _ => Split::Text(value),
    }
}

/// Appends a number's text: BOOL as 0/1, integers in full, reals as
/// [`Presented::text`] writes them (the shortest form that reads back the
/// same; a valid JSON number when finite).
pub fn number_text(value: &Presented, out: &mut Vec<u8>) {
    match value {
        Presented::Bool(b) => out.push(if *b { b'1' } else { b'0' }),
        Presented::Signed(n) => {
            let _ = write!(out, "{n}");
        }
        Presented::Unsigned(n) => {
            let _ = write!(out, "{n}");
        }
        Presented::Number(x) if x.is_finite() => {
            let _ = write!(out, "{x}");
        }
        other => out.extend_from_slice(other.text().as_bytes()),
    }
}

/// The header [`csv_row`] writes under.
pub const CSV_HEADER: &[u8] = b"time,name,value,text,quality\n";

/// Appends a CSV field: quoted when it holds a comma, a quote or a line
/// end, or when `quote` (an empty string, so it differs from no value).
pub fn csv_field(field: &[u8], quote: bool, out: &mut Vec<u8>) {
    let needs = quote
        || field
            .iter()
            .any(|b| matches!(b, b',' | b'"' | b'\r' | b'\n'));
    if !needs {
        out.extend_from_slice(field);
        return;
    }
    out.push(b'"');
    for &b in field {
        if b == b'"' {
            out.push(b'"');
        }
        out.push(b);
    }
    out.push(b'"');
}

/// A CSV field of text: guarded against formulas ([`runs_as_formula`]),
/// then as [`csv_field`]; an empty string is `""`.
pub fn csv_text(field: &[u8], out: &mut Vec<u8>) {
    if runs_as_formula(field) {
        let mut guarded = Vec::with_capacity(field.len() + 1);
        guarded.push(b'\'');
        guarded.extend_from_slice(field);
        csv_field(&guarded, false, out);
    } else {
        csv_field(field, field.is_empty(), out);
    }
}

/// Appends one CSV row `time,name,value,text,quality` (and its line end):
/// time ISO 8601 UTC with ms; `value` a number or empty; `text` a string,
/// date or time (or `nan`/`inf`/`-inf`), else empty.
pub fn csv_row(
    unix_ms: i64,
    name: &str,
    value: Option<&Presented>,
    quality: RowQuality,
    out: &mut Vec<u8>,
) {
    time::iso(unix_ms, out);
    out.push(b',');
    csv_text(name.as_bytes(), out);
    out.push(b',');
    match value.map(split) {
        Some(Split::Number(v)) => {
            number_text(v, out);
            out.push(b',');
        }
        Some(Split::Text(v)) => {
            out.push(b',');
            csv_text(v.text().as_bytes(), out);
        }
        None => out.push(b','),
    }
    out.push(b',');
    out.extend_from_slice(quality.as_str().as_bytes());
    out.push(b'\n');
}

/// Appends `text` as a JSON string.
pub fn json_string(text: &str, out: &mut Vec<u8>) {
    out.push(b'"');
    for c in text.chars() {
        match c {
            '"' => out.extend_from_slice(b"\\\""),
            '\\' => out.extend_from_slice(b"\\\\"),
            '\n' => out.extend_from_slice(b"\\n"),
            '\r' => out.extend_from_slice(b"\\r"),
            '\t' => out.extend_from_slice(b"\\t"),
            c if (c as u32) < 0x20 => {
                let _ = write!(out, "\\u{:04x}", c as u32);
            }
            c => {
                let mut buf = [0u8; 4];
                out.extend_from_slice(c.encode_utf8(&mut buf).as_bytes());
            }
        }
    }
    out.push(b'"');
}

/// Appends one JSON row `{"time","name","value","text","quality"}`: the
/// members of [`csv_row`], `value` a JSON number or null, `text` a string
/// or null.
pub fn json_row(
    unix_ms: i64,
    name: &str,
    value: Option<&Presented>,
    quality: RowQuality,
    out: &mut Vec<u8>,
) {
    out.extend_from_slice(b"{\"time\":\"");
    time::iso(unix_ms, out);
    out.extend_from_slice(b"\",\"name\":");
    json_string(name, out);
    match value.map(split) {
        Some(Split::Number(v)) => {
            out.extend_from_slice(b",\"value\":");
            number_text(v, out);
            out.extend_from_slice(b",\"text\":null");
        }
        Some(Split::Text(v)) => {
            out.extend_from_slice(b",\"value\":null,\"text\":");
            json_string(&v.text(), out);
        }
        None => out.extend_from_slice(b",\"value\":null,\"text\":null"),
    }
    out.extend_from_slice(b",\"quality\":\"");
    out.extend_from_slice(quality.as_str().as_bytes());
    out.extend_from_slice(b"\"}");
}

#[cfg(test)]
mod tests {
    use super::*;

    fn csv(value: Option<Presented>, quality: RowQuality) -> String {
        let mut out = Vec::new();
        csv_row(1_700_000_000_007, "A", value.as_ref(), quality, &mut out);
        String::from_utf8(out).unwrap()
    }

    fn json(value: Option<Presented>) -> serde_json::Value {
        let mut out = Vec::new();
        json_row(
            1_700_000_000_007,
            "A\"\u{1}",
            value.as_ref(),
            RowQuality::Good,
            &mut out,
        );
        serde_json::from_slice(&out).unwrap()
    }

    #[test]
    fn numbers_in_value_the_rest_in_text() {
        let t = "2023-11-14T22:13:20.007Z";
        assert_eq!(
            csv(Some(Presented::Bool(true)), RowQuality::Good),
            format!("{t},A,1,,good\n")
        );
        assert_eq!(
            csv(Some(Presented::Unsigned(u64::MAX)), RowQuality::Stale),
            format!("{t},A,18446744073709551615,,stale\n")
        );
        assert_eq!(
            csv(Some(Presented::Number(0.1)), RowQuality::Good),
            format!("{t},A,0.1,,good\n")
        );
        let big = csv(Some(Presented::Number(1e300)), RowQuality::Good);
        assert_eq!(big.split(',').nth(2).unwrap().parse::<f64>(), Ok(1e300));
        assert_eq!(
            csv(Some(Presented::Number(f64::NAN)), RowQuality::Good),
            format!("{t},A,,nan,good\n")
        );
        assert_eq!(
            csv(Some(Presented::Text(String::new())), RowQuality::Good),
            format!("{t},A,,\"\",good\n")
        );
        assert_eq!(
            csv(Some(Presented::Text("=1,2".into())), RowQuality::Good),
            format!("{t},A,,\"'=1,2\",good\n")
        );
        assert_eq!(
            csv(Some(Presented::Duration("PT1.5S".into())), RowQuality::Good),
            format!("{t},A,,PT1.5S,good\n")
        );
        assert_eq!(csv(None, RowQuality::Stopped), format!("{t},A,,,stopped\n"));

        let row = json(Some(Presented::Signed(-5)));
        assert_eq!(
            row,
            serde_json::json!({"time": t, "name": "A\"\u{1}", "value": -5, "text": null, "quality": "good"})
        );
        assert_eq!(json(Some(Presented::Number(-0.25)))["value"], -0.25);
        assert_eq!(json(Some(Presented::Number(1e300)))["value"], 1e300);
        let nan = json(Some(Presented::Number(f64::NEG_INFINITY)));
        assert_eq!(
            (&nan["value"], &nan["text"]),
            (&serde_json::Value::Null, &serde_json::json!("-inf"))
        );
        let dt = json(Some(Presented::DateTime("2026-11-25T10:15:00.123Z".into())));
        assert_eq!(dt["text"], "2026-11-25T10:15:00.123Z");
        assert_eq!(json(None)["value"], serde_json::Value::Null);
        // Every value of a u64 reads back exact.
        let big = json(Some(Presented::Unsigned(u64::MAX)));
        assert_eq!(big["value"].as_u64(), Some(u64::MAX));
    }
}
