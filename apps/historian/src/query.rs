//! Reading the history back: the samples of a section's variables (masks)
//! in a time range, in the order they were recorded, as a stream. The day
//! files of the range are opened one after the other and read in chunks of
//! [`CHUNK`] rows by key, so a year of a variable never sits in memory and
//! a file being written is read as it is (WAL readers do not wait).
//!
//! ```no_run
//! # use plccoms_historian::query::{Query, rows};
//! let query = Query {
//!     dir: "history".into(),
//!     section: "Demo".into(),
//!     masks: vec!["SIN*".into()],
//!     from_ms: 0,
//!     to_ms: i64::MAX,
//! };
//! for row in rows(&query)? {
//!     let row = row?;
//!     println!("{} {} {:?}", row.t, row.var.name, row.value);
//! }
//! # Ok::<(), plccoms_historian::query::QueryError>(())
//! ```

use std::collections::{HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;

use plccoms_protocol::mask::Mask;
use plccoms_protocol::IecType;
use rusqlite::types::ValueRef;
use rusqlite::{Connection, OptionalExtension};

use super::block::Packed;
use super::key::{day_of, DAY_MS, VAR_BITS, VAR_MASK};
use super::sample::{quality_from_code, Stored};
use super::store;
use plccoms_core::changes::Quality;
use plccoms_core::history_source::{self, RowQuality};

/// Rows read from a file at a time.
pub const CHUNK: usize = 8192;

/// What to read: `[from_ms, to_ms)` of the variables matching `masks` (`*`
/// wildcards, any case) of `section`'s files in `dir` (HISTORY_DIR).
#[derive(Debug, Clone)]
pub struct Query {
    pub dir: PathBuf,
    pub section: String,
    pub masks: Vec<String>,
    pub from_ms: i64,
    pub to_ms: i64,
}

#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    #[error("no history of section [{section}] in {}", dir.display())]
    NoSection { section: String, dir: PathBuf },
    #[error("no recorded variable of section [{section}] matches {masks} between the times asked")]
    NoVariables { section: String, masks: String },
    #[error(
        "{}: {samples} samples from {} to {} are damaged and left out: {what}",
        path.display(), super::time::iso_string(*first_ms), super::time::iso_string(*last_ms)
    )]
    Damaged {
        path: PathBuf,
        first_ms: i64,
        last_ms: i64,
        samples: i64,
        what: String,
    },
    #[error("{}: {source}", path.display())]
    File {
        path: PathBuf,
        #[source]
        source: rusqlite::Error,
    },
}

/// A recorded variable.
#[derive(Debug, PartialEq, Eq)]
pub struct Variable {
    pub name: String,
    /// The type as the public file gave it (`REAL`, `STRING[16]`, `DT`).
    pub type_name: String,
    pub ty: Option<IecType>,
    /// Some of its samples carry a PLC time stamp.
    pub stamped: bool,
}

/// One sample read back.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// UTC ms of the poll that read the value.
    pub t: i64,
    /// UTC ms the PLC stamped, for `HISTORY_STAMP` variables.
    pub plc_time: Option<i64>,
    pub var: Arc<Variable>,
    pub value: Stored,
    pub quality: Quality,
}

impl Row {
    /// The sample's time: the PLC's when it stamped it, else the poll's.
    pub fn time(&self) -> i64 {
        self.plc_time.unwrap_or(self.t)
    }
}

/// The day files that may hold `[from, to)`.
fn files(query: &Query) -> Result<Vec<(i64, PathBuf)>, QueryError> {
    let dir = store::section_dir(&query.dir, &query.section);
    if !dir.is_dir() {
        return Err(QueryError::NoSection {
            section: query.section.clone(),
            dir: query.dir.clone(),
        });
    }
    let (first, last) = (day_of(query.from_ms), day_of(query.to_ms.saturating_sub(1)));
    Ok(store::day_files(&dir)
        .into_iter()
        .filter(|(day, _)| (first..=last).contains(day))
        .collect())
}

fn open(path: &std::path::Path) -> Result<Connection, QueryError> {
    store::open_read(path).map_err(|source| QueryError::File {
        path: path.to_path_buf(),
        source,
    })
}

