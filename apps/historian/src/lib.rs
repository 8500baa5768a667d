//! The historian: every change of the variables a section's `HISTORY`
//! names, recorded with the time of the poll that read it and its quality,
//! in one SQLite file per section per day; and the way out again
//! (`plccoms history`, the web page's `/api/history`).
//!
//! - `record.rs`: from the change stream to samples (deadband, heartbeat,
//!   link loss and return, PLC stamps), with `capture.rs` (trigger, PRE and
//!   POST cycles). One task per section, fed by a
//!   [`plccoms_core::changes::Subscription`] that also delivers every poll cycle.
//! - `writer.rs`: one thread that commits what the recorders queue every
//!   HISTORY_SYNC, packs older samples (HISTORY_COMPACT) and applies the
//!   retention; `store.rs`: the files and their schema; `block.rs`: the
//!   packed form of samples.
//! - `query.rs`: samples of a time range as a stream; `export.rs`: CSV,
//!   JSON and Parquet; `time.rs`: the times the command line takes;
//!   `command.rs`: `plccoms history`.
//!
//! The link never waits for the historian: the recorder reads immutable
//! snapshots, and the queue to the writer is bounded by the recorders,
//! which drop (counting, logging, and recording a `dropped` event) what
//! does not fit.

pub mod block;
pub mod capture;
pub mod command;
pub mod export;
pub mod key;
pub mod query;
pub mod record;
pub mod sample;
pub mod store;
pub mod web;
mod writer;

// The history time language, shared with the web app, lives below both.
pub use plccoms_core::history_source::time;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::mpsc::Sender;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use plccoms_core::changes::unix_ms;
use plccoms_core::config::{Config, Global, History};
use plccoms_core::metrics::{self, Counter, Gauge};
use plccoms_core::section::{InfoLines, Section};
use record::{Output, Recorder};
use sample::{Event, EventKind};
use writer::Message;

/// Samples a section may have queued for the writer (about 40 bytes each):
/// 5 s of 10,000 variables changing every 100 ms, or hours of an ordinary
/// plant while the disk is full.
pub const MAX_QUEUED: u64 = 500_000;

/// The folder of the history files: HISTORY_DIR, relative to the
/// configuration file's folder, by default `history` there.
pub fn history_dir(config_path: &Path, global: &Global) -> PathBuf {
    global.history_dir(&plccoms_core::config::state_dir(config_path))
}

/// Creates `dir` if missing and proves a file can be made in it.
fn writable(dir: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    tempfile::Builder::new()
        .prefix(".plccoms-write-check")
        .tempfile_in(dir)
        .map(drop)
}

/// Whether the historian writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum State {
    Recording = 0,
    /// Writing failed (disk full, size limit): samples wait in memory.
    Stopped = 1,
}

/// What the historian reports of one section (GETINFO, metrics).
#[derive(Debug, Default)]
pub struct Stats {
    /// Samples committed to the files.
    pub written: Counter,
    /// Samples waiting for the writer (queue and current transaction).
    pub queued: AtomicU64,
    /// The most ever queued.
    pub queue_max: Gauge,
    /// Samples dropped: queue full, or beyond a file's variables.
    pub dropped: Counter,
    /// Publishes of the change stream the recorder did not see (it was
    /// late): changes in between may be missing.
    pub missed: Counter,
    /// Commits that took longer than the interval they held (HISTORY_SYNC):
    /// the writer does not keep up.
    pub overruns: Counter,
    /// Duration of the last commit round and the longest, in microseconds.
    pub flush_us: Gauge,
    pub flush_max_us: Gauge,
    /// Samples recorded twice (event capture) and stored once.
    pub duplicates: Counter,
    /// Samples moved one millisecond later (a clock set back).
    pub shifted: Counter,
    /// Bytes of the day files open for writing.
    pub bytes: Gauge,
    /// Samples packed into blocks (HISTORY_COMPACT), and the blocks.
    pub packed: Counter,
    pub blocks: Counter,
    pub state: AtomicU8,
    /// HISTORY_SYNC in milliseconds, for the flush/fill comparison.
    pub sync_ms: Gauge,
}

