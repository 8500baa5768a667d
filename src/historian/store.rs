//! The history files: one SQLite database per section per UTC day,
//! `<HISTORY_DIR>/<section>/<section>-YYYY-MM-DD.sqlite`, in WAL mode while
//! written (readers never wait for the writer, a crash loses at most the
//! transaction in progress), switched back to a single file when the day is
//! done, so a day can be copied away as it is.
//!
//! Schema (version 1), chosen for size: a sample is one row of a rowid
//! table whose integer key packs the time and the variable, so time and
//! variable cost one 6-byte varint and rows are appended in key order
//! (SQLite fills pages completely on append):
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
//! events  (id INTEGER PRIMARY KEY, time INTEGER, kind TEXT, detail TEXT)
//! history -- a view: time (ISO 8601), time_ms, name, value, quality, plc_time_ms
//! ```

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rusqlite::types::{ToSqlOutput, Value as SqlValue, ValueRef};
use rusqlite::{params, Connection, OpenFlags, OptionalExtension, ToSql};

use super::sample::{quality_code, Event, Sample, Stored};
use crate::vars::VarTable;

pub const FORMAT: &str = "plccoms-history";
pub const VERSION: i64 = 1;
/// Bits of the key that hold the variable: 32,767 variables per section and
/// day, and a key below 2^42 (a 6-byte varint).
pub const VAR_BITS: u32 = 15;
pub const VAR_MASK: i64 = (1 << VAR_BITS) - 1;
pub const DAY_MS: i64 = 86_400_000;

pub type StoreError = rusqlite::Error;

/// The UTC day (days since 1970) of `t_ms`.
pub fn day_of(t_ms: i64) -> i64 {
    t_ms.div_euclid(DAY_MS)
}

/// `YYYY-MM-DD` of a day.
pub fn day_name(day: i64) -> String {
    chrono::DateTime::from_timestamp_millis(day * DAY_MS)
        .map(|d| d.format("%Y-%m-%d").to_string())
        .unwrap_or_else(|| format!("day{day}"))
}

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
    if format.as_deref() != Some(FORMAT) || version != Some(VERSION) {
        return Err(rusqlite::Error::InvalidParameterName(format!(
            "not a {FORMAT} file of version {VERSION} (format {format:?}, version {version:?})"
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
}

const SCHEMA: &str = "
CREATE TABLE meta (key TEXT PRIMARY KEY, value) WITHOUT ROWID;
CREATE TABLE vars (id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, type TEXT NOT NULL);
CREATE TABLE samples (key INTEGER PRIMARY KEY, value);
CREATE TABLE qualities (key INTEGER PRIMARY KEY, quality INTEGER NOT NULL);
CREATE TABLE stamps (key INTEGER PRIMARY KEY, plc_time INTEGER NOT NULL);
CREATE TABLE events (id INTEGER PRIMARY KEY, time INTEGER NOT NULL, kind TEXT NOT NULL, detail TEXT NOT NULL);
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
        conn.pragma_update(None, "journal_mode", "WAL")?;
        // Every commit is on disk when it returns (one fsync per commit,
        // one commit per HISTORY_SYNC).
        conn.pragma_update(None, "synchronous", "FULL")?;
        let start_ms = day * DAY_MS;
        let exists: bool = conn.query_row(
            "SELECT count(*) FROM sqlite_master WHERE name = 'meta'",
            [],
            |r| r.get::<_, i64>(0).map(|n| n > 0),
        )?;
        if exists {
            check_format(&conn)?;
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
        Ok(DayFile {
            conn,
            day,
            path,
            start_ms,
            ids,
            next_id,
            mapped: None,
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
        let mut insert = self
            .conn
            .prepare_cached("INSERT INTO samples (key, value) VALUES (?1, ?2)")?;
        let mut shifted = false;
        loop {
            match insert.execute(params![key, sample.value]) {
                Ok(_) => break,
                Err(e) if is_constraint(&e) => {
                    let existing: (SqlValue, i64) = self.conn.query_row(
                        "SELECT value, coalesce((SELECT quality FROM qualities q WHERE q.key = s.key), 0) \
                         FROM samples s WHERE key = ?1",
                        [key],
                        |r| Ok((r.get(0)?, r.get(1)?)),
                    )?;
                    if same(&existing.0, &sample.value) && existing.1 == quality {
                        counts.duplicates += 1;
                        return Ok(());
                    }
                    // Another value at the same millisecond: the next one.
                    key += 1 << VAR_BITS;
                    shifted = true;
                    if (key >> VAR_BITS) >= DAY_MS {
                        counts.over_limit += 1;
                        return Ok(());
                    }
                }
                Err(e) => return Err(e),
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

    /// Ends writing: the WAL is folded in and the file becomes a single
    /// file again.
    pub fn close(self) {
        let _ = self.conn.pragma_update(None, "journal_mode", "DELETE");
    }
}

fn is_constraint(e: &rusqlite::Error) -> bool {
    matches!(e, rusqlite::Error::SqliteFailure(f, _) if f.code == rusqlite::ErrorCode::ConstraintViolation)
}

fn same(existing: &SqlValue, value: &Stored) -> bool {
    match (existing, value) {
        (SqlValue::Integer(a), Stored::Int(b)) => a == b,
        (SqlValue::Real(a), Stored::Real(b)) => a.to_bits() == b.to_bits(),
        (SqlValue::Text(a), Stored::Text(b)) => a == b,
        (SqlValue::Null, Stored::Null) => true,
        _ => false,
    }
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
    use crate::changes::Quality;
    use crate::vars::tests::table_of;

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
