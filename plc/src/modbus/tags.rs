//! The Modbus tag file: which registers and bits of a device a section
//! serves, under which names and types. CSV with a header line naming the
//! columns (any order, any case):
//!
//! ```text
//! name,type,table,address,bit,order,scale,offset,access,unit,description,min,max,decimals
//! Temperature,INT,input,0,,,0.1,,,°C,"Outdoor, north wall",,,1
//! Setpoint,INT,holding,10,,,0.1,,,°C,Heating setpoint,5,30,1
//! Energy,UDINT,holding,100,,CDAB
//! Pump,BOOL,coil,3
//! Alarm,BOOL,holding,20,15
//! ```
//!
//! - `name`, `type`, `table`, `address` are required; the rest optional.
//! - `table`: `coil`, `discrete`, `input` or `holding`; `address` 0-based
//!   (the 1-based reference 40001 is holding address 0, 30001 input 0,
//!   10001 discrete 0, 00001 coil 0). An address that reads as such a
//!   reference (`40001`, `00017`) loads as written, with a warning saying
//!   what it maps to; a six-digit one past 65535 (`400001`) is refused,
//!   with the same hint.
//! - `type`: every IEC type a public file has, `STRING[n]` (two characters a
//!   register, high byte first) and `TS48` (milliseconds since 1970 UTC in
//!   three registers, most significant first; clients see DT). Coils and
//!   discrete inputs are BOOL; a BOOL in a register needs `bit` 0-15.
//! - `order`: ABCD (default), CDAB, BADC or DCBA for values of two or more
//!   registers (a STRING: ABCD or BADC).
//! - `scale`, `offset`: the client sees raw x scale + offset, computed in
//!   double precision, as LREAL.
//! - `access`: `ro` or `rw`; default rw for coils and holding registers, ro
//!   for the others (which cannot be written).
//! - `unit`, `description`: for people (MQTT, Home Assistant, the web
//!   page); the telnet port shows neither.
//! - `min`, `max`: the range a writer may set (Home Assistant's number
//!   entities); `decimals`: 0-15, how many decimals a REAL, an LREAL or a
//!   scaled value is printed with (a REAL at most 6; for other types it is
//!   ignored, with a warning). A scaled value without it prints in its
//!   shortest form within NUM_OF_DECIMALS (see [`crate::value_codec`]).
//!
//! Lines starting with `#` are comments; fields may be quoted; a value past
//! the header's last column makes its line bad (empty trailing fields are
//! fine). A file that
//! is valid UTF-8 is read as UTF-8 (names are stored in cp1250, as public
//! files'), any other as cp1250. A line that does not fit is skipped with a
//! [`TagWarning`] naming its line and column; the rest loads. A line that
//! loads but is likely a mistake (an address that reads as a 1-based
//! reference, decimals that do not apply) gets a warning too. Pure: bytes
//! in, tags out.

use std::collections::HashMap;
use std::fmt;

use plccoms_protocol::value::REAL_MAX_DECIMALS;
use plccoms_protocol::{cp1250, Area, IecType};

use super::{Reference, Table};
use crate::tag_csv::name_bytes;
use crate::value_codec::{Codec, Raw, Registers, Scale, WordOrder};

/// One tag.
#[derive(Debug, Clone, PartialEq)]
pub struct Tag {
    /// cp1250 bytes, case as written.
    pub name: Box<[u8]>,
    /// The type clients see (LREAL when scaled, DT for TS48).
    pub ty: IecType,
    pub table: Table,
    pub address: u16,
    /// Bit 0-15 of a register, for a BOOL there.
    pub bit: Option<u8>,
    pub codec: Codec,
    pub writable: bool,
    /// Unit, description, range and decimals.
    pub info: crate::VarInfo,
    /// 1-based line in the file.
    pub line: usize,
}

impl Tag {
    /// Area, byte offset and bit (see the layout in [`super`]).
    pub fn place(&self) -> (Area, u32, Option<u8>) {
        let (area, offset) = self.table.place(self.address);
        match (self.table.is_bits(), self.bit) {
            (true, _) => (area, offset, Some(0)),
            // Bits 8-15 are in the register's high byte, which comes first.
            (false, Some(bit)) => (area, offset + u32::from(bit < 8), Some(bit % 8)),
            (false, None) => (area, offset, None),
        }
    }

