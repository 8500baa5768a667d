//! Recorded history as the apps read it: the web page's `/api/history` and
//! chart ask a [`HistorySource`], the historian implements it, start-up
//! wires the one to the other. Here, below both, so that neither app
//! imports the other; so are the times both take and the CSV formula guard
//! both write with.

pub mod time;

use std::sync::Arc;

use futures::stream::BoxStream;

use crate::changes::Quality;

/// One recorded value.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// UTC milliseconds of the poll that read it.
    pub unix_ms: i64,
    /// The variable's name as the protocol prints it.
    pub name: Arc<str>,
    /// As the protocol prints it; `None` where the record marks no value
    /// (the link was lost).
    pub value: Option<String>,
    pub quality: Quality,
}

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
    /// The samples of `query.section`'s variables matching `query.masks`
    /// from `from_ms` to `to_ms`, oldest first, streamed as they are read.
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
