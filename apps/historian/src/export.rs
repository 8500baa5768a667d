//! Writing history out: CSV, JSON and Parquet (zstd), long (one row per
//! sample: `time,name,value,text,quality`, the shape
//! [`plccoms_core::history_source::csv_row`] writes, /api/history's too)
//! or wide (one row per time: `time,quality` and a column per variable).
//! Everything streams from [`query::records`]: CSV and JSON row by row,
//! Parquet a row group at a time.
//!
//! Values are typed as read: numbers (BOOL as 0/1, integers in full, REAL
//! and LREAL in the shortest form that reads back the same) in `value`,
//! strings, DATE, DT, TOD and TIME in `text`, in the forms of
//! [`Presented`] (ISO 8601). Gaps are rows: the link's loss and return,
//! the server's stop and start and a damaged block's range are marker rows
//! (`__LINK`, `__SERVER`, `__DAMAGED`; wide: a row of empty cells) whose
//! quality is not `good`, so a reader who forward-fills within good
//! stretches never carries a value across one.

use std::cell::RefCell;
use std::io::{self, Write};
use std::rc::Rc;
use std::sync::Arc;

use parquet::basic::{Compression, LogicalType, Repetition, TimeUnit, Type as Physical, ZstdLevel};
use parquet::data_type::{
    BoolType, ByteArray, ByteArrayType, DoubleType, FloatType, Int32Type, Int64Type,
};
use parquet::file::properties::WriterProperties;
use parquet::file::writer::SerializedFileWriter;
use parquet::schema::types::Type;
use plccoms_protocol::IecType;

use super::query::{self, Mark, Query, QueryError, Record, Row, Variable};
use super::sample::Stored;
use super::time::iso;
use plccoms_core::changes::Quality;
use plccoms_core::history_source::{self as shape, RowQuality, Split};
use plccoms_core::present::Presented;
use plccoms_protocol::value::Value;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    Csv,
    Json,
    Parquet,
}

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(transparent)]
    Query(#[from] QueryError),
    #[error("writing: {0}")]
    Io(#[from] io::Error),
    #[error("Parquet: {0}")]
    Parquet(#[from] parquet::errors::ParquetError),
    /// Written to the end, without the samples of damaged blocks.
    #[error("{rows} rows written; left out, damaged:\n  {}", ranges.join("\n  "))]
    Damaged { rows: u64, ranges: Vec<String> },
}

/// Writes the samples `query` selects to `out`; returns the rows written.
pub fn export<W: Write + Send>(
    query: &Query,
    format: Format,
    wide: bool,
    out: W,
) -> Result<u64, ExportError> {
    let rows = query::records(query)?;
    let columns = rows.variables().to_vec();
    let damaged = Rc::new(RefCell::new(Vec::new()));
    let rows = Intact {
        rows,
        damaged: damaged.clone(),
    };
    let count = match format {
        Format::Csv => write_csv(rows, &columns, wide, out),
        Format::Json => write_json(rows, &columns, wide, out),
        Format::Parquet => write_parquet(rows, &columns, wide, out),
    }?;
    let ranges = damaged.take();
    if ranges.is_empty() {
        Ok(count)
    } else {
        Err(ExportError::Damaged {
            rows: count,
            ranges,
        })
    }
}

/// The records of a query without the samples of damaged blocks: each such
/// range is named in `damaged` (and marked by its `__DAMAGED` rows), and
/// the export goes on after it.
struct Intact {
    rows: query::Records,
    damaged: Rc<RefCell<Vec<String>>>,
}

impl Iterator for Intact {
    type Item = Result<Record, QueryError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            match self.rows.next()? {
                Err(e @ QueryError::Damaged { .. }) => {
                    self.damaged.borrow_mut().push(e.to_string())
                }
                other => return Some(other),
            }
        }
    }
}

/// Streams an export through a channel of chunks, for a web response: the
/// query runs on a blocking thread, at most a few chunks ahead of the
/// reader. The last item is an error if the export failed.
pub fn stream(
    query: Query,
    format: Format,
    wide: bool,
) -> tokio::sync::mpsc::Receiver<io::Result<bytes::Bytes>> {
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tokio::task::spawn_blocking(move || {
        let mut out = ChannelWriter {
            tx: tx.clone(),
            buffer: Vec::with_capacity(CHANNEL_CHUNK),
        };
        let result = export(&query, format, wide, &mut out).and_then(|_| Ok(out.flush()?));
        if let Err(e) = result {
            let _ = tx.blocking_send(Err(io::Error::other(e.to_string())));
        }
    });
    rx
}

const CHANNEL_CHUNK: usize = 64 * 1024;

struct ChannelWriter {
    tx: tokio::sync::mpsc::Sender<io::Result<bytes::Bytes>>,
    buffer: Vec<u8>,
}

