//! The history files: one SQLite database per section per UTC day,
//! `<HISTORY_DIR>/<section>/<section>-YYYY-MM-DD.sqlite`, in WAL mode while
//! written (readers never wait for the writer, a crash loses at most the
//! transaction in progress), switched back to a single file when the day is
//! done, so a day can be copied away as it is.
//!
//! Schema (version 3), chosen for size: a sample is first one row of a
//! rowid table whose integer key packs the time and the variable, so time
//! and variable cost one 6-byte varint and rows are appended in key order
//! (SQLite fills pages completely on append). Samples older than
//! HISTORY_COMPACT are then packed, a run of up to 65,536 consecutive keys
//! at a time, into one row of `blocks` (see [`super::block`]): a few bytes
//! a sample instead of 12 plus the value. Keys are unique across `samples`
//! and `blocks`; a late sample (a clock set back) below the packed range
//! stays a row.
//!
//! ```sql
//! meta    (key TEXT PRIMARY KEY, value)            -- format, version, section, day, day_start_ms, var_bits
//! vars    (id INTEGER PRIMARY KEY, name TEXT UNIQUE, type TEXT)
//! samples (key INTEGER PRIMARY KEY, value)
//!         -- key = (time_ms - day_start_ms) << 15 | vars.id
//!         -- value: INTEGER, REAL, TEXT (NULL: a REAL that was NaN)
//! qualities (key INTEGER PRIMARY KEY, quality INTEGER) -- 1 stale, 2 link_lost;
//!         -- a sample without a row here is good (almost all are: a byte saved)
//! stamps  (key INTEGER PRIMARY KEY, plc_time INTEGER)  -- samples.key -> PLC ms
//! blocks  (first_key INTEGER PRIMARY KEY, last_key INTEGER, samples INTEGER, data BLOB)
//!         -- the samples with keys first_key..=last_key, packed
//! packed_stamps (id INTEGER PRIMARY KEY) -- variables with PLC stamps in blocks
//! events  (id INTEGER PRIMARY KEY, time INTEGER, kind TEXT, detail TEXT)
//! history -- a view of the rows of `samples`: time (ISO 8601), time_ms,
//!         -- name, value, quality, plc_time_ms
//! ```
//!
//! Version 1 files (no `blocks`) are read as they are and gain the table
//! when written to. Version 3 seals each block with a checksum; the blocks
//! of a version 2 file are read unchecked, and the file becomes version 3
//! (new blocks sealed) when written to.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use rusqlite::types::{ToSqlOutput, ValueRef};
use rusqlite::{params, Connection, OpenFlags, OptionalExtension, ToSql};

use super::block::{self, Packed};
use super::sample::{quality_code, Event, Sample, Stored};
use plccoms_core::vars::VarTable;

pub const FORMAT: &str = "plccoms-history";
/// 3: blocks are sealed with a checksum (version 2's are read unchecked).
pub const VERSION: i64 = 3;
pub use crate::key::{day_name, day_of, DAY_MS, VAR_BITS, VAR_MASK};

pub type StoreError = rusqlite::Error;

/// The section's folder name: the section name with characters that are not
/// safe in a file name replaced by `_`.
pub fn safe_name(section: &str) -> String {
    section
        .chars()
        .map(|c| {
            if c.is_alphanumeric() || matches!(c, '-' | '_' | '.') {
                c
            } else {
                '_'
            }
        })
        .collect()
}

pub fn section_dir(dir: &Path, section: &str) -> PathBuf {
    dir.join(safe_name(section))
}

pub fn day_path(dir: &Path, section: &str, day: i64) -> PathBuf {
    let name = safe_name(section);
    dir.join(&name)
        .join(format!("{name}-{}.sqlite", day_name(day)))
}