fn file_error(path: &std::path::Path) -> impl Fn(rusqlite::Error) -> QueryError + '_ {
    move |source| QueryError::File {
        path: path.to_path_buf(),
        source,
    }
}

/// The matching variables of one file: (file id, name, type, stamped).
fn file_vars(
    conn: &Connection,
    masks: &[Mask],
) -> rusqlite::Result<Vec<(i64, String, String, bool)>> {
    let sql = if store::has_table(conn, "packed_stamps")? {
        format!("SELECT DISTINCT key & {VAR_MASK} FROM stamps UNION SELECT id FROM packed_stamps")
    } else {
        format!("SELECT DISTINCT key & {VAR_MASK} FROM stamps")
    };
    let stamped: Vec<i64> = conn
        .prepare(&sql)?
        .query_map([], |r| r.get(0))?
        .collect::<Result<_, _>>()?;
    let mut stmt = conn.prepare("SELECT id, name, type FROM vars ORDER BY id")?;
    let vars = stmt
        .query_map([], |r| {
            Ok((r.get::<_, i64>(0)?, r.get::<_, String>(1)?, r.get(2)?))
        })?
        .filter(|v| {
            v.as_ref().map_or(true, |(_, name, _)| {
                let upper = plccoms_protocol::cp1250::to_upper(name.as_bytes());
                masks.iter().any(|m| m.matches(&upper))
            })
        })
        .map(|v| v.map(|(id, name, ty)| (id, name, ty, stamped.contains(&id))))
        .collect();
    vars
}

fn masks(query: &Query) -> Vec<Mask> {
    query
        .masks
        .iter()
        .map(|m| Mask::new(m.as_bytes()))
        .collect()
}

/// The variables the range holds that match the masks, in the order they
/// were first recorded: the columns of a wide export.
pub fn variables(query: &Query) -> Result<Vec<Arc<Variable>>, QueryError> {
    let masks = masks(query);
    let mut list: Vec<Arc<Variable>> = Vec::new();
    for (_, path) in files(query)? {
        let conn = open(&path)?;
        for (_, name, type_name, stamped) in file_vars(&conn, &masks).map_err(file_error(&path))? {
            match list.iter_mut().find(|v| v.name == name) {
                Some(known) if stamped && !known.stamped => {
                    *known = Arc::new(Variable {
                        stamped: true,
                        ..Variable::clone_of(known)
                    });
                }
                Some(_) => {}
                None => list.push(Arc::new(Variable {
                    ty: IecType::parse(type_name.as_bytes()),
                    name,
                    type_name,
                    stamped,
                })),
            }
        }
    }
    if list.is_empty() {
        return Err(QueryError::NoVariables {
            section: query.section.clone(),
            masks: query.masks.join(","),
        });
    }
    Ok(list)
}

impl Variable {
    fn clone_of(v: &Variable) -> Variable {
        Variable {
            name: v.name.clone(),
            type_name: v.type_name.clone(),
            ty: v.ty,
            stamped: v.stamped,
        }
    }
}

/// The samples of the range, in the order recorded (by poll time, then
/// variable).
pub fn rows(query: &Query) -> Result<Rows, QueryError> {
    let variables = variables(query)?;
    let mut files = files(query)?;
    files.reverse();
    Ok(Rows {
        query: query.clone(),
        masks: masks(query),
        by_name: variables
            .iter()
            .map(|v| (v.name.clone(), v.clone()))
            .collect(),
        variables,
        files,
        current: None,
        buffer: VecDeque::new(),
    })
}

/// The stream of [`rows`]; each item one sample. An error item does not
/// end it: a file that cannot be read is one error and the next file
/// follows; a damaged block ([`QueryError::Damaged`]) is one error and the
/// samples after it follow.
pub struct Rows {
    query: Query,
    masks: Vec<Mask>,
    by_name: HashMap<String, Arc<Variable>>,
    variables: Vec<Arc<Variable>>,
    /// Files still to read, the next one last.
    files: Vec<(i64, PathBuf)>,
    current: Option<FileCursor>,
    buffer: VecDeque<Row>,
}

/// A block's samples, or what is damaged in it.
type Unpacked = Result<Arc<Vec<Packed>>, String>;