impl Stats {
    pub fn state(&self) -> State {
        if self.state.load(Ordering::Relaxed) == State::Stopped as u8 {
            State::Stopped
        } else {
            State::Recording
        }
    }
}

impl InfoLines for Stats {
    /// The GETINFO lines (`KEY,value`), after the vendor's keys.
    fn getinfo(&self) -> Vec<(&'static str, String)> {
        let queued = self.queued.load(Ordering::Relaxed);
        vec![
            (
                "HISTORY",
                match self.state() {
                    State::Recording => "recording".to_string(),
                    State::Stopped => "stopped (disk full or size limit; see the log)".to_string(),
                },
            ),
            (
                "HISTORY_SAMPLES",
                format!(
                    "{} written, {} dropped, {} publishes missed",
                    self.written.get(),
                    self.dropped.get(),
                    self.missed.get()
                ),
            ),
            (
                "HISTORY_QUEUE",
                format!("{queued}/{MAX_QUEUED} (max {})", self.queue_max.get()),
            ),
            (
                "HISTORY_FLUSH",
                format!(
                    "{:.1} ms of {} ms (max {:.1} ms), {} overruns",
                    self.flush_us.get() as f64 / 1000.0,
                    self.sync_ms.get(),
                    self.flush_max_us.get() as f64 / 1000.0,
                    self.overruns.get()
                ),
            ),
            (
                "HISTORY_PACKED",
                format!(
                    "{} samples in {} blocks",
                    self.packed.get(),
                    self.blocks.get()
                ),
            ),
        ]
    }
}

/// Each recording section's name and stats, for `/metrics`.
type StatsList = Arc<std::sync::Mutex<Vec<(String, Arc<Stats>)>>>;

/// The running historian: a recorder task per recording section, started
/// and stopped as the running sections change (a reload), and the writer
/// thread.
pub struct Historian {
    stop: CancellationToken,
    supervisor: Option<JoinHandle<()>>,
    writer: Option<std::thread::JoinHandle<()>>,
    tx: Sender<Message>,
    /// Per recording section, its name and stats.
    stats: StatsList,
}

/// One section's recorder.
struct Recording {
    section: Arc<Section>,
    index: usize,
    stop: CancellationToken,
    task: JoinHandle<()>,
}

/// What starts and stops the recorders.
struct Recorders {
    tx: Sender<Message>,
    stop: CancellationToken,
    stats: StatsList,
    sync: Duration,
    dir: PathBuf,
    /// Sections handed to the writer so far (the next one's number).
    added: usize,
    running: Vec<Recording>,
}

impl Recorders {
    /// Starts recording `section` if its HISTORY is set; `out` collects
    /// what the writer needs when it is not running yet.
    fn start(&mut self, section: &Arc<Section>, outs: Option<&mut Vec<writer::SectionOut>>) {
        let history = section.state().config.history.clone();
        if !history.enabled() {
            return;
        }
        let stats = Arc::new(Stats::default());
        stats.sync_ms.set(self.sync.as_millis() as u64);
        let _ = section.set_info_lines(stats.clone());
        let out = writer::SectionOut {
            name: section.name().to_string(),
            stats: stats.clone(),
        };
        match outs {
            Some(outs) => outs.push(out),
            None => {
                let _ = self.tx.send(Message::Add(out));
            }
        }
        {
            let mut list = lock(&self.stats);
            list.retain(|(name, _)| name != section.name());
            list.push((section.name().to_string(), stats.clone()));
        }
        info!(section = %section.name(), dir = %self.dir.display(), "history: recording {}", history.masks.join(", "));
        let index = self.added;
        self.added += 1;
        let stop = self.stop.child_token();
        let task = tokio::spawn(record_section(
            section.clone(),
            history,
            index,
            Queue {
                tx: self.tx.clone(),
                stats,
            },
            stop.clone(),
        ));
        self.running.push(Recording {
            section: section.clone(),
            index,
            stop,
            task,
        });
    }

