//! The writer: one thread (SQLite is blocking I/O) that takes the
//! recorders' samples from a queue and commits them every HISTORY_SYNC, one
//! transaction per section and day file. It never slows a link: the queue's
//! bound is enforced by the recorders, which drop (and count) what does not
//! fit.
//!
//! A failed write (a full disk, the size limit, an I/O error) keeps the
//! samples it could not commit, stops recording with one log line, and is
//! tried again every HISTORY_SYNC; the queue then fills and recorders drop
//! what is over its bound. Recording resumes by itself, with one log line.
//! A day file that is damaged (not a database, corrupt, not a history file)
//! is no such failure: it is moved aside to `<name>.damaged-<UTC time>`,
//! with one error line, and a new file of the day started at once.
//!
//! With HISTORY_COMPACT, the time a round leaves over (up to half of
//! HISTORY_SYNC) packs the samples older than it into blocks; a day that is
//! over is packed whole, its freed pages given back, and then closed. Days
//! left unpacked by a stop are finished after the next start.

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tracing::{error, info, warn};

use super::sample::{Event, Sample};
use super::store::{self, day_of, DayFile, WriteCounts};
use super::{State, Stats};
use plccoms_core::changes::unix_ms;
use plccoms_core::config::Retention;
use plccoms_core::vars::VarTable;

/// What the recorders send.
pub enum Message {
    Record {
        section: usize,
        table: Arc<VarTable>,
        samples: Vec<Sample>,
        events: Vec<Event>,
    },
    /// A section to record from now on (a reload added or restarted it);
    /// its `Record`s name it by the number of sections added before it.
    Add(SectionOut),
    /// A section that stopped: what it has pending is written and its
    /// files closed (its replacement, if any, opens them anew).
    Remove { section: usize },
    /// Write what is pending and end.
    Stop,
}

pub struct SectionOut {
    pub name: String,
    pub stats: Arc<Stats>,
}

pub struct Settings {
    pub dir: PathBuf,
    pub sync: Duration,
    pub retention: Retention,
    /// HISTORY_COMPACT; `None`: samples stay rows.
    pub pack_after: Option<Duration>,
}

/// Free pages given back per round by a finished day.
const SHRINK_PAGES: u32 = 4096;

/// How often retention looks at the files.
const RETENTION_EVERY: Duration = Duration::from_secs(10);

struct Section {
    out: SectionOut,
    pending: Vec<(Arc<VarTable>, Vec<Sample>)>,
    events: Vec<Event>,
    pending_samples: u64,
    files: HashMap<i64, DayFile>,
    /// Days that are over, being packed before they are closed.
    closing: Vec<DayFile>,
    /// Why writing failed, while it does.
    failing: Option<String>,
    /// While packing fails: whether that was logged.
    pack_failing: Option<bool>,
}

impl Section {
    fn new(out: SectionOut, settings: &Settings) -> Section {
        let closing = if settings.pack_after.is_some() {
            unfinished_days(settings, &out.name)
        } else {
            Vec::new()
        };
        Section {
            out,
            pending: Vec::new(),
            events: Vec::new(),
            pending_samples: 0,
            files: HashMap::new(),
            closing,
            failing: None,
            pack_failing: None,
        }
    }

    fn close(self) {
        for file in self.files.into_values().chain(self.closing) {
            file.close();
        }
    }
}