/// Reading one file, a chunk at a time. Each chunk is read in a read
/// transaction of its own, so a reader waiting for its consumer (a slow web
/// client, a stalled pipe) holds no snapshot: the writer's checkpoints go
/// through and the WAL does not grow with every commit. Between chunks the
/// writer may commit, and pack rows into a block; a chunk reads every key
/// from `next_key` to the end of what it returns, from rows and blocks of
/// one snapshot, so each sample is read once.
struct FileCursor {
    conn: Connection,
    path: PathBuf,
    start_ms: i64,
    /// File id -> variable, for the matching ones.
    vars: Vec<Option<Arc<Variable>>>,
    filter: String,
    has_stamps: bool,
    /// The file has a `blocks` table (a version 1 file gains it when written).
    has_blocks: bool,
    /// The first key not read yet; the end of the range.
    next_key: i64,
    end_key: i64,
    /// The block last unpacked (blocks never change once written): its
    /// first key and its samples, or what is damaged in it.
    block: Option<(i64, Unpacked)>,
    /// The first key of the last damaged block reported.
    reported: Option<i64>,
    /// A damaged block found by the last chunk, to report.
    damaged: Option<QueryError>,
}

impl Rows {
    /// The variables the rows are of (each row's `var` is one of these), in
    /// the order they were first recorded: the columns of a wide export.
    pub fn variables(&self) -> &[Arc<Variable>] {
        &self.variables
    }

    fn open_next(&mut self) -> Result<bool, QueryError> {
        let Some((day, path)) = self.files.pop() else {
            return Ok(false);
        };
        let conn = open(&path)?;
        let vars = file_vars(&conn, &self.masks).map_err(file_error(&path))?;
        let start_ms = day * DAY_MS;
        let mut by_id: Vec<Option<Arc<Variable>>> = Vec::new();
        for (id, name, _, _) in &vars {
            let id = *id as usize;
            if by_id.len() <= id {
                by_id.resize(id + 1, None);
            }
            by_id[id] = self.by_name.get(name).cloned();
        }
        let all: i64 = conn
            .query_row("SELECT count(*) FROM vars", [], |r| r.get(0))
            .map_err(file_error(&path))?;
        let filter = if vars.len() as i64 == all {
            String::new()
        } else {
            let ids: Vec<String> = vars.iter().map(|v| v.0.to_string()).collect();
            format!(" AND (key & {VAR_MASK}) IN ({})", ids.join(","))
        };
        let has_stamps = vars.iter().any(|v| v.3);
        let has_blocks = store::has_table(&conn, "blocks").map_err(file_error(&path))?;
        let from = (self.query.from_ms - start_ms).clamp(0, DAY_MS);
        let to = (self.query.to_ms - start_ms).clamp(0, DAY_MS);
        self.current = Some(FileCursor {
            conn,
            path,
            start_ms,
            vars: by_id,
            filter,
            has_stamps,
            has_blocks,
            next_key: from << VAR_BITS,
            end_key: if vars.is_empty() { 0 } else { to << VAR_BITS },
            block: None,
            reported: None,
            damaged: None,
        });
        Ok(true)
    }
}

/// The next block holding keys from ?1 on, below ?2. Blocks never overlap
/// and come in key order: it is the one starting at or before ?1 if it
/// reaches ?1, else the next one; both found by the primary key (a filter
/// on `last_key` alone would walk every block before it, for every block).
pub(crate) const READ_BLOCK: &str = "SELECT first_key, last_key, samples FROM blocks \
     WHERE first_key >= coalesce((SELECT first_key FROM blocks WHERE first_key <= ?1 \
                                  ORDER BY first_key DESC LIMIT 1), ?1) \
       AND last_key >= ?1 AND first_key < ?2 \
     ORDER BY first_key LIMIT 1";

impl FileCursor {
    /// `key -> column` of a side table for the keys `from..to`.
    fn side(
        &self,
        table: &str,
        column: &str,
        from: i64,
        to: i64,
    ) -> rusqlite::Result<HashMap<i64, i64>> {
        let sql = format!("SELECT key, {column} FROM {table} WHERE key >= ?1 AND key < ?2");
        let mut stmt = self.conn.prepare_cached(&sql)?;
        let rows = stmt.query_map([from, to], |r| Ok((r.get(0)?, r.get(1)?)))?;
        rows.collect()
    }

