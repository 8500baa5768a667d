//! Writing samples out: CSV, JSON and Parquet (zstd), long (one row per
//! sample: time, name, value, quality) or wide (one row per time, one
//! column per variable). Everything streams from [`query::rows`]: CSV and
//! JSON row by row, Parquet a row group at a time.
//!
//! Values are exact: integers in full (ULINT/LWORD above 2^63 too), REAL as
//! the shortest text that reads back as the same 32-bit float, LREAL as the
//! shortest that reads back as the same double, DATE and DT as ISO 8601
//! UTC, TIME and TOD in ms, BOOL as 0/1, NaN and infinities as `NaN`,
//! `inf`, `-inf`. In the wide form a sample whose quality is not `good` (an
//! outage) leaves its cell empty, so a gap shows as one.

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

use super::query::{self, Query, QueryError, Row, Variable};
use super::sample::{quality_code, Stored};
use super::time::iso;
use plccoms_core::changes::Quality;
use plccoms_core::history_source::runs_as_formula;

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
    let rows = query::rows(query)?;
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

/// The rows of a query without the samples of damaged blocks: each such
/// range is named in `damaged`, and the export goes on after it.
struct Intact {
    rows: query::Rows,
    damaged: Rc<RefCell<Vec<String>>>,
}

impl Iterator for Intact {
    type Item = Result<Row, QueryError>;

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
// Values as text.

/// How a value is written.
pub(crate) enum Written {
    Number,
    Text,
    Missing,
}

fn is_date(ty: Option<IecType>) -> bool {
    matches!(ty, Some(IecType::Dt | IecType::Date))
}

/// Appends the value's text; says whether it is a number, text or missing.
pub(crate) fn value_text(value: &Stored, ty: Option<IecType>, out: &mut Vec<u8>) -> Written {
    let mut ryu = ryu::Buffer::new();
    match value {
        Stored::Int(ms) if is_date(ty) => {
            iso(*ms, out);
            Written::Text
        }
        Stored::Real(ms) if is_date(ty) && ms.is_finite() => {
            iso(ms.round() as i64, out);
            Written::Text
        }
        Stored::Int(i) if matches!(ty, Some(IecType::Ulint | IecType::Lword)) => {
            let _ = write!(out, "{}", *i as u64);
            Written::Number
        }
        Stored::Int(i) => {
            let _ = write!(out, "{i}");
            Written::Number
        }
        Stored::Real(f) if ty == Some(IecType::Real) => {
            out.extend_from_slice(ryu.format(*f as f32).as_bytes());
            Written::Number
        }
        Stored::Real(f) => {
            out.extend_from_slice(ryu.format(*f).as_bytes());
            Written::Number
        }
        Stored::Null if matches!(ty, Some(IecType::Real | IecType::Lreal)) => {
            out.extend_from_slice(b"NaN");
            Written::Number
        }
        Stored::Null => Written::Missing,
        Stored::Text(s) => {
            out.extend_from_slice(s.as_bytes());
            Written::Text
        }
    }
}

/// The header of a wide export: time, then per variable its column (and
/// its PLC time's, when stamped).
fn wide_header(columns: &[Arc<Variable>]) -> Vec<String> {
    let mut header = vec!["time".to_string()];
    for var in columns {
        header.push(var.name.clone());
        if var.stamped {
            header.push(format!("{}.plc_time", var.name));
        }
    }
    header
}

/// Groups consecutive rows of the same poll time; each group as cells per
/// column of [`wide_header`] (minus time): the rows by column index.
struct Wide {
    /// Column index of each variable (by pointer) in the header.
    index: Vec<(*const Variable, usize)>,
    width: usize,
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