/// The day files of a section folder, oldest first.
pub fn day_files(section_dir: &Path) -> Vec<(i64, PathBuf)> {
    let Ok(entries) = std::fs::read_dir(section_dir) else {
        return Vec::new();
    };
    let mut files: Vec<(i64, PathBuf)> = entries
        .filter_map(Result::ok)
        .filter_map(|entry| {
            let name = entry.file_name().into_string().ok()?;
            let stem = name.strip_suffix(".sqlite")?;
            let date = stem.get(stem.len().checked_sub(10)?..)?;
            let date = chrono::NaiveDate::parse_from_str(date, "%Y-%m-%d").ok()?;
            let day = date
                .signed_duration_since(chrono::NaiveDate::default())
                .num_days();
            Some((day, entry.path()))
        })
        .collect();
    files.sort();
    files
}

/// Bytes a day file takes, its WAL included.
pub fn file_bytes(path: &Path) -> u64 {
    let size = |p: &Path| std::fs::metadata(p).map_or(0, |m| m.len());
    size(path) + size(&with_suffix(path, "-wal")) + size(&with_suffix(path, "-shm"))
}

fn with_suffix(path: &Path, suffix: &str) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(suffix);
    PathBuf::from(name)
}

/// Opens a day file for reading; it may be being written.
pub fn open_read(path: &Path) -> Result<Connection, StoreError> {
    let conn = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )?;
    conn.busy_timeout(std::time::Duration::from_secs(5))?;
    check_format(&conn)?;
    Ok(conn)
}

/// Whether a day file has samples packing would take: rows above its last
/// block.
pub fn needs_packing(path: &Path) -> bool {
    let check = |conn: Connection| -> Result<bool, StoreError> {
        let packed_to = last_packed_key(&conn)?;
        conn.query_row(
            "SELECT EXISTS (SELECT 1 FROM samples WHERE key > ?1)",
            [packed_to],
            |r| r.get(0),
        )
    };
    open_read(path).and_then(check).unwrap_or(false)
}

/// Whether a file has table `name` (files of an earlier version lack some).
pub fn has_table(conn: &Connection, name: &str) -> Result<bool, StoreError> {
    conn.query_row(
        "SELECT EXISTS (SELECT 1 FROM sqlite_master WHERE name = ?1)",
        [name],
        |r| r.get(0),
    )
}

/// The last key packed into a block (-1: none). Blocks never overlap and
/// come in key order, so it is the last block's: found by the primary key,
/// not by a scan of every block.
fn last_packed_key(conn: &Connection) -> Result<i64, StoreError> {
    if !has_table(conn, "blocks")? {
        return Ok(-1);
    }
    conn.query_row(
        "SELECT coalesce((SELECT last_key FROM blocks ORDER BY first_key DESC LIMIT 1), -1)",
        [],
        |r| r.get(0),
    )
}

/// Whether an error says the file itself is damaged (or not a history
/// file at all), not that writing failed (a full disk, an I/O error).
pub fn is_damaged(e: &StoreError) -> bool {
    match e {
        rusqlite::Error::SqliteFailure(f, _) => matches!(
            f.code,
            rusqlite::ErrorCode::DatabaseCorrupt | rusqlite::ErrorCode::NotADatabase
        ),
        rusqlite::Error::InvalidParameterName(text) => text.starts_with(NOT_A_HISTORY_FILE),
        _ => false,
    }
}

const NOT_A_HISTORY_FILE: &str = "not a plccoms-history file";

/// Moves a damaged day file (and its WAL and shared memory) aside, to
/// `<name>.damaged-<UTC time>`: kept for a look or a repair, out of the way
/// of recording (day files end in `.sqlite`, so queries and the retention
/// skip it). Returns the new path.
pub fn set_aside(path: &Path) -> std::io::Result<PathBuf> {
    let stamp = chrono::Utc::now().format("%Y%m%dT%H%M%SZ");
    // Never over one set aside before (twice in a second: `-2`, ...).
    let aside = (1..)
        .map(|n| {
            let mut aside = path.as_os_str().to_owned();
            aside.push(format!(".damaged-{stamp}"));
            if n > 1 {
                aside.push(format!("-{n}"));
            }
            PathBuf::from(aside)
        })
        .find(|aside| std::fs::symlink_metadata(aside).is_err())
        .expect("a free name");
    std::fs::rename(path, &aside)?;
    for suffix in ["-wal", "-shm", "-journal"] {
        let _ = std::fs::rename(with_suffix(path, suffix), with_suffix(&aside, suffix));
    }
    Ok(aside)
}

