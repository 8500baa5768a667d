//! The historian as the web page reads it (`/api/history`, the chart's range
//! mode): the samples of a section's variables over a range, read on a
//! blocking thread and streamed through a bounded channel, so a year of one
//! variable never sits in memory and never stalls the page's runtime.

use std::path::PathBuf;
use std::sync::Arc;

use futures::StreamExt;

use super::export::{value_text, Written};
use super::query::{self, Query, QueryError, Row};
use crate::web::history::{HistoryError, HistoryQuery, HistorySource, Sample, SampleStream};

/// Rows read ahead of the page's writer, at most.
const AHEAD: usize = 256;

pub struct Source {
    dir: PathBuf,
}

impl Source {
    /// The history files in `dir` (HISTORY_DIR).
    pub fn new(dir: PathBuf) -> Source {
        Source { dir }
    }
}

fn sample(row: Row) -> Sample {
    let mut text = Vec::new();
    let value = match value_text(&row.value, row.var.ty, &mut text) {
        Written::Missing => None,
        Written::Number | Written::Text => Some(String::from_utf8_lossy(&text).into_owned()),
    };
    Sample {
        unix_ms: row.t,
        name: Arc::from(row.var.name.as_str()),
        value,
        quality: row.quality,
    }
}

impl HistorySource for Source {
    fn samples(&self, query: HistoryQuery) -> Result<SampleStream, HistoryError> {
        let section = query.section.clone();
        let rows = query::rows(&Query {
            dir: self.dir.clone(),
            section: query.section,
            masks: query.masks,
            from_ms: query.from_ms,
            // The page's range includes its end; the historian's does not.
            to_ms: query.to_ms.saturating_add(1),
        })
        .map_err(|e| match e {
            QueryError::NoSection { .. } => HistoryError::UnknownSection(section),
            other => HistoryError::Failed(other.to_string()),
        })?;
        let (tx, rx) = tokio::sync::mpsc::channel(AHEAD);
        tokio::task::spawn_blocking(move || {
            for row in rows {
                let item = row
                    .map(sample)
                    .map_err(|e| HistoryError::Failed(e.to_string()));
                // The page went away: stop reading.
                if tx.blocking_send(item).is_err() {
                    break;
                }
            }
        });
        Ok(futures::stream::unfold(rx, |mut rx| async move {
            rx.recv().await.map(|item| (item, rx))
        })
        .boxed())
    }
}
