//! `GET /api/history?section=S&vars=<masks>&from=T&to=T&format=csv|json`:
//! recorded values from the historian, streamed as CSV or JSON; the page's
//! chart reads the JSON for its range mode.
//!
//! The web server does not record anything itself: it reads a
//! [`HistorySource`], which start-up hands it when a historian runs. With
//! none the endpoint answers 503 "historian not enabled".
//!
//! `from`/`to`: UTC milliseconds since 1970, or a time as `plccoms history`
//! takes it (`now`, `-1h`, `-7d`, `2026-11-30T12:00:00Z`); `to` defaults to
//! now, `from` to an hour before `to`. Output, oldest first: the long form
//! of `plccoms history` byte for byte (README, "Reading it back"), the rows
//! `time,name,value,text,quality` as CSV, or as a JSON array of
//! `{"time","name","value","text","quality"}`, gaps (`__LINK`, `__SERVER`,
//! `__DAMAGED`) included.
//!
//! An error after the first bytes went out cannot change the status: it
//! ends the body as a last row named `__ERROR`, quality `error`, its
//! message in `text`. So do the historian's time limit for an answer
//! (HISTORY_QUERY_TIMEOUT, a stalled reader included) and the damaged
//! ranges it left out.

use axum::body::{Body, Bytes};
use axum::extract::Query;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use futures::stream::StreamExt;
use serde::Deserialize;

use super::api::error;
use super::State;
use plccoms_core::history_source::{
    self as shape, HistoryError, HistoryQuery, HistorySource, RowQuality, Sample, SampleStream,
};
use plccoms_core::present::Presented;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Csv,
    Json,
}

#[derive(Deserialize)]
pub struct HistoryParams {
    section: Option<String>,
    vars: Option<String>,
    from: Option<String>,
    to: Option<String>,
    format: Option<String>,
}

/// Default span when `from` is not given.
const DEFAULT_SPAN_MS: i64 = 3_600_000;
/// Bytes gathered before a chunk of the body goes out.
const CHUNK: usize = 16 * 1024;

/// A time parameter: UTC milliseconds, or what `plccoms history` takes
/// (`now`, `-1h`, `-7d`, ISO 8601 / RFC 3339, a date).
pub fn parse_time(name: &str, text: &str, now_ms: i64) -> Result<i64, String> {
    let text = text.trim();
    let ms = match text.parse::<i64>() {
        Ok(ms) => ms,
        Err(_) => plccoms_core::history_source::time::parse(text, now_ms)
            .map_err(|e| format!("{name}={text}: {e}"))?,
    };
    // Arithmetic on times far out would wrap.
    if !(0..=LATEST_MS).contains(&ms) {
        return Err(format!(
            "{name}={text}: out of range (0 to {LATEST_MS}: 1970 to the year 9999)"
        ));
    }
    Ok(ms)
}

/// 9999-12-31T23:59:59.999Z.
const LATEST_MS: i64 = 253_402_300_799_999;

/// The query the parameters ask for, or what is wrong with them.
pub fn parse_params(params: &HistoryParams, now_ms: i64) -> Result<(HistoryQuery, Format), String> {
    let section = params
        .section
        .clone()
        .filter(|s| !s.is_empty())
        .ok_or("section= is required")?;
    let format = match params.format.as_deref().unwrap_or("json") {
        "csv" => Format::Csv,
        "json" => Format::Json,
        other => return Err(format!("format={other}: csv or json")),
    };
    let to_ms = match &params.to {
        Some(text) => parse_time("to", text, now_ms)?,
        None => now_ms,
    };
    let from_ms = match &params.from {
        Some(text) => parse_time("from", text, now_ms)?,
        None => to_ms.saturating_sub(DEFAULT_SPAN_MS),
    };
    if from_ms > to_ms {
        return Err(format!("from ({from_ms}) is after to ({to_ms})"));
    }
    let masks = super::api::parse_masks(params.vars.as_deref())
        .into_iter()
        .map(|m| plccoms_protocol::cp1250::decode(&m).into_owned())
        .collect();
    Ok((
        HistoryQuery {
            section,
            masks,
            from_ms,
            to_ms,
        },
        format,
    ))
}