    /// The variable the tag names, at its [`Tag::place`].
    pub fn var(&self) -> crate::Var {
        let (area, offset, bit) = self.place();
        crate::Var {
            name: self.name.clone(),
            area,
            offset,
            bit,
            ty: self.ty,
            codec: self.codec,
            writable: self.writable,
            info: self.info.clone().boxed(),
        }
    }

    /// Registers (or bits) the tag occupies.
    pub fn span(&self) -> u32 {
        match (&self.codec, self.table.is_bits()) {
            (_, true) => 1,
            (Codec::Registers(r), false) => r.raw.len() / 2,
            (Codec::Native | Codec::S7(_), false) => 1,
        }
    }
}

/// A problem on one line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TagWarning {
    /// 1-based line.
    pub line: usize,
    /// 1-based column (CSV field), when one field is at fault.
    pub column: Option<usize>,
    pub message: String,
}

impl fmt::Display for TagWarning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.column {
            Some(column) => write!(f, "line {}, column {column}: {}", self.line, self.message),
            None => write!(f, "line {}: {}", self.line, self.message),
        }
    }
}

/// A parsed tag file.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TagFile {
    pub tags: Vec<Tag>,
    /// The first [`crate::pubfile::MAX_WARNINGS`] problems, in file order.
    pub warnings: Vec<TagWarning>,
    /// Problems beyond those, counted only (a file of garbage must not
    /// become megabytes of messages).
    pub more_warnings: usize,
    /// The line of the first tag past [`crate::pubfile::MAX_VARS`]: the file
    /// is too large, and its parse stopped there.
    pub too_many: Option<usize>,
}

impl TagFile {
    fn warn(&mut self, warning: TagWarning) {
        if self.warnings.len() < crate::pubfile::MAX_WARNINGS {
            self.warnings.push(warning);
        } else {
            self.more_warnings += 1;
        }
    }
}

/// The columns a tag file may have.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Column {
    Name,
    Type,
    Table,
    Address,
    Bit,
    Order,
    Scale,
    Offset,
    Access,
    Unit,
    Description,
    Min,
    Max,
    Decimals,
}

const COLUMNS: [(&str, Column); 14] = [
    ("name", Column::Name),
    ("type", Column::Type),
    ("table", Column::Table),
    ("address", Column::Address),
    ("bit", Column::Bit),
    ("order", Column::Order),
    ("scale", Column::Scale),
    ("offset", Column::Offset),
    ("access", Column::Access),
    ("unit", Column::Unit),
    ("description", Column::Description),
    ("min", Column::Min),
    ("max", Column::Max),
    ("decimals", Column::Decimals),
];

const REQUIRED: [Column; 4] = [Column::Name, Column::Type, Column::Table, Column::Address];