    /// Stops the recorder of a section that stopped: what it queued is
    /// written and its files closed before a replacement opens them.
    async fn stop(&mut self, section: &Arc<Section>) {
        let Some(at) = self
            .running
            .iter()
            .position(|r| Arc::ptr_eq(&r.section, section))
        else {
            return;
        };
        let recording = self.running.remove(at);
        recording.stop.cancel();
        let _ = recording.task.await;
        let _ = self.tx.send(Message::Remove {
            section: recording.index,
        });
        lock(&self.stats).retain(|(name, _)| name != section.name());
        info!(section = %section.name(), "history: recording stopped (section stopped)");
    }

    /// Follows the running sections until the historian stops.
    async fn follow(
        mut self,
        mut watch: tokio::sync::watch::Receiver<plccoms_core::sections::SectionList>,
    ) {
        loop {
            tokio::select! {
                _ = self.stop.cancelled() => break,
                changed = watch.changed() => if changed.is_err() { break },
            }
            let now = watch.borrow_and_update().clone();
            let current: Vec<_> = self.running.iter().map(|r| r.section.clone()).collect();
            let (added, removed) = plccoms_core::sections::diff(&current, &now);
            for section in &removed {
                self.stop(section).await;
            }
            // Unchanged sections that do not record come back as `added`
            // (only recorders are in `running`): `start` passes them by.
            for section in &added {
                self.start(section, None);
            }
        }
        for recording in self.running.drain(..) {
            let _ = recording.task.await;
        }
    }
}