    /// Reads the next chunk into `buffer`, in key order; `false` when the
    /// file is done.
    fn fill(&mut self, buffer: &mut VecDeque<Row>) -> rusqlite::Result<bool> {
        while self.next_key < self.end_key {
            // The chunk's own snapshot, ended before its rows are handed
            // on (a read-only transaction: COMMIT cannot lose anything).
            self.conn.execute_batch("BEGIN")?;
            let read = self.read_chunk(buffer);
            let _ = self.conn.execute_batch("COMMIT");
            if read? || self.damaged.is_some() {
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// Reads the samples from `next_key` on, up to CHUNK rows and one
    /// block, and moves `next_key` past them; `true` if any matched.
    fn read_chunk(&mut self, buffer: &mut VecDeque<Row>) -> rusqlite::Result<bool> {
        let from = self.next_key;
        if !self.has_blocks {
            // A version 1 file being written gains the table.
            self.has_blocks = store::has_table(&self.conn, "blocks")?;
        }
        let block: Option<(i64, i64, i64)> = if self.has_blocks {
            self.conn
                .prepare_cached(READ_BLOCK)?
                .query_row([from, self.end_key], |r| {
                    Ok((r.get(0)?, r.get(1)?, r.get(2)?))
                })
                .optional()?
        } else {
            None
        };
        // Rows up to the block's end at most: those after it are the next
        // chunk's (most rows are newer than every block).
        let bound = block.map_or(self.end_key, |b| self.end_key.min(b.1 + 1));
        let sql = format!(
            "SELECT key, value FROM samples WHERE key >= ?1 AND key < ?2{} ORDER BY key LIMIT {CHUNK}",
            self.filter
        );
        let mut rows: Vec<(i64, Stored)> = Vec::new();
        {
            let mut stmt = self.conn.prepare_cached(&sql)?;
            let mut result = stmt.query([from, bound])?;
            while let Some(row) = result.next()? {
                rows.push((row.get(0)?, Stored::from_sql(row.get_ref(1)?)));
            }
        }
        // Read up to here: the bound, or the end of a full chunk.
        let to = match rows.last() {
            Some(&(last, _)) if rows.len() == CHUNK => last + 1,
            _ => bound,
        };
        let mut packed: &[Packed] = &[];
        let samples;
        if let Some((first, last, count)) = block.filter(|b| b.0 < to) {
            match self.unpacked(first, last, count)? {
                Ok(all) => {
                    samples = all;
                    let start = samples.partition_point(|s| s.key < from);
                    let end = samples.partition_point(|s| s.key < to);
                    packed = &samples[start..end];
                }
                Err(what) => {
                    if self.reported != Some(first) {
                        self.reported = Some(first);
                        self.damaged = Some(QueryError::Damaged {
                            path: self.path.clone(),
                            first_ms: self.start_ms + (first >> VAR_BITS),
                            last_ms: self.start_ms + (last >> VAR_BITS),
                            samples: count,
                            what,
                        });
                    }
                }
            }
        }
        let qualities = self.side("qualities", "quality", from, to)?;
        let stamps = if self.has_stamps {
            self.side("stamps", "plc_time", from, to)?
        } else {
            HashMap::new()
        };
        self.next_key = to;
        let before = buffer.len();
        // Both in key order: merged. A key is in a row or a block, not both.
        let mut rows = rows.into_iter().peekable();
        let mut packed = packed.iter().peekable();
        loop {
            let from_rows = match (rows.peek(), packed.peek()) {
                (Some(row), Some(sample)) => row.0 < sample.key,
                (Some(_), None) => true,
                (None, Some(_)) => false,
                (None, None) => break,
            };
            let (key, value, quality, plc_time) = if from_rows {
                let (key, value) = rows.next().expect("peeked");
                let quality = qualities.get(&key).copied().unwrap_or(0);
                (key, value, quality, stamps.get(&key).copied())
            } else {
                let s = packed.next().expect("peeked");
                (s.key, s.value.clone(), i64::from(s.quality), s.plc_time)
            };
            let Some(Some(var)) = self.vars.get((key & VAR_MASK) as usize) else {
                continue;
            };
            buffer.push_back(Row {
                t: self.start_ms + (key >> VAR_BITS),
                plc_time,
                var: var.clone(),
                value,
                quality: quality_from_code(quality),
            });
        }
        Ok(buffer.len() > before)
    }

    /// The samples of the block `first..=last`, unpacked once; `Err` names
    /// what is damaged in it.
    fn unpacked(&mut self, first: i64, last: i64, count: i64) -> rusqlite::Result<Unpacked> {
        if let Some((cached, samples)) = &self.block {
            if *cached == first {
                return Ok(samples.clone());
            }
        }
        let samples = self
            .conn
            .prepare_cached("SELECT data FROM blocks WHERE first_key = ?1")?
            .query_row([first], |r| {
                Ok(match r.get_ref(0)? {
                    ValueRef::Blob(data) => store::unpack_block(first, last, count, data)
                        .map(Arc::new)
                        .map_err(|e| e.to_string()),
                    other => Err(format!(
                        "a packed block is damaged: its data is {}, not a blob",
                        other.data_type()
                    )),
                })
            })?;
        self.block = Some((first, samples.clone()));
        Ok(samples)
    }
}

impl Iterator for Rows {
    type Item = Result<Row, QueryError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(row) = self.buffer.pop_front() {
                return Some(Ok(row));
            }
            match &mut self.current {
                Some(cursor) if cursor.damaged.is_some() => {
                    return cursor.damaged.take().map(Err);
                }
                Some(cursor) => match cursor.fill(&mut self.buffer) {
                    Ok(true) => {}
                    Ok(false) => self.current = None,
                    Err(source) => {
                        let path = cursor.path.clone();
                        self.current = None;
                        return Some(Err(QueryError::File { path, source }));
                    }
                },
                None => match self.open_next() {
                    Ok(true) => {}
                    Ok(false) => return None,
                    Err(e) => return Some(Err(e)),
                },
            }
        }
    }
}

// ---------------------------------------------------------------------------
// Gaps: the events a reader must see, merged with the samples.

/// Something in the record that is a gap for every variable: from the day
/// files' `events` table (link and server), or a damaged block left out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Gap {
    LinkLost,
    LinkRestored,
    /// The server stopped (a kill or power loss records none).
    Stop,
    Start,
    /// The first and the last time of a damaged block's samples.
    DamagedFrom,
    DamagedTo,
    /// The recorder lagged past its bound: changes before this are missing.
    Missed,
    /// Samples were dropped (queue full, disk full, size limit).
    Dropped,
}

