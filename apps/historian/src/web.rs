//! The historian as the web page reads it (`/api/history`, the chart's range
//! mode): the samples of a section's variables over a range, read on a
//! blocking thread and streamed through a bounded channel, so a year of one
//! variable never sits in memory and never stalls the page's runtime.
//!
//! A reader that stops reading costs no more than the thread waiting for
//! it: the query holds no SQLite read transaction between its chunks (the
//! recorder's checkpoints go through), and the whole answer has a time
//! limit (HISTORY_QUERY_TIMEOUT), after which reading stops and the answer
//! ends with an error saying so.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;

use super::export::presented;
use super::query::{self, Query, QueryError, Record};
use plccoms_core::history_source::{
    HistoryError, HistoryQuery, HistorySource, Sample, SampleStream,
};
use plccoms_core::present::Presented;

/// Rows read ahead of the page's writer, at most.
const AHEAD: usize = 256;

pub struct Source {
    dir: PathBuf,
    /// HISTORY_QUERY_TIMEOUT.
    limit: Duration,
}

impl Source {
    /// The history files in `dir` (HISTORY_DIR); an answer ends after
    /// `limit`.
    pub fn new(dir: PathBuf, limit: Duration) -> Source {
        Source { dir, limit }
    }
}

/// A record as the row every export writes (`plccoms history`'s long form).
fn sample(record: Record) -> Sample {
    match record {
        Record::Sample(row) => Sample {
            unix_ms: row.time(),
            name: Arc::from(row.var.name.as_str()),
            value: presented(&row.value, row.var.ty),
            quality: row.quality.into(),
        },
        Record::Mark(mark) => Sample {
            unix_ms: mark.t,
            name: Arc::from(mark.gap.name()),
            value: Some(Presented::Text(mark.gap.text().into())),
            quality: mark.gap.quality(),
        },
    }
}

type Item = Result<Sample, HistoryError>;

/// Sends an item, waiting for room until `deadline` at most; `false` when
/// the receiver is gone or the time is up. Waits (and a timer) only when
/// the channel is full.
fn send_by(
    runtime: &tokio::runtime::Handle,
    tx: &tokio::sync::mpsc::Sender<Item>,
    item: Item,
    deadline: tokio::time::Instant,
) -> bool {
    use tokio::sync::mpsc::error::TrySendError;
    match tx.try_send(item) {
        Ok(()) => true,
        Err(TrySendError::Closed(_)) => false,
        Err(TrySendError::Full(item)) => matches!(
            runtime.block_on(tokio::time::timeout_at(deadline, tx.send(item))),
            Ok(Ok(()))
        ),
    }
}