impl Write for ChannelWriter {
    fn write(&mut self, data: &[u8]) -> io::Result<usize> {
        self.buffer.extend_from_slice(data);
        if self.buffer.len() >= CHANNEL_CHUNK {
            self.flush()?;
        }
        Ok(data.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        if self.buffer.is_empty() {
            return Ok(());
        }
        let chunk = bytes::Bytes::from(std::mem::take(&mut self.buffer));
        self.tx
            .blocking_send(Ok(chunk))
            .map_err(|_| io::Error::new(io::ErrorKind::BrokenPipe, "the reader went away"))
    }
}

// ---------------------------------------------------------------------------
// Values.

/// A stored value of a variable of type `ty` as [`Presented`] shows it;
/// `None`: no value. A REAL or LREAL stored as NULL was a NaN.
pub fn presented(value: &Stored, ty: Option<IecType>) -> Option<Presented> {
    use IecType::*;
    let Some(ty) = ty else {
        return match value {
            Stored::Int(i) => Some(Presented::Signed(*i)),
            Stored::Real(f) => Some(Presented::Number(*f)),
            Stored::Text(s) => Some(Presented::Text(s.clone())),
            Stored::Null => None,
        };
    };
    let value = match (value, ty) {
        (Stored::Text(s), _) => return Some(Presented::Text(s.clone())),
        (Stored::Null, Real) => Value::Real(f32::NAN),
        (Stored::Null, Lreal) => Value::LReal(f64::NAN),
        (Stored::Null, _) => return None,
        (Stored::Int(i), Bool) => Value::Bool(*i != 0),
        // ULINT and LWORD above 2^63 are stored as their two's complement.
        (Stored::Int(i), Usint | Byte | Uint | Word | Udint | Dword | Ulint | Lword) => {
            Value::Unsigned(*i as u64)
        }
        (Stored::Int(i), Time | Tod) => match u32::try_from(*i) {
            Ok(ms) => Value::Time(ms),
            Err(_) => Value::Signed(*i),
        },
        (Stored::Int(ms), Date | Dt) => Value::Date(*ms as f64 / 1000.0),
        (Stored::Real(ms), Date | Dt) => Value::Date(ms / 1000.0),
        (Stored::Int(i), _) => Value::Signed(*i),
        (Stored::Real(f), Real) => Value::Real(*f as f32),
        (Stored::Real(f), _) => Value::LReal(*f),
    };
    Some(Presented::of_value(ty, &value))
}

/// A marker row's value: its event in `text`.
fn mark_text(mark: &Mark) -> Presented {
    Presented::Text(mark.gap.text().into())
}

/// The header of a wide export: time, quality, then per variable its
/// column (and its PLC time's, when stamped).
fn wide_header(columns: &[Arc<Variable>]) -> Vec<String> {
    let mut header = vec!["time".to_string(), "quality".to_string()];
    for var in columns {
        header.push(var.name.clone());
        if var.stamped {
            header.push(format!("{}.plc_time", var.name));
        }
    }
    header
}

/// The record's poll time, by which records are merged and grouped.
fn poll_time(record: &Record) -> i64 {
    match record {
        Record::Sample(row) => row.t,
        Record::Mark(mark) => mark.t,
    }
}

/// Groups the records of one poll time into wide rows: the gap row (the
/// worst quality among the marks and samples that are not good: all its
/// cells empty), then the row of the good samples, by column index.
struct Wide {
    /// Column index of each variable (by pointer), from 0 after `quality`.
    index: Vec<(*const Variable, usize)>,
    width: usize,
}

/// One time's wide rows.
#[derive(Default)]
struct Group {
    t: i64,
    /// The gap row's quality, if the time has one.
    gap: Option<RowQuality>,
    /// The good samples by column; none: no good row.
    cells: Vec<Option<Row>>,
    any_good: bool,
}

impl Wide {
    fn new(columns: &[Arc<Variable>]) -> Wide {
        let mut index = Vec::new();
        let mut at = 0;
        for var in columns {
            index.push((Arc::as_ptr(var), at));
            at += 1 + usize::from(var.stamped);
        }
        Wide { index, width: at }
    }

    fn column(&self, var: &Arc<Variable>) -> Option<usize> {
        let p = Arc::as_ptr(var);
        self.index.iter().find(|(q, _)| *q == p).map(|(_, i)| *i)
    }