/// The query a URL's query string (`section=S&vars=..`, percent-encoded)
/// asks for, or what is wrong with it.
pub fn parse_query(query: &str, now_ms: i64) -> Result<(HistoryQuery, Format), String> {
    let uri: axum::http::Uri = format!("/api/history?{query}")
        .parse()
        .map_err(|e| format!("not a query string: {e}"))?;
    let Query(params) = Query::<HistoryParams>::try_from_uri(&uri).map_err(|e| e.body_text())?;
    parse_params(&params, now_ms)
}

pub(super) async fn history(state: State, Query(params): Query<HistoryParams>) -> Response {
    let Some(source) = state.0.history.clone() else {
        return error(
            StatusCode::SERVICE_UNAVAILABLE,
            "historian not enabled: no history is recorded by this server",
        );
    };
    let (query, format) = match parse_params(&params, chrono::Utc::now().timestamp_millis()) {
        Ok(parsed) => parsed,
        Err(message) => return error(StatusCode::BAD_REQUEST, message),
    };
    // The name becomes part of a file path in the historian: only the
    // configured sections' names get there.
    if state.0.section(&query.section).is_none() {
        return error(
            StatusCode::NOT_FOUND,
            format!("section={}: no section named so", query.section),
        );
    }
    respond(source.as_ref(), query, format)
}

/// The response for `query` from `source`.
pub fn respond(source: &dyn HistorySource, query: HistoryQuery, format: Format) -> Response {
    let from_ms = query.from_ms;
    let samples = match source.samples(query) {
        Ok(samples) => samples,
        Err(e @ HistoryError::UnknownSection(_)) => {
            return error(StatusCode::NOT_FOUND, e.to_string())
        }
        Err(e) => return error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
    };
    let content_type = match format {
        Format::Csv => "text/csv; charset=utf-8",
        Format::Json => "application/json",
    };
    let body = Body::from_stream(encode(samples, format, from_ms));
    ([(header::CONTENT_TYPE, content_type)], body).into_response()
}

struct Encoder {
    samples: SampleStream,
    format: Format,
    /// Rows written so far (JSON needs commas between them).
    written: u64,
    /// The last row's time: an `__ERROR` row's.
    last_ms: i64,
    done: bool,
}

/// The body: the format's head, the rows in chunks of about [`CHUNK`]
/// bytes, and its tail.
fn encode(
    samples: SampleStream,
    format: Format,
    from_ms: i64,
) -> impl futures::Stream<Item = Result<Bytes, std::io::Error>> {
    let start = match format {
        Format::Csv => shape::CSV_HEADER.to_vec(),
        Format::Json => b"[".to_vec(),
    };
    let encoder = Encoder {
        samples,
        format,
        written: 0,
        last_ms: from_ms,
        done: false,
    };
    futures::stream::unfold((encoder, start), |(mut enc, mut buf)| async move {
        if enc.done {
            return None;
        }
        while buf.len() < CHUNK {
            match enc.samples.next().await {
                Some(Ok(sample)) => {
                    enc.write(&sample, &mut buf);
                }
                Some(Err(e)) => {
                    enc.finish(Some(&e.to_string()), &mut buf);
                    break;
                }
                None => {
                    enc.finish(None, &mut buf);
                    break;
                }
            }
        }
        let chunk = Bytes::from(std::mem::take(&mut buf));
        Some((Ok(chunk), (enc, buf)))
    })
}

impl Encoder {
    fn write(&mut self, sample: &Sample, out: &mut Vec<u8>) {
        match self.format {
            Format::Csv => shape::csv_row(
                sample.unix_ms,
                &sample.name,
                sample.value.as_ref(),
                sample.quality,
                out,
            ),
            Format::Json => {
                out.extend_from_slice(if self.written > 0 { b",\n" } else { b"\n" });
                shape::json_row(
                    sample.unix_ms,
                    &sample.name,
                    sample.value.as_ref(),
                    sample.quality,
                    out,
                );
            }
        }
        self.last_ms = sample.unix_ms;
        self.written += 1;
    }