pub fn run(rx: Receiver<Message>, sections: Vec<SectionOut>, settings: Settings) {
    // By the number given at `Add`: removed sections leave a gap.
    let mut sections: BTreeMap<usize, Section> = sections
        .into_iter()
        .map(|out| Section::new(out, &settings))
        .enumerate()
        .collect();
    let mut added = sections.len();
    let mut next_sync = Instant::now() + settings.sync;
    let mut next_retention = Instant::now();
    let mut over_limit = false;
    let mut stopping = false;
    while !stopping {
        let now = Instant::now();
        if now >= next_retention {
            over_limit = retention(&settings, sections.values());
            next_retention = now + RETENTION_EVERY;
        }
        match rx.recv_timeout(next_sync.saturating_duration_since(now)) {
            Ok(Message::Record {
                section,
                table,
                samples,
                events,
            }) => {
                let Some(s) = sections.get_mut(&section) else {
                    continue;
                };
                s.pending_samples += samples.len() as u64;
                if !samples.is_empty() {
                    s.pending.push((table, samples));
                }
                s.events.extend(events);
                continue;
            }
            Ok(Message::Add(out)) => {
                sections.insert(added, Section::new(out, &settings));
                added += 1;
                continue;
            }
            Ok(Message::Remove { section }) => {
                if let Some(mut s) = sections.remove(&section) {
                    flush(&mut s, &settings, over_limit);
                    s.close();
                }
                continue;
            }
            Ok(Message::Stop) | Err(RecvTimeoutError::Disconnected) => stopping = true,
            Err(RecvTimeoutError::Timeout) => {}
        }
        let interval_start = next_sync - settings.sync;
        let started = Instant::now();
        flush_all(&mut sections, &settings, over_limit);
        let took = started.elapsed();
        if !stopping {
            if let Some(after) = settings.pack_after {
                let deadline = started + settings.sync / 2;
                for section in sections.values_mut() {
                    pack(section, after, deadline);
                }
            }
        }
        let filled = started
            .saturating_duration_since(interval_start)
            .max(settings.sync);
        for section in sections.values() {
            section.out.stats.flush_us.set(took.as_micros() as u64);
            section
                .out
                .stats
                .flush_max_us
                .raise(took.as_micros() as u64);
            if took > filled {
                section.out.stats.overruns.inc();
            }
        }
        next_sync += settings.sync;
        if next_sync < Instant::now() {
            next_sync = Instant::now() + settings.sync;
        }
    }
    for section in sections.into_values() {
        section.close();
    }
}

/// Threads that commit sections' day files at once.
const FLUSH_THREADS: usize = 8;

/// Commits every section's pending samples. Each commit waits for its
/// fsync; one after another, a thousand sections' commits took longer than
/// HISTORY_SYNC on a busy disk. Committed from several threads at once,
/// the file system joins their flushes into fewer journal commits.
fn flush_all(sections: &mut BTreeMap<usize, Section>, settings: &Settings, over_limit: bool) {
    let due: Vec<std::sync::Mutex<&mut Section>> = sections
        .values_mut()
        .filter(|s| !(s.pending.is_empty() && s.events.is_empty()))
        .map(std::sync::Mutex::new)
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let work = || {
        while let Some(section) = due.get(next.fetch_add(1, Ordering::Relaxed)) {
            let mut section = section.lock().unwrap_or_else(|e| e.into_inner());
            flush(&mut section, settings, over_limit);
        }
    };
    std::thread::scope(|scope| {
        // Helpers that cannot be started leave their share to this thread.
        for _ in 1..FLUSH_THREADS.min(due.len()) {
            let _ = std::thread::Builder::new()
                .name("historian flush".into())
                .spawn_scoped(scope, work);
        }
        work();
    });
}

/// Packs a section's samples older than `after` until `deadline`, and
/// finishes the days that are over.
fn pack(section: &mut Section, after: Duration, deadline: Instant) {
    let before_ms = unix_ms(std::time::SystemTime::now()) - after.as_millis() as i64;
    let mut result = Ok(());
    for file in section.files.values_mut() {
        result = result
            .and_then(|()| packed(&section.out.stats, file.pack(before_ms, deadline)).map(drop));
    }
    let mut still = Vec::new();
    for mut file in std::mem::take(&mut section.closing) {
        let step = packed(&section.out.stats, file.pack(i64::MAX, deadline)).and_then(|more| {
            if more {
                Ok(false)
            } else {
                file.shrink(SHRINK_PAGES)
            }
        });
        match step {
            // Done once it is a single file again (a reader in the way:
            // the next round).
            Ok(true) if file.leave_wal() => {
                info!(section = %section.out.name, "history: {} finished", file.path.display());
            }
            Ok(_) => still.push(file),
            Err(e) => {
                result = result.and(Err(e));
                still.push(file);
            }
        }
    }
    section.closing = still;
    match result {
        Ok(_) => {
            if section.pack_failing.take() == Some(true) {
                info!(section = %section.out.name, "history: packing resumed");
            }
        }
        Err(e) => {
            // A full disk stops recording with one log line of its own,
            // now or at the next commit: packing says nothing of it.
            let logged = section.pack_failing.unwrap_or(false) || !is_full(&e);
            if logged && section.pack_failing != Some(true) {
                warn!(section = %section.out.name, "history: packing samples failed: {e}; they stay rows and packing is tried again");
            }
            section.pack_failing = Some(logged);
        }
    }
}