fn check_format(conn: &Connection) -> Result<(), StoreError> {
    let format: Option<String> = conn
        .query_row("SELECT value FROM meta WHERE key = 'format'", [], |r| {
            r.get(0)
        })
        .optional()?;
    let version: Option<i64> = conn
        .query_row("SELECT value FROM meta WHERE key = 'version'", [], |r| {
            r.get(0)
        })
        .optional()?;
    if format.as_deref() != Some(FORMAT) || !version.is_some_and(|v| (1..=VERSION).contains(&v)) {
        return Err(rusqlite::Error::InvalidParameterName(format!(
            "{NOT_A_HISTORY_FILE} of version 1 to {VERSION} (format {format:?}, version {version:?})"
        )));
    }
    Ok(())
}

/// What a write did besides inserting.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct WriteCounts {
    pub written: u64,
    /// The same sample again (event capture of a cycle already recorded).
    pub duplicates: u64,
    /// Another value of a variable at a millisecond it already has one for
    /// (a clock set back): stored a millisecond later.
    pub shifted: u64,
    /// Variables beyond the file's 32,767: not stored.
    pub over_limit: u64,
}

impl std::ops::AddAssign for WriteCounts {
    fn add_assign(&mut self, other: WriteCounts) {
        self.written += other.written;
        self.duplicates += other.duplicates;
        self.shifted += other.shifted;
        self.over_limit += other.over_limit;
    }
}

/// One section's day file, open for writing.
pub struct DayFile {
    conn: Connection,
    pub day: i64,
    pub path: PathBuf,
    start_ms: i64,
    ids: HashMap<String, i64>,
    next_id: i64,
    /// The table last mapped, and its variables' ids here (-1: none yet).
    mapped: Option<(Arc<VarTable>, Vec<i64>)>,
    /// The last key packed into a block (-1: none).
    packed_to: i64,
    /// The block last unpacked for a late sample: (first key, last key, samples).
    late_block: Option<(i64, i64, Vec<Packed>)>,
}

/// What packing did.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Packing {
    pub blocks: u64,
    pub samples: u64,
    /// Stopped at the deadline with samples left to pack.
    pub more: bool,
}

/// Blocks smaller than this wait for more samples (unless the day is over):
/// a block's own cost is spread over many samples.
pub const MIN_BLOCK: usize = 4096;

const SCHEMA: &str = "
CREATE TABLE meta (key TEXT PRIMARY KEY, value) WITHOUT ROWID;
CREATE TABLE vars (id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, type TEXT NOT NULL);
CREATE TABLE samples (key INTEGER PRIMARY KEY, value);
CREATE TABLE qualities (key INTEGER PRIMARY KEY, quality INTEGER NOT NULL);
CREATE TABLE stamps (key INTEGER PRIMARY KEY, plc_time INTEGER NOT NULL);
CREATE TABLE events (id INTEGER PRIMARY KEY, time INTEGER NOT NULL, kind TEXT NOT NULL, detail TEXT NOT NULL);
CREATE TABLE blocks (first_key INTEGER PRIMARY KEY, last_key INTEGER NOT NULL, samples INTEGER NOT NULL, data BLOB NOT NULL);
CREATE TABLE packed_stamps (id INTEGER PRIMARY KEY);
";