/// Parses a tag file. Never fails: bad lines become warnings.
pub fn parse(bytes: &[u8]) -> TagFile {
    let mut rows = Rows::new(bytes);
    let utf8 = rows.utf8;
    let mut file = TagFile::default();
    let mut columns: Option<HashMap<Column, usize>> = None;
    let mut seen: HashMap<Vec<u8>, usize> = HashMap::new();
    let mut header_len = 0;
    for row in &mut rows {
        let Row {
            line,
            fields,
            record,
        } = match row {
            Ok(row) => row,
            Err(warning) => {
                file.warn(warning);
                break;
            }
        };
        let Some(columns) = &columns else {
            match header(&fields, line, &mut file.warnings) {
                Some(found) => columns = Some(found),
                None => return file,
            }
            header_len = fields.len();
            continue;
        };
        if fields.iter().all(String::is_empty) {
            continue;
        }
        // A value under no column is a mistake (a column left out of the
        // header), not something to drop quietly; empty trailing fields
        // (spreadsheets write them) are fine.
        if let Some(extra) = (header_len..fields.len()).find(|&i| !fields[i].is_empty()) {
            file.warn(TagWarning {
                line,
                column: Some(extra + 1),
                message: format!(
                    "'{}' is under no column (the header names {header_len}); line skipped",
                    fields[extra]
                ),
            });
            continue;
        }
        let field = |c: Column| -> (&str, usize) {
            columns.get(&c).map_or(("", 0), |&i| {
                (fields.get(i).map_or("", String::as_str), i + 1)
            })
        };
        let mut notes = Vec::new();
        let raw_name = record.get(columns[&Column::Name]);
        match tag(&field, line, utf8, raw_name, &mut notes) {
            Ok(tag) => {
                let folded = cp1250::to_upper(&tag.name);
                if let Some(&first) = seen.get(&folded) {
                    file.warn(TagWarning {
                        line,
                        column: Some(field(Column::Name).1),
                        message: format!(
                            "duplicate name '{}' (first defined on line {first}); skipped",
                            cp1250::decode(&tag.name)
                        ),
                    });
                } else if file.tags.len() == crate::pubfile::MAX_VARS {
                    file.too_many = Some(line);
                    break;
                } else {
                    seen.insert(folded, line);
                    file.tags.push(tag);
                    for (column, message) in notes {
                        file.warn(TagWarning {
                            line,
                            column: Some(column),
                            message,
                        });
                    }
                }
            }
            Err((column, message)) => file.warn(TagWarning {
                line,
                column: (column > 0).then_some(column),
                message,
            }),
        }
    }
    if columns.is_none() {
        file.warn(TagWarning {
            line: 1,
            column: None,
            message: "no header line (expected name,type,table,address,...)".to_string(),
        });
    }
    file
}

/// The records of a CSV tag file (Modbus or S7): a BOM dropped, `#` lines
/// skipped, fields trimmed, read as UTF-8 when the whole file is, else as
/// cp1250. An unreadable record ends them with a warning naming its line.
pub(crate) struct Rows<'a> {
    bytes: &'a [u8],
    records: csv::ByteRecordsIntoIter<&'a [u8]>,
    lines: LineCounter,
    pub(crate) utf8: bool,
}

/// One record: its 1-based line, its fields as text, and as read.
pub(crate) struct Row {
    pub(crate) line: usize,
    pub(crate) fields: Vec<String>,
    pub(crate) record: csv::ByteRecord,
}

impl<'a> Rows<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Rows<'a> {
        let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        let records = csv::ReaderBuilder::new()
            .has_headers(false)
            .flexible(true)
            .trim(csv::Trim::All)
            .comment(Some(b'#'))
            .from_reader(bytes)
            .into_byte_records();
        Rows {
            bytes,
            records,
            lines: LineCounter::default(),
            utf8: std::str::from_utf8(bytes).is_ok(),
        }
    }
}

impl Iterator for Rows<'_> {
    type Item = Result<Row, TagWarning>;

    fn next(&mut self) -> Option<Self::Item> {
        let (bytes, lines) = (self.bytes, &mut self.lines);
        Some(match self.records.next()? {
            Ok(record) => {
                let line = record
                    .position()
                    .map_or(0, |p| lines.line_of(bytes, p.byte() as usize));
                let fields = record.iter().map(|f| text(f, self.utf8)).collect();
                Ok(Row {
                    line,
                    fields,
                    record,
                })
            }
            Err(e) => Err(TagWarning {
                line: e
                    .position()
                    .map_or(0, |p| lines.line_of(bytes, p.byte() as usize)),
                column: None,
                message: format!("unreadable CSV: {e}"),
            }),
        })
    }
}

/// 1-based line numbers of records. The csv crate's own line count and
/// record offsets are off after blank and comment lines (csv 1.4: the
/// offset is where the skipped lines begin), so the record's line is found
/// from that offset by skipping them here, counting as it goes.
#[derive(Default)]
pub(crate) struct LineCounter {
    at: usize,
    line: usize,
}