fn is_full(e: &store::StoreError) -> bool {
    matches!(e, rusqlite::Error::SqliteFailure(f, _) if f.code == rusqlite::ErrorCode::DiskFull)
}

/// Counts what packing did; `true` while there is more to pack.
fn packed(
    stats: &Stats,
    done: Result<store::Packing, store::StoreError>,
) -> Result<bool, store::StoreError> {
    let packing = done?;
    stats.packed.add(packing.samples);
    stats.blocks.add(packing.blocks);
    Ok(packing.more)
}

/// The day files of a section, before today, that still have samples to
/// pack: a stop came before they were finished.
fn unfinished_days(settings: &Settings, section: &str) -> Vec<DayFile> {
    let today = day_of(unix_ms(std::time::SystemTime::now()));
    store::day_files(&store::section_dir(&settings.dir, section))
        .into_iter()
        .filter(|(day, path)| *day < today && store::needs_packing(path))
        .filter_map(
            |(day, path)| match DayFile::open(&settings.dir, section, day) {
                Ok(file) => Some(file),
                Err(e) => {
                    warn!(
                        section,
                        "history: cannot open {} to pack it: {e}",
                        path.display()
                    );
                    None
                }
            },
        )
        .collect()
}

/// Commits what a section has pending.
fn flush(section: &mut Section, settings: &Settings, over_limit: bool) {
    if section.pending.is_empty() && section.events.is_empty() {
        return;
    }
    let stats = section.out.stats.clone();
    if over_limit {
        fail(
            section,
            "the history size limit (HISTORY_RETENTION) is reached".into(),
        );
        return;
    }
    match write(section, settings) {
        Ok(counts) => {
            if section.failing.take().is_some() {
                info!(section = %section.out.name, "history: recording resumed");
            }
            stats.state.store(State::Recording as u8, Ordering::Relaxed);
            stats.written.add(counts.written);
            stats.duplicates.add(counts.duplicates);
            stats.shifted.add(counts.shifted);
            if counts.over_limit > 0 {
                stats.dropped.add(counts.over_limit);
                warn!(section = %section.out.name, "history: {} samples of variables beyond the 32,767 of a day file were not stored", counts.over_limit);
            }
            stats
                .queued
                .fetch_sub(section.pending_samples, Ordering::Relaxed);
            section.pending.clear();
            section.events.clear();
            section.pending_samples = 0;
        }
        Err(e) => {
            fail(section, e.to_string());
            // A fresh connection on the next try.
            for (_, file) in section.files.drain() {
                drop(file);
            }
        }
    }
    // Close the files of days that are over (kept open for a late sample
    // at midnight only until the next flush after).
    let today = day_of(unix_ms(std::time::SystemTime::now()));
    let old: Vec<i64> = section
        .files
        .keys()
        .copied()
        .filter(|&d| d < today - 1 || (d < today && section.pending.is_empty()))
        .collect();
    for day in old {
        if let Some(file) = section.files.remove(&day) {
            if settings.pack_after.is_some() {
                section.closing.push(file);
            } else {
                file.close();
            }
        }
    }
    stats.bytes.set(
        section
            .files
            .values()
            .map(|f| store::file_bytes(&f.path))
            .sum(),
    );
}