const BLOCKS_V1: &str = "
CREATE TABLE IF NOT EXISTS blocks (first_key INTEGER PRIMARY KEY, last_key INTEGER NOT NULL, samples INTEGER NOT NULL, data BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS packed_stamps (id INTEGER PRIMARY KEY);
UPDATE meta SET value = 3 WHERE key = 'version';
";

impl DayFile {
    /// Opens (creating if need be) the day file of `section` for `day`.
    pub fn open(dir: &Path, section: &str, day: i64) -> Result<DayFile, StoreError> {
        let path = day_path(dir, section, day);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| {
                rusqlite::Error::InvalidPath(PathBuf::from(format!("{}: {e}", parent.display())))
            })?;
        }
        let conn = Connection::open(&path)?;
        conn.busy_timeout(std::time::Duration::from_secs(5))?;
        // A file that is not a history file is left as it is.
        let existing = has_table(&conn, "meta")?;
        if existing {
            check_format(&conn)?;
        }
        // Packing frees the pages of the rows it packs; a finished day
        // gives them back (only a new file can take this setting).
        conn.pragma_update(None, "auto_vacuum", "INCREMENTAL")?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        // Every commit is on disk when it returns (one fsync per commit,
        // one commit per HISTORY_SYNC).
        conn.pragma_update(None, "synchronous", "FULL")?;
        let start_ms = day * DAY_MS;
        if existing {
            conn.execute_batch(BLOCKS_V1)?;
        } else {
            let tx = conn.unchecked_transaction()?;
            tx.execute_batch(SCHEMA)?;
            let created = chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Millis, true);
            let meta: [(&str, &dyn ToSql); 7] = [
                ("format", &FORMAT),
                ("version", &VERSION),
                ("section", &section),
                ("day", &day_name(day)),
                ("day_start_ms", &start_ms),
                ("var_bits", &VAR_BITS),
                ("created", &created),
            ];
            for (key, value) in meta {
                tx.execute("INSERT INTO meta VALUES (?1, ?2)", params![key, value])?;
            }
            tx.execute_batch(&view_sql(start_ms))?;
            tx.commit()?;
        }
        let mut ids = HashMap::new();
        let mut next_id = 0;
        {
            let mut stmt = conn.prepare("SELECT id, name FROM vars")?;
            let mut rows = stmt.query([])?;
            while let Some(row) = rows.next()? {
                let id: i64 = row.get(0)?;
                ids.insert(row.get(1)?, id);
                next_id = next_id.max(id + 1);
            }
        }
        let packed_to = last_packed_key(&conn)?;
        Ok(DayFile {
            conn,
            day,
            path,
            start_ms,
            ids,
            next_id,
            mapped: None,
            packed_to,
            late_block: None,
        })
    }

    /// Writes samples (all of this day) of variables of `table`, and
    /// events, in one transaction.
    pub fn write(
        &mut self,
        parts: &[(&Arc<VarTable>, &[Sample])],
        events: &[Event],
    ) -> Result<WriteCounts, StoreError> {
        self.conn.execute_batch("BEGIN")?;
        match self.write_all(parts, events) {
            Ok(counts) => {
                self.conn.execute_batch("COMMIT")?;
                Ok(counts)
            }
            Err(e) => {
                let _ = self.conn.execute_batch("ROLLBACK");
                Err(e)
            }
        }
    }

    fn write_all(
        &mut self,
        parts: &[(&Arc<VarTable>, &[Sample])],
        events: &[Event],
    ) -> Result<WriteCounts, StoreError> {
        let mut counts = WriteCounts::default();
        for &(table, samples) in parts {
            self.map_table(table);
            for sample in samples {
                let id = self.var_id(table, sample.var)?;
                let Some(id) = id else {
                    counts.over_limit += 1;
                    continue;
                };
                let key = ((sample.t - self.start_ms) << VAR_BITS) | id;
                self.insert(key, sample, &mut counts)?;
            }
        }
        {
            let mut stmt = self
                .conn
                .prepare_cached("INSERT INTO events (time, kind, detail) VALUES (?1, ?2, ?3)")?;
            for event in events {
                stmt.execute(params![event.t, event.kind.as_str(), event.detail])?;
            }
        }
        Ok(counts)
    }

    fn map_table(&mut self, table: &Arc<VarTable>) {
        if !self
            .mapped
            .as_ref()
            .is_some_and(|(t, _)| Arc::ptr_eq(t, table))
        {
            self.mapped = Some((table.clone(), vec![-1; table.len()]));
        }
    }

    /// The file's id of variable `var` of the mapped table; `None` past the
    /// limit.
    fn var_id(&mut self, table: &VarTable, var: u32) -> Result<Option<i64>, StoreError> {
        let Some((_, map)) = &mut self.mapped else {
            return Ok(None);
        };
        let known = map[var as usize];
        if known >= 0 {
            return Ok(Some(known));
        }
        let v = table.var(var);
        let name = plccoms_protocol::cp1250::decode(&v.name).into_owned();
        let id = match self.ids.get(&name) {
            Some(&id) => id,
            None => {
                if self.next_id > VAR_MASK {
                    return Ok(None);
                }
                let id = self.next_id;
                self.conn.execute(
                    "INSERT INTO vars (id, name, type) VALUES (?1, ?2, ?3)",
                    params![id, name, v.ty.to_string()],
                )?;
                self.next_id += 1;
                self.ids.insert(name, id);
                id
            }
        };
        map[var as usize] = id;
        Ok(Some(id))
    }

    fn insert(
        &mut self,
        mut key: i64,
        sample: &Sample,
        counts: &mut WriteCounts,
    ) -> Result<(), StoreError> {
        let quality = quality_code(sample.quality);
        let mut shifted = false;
        loop {
            // The sample already at this key, in a block or a row.
            let mut taken = None;
            if key <= self.packed_to {
                taken = self.packed_at(key)?.map(|(v, q)| (v, i64::from(q)));
            }
            if taken.is_none() {
                let inserted = self
                    .conn
                    .prepare_cached("INSERT INTO samples (key, value) VALUES (?1, ?2)")?
                    .execute(params![key, sample.value]);
                match inserted {
                    Ok(_) => break,
                    Err(e) if is_constraint(&e) => {
                        taken = Some(self.conn.query_row(
                            "SELECT value, coalesce((SELECT quality FROM qualities q WHERE q.key = s.key), 0) \
                             FROM samples s WHERE key = ?1",
                            [key],
                            |r| Ok((Stored::from_sql(r.get_ref(0)?), r.get(1)?)),
                        )?);
                    }
                    Err(e) => return Err(e),
                }
            }
            if let Some((value, q)) = taken {
                if same_stored(&value, &sample.value) && q == quality {
                    counts.duplicates += 1;
                    return Ok(());
                }
            }
            // Another value at the same millisecond: the next one.
            key += 1 << VAR_BITS;
            shifted = true;
            if (key >> VAR_BITS) >= DAY_MS {
                counts.over_limit += 1;
                return Ok(());
            }
        }
        counts.written += 1;
        counts.shifted += u64::from(shifted);
        if quality != 0 {
            self.conn
                .prepare_cached("INSERT OR REPLACE INTO qualities (key, quality) VALUES (?1, ?2)")?
                .execute(params![key, quality])?;
        }
        if let Some(plc_time) = sample.plc_time {
            self.conn
                .prepare_cached("INSERT OR REPLACE INTO stamps (key, plc_time) VALUES (?1, ?2)")?
                .execute(params![key, plc_time])?;
        }
        Ok(())
    }

    /// The value and quality of a packed sample, if `key` is one.
    fn packed_at(&mut self, key: i64) -> Result<Option<(Stored, u8)>, StoreError> {
        let cached = self
            .late_block
            .as_ref()
            .is_some_and(|(first, last, _)| (*first..=*last).contains(&key));
        if !cached {
            let block: Option<(i64, i64, Vec<u8>)> = self
                .conn
                .query_row(
                    "SELECT first_key, last_key, data FROM blocks WHERE first_key <= ?1 \
                     ORDER BY first_key DESC LIMIT 1",
                    [key],
                    |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
                )
                .optional()?;
            let Some((first, last, data)) = block.filter(|b| b.1 >= key) else {
                return Ok(None);
            };
            // A damaged block takes no late sample: it stays a row, read
            // back beside the block's damage, and recording goes on.
            let rows = block::decode(&data).unwrap_or_default();
            self.late_block = Some((first, last, rows));
        }
        let rows = &self.late_block.as_ref().expect("cached above").2;
        Ok(rows
            .binary_search_by_key(&key, |r| r.key)
            .ok()
            .map(|i| (rows[i].value.clone(), rows[i].quality)))
    }

    /// Packs the samples polled before `before_ms` (`i64::MAX`: all of
    /// them) into blocks, one transaction a block, until `deadline`.
    pub fn pack(&mut self, before_ms: i64, deadline: Instant) -> Result<Packing, StoreError> {
        let all = before_ms == i64::MAX;
        let end_key = (before_ms.saturating_sub(self.start_ms)).clamp(0, DAY_MS) << VAR_BITS;
        let mut packing = Packing::default();
        loop {
            if Instant::now() >= deadline {
                packing.more = self.has_rows_to_pack(end_key)?;
                break;
            }
            let rows = self.rows_to_pack(end_key)?;
            let (Some(first), Some(last)) = (rows.first(), rows.last()) else {
                break;
            };
            if rows.len() < MIN_BLOCK && !all {
                break;
            }
            let (first, last) = (first.key, last.key);
            let data = block::encode(&rows);
            let tx = self.conn.unchecked_transaction()?;
            tx.prepare_cached(
                "INSERT INTO blocks (first_key, last_key, samples, data) VALUES (?1, ?2, ?3, ?4)",
            )?
            .execute(params![first, last, rows.len() as i64, data])?;
            for var in rows
                .iter()
                .filter(|r| r.plc_time.is_some())
                .map(|r| r.key & VAR_MASK)
            {
                tx.prepare_cached("INSERT OR IGNORE INTO packed_stamps (id) VALUES (?1)")?
                    .execute([var])?;
            }
            for table in ["samples", "qualities", "stamps"] {
                tx.prepare_cached(&format!("DELETE FROM {table} WHERE key > ?1 AND key <= ?2"))?
                    .execute(params![self.packed_to, last])?;
            }
            tx.commit()?;
            self.packed_to = last;
            packing.blocks += 1;
            packing.samples += rows.len() as u64;
            if rows.len() < block::MAX_ROWS {
                break;
            }
        }
        Ok(packing)
    }

    fn has_rows_to_pack(&self, end_key: i64) -> Result<bool, StoreError> {
        self.conn
            .prepare_cached("SELECT EXISTS (SELECT 1 FROM samples WHERE key > ?1 AND key < ?2)")?
            .query_row([self.packed_to, end_key], |r| r.get(0))
    }

    /// The next samples to pack: rows above the packed range and below
    /// `end_key`, with their qualities and stamps.
    fn rows_to_pack(&self, end_key: i64) -> Result<Vec<Packed>, StoreError> {
        let mut stmt = self.conn.prepare_cached(&format!(
            "SELECT key, value FROM samples WHERE key > ?1 AND key < ?2 ORDER BY key LIMIT {}",
            block::MAX_ROWS
        ))?;
        let mut rows: Vec<Packed> = stmt
            .query_map([self.packed_to, end_key], |r| {
                Ok(Packed {
                    key: r.get(0)?,
                    value: Stored::from_sql(r.get_ref(1)?),
                    quality: 0,
                    plc_time: None,
                })
            })?
            .collect::<Result<_, _>>()?;
        let Some(last) = rows.last().map(|r| r.key) else {
            return Ok(rows);
        };
        for (table, column) in [("qualities", "quality"), ("stamps", "plc_time")] {
            let mut stmt = self.conn.prepare_cached(&format!(
                "SELECT key, {column} FROM {table} WHERE key > ?1 AND key <= ?2"
            ))?;
            let side = stmt.query_map([self.packed_to, last], |r| {
                Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?))
            })?;
            for item in side {
                let (key, v) = item?;
                if let Ok(i) = rows.binary_search_by_key(&key, |r| r.key) {
                    if table == "qualities" {
                        rows[i].quality = v.clamp(0, 2) as u8;
                    } else {
                        rows[i].plc_time = Some(v);
                    }
                }
            }
        }
        Ok(rows)
    }

    /// Gives pages freed by packing back to the file system, up to `pages`
    /// of them; `true` when none are left.
    pub fn shrink(&mut self, pages: u32) -> Result<bool, StoreError> {
        let auto_vacuum: i64 = self
            .conn
            .query_row("PRAGMA auto_vacuum", [], |r| r.get(0))?;
        if auto_vacuum != 2 {
            // A file of an earlier version (no incremental vacuum): rebuilt
            // once, from its live pages only.
            self.conn.execute_batch("VACUUM")?;
            return Ok(true);
        }
        // Stepped to the end: a step frees one page.
        self.conn
            .execute_batch(&format!("PRAGMA incremental_vacuum({pages})"))?;
        let free: i64 = self
            .conn
            .query_row("PRAGMA freelist_count", [], |r| r.get(0))?;
        Ok(free == 0)
    }

    /// Folds the WAL in: the file becomes a single file again. `false`
    /// while a reader has it open (SQLite then keeps WAL mode).
    pub fn leave_wal(&self) -> bool {
        self.conn
            .query_row("PRAGMA journal_mode = DELETE", [], |r| {
                r.get::<_, String>(0)
            })
            .is_ok_and(|mode| mode.eq_ignore_ascii_case("delete"))
    }

    /// Ends writing, leaving WAL mode if no reader is in the way.
    pub fn close(self) {
        self.leave_wal();
    }
}

