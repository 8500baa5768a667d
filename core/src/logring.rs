//! The last warnings and errors the server logged, kept in memory for the
//! web page: a `tracing` layer that copies each WARN and ERROR event into a
//! bounded ring. Memory is bounded whatever is logged: at most [`CAPACITY`]
//! entries of at most [`MAX_MESSAGE`] bytes each.

use std::collections::VecDeque;
use std::fmt::Write as _;
use std::sync::{Mutex, OnceLock};

use serde::Serialize;
use tracing::field::{Field, Visit};
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::layer::Context;
use tracing_subscriber::Layer;

/// Entries kept: the oldest goes when a new one comes.
pub const CAPACITY: usize = 200;
/// Longest message kept, in bytes; longer ones are cut (at a character
/// boundary) and end in `…`.
pub const MAX_MESSAGE: usize = 2048;

#[derive(Debug, Clone, Serialize)]
pub struct LogEntry {
    /// Increases with every entry, so a reader can ask for what is new.
    pub seq: u64,
    /// UTC milliseconds.
    pub unix_ms: i64,
    /// `WARN` or `ERROR`.
    pub level: &'static str,
    /// The message, then the event's other fields as `name=value`.
    pub message: String,
}

#[derive(Default)]
pub struct LogRing {
    inner: Mutex<Ring>,
}

#[derive(Default)]
struct Ring {
    entries: VecDeque<LogEntry>,
    next_seq: u64,
}

impl LogRing {
    pub fn push(&self, level: &'static str, message: String) {
        let mut ring = self.inner.lock().unwrap_or_else(|p| p.into_inner());
        ring.next_seq += 1;
        let entry = LogEntry {
            seq: ring.next_seq,
            unix_ms: chrono::Utc::now().timestamp_millis(),
            level,
            message,
        };
        if ring.entries.len() == CAPACITY {
            ring.entries.pop_front();
        }
        ring.entries.push_back(entry);
    }

    /// The entries kept, oldest first.
    pub fn entries(&self) -> Vec<LogEntry> {
        let ring = self.inner.lock().unwrap_or_else(|p| p.into_inner());
        ring.entries.iter().cloned().collect()
    }
}

/// The process's ring, filled by [`layer`].
pub fn global() -> &'static LogRing {
    static RING: OnceLock<LogRing> = OnceLock::new();
    RING.get_or_init(LogRing::default)
}

/// The layer that fills [`global`]; `main` adds it to the subscriber.
pub fn layer() -> RingLayer {
    RingLayer
}

pub struct RingLayer;

impl<S: Subscriber> Layer<S> for RingLayer {
    fn on_event(&self, event: &Event<'_>, _ctx: Context<'_, S>) {
        let level = match *event.metadata().level() {
            Level::ERROR => "ERROR",
            Level::WARN => "WARN",
            _ => return,
        };
        let mut text = Text::default();
        event.record(&mut text);
        global().push(level, text.finish());
    }
}

/// An event's fields as one line: the message first, the rest after it.
#[derive(Default)]
struct Text {
    message: String,
    fields: String,
}

impl Text {
    fn finish(self) -> String {
        let mut line = self.fields;
        if !self.message.is_empty() {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&self.message);
        }
        cut(line)
    }
}

impl Visit for Text {
    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            let _ = write!(self.message, "{value:?}");
        } else {
            if !self.fields.is_empty() {
                self.fields.push(' ');
            }
            let _ = write!(self.fields, "{}={value:?}", field.name());
        }
    }

    fn record_str(&mut self, field: &Field, value: &str) {
        if field.name() == "message" {
            self.message.push_str(value);
        } else {
            self.record_debug(field, &format_args!("{value}"));
        }
    }
}

fn cut(mut line: String) -> String {
    if line.len() > MAX_MESSAGE {
        let mut end = MAX_MESSAGE;
        while !line.is_char_boundary(end) {
            end -= 1;
        }
        line.truncate(end);
        line.push('…');
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracing_subscriber::layer::SubscriberExt;

    #[test]
    fn warnings_and_errors_are_kept_with_their_fields_and_bounded() {
        let subscriber = tracing_subscriber::registry().with(layer());
        tracing::subscriber::with_default(subscriber, || {
            let before = global().entries().last().map_or(0, |e| e.seq);
            tracing::info!("not kept");
            tracing::warn!(section = "Demo", "link lost: {}", "timeout");
            tracing::error!("{}", "x".repeat(MAX_MESSAGE * 2));
            let new: Vec<_> = global()
                .entries()
                .into_iter()
                .filter(|e| e.seq > before)
                .collect();
            assert_eq!(new.len(), 2, "{new:?}");
            assert_eq!(new[0].level, "WARN");
            assert_eq!(new[0].message, "section=Demo: link lost: timeout");
            assert_eq!(new[1].level, "ERROR");
            assert!(new[1].message.len() <= MAX_MESSAGE + '…'.len_utf8());
            for _ in 0..CAPACITY + 5 {
                tracing::warn!("again");
            }
            assert_eq!(global().entries().len(), CAPACITY);
        });
    }
}