    fn finish(&mut self, failure: Option<&str>, out: &mut Vec<u8>) {
        if let Some(message) = failure {
            let row = Sample {
                unix_ms: self.last_ms,
                name: shape::ERROR.into(),
                value: Some(Presented::Text(message.into())),
                quality: RowQuality::Error,
            };
            self.write(&row, out);
        }
        self.done = true;
        if self.format == Format::Json {
            out.extend_from_slice(b"\n]\n");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::changes::Quality;

    /// Samples held in memory, filtered as a historian would.
    struct Recorded(Vec<Sample>, Option<HistoryError>);

    impl HistorySource for Recorded {
        fn samples(&self, query: HistoryQuery) -> Result<SampleStream, HistoryError> {
            if query.section != "Demo" {
                return Err(HistoryError::UnknownSection(query.section));
            }
            let masks: Vec<_> = query
                .masks
                .iter()
                .map(|m| plccoms_protocol::mask::Mask::new(m.as_bytes()))
                .collect();
            let mut items: Vec<Result<Sample, HistoryError>> = self
                .0
                .iter()
                .filter(|s| (query.from_ms..=query.to_ms).contains(&s.unix_ms))
                .filter(|s| masks.iter().any(|m| m.matches(s.name.as_bytes())))
                .cloned()
                .map(Ok)
                .collect();
            items.extend(self.1.clone().map(Err));
            Ok(futures::stream::iter(items).boxed())
        }
    }

    fn sample(unix_ms: i64, name: &str, value: Option<Presented>, quality: Quality) -> Sample {
        Sample {
            unix_ms,
            name: name.into(),
            value,
            quality: quality.into(),
        }
    }

    fn text(text: &str) -> Option<Presented> {
        Some(Presented::Text(text.into()))
    }

    fn recorded(failure: Option<HistoryError>) -> Recorded {
        Recorded(
            vec![
                sample(1_000, "SINUS", Some(Presented::Number(0.5)), Quality::Good),
                sample(1_000, "TEXT", text("\"a, \"b\"\""), Quality::Good),
                sample(
                    2_000,
                    "SINUS",
                    Some(Presented::Number(0.5)),
                    Quality::LinkLost,
                ),
                Sample {
                    unix_ms: 2_000,
                    name: "__LINK".into(),
                    value: text("link_lost"),
                    quality: RowQuality::LinkLost,
                },
                sample(9_000, "SINUS", Some(Presented::Number(0.7)), Quality::Good),
            ],
            failure,
        )
    }

    fn params(query: &str) -> HistoryParams {
        let q: Query<HistoryParams> =
            Query::try_from_uri(&format!("http://x/api/history?{query}").parse().unwrap()).unwrap();
        q.0
    }

    async fn body(source: &Recorded, query: &str) -> (StatusCode, String) {
        let (query, format) = parse_params(&params(query), 10_000).unwrap();
        let response = respond(source, query, format);
        let status = response.status();
        let bytes = axum::body::to_bytes(response.into_body(), usize::MAX)
            .await
            .unwrap();
        (status, String::from_utf8(bytes.to_vec()).unwrap())
    }

    /// The rows of `plccoms history`'s long form: `time,name,value,text,
    /// quality`, numbers in `value`, strings in `text`, gaps as rows.
    #[tokio::test]
    async fn csv_and_json_of_a_range() {
        let source = recorded(None);
        let (status, csv) = body(
            &source,
            "section=Demo&vars=s*,text,__link&from=0&to=5000&format=csv",
        )
        .await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(
            csv,
            "time,name,value,text,quality\n\
             1970-01-01T00:00:01.000Z,SINUS,0.5,,good\n\
             1970-01-01T00:00:01.000Z,TEXT,,\"\"\"a, \"\"b\"\"\"\"\",good\n\
             1970-01-01T00:00:02.000Z,SINUS,0.5,,link_lost\n\
             1970-01-01T00:00:02.000Z,__LINK,,link_lost,link_lost\n"
        );
        let (_, json) = body(&source, "section=Demo&vars=sinus&from=1970-01-01T00:00:01Z").await;
        let rows: serde_json::Value = serde_json::from_str(&json).unwrap();
        let rows = rows.as_array().unwrap();
        assert_eq!(rows.len(), 3);
        assert_eq!(
            rows[0],
            serde_json::json!({"time": "1970-01-01T00:00:01.000Z", "name": "SINUS", "value": 0.5,
                               "text": null, "quality": "good"})
        );
        assert_eq!(rows[1]["quality"], "link_lost");
    }

    /// Names and values a spreadsheet would run as formulas get a `'`
    /// before them; numbers, negative ones too, stay as they are.
    #[tokio::test]
    async fn csv_cells_a_spreadsheet_would_run_are_escaped() {
        let source = Recorded(
            vec![
                sample(1_000, "+CMD", Some(Presented::Number(-3.5)), Quality::Good),
                sample(1_000, "TEXT", text("=HYPERLINK(\"x\",1)"), Quality::Good),
                sample(1_000, "TEXT", text("@SUM(A1)"), Quality::Good),
                sample(1_000, "TEXT", text("-5"), Quality::Good),
            ],
            None,
        );
        let (_, csv) = body(&source, "section=Demo&from=0&to=5000&format=csv").await;
        assert_eq!(
            csv,
            "time,name,value,text,quality\n\
             1970-01-01T00:00:01.000Z,'+CMD,-3.5,,good\n\
             1970-01-01T00:00:01.000Z,TEXT,,\"'=HYPERLINK(\"\"x\"\",1)\",good\n\
             1970-01-01T00:00:01.000Z,TEXT,,'@SUM(A1),good\n\
             1970-01-01T00:00:01.000Z,TEXT,,-5,good\n"
        );
    }

    /// A failure after the start ends the body with an `__ERROR` row at
    /// the last row's time (the range's start if none came).
    #[tokio::test]
    async fn a_failure_after_the_start_ends_the_body_saying_so() {
        let source = recorded(Some(HistoryError::Failed("disk read error".into())));
        let (_, json) = body(&source, "section=Demo&vars=TEXT&from=0").await;
        let rows: serde_json::Value = serde_json::from_str(&json).unwrap();
        assert_eq!(
            rows,
            serde_json::json!([
                {"time": "1970-01-01T00:00:01.000Z", "name": "TEXT", "value": null,
                 "text": "\"a, \"b\"\"", "quality": "good"},
                {"time": "1970-01-01T00:00:01.000Z", "name": "__ERROR", "value": null,
                 "text": "disk read error", "quality": "error"}
            ])
        );
        let (_, csv) = body(&source, "section=Demo&vars=nothing&from=500&format=csv").await;
        assert_eq!(
            csv,
            "time,name,value,text,quality\n\
             1970-01-01T00:00:00.500Z,__ERROR,,disk read error,error\n"
        );
        let (status, _) = body(&source, "section=Other").await;
        assert_eq!(status, StatusCode::NOT_FOUND);
    }

    #[test]
    fn parameters_are_checked_and_named() {
        let err = |q: &str| parse_params(&params(q), 10_000).unwrap_err();
        assert_eq!(err("vars=a"), "section= is required");
        assert!(err("section=D&from=yesterday")
            .starts_with("from=yesterday: 'yesterday' is not a time"));
        let (query, _) = parse_params(&params("section=D&from=-1h&to=now"), 10_000_000).unwrap();
        assert_eq!((query.from_ms, query.to_ms), (6_400_000, 10_000_000));
        assert_eq!(err("section=D&from=5&to=4"), "from (5) is after to (4)");
        assert_eq!(err("section=D&format=xml"), "format=xml: csv or json");
        let (query, format) = parse_params(&params("section=D"), 10_000_000).unwrap();
        assert_eq!(
            (query.from_ms, query.to_ms, format),
            (6_400_000, 10_000_000, Format::Json)
        );
        assert_eq!(query.masks, ["*"]);
    }
}