fn is_constraint(e: &rusqlite::Error) -> bool {
    matches!(e, rusqlite::Error::SqliteFailure(f, _) if f.code == rusqlite::ErrorCode::ConstraintViolation)
}

fn same_stored(a: &Stored, b: &Stored) -> bool {
    match (a, b) {
        (Stored::Real(x), Stored::Real(y)) => x.to_bits() == y.to_bits(),
        (x, y) => x == y,
    }
}

/// A block's samples; a damaged block is an error of the file.
pub fn unpack(data: &[u8]) -> Result<Vec<Packed>, StoreError> {
    block::decode(data).map_err(|e| {
        rusqlite::Error::FromSqlConversionFailure(0, rusqlite::types::Type::Blob, Box::new(e))
    })
}

/// The samples of the block row `(first_key, last_key, samples, data)`,
/// checked against the row: damage of the data or of the row is an error.
pub fn unpack_block(
    first: i64,
    last: i64,
    count: i64,
    data: &[u8],
) -> Result<Vec<Packed>, block::BlockError> {
    let samples = block::decode(data)?;
    let keys = samples.first().map(|s| s.key)..=samples.last().map(|s| s.key);
    if samples.len() as i64 != count || keys != (Some(first)..=Some(last)) {
        return Err(block::BlockError {
            what: format!(
                "its row says {count} samples with keys {first} to {last}, it holds {} with keys {:?} to {:?}",
                samples.len(),
                keys.start(),
                keys.end()
            ),
            at: 0,
            len: data.len(),
        });
    }
    Ok(samples)
}