    /// Reads the records of the next poll time into `group`; `false` at
    /// the end.
    fn next_group(
        &self,
        rows: &mut std::iter::Peekable<Intact>,
        group: &mut Group,
    ) -> Result<bool, QueryError> {
        group.cells.clear();
        group.cells.resize(self.width, None);
        group.gap = None;
        group.any_good = false;
        let Some(first) = rows.next() else {
            return Ok(false);
        };
        let first = first?;
        group.t = poll_time(&first);
        let mut put = |record: Record| match record {
            Record::Mark(mark) => group.gap = group.gap.max(Some(mark.gap.quality())),
            Record::Sample(row) if row.quality != Quality::Good => {
                group.gap = group.gap.max(Some(row.quality.into()))
            }
            Record::Sample(row) => {
                if let Some(i) = self.column(&row.var) {
                    group.cells[i] = Some(row);
                    group.any_good = true;
                }
            }
        };
        put(first);
        while let Some(Ok(next)) = rows.peek() {
            if poll_time(next) != group.t {
                break;
            }
            if let Some(Ok(record)) = rows.next() {
                put(record);
            }
        }
        Ok(true)
    }
}

// ---------------------------------------------------------------------------
// CSV.

/// A wide cell: a number, or text guarded against formulas.
fn csv_cell(row: &Row, out: &mut Vec<u8>) {
    match presented(&row.value, row.var.ty) {
        None => {}
        Some(value) => match shape::split(&value) {
            Split::Number(v) => shape::number_text(v, out),
            Split::Text(v) => shape::csv_text(v.text().as_bytes(), out),
        },
    }
}

/// The output buffered, and a line being built.
fn text_buffers<W: Write>(out: W) -> (io::BufWriter<W>, Vec<u8>) {
    (
        io::BufWriter::with_capacity(256 * 1024, out),
        Vec::with_capacity(256),
    )
}

/// One long row of a record, as [`shape::csv_row`] or [`shape::json_row`].
fn long_row(
    record: &Record,
    out: &mut Vec<u8>,
    write: fn(i64, &str, Option<&Presented>, RowQuality, &mut Vec<u8>),
) {
    match record {
        Record::Sample(row) => write(
            row.time(),
            &row.var.name,
            presented(&row.value, row.var.ty).as_ref(),
            row.quality.into(),
            out,
        ),
        Record::Mark(mark) => write(
            mark.t,
            mark.gap.name(),
            Some(&mark_text(mark)),
            mark.gap.quality(),
            out,
        ),
    }
}

fn write_csv<W: Write>(
    mut rows: Intact,
    columns: &[Arc<Variable>],
    wide: bool,
    out: W,
) -> Result<u64, ExportError> {
    let (mut out, mut line) = text_buffers(out);
    let mut count = 0u64;
    if !wide {
        out.write_all(shape::CSV_HEADER)?;
        for record in rows.by_ref() {
            line.clear();
            long_row(&record?, &mut line, shape::csv_row);
            out.write_all(&line)?;
            count += 1;
        }
    } else {
        let header = wide_header(columns);
        line.clear();
        for (i, name) in header.iter().enumerate() {
            if i > 0 {
                line.push(b',');
            }
            shape::csv_text(name.as_bytes(), &mut line);
        }
        line.push(b'\n');
        out.write_all(&line)?;
        let wide = Wide::new(columns);
        let mut rows = rows.peekable();
        let mut group = Group::default();
        while wide.next_group(&mut rows, &mut group)? {
            if let Some(quality) = group.gap {
                line.clear();
                iso(group.t, &mut line);
                line.push(b',');
                line.extend_from_slice(quality.as_str().as_bytes());
                line.extend(std::iter::repeat_n(b',', wide.width));
                line.push(b'\n');
                out.write_all(&line)?;
                count += 1;
            }
            if !group.any_good {
                continue;
            }
            line.clear();
            iso(group.t, &mut line);
            line.extend_from_slice(b",good");
            for var in columns {
                let cell = wide.column(var).and_then(|i| group.cells[i].as_ref());
                line.push(b',');
                if let Some(row) = cell {
                    csv_cell(row, &mut line);
                }
                if var.stamped {
                    line.push(b',');
                    if let Some(plc) = cell.and_then(|r| r.plc_time) {
                        iso(plc, &mut line);
                    }
                }
            }
            line.push(b'\n');
            out.write_all(&line)?;
            count += 1;
        }
    }
    out.flush()?;
    Ok(count)
}

// ---------------------------------------------------------------------------
// JSON.

/// A wide cell: a JSON number, or a string (NaN and infinities too: JSON
/// has no number for them), or null.
fn json_cell(row: Option<&Row>, out: &mut Vec<u8>) {
    match row.and_then(|row| presented(&row.value, row.var.ty)) {
        None => out.extend_from_slice(b"null"),
        Some(value) => match shape::split(&value) {
            Split::Number(v) => shape::number_text(v, out),
            Split::Text(v) => shape::json_string(&v.text(), out),
        },
    }
}

fn write_json<W: Write>(
    mut rows: Intact,
    columns: &[Arc<Variable>],
    wide: bool,
    out: W,
) -> Result<u64, ExportError> {
    let (mut out, mut line) = text_buffers(out);
    let mut count = 0u64;
    out.write_all(b"[")?;
    let mut separator: &[u8] = b"\n";
    if !wide {
        for record in rows.by_ref() {
            line.clear();
            line.extend_from_slice(separator);
            long_row(&record?, &mut line, shape::json_row);
            out.write_all(&line)?;
            separator = b",\n";
            count += 1;
        }
    } else {
        let wide = Wide::new(columns);
        let names = wide_header(columns);
        let mut rows = rows.peekable();
        let mut group = Group::default();
        while wide.next_group(&mut rows, &mut group)? {
            let mut lines: [(Option<RowQuality>, bool); 2] =
                [(group.gap, true), (Some(RowQuality::Good), false)];
            if !group.any_good {
                lines[1].0 = None;
            }
            for (quality, empty) in lines {
                let Some(quality) = quality else { continue };
                line.clear();
                line.extend_from_slice(separator);
                line.extend_from_slice(b"{\"time\":\"");
                iso(group.t, &mut line);
                line.extend_from_slice(b"\",\"quality\":\"");
                line.extend_from_slice(quality.as_str().as_bytes());
                line.push(b'"');
                for var in columns {
                    let i = wide.column(var).unwrap_or(0);
                    let cell = group.cells[i].as_ref().filter(|_| !empty);
                    line.push(b',');
                    shape::json_string(&names[i + 2], &mut line);
                    line.push(b':');
                    json_cell(cell, &mut line);
                    if var.stamped {
                        line.push(b',');
                        shape::json_string(&names[i + 3], &mut line);
                        line.push(b':');
                        match cell.and_then(|r| r.plc_time) {
                            Some(plc) => {
                                line.push(b'"');
                                iso(plc, &mut line);
                                line.push(b'"');
                            }
                            None => line.extend_from_slice(b"null"),
                        }
                    }
                }
                line.push(b'}');
                out.write_all(&line)?;
                separator = b",\n";
                count += 1;
            }
        }
    }
    out.write_all(b"\n]\n")?;
    out.flush()?;
    Ok(count)
}

// ---------------------------------------------------------------------------
// Parquet.

/// A column being filled for the next row group.
enum Column {
    Bool(Vec<bool>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    F32(Vec<f32>),
    F64(Vec<f64>),
    Bytes(Vec<ByteArray>),
}

struct Filling {
    values: Column,
    /// Definition levels (1: a value, 0: null); empty for required columns.
    defs: Vec<i16>,
    optional: bool,
}

impl Filling {
    fn new(values: Column, optional: bool) -> Filling {
        Filling {
            values,
            defs: Vec::new(),
            optional,
        }
    }