impl LineCounter {
    pub(crate) fn line_of(&mut self, bytes: &[u8], offset: usize) -> usize {
        let mut start = offset.min(bytes.len());
        loop {
            match bytes.get(start) {
                Some(b'\n') => start += 1,
                Some(b'\r') if bytes.get(start + 1) == Some(&b'\n') => start += 2,
                Some(b'#') => match bytes[start..].iter().position(|&b| b == b'\n') {
                    Some(end) => start += end + 1,
                    None => start = bytes.len(),
                },
                _ => break,
            }
        }
        if start < self.at {
            self.at = 0;
            self.line = 0;
        }
        self.line += bytes[self.at..start]
            .iter()
            .filter(|&&b| b == b'\n')
            .count();
        self.at = start;
        self.line + 1
    }
}

/// A field's text: as it is in a UTF-8 file, else decoded from cp1250.
pub(crate) fn text(field: &[u8], utf8: bool) -> String {
    if utf8 {
        String::from_utf8_lossy(field).into_owned()
    } else {
        cp1250::decode(field).into_owned()
    }
}

/// The header's columns by name; `None` (with a warning) when a required
/// one is missing.
fn header(
    fields: &[String],
    line: usize,
    warnings: &mut Vec<TagWarning>,
) -> Option<HashMap<Column, usize>> {
    let mut columns = HashMap::new();
    for (i, name) in fields.iter().enumerate() {
        match COLUMNS.iter().find(|(n, _)| n.eq_ignore_ascii_case(name)) {
            Some(&(_, column)) if !columns.contains_key(&column) => {
                columns.insert(column, i);
            }
            Some(_) => warnings.push(TagWarning {
                line,
                column: Some(i + 1),
                message: format!("column '{name}' given twice; the first counts"),
            }),
            None => warnings.push(TagWarning {
                line,
                column: Some(i + 1),
                message: format!("unknown column '{name}' ignored"),
            }),
        }
    }
    let missing: Vec<&str> = REQUIRED
        .iter()
        .filter(|c| !columns.contains_key(c))
        .map(|c| COLUMNS.iter().find(|(_, k)| k == c).map_or("", |(n, _)| *n))
        .collect();
    if missing.is_empty() {
        return Some(columns);
    }
    warnings.push(TagWarning {
        line,
        column: None,
        message: format!(
            "the header lacks the column(s) {}; no tag loaded",
            missing.join(", ")
        ),
    });
    None
}

type Field<'a> = dyn Fn(Column) -> (&'a str, usize) + 'a;