fn fail(section: &mut Section, why: String) {
    if section.failing.is_none() {
        error!(section = %section.out.name, "history: recording stopped: {why}; samples are kept in memory up to the queue's bound and recording resumes by itself");
        section
            .out
            .stats
            .state
            .store(State::Stopped as u8, Ordering::Relaxed);
    }
    section.failing = Some(why);
}

fn write(section: &mut Section, settings: &Settings) -> Result<WriteCounts, store::StoreError> {
    // Samples by day, each day one transaction.
    let mut days: Vec<i64> = section
        .pending
        .iter()
        .flat_map(|(_, s)| s.iter().map(|s| day_of(s.t)))
        .chain(section.events.iter().map(|e| day_of(e.t)))
        .collect();
    days.sort_unstable();
    days.dedup();
    let mut counts = WriteCounts::default();
    for day in days {
        let file = match section.files.entry(day) {
            std::collections::hash_map::Entry::Occupied(o) => o.into_mut(),
            std::collections::hash_map::Entry::Vacant(v) => {
                // A late sample of a day being finished: the same
                // connection, so that it sees what was packed.
                let file = match section.closing.iter().position(|f| f.day == day) {
                    Some(i) => section.closing.swap_remove(i),
                    None => open_day(settings, &section.out.name, day)?,
                };
                v.insert(file)
            }
        };
        let parts: Vec<(&Arc<VarTable>, Vec<Sample>)> = section
            .pending
            .iter()
            .map(|(table, samples)| {
                (
                    table,
                    samples
                        .iter()
                        .filter(|s| day_of(s.t) == day)
                        .cloned()
                        .collect(),
                )
            })
            .collect();
        let parts: Vec<(&Arc<VarTable>, &[Sample])> =
            parts.iter().map(|(t, s)| (*t, s.as_slice())).collect();
        let events: Vec<Event> = section
            .events
            .iter()
            .filter(|e| day_of(e.t) == day)
            .cloned()
            .collect();
        counts += match file.write(&parts, &events) {
            Err(e) if store::is_damaged(&e) => {
                // Damaged under a running writer: a new file, at once.
                let path = file.path.clone();
                drop(section.files.remove(&day));
                set_aside(&section.out.name, &path, &e)?;
                let file = section.files.entry(day).or_insert(DayFile::open(
                    &settings.dir,
                    &section.out.name,
                    day,
                )?);
                file.write(&parts, &events)?
            }
            done => done?,
        };
    }
    Ok(counts)
}

/// Opens a day file for writing; a damaged one is set aside and a new one
/// started, so that recording does not stop until the next day.
fn open_day(settings: &Settings, section: &str, day: i64) -> Result<DayFile, store::StoreError> {
    match DayFile::open(&settings.dir, section, day) {
        Err(e) if store::is_damaged(&e) => {
            set_aside(section, &store::day_path(&settings.dir, section, day), &e)?;
            DayFile::open(&settings.dir, section, day)
        }
        done => done,
    }
}

/// Moves a damaged day file aside, saying so; the error again if it
/// cannot (recording then stops, and the move is tried at the next commit).
fn set_aside(
    section: &str,
    path: &std::path::Path,
    damage: &store::StoreError,
) -> Result<(), store::StoreError> {
    match store::set_aside(path) {
        Ok(aside) => {
            error!(
                section,
                "history: {} is damaged ({damage}); kept as {} and a new file started \
                 (samples in the damaged file are not read until it is repaired and renamed back)",
                path.display(),
                aside.display()
            );
            Ok(())
        }
        Err(e) => {
            warn!(
                section,
                "history: {} is damaged ({damage}) and cannot be moved aside: {e}",
                path.display()
            );
            Err(clone_error(damage))
        }
    }
}

fn clone_error(e: &store::StoreError) -> store::StoreError {
    match e {
        rusqlite::Error::SqliteFailure(f, text) => rusqlite::Error::SqliteFailure(*f, text.clone()),
        other => rusqlite::Error::InvalidParameterName(other.to_string()),
    }
}