    fn null(&mut self) {
        self.defs.push(0);
    }

    fn defined(&mut self) {
        if self.optional {
            self.defs.push(1);
        }
    }

    fn push_i64(&mut self, v: i64) {
        self.defined();
        match &mut self.values {
            Column::I64(values) => values.push(v),
            Column::I32(values) => values.push(v as i32),
            Column::Bool(values) => values.push(v != 0),
            Column::F32(values) => values.push(v as f32),
            Column::F64(values) => values.push(v as f64),
            Column::Bytes(values) => values.push(ByteArray::from(v.to_string().into_bytes())),
        }
    }

    fn push_f64(&mut self, v: f64) {
        self.defined();
        match &mut self.values {
            Column::F64(values) => values.push(v),
            Column::F32(values) => values.push(v as f32),
            Column::I64(values) => values.push(v.round() as i64),
            Column::I32(values) => values.push(v.round() as i32),
            Column::Bool(values) => values.push(v != 0.0),
            Column::Bytes(values) => values.push(ByteArray::from(v.to_string().into_bytes())),
        }
    }

    fn push_bytes(&mut self, v: &[u8]) {
        self.push_shared(bytes::Bytes::copy_from_slice(v));
    }

    /// Bytes shared with other rows (a name, a quality): no copy.
    fn push_shared(&mut self, v: bytes::Bytes) {
        if !matches!(self.values, Column::Bytes(_)) {
            return self.null();
        }
        self.defined();
        if let Column::Bytes(values) = &mut self.values {
            values.push(ByteArray::from(v));
        }
    }

    /// A sample's value, in the column's type.
    fn push_value(&mut self, value: &Stored, ty: Option<IecType>) {
        match value {
            Stored::Int(i) => self.push_i64(*i),
            Stored::Real(f) => self.push_f64(*f),
            Stored::Text(s) => self.push_bytes(s.as_bytes()),
            Stored::Null if matches!(ty, Some(IecType::Real | IecType::Lreal)) => {
                self.push_f64(f64::NAN)
            }
            Stored::Null => self.null(),
        }
    }