fn lock<T>(mutex: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

/// Whether the historian has work: a section whose HISTORY is set.
pub fn records(sections: &[Arc<Section>]) -> bool {
    sections
        .iter()
        .any(|section| section.state().config.history.enabled())
}

impl Historian {
    /// Starts recording the sections whose HISTORY is set, and follows
    /// `sections` (a reload starts and stops recorders); `None` when none
    /// records now; an error naming the key and the fix when the history
    /// folder cannot be written (a configured historian that records nothing
    /// must not start).
    pub fn start(
        config: &Config,
        sections: &plccoms_core::sections::Sections,
    ) -> Result<Option<Historian>, String> {
        let mut watch = sections.watch();
        let first = watch.borrow_and_update().clone();
        if !records(&first) {
            return Ok(None);
        }
        let dir = history_dir(&config.path, &config.global);
        writable(&dir).map_err(|e| {
            format!(
                "HISTORY_DIR {}: {e}; make the folder writable by the server's user, or set HISTORY_DIR to one that is (a relative path starts in $STATE_DIRECTORY under systemd, else beside the configuration)",
                dir.display()
            )
        })?;
        let (tx, rx) = std::sync::mpsc::channel();
        let stop = CancellationToken::new();
        let stats = Arc::new(std::sync::Mutex::new(Vec::new()));
        let mut recorders = Recorders {
            tx: tx.clone(),
            stop: stop.clone(),
            stats: stats.clone(),
            sync: config.global.history_sync,
            dir: dir.clone(),
            added: 0,
            running: Vec::new(),
        };
        let mut outs = Vec::new();
        for section in first.iter() {
            recorders.start(section, Some(&mut outs));
        }
        let settings = writer::Settings {
            dir,
            sync: config.global.history_sync,
            retention: config.global.history_retention,
            pack_after: (!config.global.history_compact.is_zero())
                .then_some(config.global.history_compact),
        };
        let writer = std::thread::Builder::new()
            .name("historian".into())
            .spawn(move || writer::run(rx, outs, settings))
            .map_err(|e| format!("cannot start the writer thread: {e}"))?;
        let supervisor = tokio::spawn(recorders.follow(watch));
        Ok(Some(Historian {
            stop,
            supervisor: Some(supervisor),
            writer: Some(writer),
            tx,
            stats,
        }))
    }

    /// Stops recording: what is queued is committed and the files closed.
    pub async fn stop(mut self) {
        self.stop.cancel();
        if let Some(supervisor) = self.supervisor.take() {
            let _ = supervisor.await;
        }
        let _ = self.tx.send(Message::Stop);
        if let Some(writer) = self.writer.take() {
            let _ = tokio::task::spawn_blocking(move || writer.join()).await;
        }
    }

    /// The metrics of every recording section.
    pub fn metrics(&self) -> Arc<dyn metrics::Source> {
        Arc::new(Metrics(self.stats.clone()))
    }
}

/// A recorder's end of the queue to the writer.
struct Queue {
    tx: Sender<Message>,
    stats: Arc<Stats>,
}

impl Queue {
    /// Queues `out`, unless that would go past [`MAX_QUEUED`]; `false`:
    /// dropped.
    fn offer(
        &self,
        section: usize,
        table: &Arc<plccoms_core::vars::VarTable>,
        out: Output,
    ) -> bool {
        let n = out.samples.len() as u64;
        let queued = self.stats.queued.load(Ordering::Relaxed);
        if queued + n > MAX_QUEUED {
            return false;
        }
        self.stats.queued.fetch_add(n, Ordering::Relaxed);
        self.stats.queue_max.raise(queued + n);
        let sent = self.tx.send(Message::Record {
            section,
            table: table.clone(),
            samples: out.samples,
            events: out.events,
        });
        if sent.is_err() {
            self.stats.queued.fetch_sub(n, Ordering::Relaxed);
        }
        sent.is_ok()
    }
}

/// Logs at most once a minute, with what happened meanwhile.
struct RateLimited {
    last: Option<Instant>,
    count: u64,
}

impl RateLimited {
    fn new() -> RateLimited {
        RateLimited {
            last: None,
            count: 0,
        }
    }

    /// Adds `n`; returns the total to log if a minute has passed.
    fn add(&mut self, n: u64) -> Option<u64> {
        self.count += n;
        let due = self
            .last
            .is_none_or(|last| last.elapsed() >= Duration::from_secs(60));
        if due && self.count > 0 {
            self.last = Some(Instant::now());
            return Some(std::mem::take(&mut self.count));
        }
        None
    }
}

/// One section's recorder task.
async fn record_section(
    section: Arc<Section>,
    history: History,
    index: usize,
    queue: Queue,
    stop: CancellationToken,
) {
    let mut sub = section
        .subscribe(&Recorder::masks(&history))
        .every_poll()
        .every_change();
    let mut recorder = Recorder::new(section.name(), history, *section.format());
    let mut missed_log = RateLimited::new();
    let mut dropped_log = RateLimited::new();
    // Dropped samples not yet told in an event: count, first and last time.
    let mut dropped: Option<(u64, i64, i64)> = None;
    let mut table = sub.table().clone();
    let now = || unix_ms(SystemTime::now());
    let mut pending = Output {
        samples: Vec::new(),
        events: vec![Event {
            t: now(),
            kind: EventKind::Start,
            detail: String::new(),
        }],
    };
    loop {
        let batch = tokio::select! {
            _ = stop.cancelled() => None,
            batch = sub.next() => batch,
        };
        let Some(batch) = batch else { break };
        table = batch.snapshot.table.clone();
        recorder.on_batch(&batch, now(), &mut pending);
        if batch.missed > 0 {
            queue.stats.missed.add(batch.missed);
            if let Some(n) = missed_log.add(batch.missed) {
                warn!(section = %section.name(), "history: {n} publishes were not seen by the recorder (it lagged past {} publishes or {} MiB of them): changes in between are missing, marked by a __RECORDER gap in exports", plccoms_core::changes::FOLLOW_BOUND, plccoms_core::changes::FOLLOW_BYTES >> 20);
            }
        }
        if pending.is_empty() {
            continue;
        }
        if let Some((n, first, last)) = dropped {
            pending.events.push(Event {
                t: now(),
                kind: EventKind::Dropped,
                detail: format!("{n} samples from {first} to {last} (ms): queue full"),
            });
        }
        let n = pending.samples.len() as u64;
        let (first, last) = (
            pending.samples.first().map_or(0, |s| s.t),
            pending.samples.last().map_or(0, |s| s.t),
        );
        if queue.offer(index, &table, std::mem::take(&mut pending)) {
            dropped = None;
        } else {
            queue.stats.dropped.add(n);
            dropped = Some(match dropped {
                Some((m, f, _)) => (m + n, f, last),
                None => (n, first, last),
            });
            if let Some(total) = dropped_log.add(n) {
                warn!(section = %section.name(), "history: {total} samples dropped: the writer's queue is full ({MAX_QUEUED} samples)");
            }
        }
    }
    let mut end = Output::default();
    end.events.push(Event {
        t: now(),
        kind: EventKind::Stop,
        detail: String::new(),
    });
    queue.offer(index, &table, end);
}

/// The historian's metrics, `plccoms_historian_*`, one `section` label.
struct Metrics(StatsList);

impl metrics::Source for Metrics {
    fn render(&self, out: &mut String) {
        type Get = fn(&Stats) -> u64;
        let families: [(&str, &str, &str, Get); 11] = [
            ("plccoms_historian_samples_written_total", "counter", "Samples committed to the history files.", |s| s.written.get()),
            ("plccoms_historian_samples_dropped_total", "counter", "Samples not recorded: the writer's queue was full, or past a file's variables.", |s| s.dropped.get()),
            ("plccoms_historian_publishes_missed_total", "counter", "Change-stream publishes the recorder did not see; changes in between may be missing.", |s| s.missed.get()),
            ("plccoms_historian_queue_samples", "gauge", "Samples waiting for the writer.", |s| s.queued.load(Ordering::Relaxed)),
            ("plccoms_historian_queue_max_samples", "gauge", "The most samples ever waiting for the writer.", |s| s.queue_max.get()),
            ("plccoms_historian_flush_seconds", "gauge", "Duration of the last commit round (compare with HISTORY_SYNC).", |s| s.flush_us.get()),
            ("plccoms_historian_flush_overruns_total", "counter", "Commit rounds that took longer than the interval they held.", |s| s.overruns.get()),
            ("plccoms_historian_samples_packed_total", "counter", "Samples packed into compressed blocks (HISTORY_COMPACT).", |s| s.packed.get()),
            ("plccoms_historian_blocks_total", "counter", "Compressed blocks written.", |s| s.blocks.get()),
            ("plccoms_historian_file_bytes", "gauge", "Bytes of the day files being written.", |s| s.bytes.get()),
            ("plccoms_historian_recording", "gauge", "1 while recording, 0 while stopped (disk full, size limit).", |s| u64::from(s.state() == State::Recording)),
        ];
        let sections = lock(&self.0).clone();
        for (name, kind, help, get) in families {
            metrics::header(out, name, kind, help);
            for (section, stats) in &sections {
                let labels = format!("section=\"{}\"", metrics::escape_label(section));
                let value = get(stats);
                if name == "plccoms_historian_flush_seconds" {
                    let _ = writeln!(out, "{name}{{{labels}}} {}", value as f64 / 1e6);
                } else {
                    let _ = writeln!(out, "{name}{{{labels}}} {value}");
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::metrics::Source;

    #[test]
    fn metrics_and_getinfo() {
        let stats = Arc::new(Stats::default());
        stats.written.add(5);
        stats.flush_us.set(2500);
        stats.sync_ms.set(1000);
        stats.queue_max.raise(7);
        let mut out = String::new();
        Metrics(Arc::new(std::sync::Mutex::new(vec![(
            "Boiler".into(),
            stats.clone(),
        )])))
        .render(&mut out);
        assert!(out.contains("# TYPE plccoms_historian_samples_written_total counter\n"));
        assert!(out.contains("plccoms_historian_samples_written_total{section=\"Boiler\"} 5\n"));
        assert!(out.contains("plccoms_historian_flush_seconds{section=\"Boiler\"} 0.0025\n"));
        assert!(out.contains("plccoms_historian_recording{section=\"Boiler\"} 1\n"));
        let info = stats.getinfo();
        assert_eq!(info[0], ("HISTORY", "recording".to_string()));
        assert_eq!(
            info[3],
            (
                "HISTORY_FLUSH",
                "2.5 ms of 1000 ms (max 0.0 ms), 0 overruns".to_string()
            )
        );
    }

    #[test]
    fn rate_limited_logging() {
        let mut log = RateLimited::new();
        assert_eq!(log.add(3), Some(3));
        assert_eq!(log.add(2), None);
        assert_eq!(log.add(0), None);
    }
}