/// The `history` view: samples with their time, name and quality spelled
/// out, for sqlite3, DB Browser, pandas.read_sql and MATLAB.
fn view_sql(start_ms: i64) -> String {
    format!(
        "CREATE VIEW history AS SELECT
            strftime('%Y-%m-%dT%H:%M:%fZ', ({start_ms} + (s.key >> {VAR_BITS})) / 1000.0, 'unixepoch') AS time,
            {start_ms} + (s.key >> {VAR_BITS}) AS time_ms,
            v.name AS name,
            s.value AS value,
            CASE q.quality WHEN 1 THEN 'stale' WHEN 2 THEN 'link_lost' ELSE 'good' END AS quality,
            st.plc_time AS plc_time_ms
         FROM samples s
         JOIN vars v ON v.id = (s.key & {VAR_MASK})
         LEFT JOIN qualities q ON q.key = s.key
         LEFT JOIN stamps st ON st.key = s.key;"
    )
}

impl ToSql for Stored {
    fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
        Ok(ToSqlOutput::Borrowed(match self {
            Stored::Int(i) => ValueRef::Integer(*i),
            Stored::Real(f) => ValueRef::Real(*f),
            Stored::Text(s) => ValueRef::Text(s.as_bytes()),
            Stored::Null => ValueRef::Null,
        }))
    }
}