    fn write(
        &mut self,
        writer: &mut parquet::file::writer::SerializedColumnWriter<'_>,
    ) -> Result<(), ExportError> {
        let defs = self.optional.then_some(self.defs.as_slice());
        match &mut self.values {
            Column::Bool(v) => writer.typed::<BoolType>().write_batch(v, defs, None)?,
            Column::I32(v) => writer.typed::<Int32Type>().write_batch(v, defs, None)?,
            Column::I64(v) => writer.typed::<Int64Type>().write_batch(v, defs, None)?,
            Column::F32(v) => writer.typed::<FloatType>().write_batch(v, defs, None)?,
            Column::F64(v) => writer.typed::<DoubleType>().write_batch(v, defs, None)?,
            Column::Bytes(v) => writer.typed::<ByteArrayType>().write_batch(v, defs, None)?,
        };
        match &mut self.values {
            Column::Bool(v) => v.clear(),
            Column::I32(v) => v.clear(),
            Column::I64(v) => v.clear(),
            Column::F32(v) => v.clear(),
            Column::F64(v) => v.clear(),
            Column::Bytes(v) => v.clear(),
        }
        self.defs.clear();
        Ok(())
    }
}

fn field(
    name: &str,
    physical: Physical,
    logical: Option<LogicalType>,
    optional: bool,
) -> Result<Arc<Type>, ExportError> {
    Ok(Arc::new(
        Type::primitive_type_builder(name, physical)
            .with_repetition(if optional {
                Repetition::OPTIONAL
            } else {
                Repetition::REQUIRED
            })
            .with_logical_type(logical)
            .build()?,
    ))
}

fn timestamp() -> Option<LogicalType> {
    Some(LogicalType::timestamp(true, TimeUnit::MILLIS))
}

fn string() -> Option<LogicalType> {
    Some(LogicalType::String)
}

/// The Parquet column of a variable of type `ty` in a wide export.
fn typed_column(name: &str, ty: Option<IecType>) -> Result<(Arc<Type>, Column), ExportError> {
    use IecType::*;
    Ok(match ty {
        Some(Bool) => (
            field(name, Physical::BOOLEAN, None, true)?,
            Column::Bool(Vec::new()),
        ),
        Some(Sint | Int | Dint | Usint | Byte | Uint | Word) => (
            field(name, Physical::INT32, None, true)?,
            Column::I32(Vec::new()),
        ),
        Some(Udint | Dword | Lint | Time | Tod) => (
            field(name, Physical::INT64, None, true)?,
            Column::I64(Vec::new()),
        ),
        Some(Ulint | Lword) => (
            field(
                name,
                Physical::INT64,
                Some(LogicalType::integer(64, false)),
                true,
            )?,
            Column::I64(Vec::new()),
        ),
        Some(Real) => (
            field(name, Physical::FLOAT, None, true)?,
            Column::F32(Vec::new()),
        ),
        Some(Lreal) => (
            field(name, Physical::DOUBLE, None, true)?,
            Column::F64(Vec::new()),
        ),
        Some(Date | Dt) => (
            field(name, Physical::INT64, timestamp(), true)?,
            Column::I64(Vec::new()),
        ),
        Some(String(_)) | None => (
            field(name, Physical::BYTE_ARRAY, string(), true)?,
            Column::Bytes(Vec::new()),
        ),
    })
}

/// Rows per row group: about a million cells, at least 1024 rows.
fn group_rows(columns: usize) -> usize {
    (1_000_000 / columns.max(1)).clamp(1024, 1 << 17)
}

/// The quality strings, shared by the rows that hold them.
fn quality_bytes() -> impl Fn(RowQuality) -> bytes::Bytes {
    let all = [
        RowQuality::Good,
        RowQuality::Stale,
        RowQuality::LinkLost,
        RowQuality::Stopped,
        RowQuality::Damaged,
        RowQuality::Error,
    ]
    .map(|q| (q, bytes::Bytes::from_static(q.as_str().as_bytes())));
    move |q| {
        all.iter()
            .find(|(k, _)| *k == q)
            .map(|(_, b)| b.clone())
            .unwrap_or_default()
    }
}

fn write_parquet<W: Write + Send>(
    rows: Intact,
    columns: &[Arc<Variable>],
    wide: bool,
    out: W,
) -> Result<u64, ExportError> {
    let mut fields = vec![field("time", Physical::INT64, timestamp(), false)?];
    let mut fill = vec![Filling::new(Column::I64(Vec::new()), false)];
    if wide {
        fields.push(field("quality", Physical::BYTE_ARRAY, string(), false)?);
        fill.push(Filling::new(Column::Bytes(Vec::new()), false));
        for var in columns {
            let (f, c) = typed_column(&var.name, var.ty)?;
            fields.push(f);
            fill.push(Filling::new(c, true));
            if var.stamped {
                fields.push(field(
                    &format!("{}.plc_time", var.name),
                    Physical::INT64,
                    timestamp(),
                    true,
                )?);
                fill.push(Filling::new(Column::I64(Vec::new()), true));
            }
        }
    } else {
        fields.push(field("name", Physical::BYTE_ARRAY, string(), false)?);
        fill.push(Filling::new(Column::Bytes(Vec::new()), false));
        fields.push(field("value", Physical::DOUBLE, None, true)?);
        fill.push(Filling::new(Column::F64(Vec::new()), true));
        fields.push(field("text", Physical::BYTE_ARRAY, string(), true)?);
        fill.push(Filling::new(Column::Bytes(Vec::new()), true));
        fields.push(field("quality", Physical::BYTE_ARRAY, string(), false)?);
        fill.push(Filling::new(Column::Bytes(Vec::new()), false));
    }
    let schema = Arc::new(
        Type::group_type_builder("history")
            .with_fields(fields)
            .build()?,
    );
    let props = Arc::new(
        WriterProperties::builder()
            .set_compression(Compression::ZSTD(ZstdLevel::try_new(3)?))
            .build(),
    );
    let mut writer = SerializedFileWriter::new(out, schema, props)?;
    let per_group = group_rows(fill.len());
    let mut in_group = 0usize;
    let mut count = 0u64;
    let flush = |fill: &mut Vec<Filling>,
                 writer: &mut SerializedFileWriter<W>|
     -> Result<(), ExportError> {
        let mut group = writer.next_row_group()?;
        let mut i = 0;
        while let Some(mut column) = group.next_column()? {
            fill[i].write(&mut column)?;
            column.close()?;
            i += 1;
        }
        group.close()?;
        Ok(())
    };
    let quality = quality_bytes();
    // A row done: a row group written when full.
    let mut row_done = |fill: &mut Vec<Filling>,
                        writer: &mut SerializedFileWriter<W>|
     -> Result<(), ExportError> {
        count += 1;
        in_group += 1;
        if in_group == per_group {
            flush(fill, writer)?;
            in_group = 0;
        }
        Ok(())
    };
    if wide {
        let layout = Wide::new(columns);
        let mut rows = rows.peekable();
        let mut group = Group::default();
        while layout.next_group(&mut rows, &mut group)? {
            if let Some(gap) = group.gap {
                fill[0].push_i64(group.t);
                fill[1].push_shared(quality(gap));
                for column in &mut fill[2..] {
                    column.null();
                }
                row_done(&mut fill, &mut writer)?;
            }
            if !group.any_good {
                continue;
            }
            fill[0].push_i64(group.t);
            fill[1].push_shared(quality(RowQuality::Good));
            for var in columns {
                let Some(i) = layout.column(var) else {
                    continue;
                };
                let cell = group.cells[i].as_ref();
                match cell {
                    Some(row) => fill[i + 2].push_value(&row.value, row.var.ty),
                    None => fill[i + 2].null(),
                }
                if var.stamped {
                    match cell.and_then(|r| r.plc_time) {
                        Some(ms) => fill[i + 3].push_i64(ms),
                        None => fill[i + 3].null(),
                    }
                }
            }
            row_done(&mut fill, &mut writer)?;
        }
    } else {
        let mut names: Vec<(*const Variable, bytes::Bytes)> = Vec::new();
        for record in rows {
            match record? {
                Record::Sample(row) => {
                    fill[0].push_i64(row.time());
                    let key = Arc::as_ptr(&row.var);
                    let name = match names.iter().find(|(p, _)| *p == key) {
                        Some((_, name)) => name.clone(),
                        None => {
                            let name = bytes::Bytes::from(row.var.name.clone());
                            names.push((key, name.clone()));
                            name
                        }
                    };
                    fill[1].push_shared(name);
                    match presented(&row.value, row.var.ty) {
                        None => {
                            fill[2].null();
                            fill[3].null();
                        }
                        Some(value) => match shape::split(&value) {
                            Split::Number(v) => {
                                fill[2].push_f64(number(v));
                                fill[3].null();
                            }
                            Split::Text(v) => {
                                fill[2].null();
                                fill[3].push_bytes(v.text().as_bytes());
                            }
                        },
                    }
                    fill[4].push_shared(quality(row.quality.into()));
                }
                Record::Mark(mark) => {
                    fill[0].push_i64(mark.t);
                    fill[1].push_shared(bytes::Bytes::from_static(mark.gap.name().as_bytes()));
                    fill[2].null();
                    fill[3].push_shared(bytes::Bytes::from_static(mark.gap.text().as_bytes()));
                    fill[4].push_shared(quality(mark.gap.quality()));
                }
            }
            row_done(&mut fill, &mut writer)?;
        }
    }
    if in_group > 0 || count == 0 {
        flush(&mut fill, &mut writer)?;
    }
    writer.close()?;
    Ok(count)
}

/// A number of the `value` column as a double (BOOL 0/1).
fn number(value: &Presented) -> f64 {
    match value {
        Presented::Bool(b) => f64::from(u8::from(*b)),
        Presented::Signed(n) => *n as f64,
        Presented::Unsigned(n) => *n as f64,
        Presented::Number(x) => *x,
        _ => f64::NAN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn text(value: Stored, ty: IecType) -> String {
        presented(&value, Some(ty)).map_or(String::new(), |v| v.text())
    }

    #[test]
    fn exact_value_texts() {
        assert_eq!(text(Stored::Real(f64::from(0.1f32)), IecType::Real), "0.1");
        assert_eq!(text(Stored::Real(0.1), IecType::Lreal), "0.1");
        assert_eq!(text(Stored::Null, IecType::Lreal), "nan");
        assert_eq!(text(Stored::Null, IecType::Int), "");
        assert_eq!(text(Stored::Real(f64::INFINITY), IecType::Lreal), "inf");
        assert_eq!(
            text(Stored::Int(-1), IecType::Ulint),
            "18446744073709551615"
        );
        assert_eq!(text(Stored::Int(-1), IecType::Lint), "-1");
        assert_eq!(
            presented(&Stored::Int(1), Some(IecType::Bool)),
            Some(Presented::Bool(true))
        );
    }

    /// A stored value is presented as `Presented` presents the value it was
    /// stored from: the web page, MQTT and the exports show one form.
    #[test]
    fn the_forms_of_presented() {
        let cases = [
            (IecType::Dt, Value::Date(1_795_601_700.123)),
            (IecType::Dt, Value::Date(0.0)),
            (IecType::Date, Value::Date(1_795_564_800.0)),
            (IecType::Tod, Value::Time(36_900_123)),
            (IecType::Time, Value::Time(3_723_456)),
            (IecType::Time, Value::Time(0)),
            (IecType::Real, Value::Real(22.3)),
            (IecType::Real, Value::Real(f32::NAN)),
            (IecType::Lreal, Value::LReal(-1.0e-300)),
            (IecType::Bool, Value::Bool(false)),
            (IecType::Udint, Value::Unsigned(4_000_000_000)),
            (IecType::Sint, Value::Signed(-128)),
            (IecType::String(8), Value::Str(b"P\xF8\xEDli\x9A".to_vec())),
        ];
        for (ty, value) in cases {
            let want = Presented::of_value(ty, &value);
            let got = presented(&Stored::from_value(&value), Some(ty)).unwrap();
            // (A NaN is no equal of itself: compared as text and number.)
            assert_eq!(
                (got.text(), got.as_number()),
                (want.text(), want.as_number()),
                "{ty:?} {value:?}"
            );
        }
    }
}

#[cfg(test)]
mod stream_tests {
    use super::*;
    use crate::sample::{Event, EventKind, Sample};
    use crate::store::{day_of, DayFile};
    use plccoms_core::vars::table_of;

    /// A day file with A (INT), B (LREAL, stamped), D (DT), S (STRING), a
    /// link outage, a server stop and start, and a sample of C that the
    /// masks leave out.
    fn history() -> (tempfile::TempDir, Query) {
        let dir = tempfile::tempdir().unwrap();
        let table = Arc::new(table_of(&[
            ("A", "INT"),
            ("B", "LREAL"),
            ("C", "INT"),
            ("D", "DT"),
            ("S", "STRING[8]"),
        ]));
        let id = |n: &str| table.lookup(n.as_bytes()).unwrap();
        let t = 1_700_000_000_000;
        let sample = |var, dt: i64, value, quality, plc_time| Sample {
            t: t + dt,
            var,
            value,
            quality,
            plc_time,
        };
        let samples = [
            sample(id("A"), 0, Stored::Int(1), Quality::Good, None),
            sample(id("B"), 0, Stored::Real(0.5), Quality::Good, Some(t - 7)),
            sample(id("C"), 0, Stored::Int(9), Quality::Good, None),
            sample(id("D"), 0, Stored::Int(t), Quality::Good, None),
            sample(id("S"), 0, Stored::Text("x,y".into()), Quality::Good, None),
            sample(id("A"), 100, Stored::Int(1), Quality::LinkLost, None),
            sample(id("B"), 100, Stored::Real(0.5), Quality::LinkLost, None),
            sample(id("A"), 300, Stored::Int(2), Quality::Good, None),
            sample(id("B"), 300, Stored::Null, Quality::Good, None),
        ];
        let event = |dt: i64, kind| Event {
            t: t + dt,
            kind,
            detail: String::new(),
        };
        let events = [
            event(100, EventKind::LinkLost),
            event(300, EventKind::LinkRestored),
            event(400, EventKind::Stop),
            event(500, EventKind::Table),
            event(600, EventKind::Start),
        ];
        let mut file = DayFile::open(dir.path(), "S", day_of(t)).unwrap();
        file.write(&[(&table, &samples)], &events).unwrap();
        file.close();
        let query = Query {
            dir: dir.path().to_path_buf(),
            section: "S".into(),
            masks: vec!["a".into(), "B".into(), "D".into(), "S".into()],
            from_ms: t,
            to_ms: t + 1000,
        };
        (dir, query)
    }

    fn export_text(query: &Query, format: Format, wide: bool) -> String {
        let mut out = Vec::new();
        export(query, format, wide, &mut out).unwrap();
        String::from_utf8(out).unwrap()
    }

    fn csv(query: &Query, wide: bool) -> String {
        export_text(query, Format::Csv, wide)
    }

    #[test]
    fn long_and_wide_typed_with_gaps_stamps_and_nan() {
        let (_dir, query) = history();
        assert_eq!(
            csv(&query, false),
            "time,name,value,text,quality\n\
             2023-11-14T22:13:20.000Z,A,1,,good\n\
             2023-11-14T22:13:19.993Z,B,0.5,,good\n\
             2023-11-14T22:13:20.000Z,D,,2023-11-14T22:13:20.000Z,good\n\
             2023-11-14T22:13:20.000Z,S,,\"x,y\",good\n\
             2023-11-14T22:13:20.100Z,__LINK,,link_lost,link_lost\n\
             2023-11-14T22:13:20.100Z,A,1,,link_lost\n\
             2023-11-14T22:13:20.100Z,B,0.5,,link_lost\n\
             2023-11-14T22:13:20.300Z,__LINK,,link_restored,link_lost\n\
             2023-11-14T22:13:20.300Z,A,2,,good\n\
             2023-11-14T22:13:20.300Z,B,,nan,good\n\
             2023-11-14T22:13:20.400Z,__SERVER,,stop,stopped\n\
             2023-11-14T22:13:20.600Z,__SERVER,,start,stopped\n"
        );
        assert_eq!(
            csv(&query, true),
            "time,quality,A,B,B.plc_time,D,S\n\
             2023-11-14T22:13:20.000Z,good,1,0.5,2023-11-14T22:13:19.993Z,2023-11-14T22:13:20.000Z,\"x,y\"\n\
             2023-11-14T22:13:20.100Z,link_lost,,,,,\n\
             2023-11-14T22:13:20.300Z,link_lost,,,,,\n\
             2023-11-14T22:13:20.300Z,good,2,nan,,,\n\
             2023-11-14T22:13:20.400Z,stopped,,,,,\n\
             2023-11-14T22:13:20.600Z,stopped,,,,,\n"
        );
        let rows: serde_json::Value =
            serde_json::from_str(&export_text(&query, Format::Json, false)).unwrap();
        assert_eq!(
            rows[0],
            serde_json::json!({"time": "2023-11-14T22:13:20.000Z", "name": "A", "value": 1,
                               "text": null, "quality": "good"})
        );
        assert_eq!(rows[3]["text"], "x,y");
        assert_eq!(
            rows[4],
            serde_json::json!({"time": "2023-11-14T22:13:20.100Z", "name": "__LINK", "value": null,
                               "text": "link_lost", "quality": "link_lost"})
        );
        assert_eq!(
            (&rows[9]["value"], &rows[9]["text"]),
            (&serde_json::Value::Null, &serde_json::json!("nan"))
        );
        let wide: serde_json::Value =
            serde_json::from_str(&export_text(&query, Format::Json, true)).unwrap();
        assert_eq!(
            wide[0],
            serde_json::json!({"time": "2023-11-14T22:13:20.000Z", "quality": "good", "A": 1, "B": 0.5,
                               "B.plc_time": "2023-11-14T22:13:19.993Z", "D": "2023-11-14T22:13:20.000Z", "S": "x,y"})
        );
        assert_eq!(wide[1]["quality"], "link_lost");
        assert_eq!(wide[1]["A"], serde_json::Value::Null);
        assert_eq!(wide[3]["B"], "nan");
        assert_eq!(wide.as_array().unwrap().len(), 6);
        // Nothing of the range: none; an unknown section: an error naming it.
        let empty = Query {
            from_ms: query.to_ms,
            to_ms: query.to_ms + 1,
            ..query.clone()
        };
        assert_eq!(csv(&empty, false), "time,name,value,text,quality\n");
        let other = Query {
            section: "T".into(),
            ..query
        };
        assert!(export(&other, Format::Csv, false, Vec::new())
            .unwrap_err()
            .to_string()
            .contains("no history of section [T]"));
    }

    #[tokio::test]
    async fn a_stream_of_chunks_is_the_export() {
        let (_dir, query) = history();
        let mut rx = stream(query.clone(), Format::Csv, false);
        let mut got = Vec::new();
        while let Some(chunk) = rx.recv().await {
            got.extend_from_slice(&chunk.unwrap());
        }
        assert_eq!(String::from_utf8(got).unwrap(), csv(&query, false));
    }
}