impl Gap {
    /// The marker row's name.
    pub fn name(self) -> &'static str {
        match self {
            Gap::LinkLost | Gap::LinkRestored => history_source::LINK,
            Gap::Stop | Gap::Start => history_source::SERVER,
            Gap::DamagedFrom | Gap::DamagedTo => history_source::DAMAGED,
            Gap::Missed | Gap::Dropped => history_source::RECORDER,
        }
    }

    pub fn quality(self) -> RowQuality {
        match self {
            Gap::LinkLost | Gap::LinkRestored => RowQuality::LinkLost,
            Gap::Stop | Gap::Start => RowQuality::Stopped,
            Gap::DamagedFrom | Gap::DamagedTo => RowQuality::Damaged,
            Gap::Missed | Gap::Dropped => RowQuality::Missed,
        }
    }

    /// The marker row's `text`: the event, as the `events` table names it.
    pub fn text(self) -> &'static str {
        match self {
            Gap::LinkLost => "link_lost",
            Gap::LinkRestored => "link_restored",
            Gap::Stop => "stop",
            Gap::Start => "start",
            Gap::DamagedFrom => "damaged_from",
            Gap::DamagedTo => "damaged_to",
            Gap::Missed => "missed",
            Gap::Dropped => "dropped",
        }
    }
}

/// A gap at a time (UTC ms).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mark {
    pub t: i64,
    pub gap: Gap,
}