impl HistorySource for Source {
    fn samples(&self, query: HistoryQuery) -> Result<SampleStream, HistoryError> {
        let section = query.section.clone();
        let rows = query::records(&Query {
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
        let deadline = tokio::time::Instant::now() + self.limit;
        let too_long = HistoryError::Failed(format!(
            "the answer took longer than HISTORY_QUERY_TIMEOUT ({} s) and was cut off; \
             ask for a shorter range or fewer variables",
            self.limit.as_secs()
        ));
        let (tx, rx) = tokio::sync::mpsc::channel(AHEAD);
        let complete = Arc::new(AtomicBool::new(false));
        let runtime = tokio::runtime::Handle::current();
        let read_all = complete.clone();
        tokio::task::spawn_blocking(move || {
            // Damaged ranges are left out (their `__DAMAGED` rows mark
            // them) and named at the end.
            let mut damaged = Vec::new();
            for row in rows {
                let item = match row {
                    Ok(row) => Ok(sample(row)),
                    Err(e @ QueryError::Damaged { .. }) => {
                        damaged.push(e.to_string());
                        continue;
                    }
                    Err(e) => Err(HistoryError::Failed(e.to_string())),
                };
                // The page went away, or the time is up: stop reading.
                if !send_by(&runtime, &tx, item, deadline) {
                    return;
                }
            }
            if !damaged.is_empty() {
                let item = Err(HistoryError::Failed(damaged.join("; ")));
                if !send_by(&runtime, &tx, item, deadline) {
                    return;
                }
            }
            read_all.store(true, Ordering::Release);
        });
        let state = Some((rx, complete, too_long));
        Ok(futures::stream::unfold(state, move |state| async move {
            let (mut rx, complete, too_long) = state?;
            if tokio::time::Instant::now() < deadline {
                match tokio::time::timeout_at(deadline, rx.recv()).await {
                    Ok(Some(item)) => return Some((item, Some((rx, complete, too_long)))),
                    Ok(None) if complete.load(Ordering::Acquire) => return None,
                    Ok(None) if tokio::time::Instant::now() < deadline => {
                        let stopped = "reading the history stopped before the end (see the log)";
                        return Some((Err(HistoryError::Failed(stopped.into())), None));
                    }
                    Ok(None) | Err(_) => {}
                }
            }
            Some((Err(too_long), None))
        })
        .boxed())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::{Sample as Recorded, Stored};
    use crate::store::{day_of, DayFile, DAY_MS};
    use plccoms_core::changes::Quality;
    use plccoms_core::vars::table_of;

    /// A damaged block: the samples before and after it come, then an
    /// error naming the file and the range left out.
    #[tokio::test]
    async fn damaged_ranges_are_named_at_the_end() {
        let dir = tempfile::tempdir().unwrap();
        let table = Arc::new(table_of(&[("A", "LREAL")]));
        let a = table.lookup(b"A").unwrap();
        let day = day_of(1_700_000_000_000);
        let at = |i: i64| day * DAY_MS + i * 10;
        let samples: Vec<Recorded> = (0..3 * 65_536)
            .map(|i| Recorded {
                t: at(i),
                var: a,
                value: Stored::Real(i as f64 / 3.0),
                quality: Quality::Good,
                plc_time: None,
            })
            .collect();
        let mut file = DayFile::open(dir.path(), "S", day).unwrap();
        file.write(&[(&table, &samples)], &[]).unwrap();
        file.pack(
            i64::MAX,
            std::time::Instant::now() + Duration::from_secs(600),
        )
        .unwrap();
        let path = file.path.clone();
        file.close();
        rusqlite::Connection::open(&path)
            .unwrap()
            .execute(
                "UPDATE blocks SET data = CAST(substr(data, 1, 5) || x'00' || substr(data, 7) AS BLOB) \
                 WHERE first_key = (SELECT first_key FROM blocks ORDER BY first_key LIMIT 1 OFFSET 1)",
                [],
            )
            .unwrap();
        let source = Source::new(dir.path().to_path_buf(), Duration::from_secs(600));
        let items: Vec<_> = source
            .samples(HistoryQuery {
                section: "S".into(),
                masks: vec!["*".into()],
                from_ms: at(0),
                to_ms: at(3 * 65_536),
            })
            .unwrap()
            .collect()
            .await;
        let (last, samples) = items.split_last().unwrap();
        assert!(samples.iter().all(Result::is_ok));
        // The block's samples are left out, its range marked by two rows.
        assert_eq!(samples.len(), 2 * 65_536 + 2);
        let marked: Vec<_> = samples
            .iter()
            .flatten()
            .filter(|s| &*s.name == "__DAMAGED")
            .map(|s| (s.unix_ms, s.quality.as_str()))
            .collect();
        assert_eq!(
            marked,
            [(at(65_536), "damaged"), (at(2 * 65_536 - 1), "damaged")]
        );
        let Err(HistoryError::Failed(message)) = last else {
            panic!("{last:?}");
        };
        assert!(
            message.contains("S-2023-11-14.sqlite") && message.contains("65536 samples from"),
            "{message}"
        );
    }
}
