//! Reading the history back: the samples of a section's variables (masks)
//! in a time range, in the order they were recorded, as a stream. The day
//! files of the range are opened one after the other and read in chunks of
//! [`CHUNK`] rows by key, so a year of a variable never sits in memory and
//! a file being written is read as it is (WAL readers do not wait).
//!
//! ```no_run
//! # use plccoms::historian::query::{Query, rows};
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
//! # Ok::<(), plccoms::historian::query::QueryError>(())
//! ```

use std::collections::{HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;

use plccoms_protocol::mask::Mask;
use plccoms_protocol::IecType;
use rusqlite::{Connection, OptionalExtension};

use super::sample::{quality_from_code, Stored};
use super::store::{self, day_of, DAY_MS, VAR_BITS, VAR_MASK};
use crate::changes::Quality;

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

/// The stream of [`rows`]; each item one sample.
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

struct FileCursor {
    conn: Connection,
    path: PathBuf,
    start_ms: i64,
    /// File id -> variable, for the matching ones.
    vars: Vec<Option<Arc<Variable>>>,
    filter: String,
    next_key: i64,
    end_key: i64,
    has_stamps: bool,
    /// Rows of `samples` read and not yet merged, with their keys.
    rows: VecDeque<(i64, Row)>,
    rows_done: bool,
    /// Samples of blocks unpacked and not yet merged, and where the next
    /// block starts (none left: `blocks_done`).
    packed: VecDeque<(i64, Row)>,
    next_block_key: i64,
    blocks_done: bool,
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
        // One snapshot for the whole file: samples being packed meanwhile
        // are read once, from where they were.
        conn.execute_batch("BEGIN").map_err(file_error(&path))?;
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
            next_key: from << VAR_BITS,
            end_key: to << VAR_BITS,
            has_stamps,
            rows: VecDeque::new(),
            rows_done: vars.is_empty(),
            packed: VecDeque::new(),
            next_block_key: from << VAR_BITS,
            blocks_done: vars.is_empty() || !has_blocks,
        });
        Ok(true)
    }
}

/// The next block holding keys from ?1 on, below ?2. Blocks never overlap
/// and come in key order: it is the one starting at or before ?1 if it
/// reaches ?1, else the next one; both found by the primary key (a filter
/// on `last_key` alone would walk every block before it, for every block).
pub(crate) const READ_BLOCK: &str = "SELECT last_key, data FROM blocks \
     WHERE first_key >= coalesce((SELECT first_key FROM blocks WHERE first_key <= ?1 \
                                  ORDER BY first_key DESC LIMIT 1), ?1) \
       AND last_key >= ?1 AND first_key < ?2 \
     ORDER BY first_key LIMIT 1";

impl FileCursor {
    /// `key -> column` of a side table for the keys of the chunk being
    /// read (from `next_key` to `last`).
    fn side(&self, table: &str, column: &str, last: i64) -> rusqlite::Result<HashMap<i64, i64>> {
        let sql = format!("SELECT key, {column} FROM {table} WHERE key >= ?1 AND key <= ?2");
        let mut stmt = self.conn.prepare_cached(&sql)?;
        let rows = stmt.query_map([self.next_key, last], |r| Ok((r.get(0)?, r.get(1)?)))?;
        rows.collect()
    }

    /// Merges the next samples of `samples` and of the blocks into
    /// `buffer`, in key order; `false` when the file is done.
    fn fill(&mut self, buffer: &mut VecDeque<Row>) -> rusqlite::Result<bool> {
        loop {
            if self.rows.is_empty() && !self.rows_done {
                self.read_rows()?;
            }
            if self.packed.is_empty() && !self.blocks_done {
                self.read_block()?;
            }
            if self.rows.is_empty() && self.packed.is_empty() {
                if self.rows_done && self.blocks_done {
                    return Ok(false);
                }
                continue;
            }
            let mut merged = false;
            loop {
                let from_rows = match (self.rows.front(), self.packed.front()) {
                    (Some(row), Some(packed)) => row.0 < packed.0,
                    (Some(_), None) if self.blocks_done => true,
                    (None, Some(_)) if self.rows_done => false,
                    _ => break,
                };
                let side = if from_rows {
                    &mut self.rows
                } else {
                    &mut self.packed
                };
                if let Some((_, row)) = side.pop_front() {
                    buffer.push_back(row);
                    merged = true;
                }
            }
            if merged {
                return Ok(true);
            }
        }
    }

    /// Reads the next chunk of `samples` rows.
    fn read_rows(&mut self) -> rusqlite::Result<()> {
        let sql = format!(
            "SELECT key, value FROM samples WHERE key >= ?1 AND key < ?2{} ORDER BY key LIMIT {CHUNK}",
            self.filter
        );
        let mut stmt = self.conn.prepare_cached(&sql)?;
        let mut rows = stmt.query([self.next_key, self.end_key])?;
        let mut last = None;
        let mut returned = 0;
        let start = self.rows.len();
        while let Some(row) = rows.next()? {
            let key: i64 = row.get(0)?;
            last = Some(key);
            returned += 1;
            let Some(Some(var)) = self.vars.get((key & VAR_MASK) as usize) else {
                continue;
            };
            self.rows.push_back((
                key,
                Row {
                    t: self.start_ms + (key >> VAR_BITS),
                    plc_time: None,
                    var: var.clone(),
                    value: Stored::from_sql(row.get_ref(1)?),
                    quality: Quality::Good,
                },
            ));
        }
        drop(rows);
        drop(stmt);
        let Some(last) = last else {
            self.rows_done = true;
            return Ok(());
        };
        // Qualities other than good and PLC stamps: side tables, few rows.
        let qualities = self.side("qualities", "quality", last)?;
        let stamps = if self.has_stamps {
            self.side("stamps", "plc_time", last)?
        } else {
            HashMap::new()
        };
        for (key, row) in self.rows.iter_mut().skip(start) {
            if let Some(&code) = qualities.get(key) {
                row.quality = quality_from_code(code);
            }
            row.plc_time = stamps.get(key).copied();
        }
        self.next_key = last + 1;
        if returned < CHUNK {
            self.rows_done = true;
        }
        Ok(())
    }

    /// Unpacks the next block that holds samples of the range.
    fn read_block(&mut self) -> rusqlite::Result<()> {
        let block: Option<(i64, Vec<u8>)> = self
            .conn
            .prepare_cached(READ_BLOCK)?
            .query_row([self.next_block_key, self.end_key], |r| {
                Ok((r.get(0)?, r.get(1)?))
            })
            .optional()?;
        let Some((last, data)) = block else {
            self.blocks_done = true;
            return Ok(());
        };
        for sample in store::unpack(&data)? {
            if sample.key < self.next_block_key || sample.key >= self.end_key {
                continue;
            }
            let Some(Some(var)) = self.vars.get((sample.key & VAR_MASK) as usize) else {
                continue;
            };
            self.packed.push_back((
                sample.key,
                Row {
                    t: self.start_ms + (sample.key >> VAR_BITS),
                    plc_time: sample.plc_time,
                    var: var.clone(),
                    value: sample.value,
                    quality: quality_from_code(i64::from(sample.quality)),
                },
            ));
        }
        self.next_block_key = last + 1;
        Ok(())
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