/// The link, server and recorder events of the range, in time order.
pub fn marks(query: &Query) -> Result<Vec<Mark>, QueryError> {
    let mut marks = Vec::new();
    for (_, path) in files(query)? {
        let conn = open(&path)?;
        if !store::has_table(&conn, "events").map_err(file_error(&path))? {
            continue;
        }
        let mut stmt = conn
            .prepare(
                "SELECT time, kind FROM events WHERE time >= ?1 AND time < ?2 \
                 AND kind IN ('link_lost', 'link_restored', 'stop', 'start', 'missed', 'dropped') \
                 ORDER BY time, id",
            )
            .map_err(file_error(&path))?;
        let rows = stmt
            .query_map([query.from_ms, query.to_ms], |r| {
                Ok((r.get::<_, i64>(0)?, r.get::<_, String>(1)?))
            })
            .map_err(file_error(&path))?;
        for row in rows {
            let (t, kind) = row.map_err(file_error(&path))?;
            let gap = match kind.as_str() {
                "link_lost" => Gap::LinkLost,
                "link_restored" => Gap::LinkRestored,
                "stop" => Gap::Stop,
                "missed" => Gap::Missed,
                "dropped" => Gap::Dropped,
                _ => Gap::Start,
            };
            marks.push(Mark { t, gap });
        }
    }
    // Day files hold their own day's events: in order already, but a clock
    // set back must not unsort the merge.
    marks.sort_by_key(|m| m.t);
    Ok(marks)
}

/// One item of [`records`].
#[derive(Debug, Clone, PartialEq)]
pub enum Record {
    Sample(Row),
    Mark(Mark),
}

/// The samples of [`rows`] and the gaps of [`marks`], merged by poll time;
/// a mark before the samples of its time (a link's return is recorded at
/// the time of the fresh samples, which begin the next good stretch). A
/// damaged block is, besides its error item, a `DamagedFrom` and a
/// `DamagedTo` mark at its first and last time.
pub fn records(query: &Query) -> Result<Records, QueryError> {
    Ok(Records {
        rows: rows(query)?,
        marks: marks(query)?.into(),
        next: None,
    })
}

pub struct Records {
    rows: Rows,
    marks: VecDeque<Mark>,
    /// A row read ahead.
    next: Option<Row>,
}

impl Records {
    pub fn variables(&self) -> &[Arc<Variable>] {
        self.rows.variables()
    }

    fn insert(&mut self, mark: Mark) {
        let at = self.marks.partition_point(|m| m.t <= mark.t);
        self.marks.insert(at, mark);
    }
}

impl Iterator for Records {
    type Item = Result<Record, QueryError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.next.is_none() {
            match self.rows.next() {
                Some(Ok(row)) => self.next = Some(row),
                Some(Err(e)) => {
                    if let QueryError::Damaged {
                        first_ms, last_ms, ..
                    } = &e
                    {
                        let (first, last) = (*first_ms, *last_ms);
                        self.insert(Mark {
                            t: first,
                            gap: Gap::DamagedFrom,
                        });
                        self.insert(Mark {
                            t: last,
                            gap: Gap::DamagedTo,
                        });
                    }
                    return Some(Err(e));
                }
                None => {}
            }
        }
        match (&self.next, self.marks.front()) {
            (Some(row), Some(mark)) if mark.t <= row.t => {
                self.marks.pop_front().map(Record::Mark).map(Ok)
            }
            (Some(_), _) => self.next.take().map(Record::Sample).map(Ok),
            (None, Some(_)) => self.marks.pop_front().map(Record::Mark).map(Ok),
            (None, None) => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each block is found by the primary key: a plan that walks the blocks
    /// makes reading a day of many blocks quadratic.
    #[test]
    fn the_next_block_is_found_by_the_primary_key() {
        let dir = tempfile::tempdir().unwrap();
        let file = store::DayFile::open(dir.path(), "Q", 19_000).unwrap();
        let path = file.path.clone();
        file.close();
        let conn = Connection::open(path).unwrap();
        let plan: Vec<String> = conn
            .prepare(&format!("EXPLAIN QUERY PLAN {READ_BLOCK}"))
            .unwrap()
            .query_map([0, 1], |r| r.get(3))
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert!(
            plan.iter().all(|step| !step.starts_with("SCAN")),
            "{plan:?}"
        );
        assert_eq!(
            plan.iter().filter(|s| s.contains("PRIMARY KEY")).count(),
            2,
            "{plan:?}"
        );
    }
}