/// The tag of one line, or the column at fault and why; `notes` gets
/// (column, message) for what loads but is likely a mistake.
fn tag(
    field: &Field<'_>,
    line: usize,
    utf8: bool,
    raw_name: Option<&[u8]>,
    notes: &mut Vec<(usize, String)>,
) -> Result<Tag, (usize, String)> {
    let (name_text, name_col) = field(Column::Name);
    let name = name_bytes(name_text, utf8, raw_name.unwrap_or_default())
        .map_err(|message| (name_col, message))?;

    let (type_text, type_col) = field(Column::Type);
    let raw = if type_text.eq_ignore_ascii_case("TS48") {
        Raw::Ts48
    } else {
        Raw::Iec(IecType::parse(type_text.as_bytes()).ok_or_else(|| {
            (
                type_col,
                format!("unknown type '{type_text}' (an IEC type, STRING[n] or TS48)"),
            )
        })?)
    };

    let (table_text, table_col) = field(Column::Table);
    let table = Table::parse(table_text).ok_or_else(|| {
        (
            table_col,
            format!("unknown table '{table_text}' (coil, discrete, input or holding)"),
        )
    })?;

    let (address_text, address_col) = field(Column::Address);
    let address: u16 = address_text.parse().map_err(|_| {
        let reference = Reference::parse(address_text)
            .map(|r| {
                format!(
                    ": the 1-based reference {} is {} {}",
                    r.text, r.table, r.address
                )
            })
            .unwrap_or_default();
        (
            address_col,
            format!("bad address '{address_text}' (0 to 65535, 0-based){reference}"),
        )
    })?;
    // 40001 in a manual is holding 0 on the wire; a device without
    // register 40001 answers "illegal data address" and nothing more.
    if let Some(reference) = Reference::parse(address_text) {
        notes.push((
            address_col,
            format!(
                "{}; the tag loads as written",
                reference.hint(table, address)
            ),
        ));
    }

    let (bit_text, bit_col) = field(Column::Bit);
    let bit = if bit_text.is_empty() {
        None
    } else {
        match bit_text.parse::<u8>() {
            Ok(b) if b <= 15 => Some(b),
            _ => return Err((bit_col, format!("bad bit '{bit_text}' (0 to 15)"))),
        }
    };

    let is_bool = raw == Raw::Iec(IecType::Bool);
    if table.is_bits() {
        if !is_bool {
            return Err((type_col, format!("a {table} holds a BOOL, not {raw}")));
        }
        if bit.is_some() {
            return Err((
                bit_col,
                format!("a {table} has no bits to choose (bit is for registers)"),
            ));
        }
    } else if is_bool && bit.is_none() {
        return Err((
            bit_col,
            "a BOOL in a register needs its bit (0 to 15)".to_string(),
        ));
    } else if !is_bool && bit.is_some() {
        return Err((
            bit_col,
            format!("bit given for a {raw} (only BOOL has a bit)"),
        ));
    }

    let (order_text, order_col) = field(Column::Order);
    let order = if order_text.is_empty() {
        WordOrder::Abcd
    } else {
        WordOrder::parse(order_text).ok_or_else(|| {
            (
                order_col,
                format!("unknown order '{order_text}' (ABCD, CDAB, BADC or DCBA)"),
            )
        })?
    };
    if is_bool && order != WordOrder::Abcd {
        return Err((order_col, "a BOOL has no word order".to_string()));
    }
    if matches!(raw, Raw::Iec(IecType::String(_)))
        && !matches!(order, WordOrder::Abcd | WordOrder::Badc)
    {
        return Err((order_col, format!("a STRING is ABCD or BADC, not {order}")));
    }

    let number = |column: Column| -> Result<Option<f64>, (usize, String)> {
        let (text, col) = field(column);
        if text.is_empty() {
            return Ok(None);
        }
        match text.parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(Some(x)),
            _ => Err((col, format!("'{text}' is not a number"))),
        }
    };
    let factor = number(Column::Scale)?;
    let offset = number(Column::Offset)?;
    let scale = match (factor, offset) {
        (None, None) => None,
        (Some(0.0), _) => {
            return Err((
                field(Column::Scale).1,
                "scale 0 cannot be written back".to_string(),
            ))
        }
        (factor, offset) => {
            let scalable = matches!(raw, Raw::Iec(ty) if !matches!(ty,
                IecType::Bool | IecType::String(_) | IecType::Date | IecType::Dt | IecType::Time | IecType::Tod));
            if !scalable {
                let col = field(if factor.is_some() {
                    Column::Scale
                } else {
                    Column::Offset
                })
                .1;
                return Err((col, format!("a {raw} cannot be scaled")));
            }
            Some(Scale {
                factor: factor.unwrap_or(1.0),
                offset: offset.unwrap_or(0.0),
            })
        }
    };

    let min = number(Column::Min)?;
    let max = number(Column::Max)?;
    if let (Some(lo), Some(hi)) = (min, max) {
        if lo > hi {
            return Err((field(Column::Max).1, format!("max {hi} is below min {lo}")));
        }
    }
    let (decimals_text, decimals_col) = field(Column::Decimals);
    let decimals = match decimals_text {
        "" => None,
        text => match text.parse::<u8>() {
            Ok(n) if n <= 15 => Some(n),
            _ => {
                return Err((
                    decimals_col,
                    format!("decimals '{text}' is not a whole number 0-15"),
                ))
            }
        },
    };

    let (access_text, access_col) = field(Column::Access);
    let writable = match access_text.to_ascii_lowercase().as_str() {
        "" => table.writable(),
        "rw" => {
            if !table.writable() {
                return Err((access_col, format!("a {table} is read-only (access ro)")));
            }
            true
        }
        "ro" => false,
        _ => {
            return Err((
                access_col,
                format!("unknown access '{access_text}' (ro or rw)"),
            ))
        }
    };

    let (ty, codec) = if table.is_bits() || is_bool {
        (IecType::Bool, Codec::Native)
    } else {
        let ty = match (raw, scale) {
            // Computed in double precision: a REAL would turn 223 x 0.1
            // into 22.299999 and lose a large counter's last digits.
            (_, Some(_)) => IecType::Lreal,
            (Raw::Ts48, None) => IecType::Dt,
            (Raw::Iec(ty), None) => ty,
        };
        (ty, Codec::Registers(Registers { raw, order, scale }))
    };
    let decimals = match (decimals, ty) {
        (Some(n), IecType::Real) if n > REAL_MAX_DECIMALS => {
            notes.push((
                decimals_col,
                format!("a REAL shows at most {REAL_MAX_DECIMALS} decimals, not {n}; {REAL_MAX_DECIMALS} are printed"),
            ));
            Some(REAL_MAX_DECIMALS)
        }
        (Some(_), IecType::Real | IecType::Lreal) | (None, _) => decimals,
        (Some(_), ty) => {
            notes.push((
                decimals_col,
                format!("decimals apply to REAL, LREAL and scaled values, not to {ty}; ignored"),
            ));
            None
        }
    };
    let tag = Tag {
        name,
        ty,
        table,
        address,
        bit,
        codec,
        writable,
        info: crate::VarInfo {
            unit: field(Column::Unit).0.to_string(),
            description: field(Column::Description).0.to_string(),
            min,
            max,
            decimals,
        },
        line,
    };
    if u32::from(address) + tag.span() > 65_536 {
        return Err((
            address_col,
            format!("{raw} at {address} runs past the end of the table (65535)"),
        ));
    }
    Ok(tag)
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "name,type,table,address,bit,order,scale,offset,access,unit,description\n";

    fn one(line: &str) -> Result<Tag, TagWarning> {
        let file = parse(format!("{HEADER}{line}\n").as_bytes());
        match (
            file.tags.into_iter().next(),
            file.warnings.into_iter().next(),
        ) {
            (Some(tag), None) => Ok(tag),
            (_, Some(warning)) => Err(warning),
            (None, None) => panic!("nothing for {line}"),
        }
    }

    #[test]
    fn every_table_and_the_layout() {
        let coil = one("Pump,BOOL,coil,3").unwrap();
        assert_eq!(coil.place(), (Area::Y, 3, Some(0)));
        assert!(coil.writable);
        let input = one("In,bool,discrete,65535").unwrap();
        assert_eq!(input.place(), (Area::X, 65535, Some(0)));
        assert!(!input.writable);
        let high = one("Alarm,BOOL,holding,20,15").unwrap();
        assert_eq!(high.place(), (Area::R, 40, Some(7)));
        let low = one("Ready,BOOL,input,20,0").unwrap();
        assert_eq!(
            low.place(),
            (Area::R, super::super::INPUT_BASE + 41, Some(0))
        );
        let energy = one("Energy,UDINT,holding,100,,CDAB").unwrap();
        assert_eq!(energy.place(), (Area::R, 200, None));
        assert_eq!(energy.codec.byte_len(energy.ty), 4);
        let t = one("T,INT,input,0,,,0.1,-40,,°C,\"Outdoor, north\"").unwrap();
        assert_eq!(t.ty, IecType::Lreal);
        assert_eq!(t.info.unit, "°C");
        assert_eq!(t.info.description, "Outdoor, north");
        let ts = one("Stamp,TS48,holding,10").unwrap();
        assert_eq!((ts.ty, ts.span()), (IecType::Dt, 3));
        let s = one("Text,STRING[5],holding,50,,BADC").unwrap();
        assert_eq!(s.span(), 3);
    }

    #[test]
    fn range_and_decimals_reach_the_variable() {
        let file = parse(
            "name,type,table,address,scale,unit,description,min,max,decimals\n\
             Setpoint,INT,holding,10,0.1,°C,Heating setpoint,5,30,1\n\
             Plain,INT,holding,11\n\
             Bad,INT,holding,12,,,,30,5\n\
             Worse,INT,holding,13,,,,,,16\n"
                .as_bytes(),
        );
        let setpoint = file.tags[0].var();
        let info = setpoint.info.as_deref().expect("info");
        assert_eq!(
            (info.unit.as_str(), info.min, info.max, info.decimals),
            ("°C", Some(5.0), Some(30.0), Some(1))
        );
        assert_eq!(info.description, "Heating setpoint");
        assert_eq!(file.tags[1].var().info, None, "nothing said, nothing kept");
        let warnings: Vec<String> = file.warnings.iter().map(|w| w.to_string()).collect();
        assert_eq!(
            warnings,
            [
                "line 4, column 9: max 5 is below min 30",
                "line 5, column 10: decimals '16' is not a whole number 0-15"
            ]
        );
    }

    /// The S7 user's `Temperature,REAL,holding,40001`: it loads, and the
    /// warning says what 40001 means on the wire.
    #[test]
    fn an_address_like_a_reference_loads_with_its_mapping() {
        let file = parse(
            "name,type,table,address\n\
             Temperature,REAL,holding,40001\n\
             Level,INT,input,30010\n\
             Switch,BOOL,coil,00017\n\
             Wrong,INT,holding,10001\n\
             Plain,INT,holding,40000\n\
             Low,INT,holding,9999\n\
             Six,INT,holding,400001\n"
                .as_bytes(),
        );
        let names: Vec<&[u8]> = file.tags.iter().map(|t| &t.name[..]).collect();
        assert_eq!(
            names,
            [
                &b"Temperature"[..],
                b"Level",
                b"Switch",
                b"Wrong",
                b"Plain",
                b"Low"
            ]
        );
        assert_eq!(file.tags[0].address, 40001, "loaded as written");
        let shown: Vec<String> = file.warnings.iter().map(|w| w.to_string()).collect();
        assert_eq!(
            shown,
            [
                "line 2, column 4: holding 40001 looks like the 1-based reference 40001, \
                 which is holding 0 (addresses are 0-based); the tag loads as written",
                "line 3, column 4: input 30010 looks like the 1-based reference 30010, \
                 which is input 9 (addresses are 0-based); the tag loads as written",
                "line 4, column 4: coil 17 looks like the 1-based reference 00017, \
                 which is coil 16 (addresses are 0-based); the tag loads as written",
                "line 5, column 4: holding 10001 looks like the 1-based reference 10001, \
                 which is discrete 0 (addresses are 0-based); the tag loads as written",
                "line 8, column 4: bad address '400001' (0 to 65535, 0-based): \
                 the 1-based reference 400001 is holding 0",
            ]
        );
    }

    #[test]
    fn scaled_values_are_lreal_and_decimals_apply_to_reals() {
        let file = parse(
            "name,type,table,address,scale,decimals\n\
             Scaled,INT,holding,0,0.1,1\n\
             Real,REAL,holding,1,,8\n\
             Long,LREAL,holding,3,,12\n\
             Count,INT,holding,7,,2\n"
                .as_bytes(),
        );
        let decimals: Vec<(IecType, Option<u8>)> =
            file.tags.iter().map(|t| (t.ty, t.info.decimals)).collect();
        assert_eq!(
            decimals,
            [
                (IecType::Lreal, Some(1)),
                (IecType::Real, Some(6)),
                (IecType::Lreal, Some(12)),
                (IecType::Int, None)
            ]
        );
        let shown: Vec<String> = file.warnings.iter().map(|w| w.to_string()).collect();
        assert_eq!(
            shown,
            [
                "line 3, column 6: a REAL shows at most 6 decimals, not 8; 6 are printed",
                "line 5, column 6: decimals apply to REAL, LREAL and scaled values, not to INT; ignored",
            ]
        );
    }

    #[test]
    fn bad_lines_name_line_and_column_and_the_rest_loads() {
        let text = "# a comment\n\
name,type,table,address,access\n\
good,INT,holding,0\n\
bad1,INT,holdng,1\n\
bad2,WORD,input,1,rw\n\
bad3,DINT,holding,65535\n\
\n\
bad4,BOOL,holding,7\n\
GOOD,INT,holding,2\n\
bad5 x,INT,holding,3\n\
good2,LREAL,input,4\n\
bad6,REAL,holding,5,,CDAB\n\
good3,INT,holding,6,,,\n";
        let file = parse(text.as_bytes());
        let names: Vec<&[u8]> = file.tags.iter().map(|t| &t.name[..]).collect();
        assert_eq!(names, [&b"good"[..], b"good2", b"good3"]);
        let shown: Vec<String> = file.warnings.iter().map(|w| w.to_string()).collect();
        assert_eq!(
            shown[0],
            "line 4, column 3: unknown table 'holdng' (coil, discrete, input or holding)"
        );
        assert_eq!(
            shown[1],
            "line 5, column 5: a input is read-only (access ro)"
        );
        assert!(
            shown[2].starts_with("line 6, column 4: DINT at 65535 runs past"),
            "{}",
            shown[2]
        );
        assert!(
            shown[3].starts_with("line 8: a BOOL in a register needs"),
            "{}",
            shown[3]
        );
        assert!(
            shown[4].starts_with("line 9, column 1: duplicate name 'GOOD'"),
            "{}",
            shown[4]
        );
        assert!(
            shown[5].starts_with("line 10, column 1: invalid character"),
            "{}",
            shown[5]
        );
        assert_eq!(
            shown[6],
            "line 12, column 6: 'CDAB' is under no column (the header names 5); line skipped"
        );
    }

    #[test]
    fn a_file_past_the_variable_bound_stops_at_its_line() {
        let bound = crate::pubfile::MAX_VARS;
        let mut text = b"name,type,table,address\n".to_vec();
        for i in 0..=bound {
            text.extend_from_slice(format!("t{i},INT,holding,{}\n", i % 1000).as_bytes());
        }
        let file = parse(&text);
        assert_eq!(file.tags.len(), bound);
        assert_eq!(file.too_many, Some(bound + 2));
    }

    #[test]
    fn a_header_without_required_columns_loads_nothing() {
        let file = parse(b"name,type,address\nx,INT,0\n");
        assert!(file.tags.is_empty());
        assert_eq!(
            file.warnings[0].to_string(),
            "line 1: the header lacks the column(s) table; no tag loaded"
        );
        assert_eq!(parse(b"").warnings.len(), 1);
    }

    /// A file of bad lines keeps the first problems and counts the rest.
    #[test]
    fn warnings_are_bounded() {
        let mut bytes = b"name,type,table,address\n".to_vec();
        for i in 0..1000 {
            bytes.extend_from_slice(format!("v{i},NOPE,holding,{i}\n").as_bytes());
        }
        let file = parse(&bytes);
        assert_eq!(file.warnings.len(), crate::pubfile::MAX_WARNINGS);
        assert_eq!(file.more_warnings, 1000 - crate::pubfile::MAX_WARNINGS);
        assert!(file.warnings[0].to_string().starts_with("line 2"));
    }

    /// The README's example tag files load without a warning.
    #[test]
    fn the_readme_examples_load() {
        let readme = include_str!("../../../README.md");
        let blocks: Vec<&str> = readme
            .split("```csv\n")
            .skip(1)
            .map(|rest| rest.split("```").next().unwrap_or_default())
            .collect();
        assert_eq!(blocks.len(), 2);
        for block in blocks {
            let file = parse(block.as_bytes());
            assert!(file.warnings.is_empty(), "{:?}", file.warnings);
            assert!(file.tags.len() >= 6);
        }
        let demo = parse(include_bytes!("../../../conf/demo-modbus.csv"));
        assert!(demo.warnings.is_empty(), "{:?}", demo.warnings);
    }

    #[test]
    fn cp1250_and_utf8_names() {
        let utf8 = parse("name,type,table,address\nteplota_kuchyně,INT,holding,0\n".as_bytes());
        assert_eq!(&utf8.tags[0].name[..], b"teplota_kuchyn\xEC");
        let raw = parse(b"name,type,table,address\nteplota_kuchyn\xEC,INT,holding,0\n");
        assert_eq!(&raw.tags[0].name[..], b"teplota_kuchyn\xEC");
    }
}