/// Deletes day files past the retention; returns whether the files still
/// take more than the size limit (recording must stop).
fn retention<'a>(settings: &Settings, sections: impl Iterator<Item = &'a Section>) -> bool {
    let Retention { days, bytes } = settings.retention;
    if days.is_none() && bytes.is_none() {
        return false;
    }
    let today = day_of(unix_ms(std::time::SystemTime::now()));
    let mut files: Vec<(i64, PathBuf, u64, bool)> = Vec::new();
    let Ok(entries) = std::fs::read_dir(&settings.dir) else {
        return false;
    };
    let open: Vec<&PathBuf> = sections
        .flat_map(|s| s.files.values().chain(&s.closing).map(|f| &f.path))
        .collect();
    for entry in entries.filter_map(Result::ok) {
        if !entry.path().is_dir() {
            continue;
        }
        for (day, path) in store::day_files(&entry.path()) {
            let size = store::file_bytes(&path);
            let is_open = open.contains(&&path);
            files.push((day, path, size, is_open));
        }
    }
    files.sort_by_key(|f| f.0);
    let mut total: u64 = files.iter().map(|f| f.2).sum();
    for (day, path, size, is_open) in &files {
        let too_old = days.is_some_and(|keep| *day <= today - i64::from(keep));
        let too_big = bytes.is_some_and(|limit| total > limit);
        if (too_old || too_big) && !is_open && *day < today {
            match remove_day(path) {
                Ok(()) => {
                    info!(
                        "history: deleted {} ({})",
                        path.display(),
                        if too_old {
                            "older than the retention"
                        } else {
                            "over the size limit"
                        }
                    );
                    total -= size;
                }
                Err(e) => warn!("history: cannot delete {}: {e}", path.display()),
            }
        }
    }
    bytes.is_some_and(|limit| total > limit)
}