    /// Reads the next group (rows of one time) from `rows` into `cells`
    /// (one per column, `None`: no value).
    fn next_group(
        &self,
        rows: &mut std::iter::Peekable<Intact>,
        cells: &mut Vec<Option<Row>>,
    ) -> Result<Option<i64>, QueryError> {
        cells.clear();
        cells.resize(self.width, None);
        let Some(first) = rows.next() else {
            return Ok(None);
        };
        let first = first?;
        let t = first.t;
        let mut put = |row: Row| {
            if let Some(i) = self.column(&row.var) {
                cells[i] = Some(row);
            }
        };
        put(first);
        while let Some(Ok(next)) = rows.peek() {
            if next.t != t {
                break;
            }
            if let Some(Ok(row)) = rows.next() {
                put(row);
            }
        }
        Ok(Some(t))
    }
}

// ---------------------------------------------------------------------------
// CSV.

/// Appends a CSV field: quoted when it holds a comma, a quote or a line
/// end, and always when it is a text value (so an empty string differs
/// from no value).
fn csv_field(field: &[u8], quote: bool, out: &mut Vec<u8>) {
    let needs = quote
        || field
            .iter()
            .any(|b| matches!(b, b',' | b'"' | b'\r' | b'\n'));
    if !needs {
        out.extend_from_slice(field);
        return;
    }
    out.push(b'"');
    for &b in field {
        if b == b'"' {
            out.push(b'"');
        }
        out.push(b);
    }
    out.push(b'"');
}

/// A CSV field of text: guarded against formulas, then as [`csv_field`].
fn csv_text(field: &[u8], quote: bool, out: &mut Vec<u8>) {
    if runs_as_formula(field) {
        let mut guarded = Vec::with_capacity(field.len() + 1);
        guarded.push(b'\'');
        guarded.extend_from_slice(field);
        csv_field(&guarded, quote, out);
    } else {
        csv_field(field, quote, out);
    }
}

fn csv_value(row: &Row, out: &mut Vec<u8>, scratch: &mut Vec<u8>) {
    scratch.clear();
    let kind = value_text(&row.value, row.var.ty, scratch);
    let is_string = matches!(row.var.ty, Some(IecType::String(_))) && matches!(kind, Written::Text);
    if matches!(kind, Written::Text) {
        csv_text(scratch, is_string && scratch.is_empty(), out);
    } else {
        csv_field(scratch, false, out);
    }
}

/// The output buffered, a line and a value being built.
fn text_buffers<W: Write>(out: W) -> (io::BufWriter<W>, Vec<u8>, Vec<u8>) {
    (
        io::BufWriter::with_capacity(256 * 1024, out),
        Vec::with_capacity(256),
        Vec::with_capacity(64),
    )
}

fn write_csv<W: Write>(
    mut rows: Intact,
    columns: &[Arc<Variable>],
    wide: bool,
    out: W,
) -> Result<u64, ExportError> {
    let (mut out, mut line, mut scratch) = text_buffers(out);
    let mut count = 0u64;
    if !wide {
        out.write_all(b"time,name,value,quality\n")?;
        for row in rows.by_ref() {
            let row = row?;
            line.clear();
            iso(row.time(), &mut line);
            line.push(b',');
            csv_text(row.var.name.as_bytes(), false, &mut line);
            line.push(b',');
            csv_value(&row, &mut line, &mut scratch);
            line.push(b',');
            line.extend_from_slice(row.quality.as_str().as_bytes());
            line.push(b'\n');
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
            csv_text(name.as_bytes(), false, &mut line);
        }
        line.push(b'\n');
        out.write_all(&line)?;
        let wide = Wide::new(columns);
        let mut rows = rows.peekable();
        let mut cells = Vec::new();
        while let Some(t) = wide.next_group(&mut rows, &mut cells)? {
            line.clear();
            iso(t, &mut line);
            for var in columns {
                let cell = wide.column(var).and_then(|i| cells[i].as_ref());
                line.push(b',');
                if let Some(row) = cell.filter(|r| r.quality == Quality::Good) {
                    csv_value(row, &mut line, &mut scratch);
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

fn json_value(row: &Row, out: &mut Vec<u8>, scratch: &mut Vec<u8>) -> io::Result<()> {
    scratch.clear();
    match value_text(&row.value, row.var.ty, scratch) {
        Written::Missing => out.extend_from_slice(b"null"),
        Written::Number
            if scratch
                .first()
                .is_some_and(|b| b.is_ascii_digit() || *b == b'-')
                && !scratch.ends_with(b"inf") =>
        {
            out.extend_from_slice(scratch)
        }
        // NaN and infinities have no JSON number: as text.
        Written::Number | Written::Text => {
            serde_json::to_writer(&mut *out, &String::from_utf8_lossy(scratch))?
        }
    }
    Ok(())
}

fn json_string(text: &str, out: &mut Vec<u8>) -> io::Result<()> {
    serde_json::to_writer(out, text).map_err(io::Error::from)
}

fn write_json<W: Write>(
    mut rows: Intact,
    columns: &[Arc<Variable>],
    wide: bool,
    out: W,
) -> Result<u64, ExportError> {
    let (mut out, mut line, mut scratch) = text_buffers(out);
    let mut count = 0u64;
    out.write_all(b"[")?;
    let mut separator: &[u8] = b"\n";
    if !wide {
        for row in rows.by_ref() {
            let row = row?;
            line.clear();
            line.extend_from_slice(separator);
            line.extend_from_slice(b"{\"time\":\"");
            iso(row.time(), &mut line);
            line.extend_from_slice(b"\",\"name\":");
            json_string(&row.var.name, &mut line)?;
            line.extend_from_slice(b",\"value\":");
            json_value(&row, &mut line, &mut scratch)?;
            line.extend_from_slice(b",\"quality\":\"");
            line.extend_from_slice(row.quality.as_str().as_bytes());
            line.extend_from_slice(b"\"}");
            out.write_all(&line)?;
            separator = b",\n";
            count += 1;
        }
    } else {
        let wide = Wide::new(columns);
        let names = wide_header(columns);
        let mut rows = rows.peekable();
        let mut cells = Vec::new();
        while let Some(t) = wide.next_group(&mut rows, &mut cells)? {
            line.clear();
            line.extend_from_slice(separator);
            line.extend_from_slice(b"{\"time\":\"");
            iso(t, &mut line);
            line.push(b'"');
            for var in columns {
                let i = wide.column(var).unwrap_or(0);
                line.push(b',');
                json_string(&names[i + 1], &mut line)?;
                line.push(b':');
                match cells[i].as_ref().filter(|r| r.quality == Quality::Good) {
                    Some(row) => json_value(row, &mut line, &mut scratch)?,
                    None => line.extend_from_slice(b"null"),
                }
                if var.stamped {
                    line.push(b',');
                    json_string(&names[i + 2], &mut line)?;
                    line.push(b':');
                    match cells[i].as_ref().and_then(|r| r.plc_time) {
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

fn write_parquet<W: Write + Send>(
    rows: Intact,
    columns: &[Arc<Variable>],
    wide: bool,
    out: W,
) -> Result<u64, ExportError> {
    let mut fields = vec![field("time", Physical::INT64, timestamp(), false)?];
    let mut fill = vec![Filling::new(Column::I64(Vec::new()), false)];
    if wide {
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
    if wide {
        let layout = Wide::new(columns);
        let mut rows = rows.peekable();
        let mut cells = Vec::new();
        while let Some(t) = layout.next_group(&mut rows, &mut cells)? {
            fill[0].push_i64(t);
            for var in columns {
                let Some(i) = layout.column(var) else {
                    continue;
                };
                let cell = cells[i].as_ref();
                match cell.filter(|r| r.quality == Quality::Good) {
                    Some(row) => fill[i + 1].push_value(&row.value, row.var.ty),
                    None => fill[i + 1].null(),
                }
                if var.stamped {
                    match cell.and_then(|r| r.plc_time) {
                        Some(ms) => fill[i + 2].push_i64(ms),
                        None => fill[i + 2].null(),
                    }
                }
            }
            count += 1;
            in_group += 1;
            if in_group == per_group {
                flush(&mut fill, &mut writer)?;
                in_group = 0;
            }
        }
    } else {
        let mut names: Vec<(*const Variable, bytes::Bytes)> = Vec::new();
        let qualities = [Quality::Good, Quality::Stale, Quality::LinkLost]
            .map(|q| bytes::Bytes::from_static(q.as_str().as_bytes()));
        for row in rows {
            let row = row?;
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
            match &row.value {
                Stored::Text(s) => {
                    fill[2].null();
                    fill[3].push_bytes(s.as_bytes());
                }
                value => {
                    fill[2].push_value(value, row.var.ty);
                    fill[3].null();
                }
            }
            fill[4].push_shared(qualities[quality_code(row.quality) as usize].clone());
            count += 1;
            in_group += 1;
            if in_group == per_group {
                flush(&mut fill, &mut writer)?;
                in_group = 0;
            }
        }
    }
    if in_group > 0 || count == 0 {
        flush(&mut fill, &mut writer)?;
    }
    writer.close()?;
    Ok(count)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn text(value: Stored, ty: IecType) -> String {
        let mut out = Vec::new();
        value_text(&value, Some(ty), &mut out);
        String::from_utf8(out).unwrap()
    }

    #[test]
    fn exact_value_texts() {
        assert_eq!(text(Stored::Real(f64::from(0.1f32)), IecType::Real), "0.1");
        assert_eq!(text(Stored::Real(0.1), IecType::Lreal), "0.1");
        assert_eq!(text(Stored::Null, IecType::Lreal), "NaN");
        assert_eq!(text(Stored::Real(f64::INFINITY), IecType::Lreal), "inf");
        assert_eq!(
            text(Stored::Int(-1), IecType::Ulint),
            "18446744073709551615"
        );
        assert_eq!(text(Stored::Int(-1), IecType::Lint), "-1");
        assert_eq!(
            text(Stored::Int(1_700_000_000_000), IecType::Dt),
            "2023-11-14T22:13:20.000Z"
        );
        for (text, guarded) in [
            ("=1+2", true),
            ("+CMD", true),
            ("@A1", true),
            ("\tx", true),
            ("\rx", true),
            ("-1+2", true),
            ("-5", false),
            ("-1.5e3", false),
            ("+inf", false),
            ("a=b", false),
            ("", false),
        ] {
            assert_eq!(runs_as_formula(text.as_bytes()), guarded, "{text:?}");
        }
        let mut out = Vec::new();
        csv_text(b"=a,b", false, &mut out);
        assert_eq!(out, b"\"'=a,b\"");
        let mut out = Vec::new();
        csv_field(b"a,\"b\"", false, &mut out);
        csv_field(b"", true, &mut out);
        assert_eq!(out, b"\"a,\"\"b\"\"\"\"\"");
    }
}

#[cfg(test)]
mod stream_tests {
    use super::*;
    use crate::sample::Sample;
    use crate::store::{day_of, DayFile};
    use plccoms_core::vars::table_of;

    /// A day file with A (INT) and B (LREAL, stamped), an outage sample
    /// and a sample of C that the masks leave out.
    fn history() -> (tempfile::TempDir, Query) {
        let dir = tempfile::tempdir().unwrap();
        let table = Arc::new(table_of(&[("A", "INT"), ("B", "LREAL"), ("C", "INT")]));
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
            sample(id("A"), 100, Stored::Int(1), Quality::LinkLost, None),
            sample(id("B"), 100, Stored::Null, Quality::Good, None),
        ];
        let mut file = DayFile::open(dir.path(), "S", day_of(t)).unwrap();
        file.write(&[(&table, &samples)], &[]).unwrap();
        file.close();
        let query = Query {
            dir: dir.path().to_path_buf(),
            section: "S".into(),
            masks: vec!["a".into(), "B".into()],
            from_ms: t,
            to_ms: t + 1000,
        };
        (dir, query)
    }

    fn csv(query: &Query, wide: bool) -> String {
        let mut out = Vec::new();
        export(query, Format::Csv, wide, &mut out).unwrap();
        String::from_utf8(out).unwrap()
    }

    #[test]
    fn long_and_wide_with_quality_stamps_and_nan() {
        let (_dir, query) = history();
        assert_eq!(
            csv(&query, false),
            "time,name,value,quality\n\
             2023-11-14T22:13:20.000Z,A,1,good\n\
             2023-11-14T22:13:19.993Z,B,0.5,good\n\
             2023-11-14T22:13:20.100Z,A,1,link_lost\n\
             2023-11-14T22:13:20.100Z,B,NaN,good\n"
        );
        assert_eq!(
            csv(&query, true),
            "time,A,B,B.plc_time\n\
             2023-11-14T22:13:20.000Z,1,0.5,2023-11-14T22:13:19.993Z\n\
             2023-11-14T22:13:20.100Z,,NaN,\n"
        );
        let mut json = Vec::new();
        export(&query, Format::Json, false, &mut json).unwrap();
        let rows: serde_json::Value = serde_json::from_slice(&json).unwrap();
        assert_eq!(rows[3]["value"], "NaN");
        assert_eq!(rows[2]["quality"], "link_lost");
        // Nothing of the range: none; an unknown section: an error naming it.
        let empty = Query {
            from_ms: query.to_ms,
            to_ms: query.to_ms + 1,
            ..query.clone()
        };
        assert_eq!(csv(&empty, false), "time,name,value,quality\n");
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