impl Stored {
    /// A value as read back from a file.
    pub fn from_sql(value: ValueRef<'_>) -> Stored {
        match value {
            ValueRef::Integer(i) => Stored::Int(i),
            ValueRef::Real(f) => Stored::Real(f),
            ValueRef::Text(t) | ValueRef::Blob(t) => {
                Stored::Text(String::from_utf8_lossy(t).into_owned())
            }
            ValueRef::Null => Stored::Null,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::changes::Quality;
    use plccoms_core::vars::table_of;

    #[test]
    fn names_and_days() {
        assert_eq!(day_name(day_of(1_700_000_000_000)), "2023-11-14");
        assert_eq!(day_of(-1), -1);
        assert_eq!(safe_name("My PLC/1"), "My_PLC_1");
        let dir = tempfile::tempdir().unwrap();
        let day = day_of(1_700_000_000_000);
        let path = day_path(dir.path(), "A b", day);
        assert!(path.ends_with("A_b/A_b-2023-11-14.sqlite"));
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, b"").unwrap();
        std::fs::write(path.with_file_name("notes.txt"), b"").unwrap();
        assert_eq!(day_files(path.parent().unwrap()), [(day, path)]);
    }

    #[test]
    fn samples_duplicates_and_a_clock_set_back() {
        let dir = tempfile::tempdir().unwrap();
        let table = Arc::new(table_of(&[("A", "INT"), ("B", "STRING")]));
        let a = table.lookup(b"A").unwrap();
        let b = table.lookup(b"B").unwrap();
        let t = 1_700_000_000_123;
        let mut file = DayFile::open(dir.path(), "S", day_of(t)).unwrap();
        let sample = |var, t, value| Sample {
            t,
            var,
            value,
            quality: Quality::Good,
            plc_time: None,
        };
        let samples = [
            sample(a, t, Stored::Int(1)),
            sample(b, t, Stored::Text("ž".into())),
            sample(a, t, Stored::Int(1)),
            sample(a, t, Stored::Int(2)),
        ];
        let counts = file.write(&[(&table, &samples)], &[]).unwrap();
        assert_eq!(
            counts,
            WriteCounts {
                written: 3,
                duplicates: 1,
                shifted: 1,
                over_limit: 0
            }
        );
        let rows: Vec<(String, i64, String)> = file
            .conn
            .prepare("SELECT time, time_ms, name FROM history")
            .unwrap()
            .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(
            rows,
            [
                ("2023-11-14T22:13:20.123Z".into(), t, "A".into()),
                ("2023-11-14T22:13:20.123Z".into(), t, "B".into()),
                ("2023-11-14T22:13:20.124Z".into(), t + 1, "A".into()),
            ]
        );
    }
}