fn remove_day(path: &std::path::Path) -> std::io::Result<()> {
    std::fs::remove_file(path)?;
    for suffix in ["-wal", "-shm", "-journal"] {
        let mut name = path.as_os_str().to_owned();
        name.push(suffix);
        let _ = std::fs::remove_file(PathBuf::from(name));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::day_path;

    /// A day that is over is packed whole, shrunk and closed by the writer;
    /// one a stop left unpacked is finished after the next start.
    #[test]
    fn days_that_are_over_are_packed_and_finished() {
        use crate::sample::Stored;
        use plccoms_core::changes::Quality;
        let dir = tempfile::tempdir().unwrap();
        let table = Arc::new(plccoms_core::vars::table_of(&[
            ("A", "UDINT"),
            ("B", "LREAL"),
        ]));
        let ids = [table.lookup(b"A").unwrap(), table.lookup(b"B").unwrap()];
        let today = day_of(unix_ms(std::time::SystemTime::now()));
        let samples = |day: i64| -> Vec<Sample> {
            (0..5_000i64)
                .flat_map(|c| {
                    ids.iter().map(move |&var| Sample {
                        t: day * store::DAY_MS + c * 100,
                        var,
                        value: Stored::Real(c as f64 / 7.0),
                        quality: Quality::Good,
                        plc_time: None,
                    })
                })
                .collect()
        };
        // Two days ago, left as rows by an earlier run.
        let mut old = DayFile::open(dir.path(), "W", today - 2).unwrap();
        old.write(&[(&table, &samples(today - 2))], &[]).unwrap();
        old.close();
        let settings = Settings {
            dir: dir.path().to_path_buf(),
            sync: Duration::from_millis(50),
            retention: Retention::default(),
            pack_after: Some(Duration::from_secs(3600)),
        };
        let stats = Arc::new(Stats::default());
        let (tx, rx) = std::sync::mpsc::channel();
        let out = SectionOut {
            name: "W".into(),
            stats: stats.clone(),
        };
        let writer = std::thread::spawn(move || run(rx, vec![out], settings));
        // Yesterday, recorded now (late): written, then finished.
        tx.send(Message::Record {
            section: 0,
            table: table.clone(),
            samples: samples(today - 1),
            events: Vec::new(),
        })
        .unwrap();
        let finished = |day: i64| -> bool {
            let path = day_path(dir.path(), "W", day);
            let Ok(conn) = store::open_read(&path) else {
                return false;
            };
            let get = |sql: &str| -> i64 { conn.query_row(sql, [], |r| r.get(0)).unwrap_or(-1) };
            let mode: String = conn
                .query_row("PRAGMA journal_mode", [], |r| r.get(0))
                .unwrap_or_default();
            get("SELECT count(*) FROM samples") == 0
                && get("SELECT coalesce(sum(samples), 0) FROM blocks") == 10_000
                && get("PRAGMA freelist_count") == 0
                && mode == "delete"
        };
        // Each check opens the file: the writer leaves WAL mode in a round
        // when no check is in the way.
        let deadline = Instant::now() + Duration::from_secs(60);
        while !(finished(today - 2) && finished(today - 1)) {
            assert!(Instant::now() < deadline, "packed {}", stats.packed.get());
            std::thread::sleep(Duration::from_millis(20));
        }
        tx.send(Message::Stop).unwrap();
        writer.join().unwrap();
        assert_eq!(stats.packed.get(), 20_000);
    }

    /// A file at a day's path that is not a history file, or not a
    /// database at all, is kept aside and a new file of the day opened.
    #[test]
    fn a_damaged_or_foreign_day_file_is_set_aside() {
        let dir = tempfile::tempdir().unwrap();
        let settings = Settings {
            dir: dir.path().to_path_buf(),
            sync: Duration::from_secs(1),
            retention: Retention::default(),
            pack_after: None,
        };
        let day = day_of(unix_ms(std::time::SystemTime::now()));
        let path = day_path(dir.path(), "D", day);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let foreign = rusqlite::Connection::open(&path).unwrap();
        foreign
            .execute_batch(
                "CREATE TABLE meta (key, value); INSERT INTO meta VALUES ('format', 'other');",
            )
            .unwrap();
        drop(foreign);
        for damage in [None, Some(b"not a database at all".to_vec())] {
            if let Some(bytes) = &damage {
                std::fs::write(&path, bytes).unwrap();
            }
            let before = std::fs::read(&path).unwrap();
            let file = open_day(&settings, "D", day).unwrap();
            file.close();
            let aside: Vec<PathBuf> = std::fs::read_dir(path.parent().unwrap())
                .unwrap()
                .filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.to_string_lossy().contains(".sqlite.damaged-"))
                .filter(|p| std::fs::read(p).is_ok_and(|b| b == before))
                .collect();
            assert_eq!(aside.len(), 1, "{damage:?}");
            store::open_read(&path).unwrap();
        }
    }

    #[test]
    fn retention_by_days_and_by_size() {
        let dir = tempfile::tempdir().unwrap();
        let today = day_of(unix_ms(std::time::SystemTime::now()));
        let make = |section: &str, day: i64, bytes: usize| {
            let path = day_path(dir.path(), section, day);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, vec![0u8; bytes]).unwrap();
            path
        };
        let old = make("A", today - 40, 10);
        let wal = PathBuf::from(format!("{}-wal", old.display()));
        std::fs::write(&wal, b"x").unwrap();
        let a_week = make("A", today - 7, 1000);
        let b_yesterday = make("B", today - 1, 1000);
        let b_today = make("B", today, 1000);
        let settings = |days, bytes| Settings {
            dir: dir.path().to_path_buf(),
            sync: Duration::from_secs(1),
            retention: Retention { days, bytes },
            pack_after: None,
        };
        // 30 days: the 40-day-old file (and its WAL) goes.
        assert!(!retention(&settings(Some(30), None), [].iter()));
        assert!(!old.exists() && !wal.exists());
        assert!(a_week.exists() && b_yesterday.exists());
        // 2500 bytes for 3000: the oldest goes, whatever its section.
        assert!(!retention(&settings(None, Some(2500)), [].iter()));
        assert!(!a_week.exists() && b_yesterday.exists() && b_today.exists());
        // Today's file is never deleted: over the limit, recording stops.
        assert!(retention(&settings(None, Some(500)), [].iter()));
        assert!(!b_yesterday.exists() && b_today.exists());
    }
}
