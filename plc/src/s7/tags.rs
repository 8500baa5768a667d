//! The S7 tag file: which data block bytes, merkers, inputs and outputs a
//! section serves, under which names and types. CSV with a header line
//! naming the columns (any order, any case; `name` and `address` required):
//!
//! ```text
//! name,address,type,unit,description,access
//! Speed,DB1.DBW2,INT,rpm,Conveyor speed,
//! Running,DB1.DBX0.0,BOOL,,,ro
//! Recipe,DB1.DBS10.20,,,Recipe name,
//! Energy,DB2.DBD0,REAL,kWh,,
//! Stamp,DB2.DBB4,DTL,,,
//! Levels,DB3.DBW0,ARRAY[0..9] OF INT,mm,,
//! Lamp,Q0.1,BOOL
//! Counter,MD10,DINT
//! ```
//!
//! - `address`: TIA Portal's notation, German or English mnemonics:
//!   `DB1.DBX0.0` (bit), `DB1.DBB1`, `DB1.DBW2`, `DB1.DBD4`,
//!   `DB1.DBS10.20` (an S7 STRING of 20 at byte 10); `M10.1`, `MB10`,
//!   `MW10`, `MD10`; inputs `I0.0`/`E0.0`, `IB0`/`EB0`, `IW64`/`EW64`,
//!   `ID0`/`ED0`; outputs `Q0.0`/`A0.0`, `QB`/`AB`, `QW`/`AW`, `QD`/`AD`.
//! - `type`: see [`super::value`]; empty: what the address names (BOOL,
//!   BYTE, WORD, DWORD, `STRING[n]`). A type of 1 to 4 bytes must match the
//!   address's width (`DBW` for an INT); a longer one starts at its byte
//!   (`DB1.DBB4` for an LREAL or a DTL). `ARRAY[lo..hi] OF <type>` makes
//!   the variables `name[lo]` to `name[hi]`, one after another (a BOOL
//!   array bit after bit; strings each on an even byte, as STEP 7 lays
//!   them out).
//! - `access`: `ro` or `rw`; default rw, inputs ro.
//! - `unit`, `description`, `min`, `max`, `decimals`: as in a Modbus tag
//!   file.
//!
//! Lines starting with `#` are comments. A line that does not fit is
//! skipped with a [`TagWarning`] naming its line, column and what was
//! expected; the rest loads. Pure: bytes in, tags out.

use std::collections::HashMap;

use plccoms_protocol::{cp1250, IecType};

use super::value::Layout;
use super::{Region, BLOCK};
use crate::modbus::tags::{Row, Rows, TagWarning};
use crate::tag_csv::name_bytes;
use crate::value_codec::Codec;

/// Most elements one ARRAY line may make.
pub const MAX_ARRAY: u32 = 65_536;

/// One variable of the file.
#[derive(Debug, Clone, PartialEq)]
pub struct Tag {
    /// cp1250 bytes, case as written (`Levels[3]` for an array element).
    pub name: Box<[u8]>,
    pub region: Region,
    pub byte: u32,
    /// A BOOL's bit.
    pub bit: Option<u8>,
    pub layout: Layout,
    pub writable: bool,
    pub info: crate::VarInfo,
    /// 1-based line in the file.
    pub line: usize,
}

impl Tag {
    /// The variable the tag names (see the layout in [`super`]).
    pub fn var(&self) -> crate::Var {
        let (area, offset) = self.region.place(self.byte);
        let (ty, codec) = match self.bit {
            Some(_) => (IecType::Bool, Codec::Native),
            None => (self.layout.client_type(), Codec::S7(self.layout)),
        };
        crate::Var {
            name: self.name.clone(),
            area,
            offset,
            bit: self.bit,
            ty,
            codec,
            writable: self.writable,
            info: self.info.clone().boxed(),
        }
    }
}

/// A parsed tag file.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TagFile {
    pub tags: Vec<Tag>,
    /// The first [`crate::pubfile::MAX_WARNINGS`] problems, in file order.
    pub warnings: Vec<TagWarning>,
    pub more_warnings: usize,
    /// The line of the first tag past [`crate::pubfile::MAX_VARS`].
    pub too_many: Option<usize>,
}

impl TagFile {
    fn warn(&mut self, line: usize, column: usize, message: String) {
        if self.warnings.len() < crate::pubfile::MAX_WARNINGS {
            self.warnings.push(TagWarning {
                line,
                column: (column > 0).then_some(column),
                message,
            });
        } else {
            self.more_warnings += 1;
        }
    }
}

/// An address's width: a bit, 1, 2 or 4 bytes, or an S7 STRING of `n`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Width {
    Bit(u8),
    Bytes(u32),
    String(u16),
}

/// A parsed address.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Address {
    pub region: Region,
    pub byte: u32,
    pub width: Width,
}

const EXPECTED: &str = "DB1.DBX0.0, DB1.DBB0, DB1.DBW0, DB1.DBD0, DB1.DBS0.20, M0.0, MB0, MW0, MD0, I0.0/E0.0, IW0/EW0, Q0.0/A0.0, QW0/AW0";

/// An address in TIA Portal's notation, or what is wrong with it.
pub fn parse_address(text: &str) -> Result<Address, String> {
    let upper = text.trim().to_ascii_uppercase();
    let bad = |why: &str| format!("bad address '{text}': {why} (expected e.g. {EXPECTED})");
    let number = |s: &str, what: &str, max: u32| -> Result<u32, String> {
        if s.is_empty() || s.len() > 6 || !s.bytes().all(|b| b.is_ascii_digit()) {
            return Err(bad(&format!("{what} is not a number")));
        }
        let n: u32 = s
            .parse()
            .map_err(|_| bad(&format!("{what} is not a number")))?;
        if n > max {
            return Err(bad(&format!("{what} {n} is past {max}")));
        }
        Ok(n)
    };
    let (region, rest) = if let Some(db) = upper.strip_prefix("DB") {
        let (n, rest) = db
            .split_once('.')
            .ok_or_else(|| bad("a DB address is DBn.DBX, DBB, DBW, DBD or DBS"))?;
        let n = number(n, "DB number", u32::from(super::MAX_DB))?;
        if n == 0 {
            return Err(bad("DB numbers start at 1"));
        }
        let rest = rest
            .strip_prefix("DB")
            .ok_or_else(|| bad("after DBn. comes DBX, DBB, DBW, DBD or DBS"))?;
        (Region::Db(n as u16), rest)
    } else {
        let mut chars = upper.chars();
        let region = match chars.next() {
            Some('I' | 'E') => Region::Inputs,
            Some('Q' | 'A') => Region::Outputs,
            Some('M') => Region::Merkers,
            Some('T' | 'C' | 'Z') => return Err(bad(
                "timers and counters are not served; read the DB or merker that holds the value",
            )),
            _ => return Err(bad("unknown area")),
        };
        let rest = chars.as_str();
        // `M10.1` is a bit: no width letter.
        if rest.starts_with(|c: char| c.is_ascii_digit()) {
            let (byte, bit) = rest.split_once('.').ok_or_else(|| {
                bad("a bit address is byte.bit, a byte MB, a word MW, a double word MD")
            })?;
            let byte = number(byte, "byte", BLOCK - 1)?;
            let bit = number(bit, "bit", 7)? as u8;
            return Ok(Address {
                region,
                byte,
                width: Width::Bit(bit),
            });
        }
        (region, rest)
    };
    let mut chars = rest.chars();
    let kind = chars
        .next()
        .ok_or_else(|| bad("no width letter (X, B, W, D)"))?;
    let rest = chars.as_str();
    let in_db = matches!(region, Region::Db(_));
    let width_bytes = match kind {
        'B' => 1,
        'W' => 2,
        'D' => 4,
        'X' if in_db => 0,
        'S' if in_db => 0,
        _ => return Err(bad(&format!("unknown width letter '{kind}'"))),
    };
    match kind {
        'X' | 'S' => {
            let (byte, second) = rest.split_once('.').ok_or_else(|| {
                bad(if kind == 'X' {
                    "DBX needs byte.bit"
                } else {
                    "DBS needs byte.length"
                })
            })?;
            let byte = number(byte, "byte", BLOCK - 1)?;
            let width = if kind == 'X' {
                Width::Bit(number(second, "bit", 7)? as u8)
            } else {
                let n = number(second, "string length", u32::from(super::value::MAX_STRING))?;
                if n == 0 {
                    return Err(bad("a string holds 1 to 254 characters"));
                }
                Width::String(n as u16)
            };
            Ok(Address {
                region,
                byte,
                width,
            })
        }
        _ => Ok(Address {
            region,
            byte: number(rest, "byte", BLOCK - 1)?,
            width: Width::Bytes(width_bytes),
        }),
    }
}

/// `ARRAY[lo..hi] OF <type>`: the bounds and the element type's text.
fn parse_array(text: &str) -> Option<Result<(i64, i64, &str), String>> {
    let upper = text.to_ascii_uppercase();
    if !upper.trim_start().starts_with("ARRAY") {
        return None;
    }
    let bad = || format!("bad array type '{text}' (expected ARRAY[lo..hi] OF <type>)");
    let open = text.find('[')?;
    let close = text.find(']')?;
    if close < open {
        return Some(Err(bad()));
    }
    let Some((lo, hi)) = text[open + 1..close].split_once("..") else {
        return Some(Err(bad()));
    };
    let (Ok(lo), Ok(hi)) = (lo.trim().parse::<i64>(), hi.trim().parse::<i64>()) else {
        return Some(Err(bad()));
    };
    let rest = text[close + 1..].trim_start();
    if rest.len() < 3 || !rest[..3].eq_ignore_ascii_case("OF ") {
        return Some(Err(bad()));
    }
    if hi < lo || hi - lo >= i64::from(MAX_ARRAY) {
        return Some(Err(format!(
            "array bounds {lo}..{hi}: 1 to {MAX_ARRAY} elements"
        )));
    }
    Some(Ok((lo, hi, rest[3..].trim())))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Column {
    Name,
    Address,
    Type,
    Unit,
    Description,
    Access,
    Min,
    Max,
    Decimals,
}

const COLUMNS: [(&str, Column); 9] = [
    ("name", Column::Name),
    ("address", Column::Address),
    ("type", Column::Type),
    ("unit", Column::Unit),
    ("description", Column::Description),
    ("access", Column::Access),
    ("min", Column::Min),
    ("max", Column::Max),
    ("decimals", Column::Decimals),
];

/// Parses a tag file. Never fails: bad lines become warnings.
pub fn parse(bytes: &[u8]) -> TagFile {
    let mut rows = Rows::new(bytes);
    let utf8 = rows.utf8;
    let mut file = TagFile::default();
    let mut columns: Option<HashMap<Column, usize>> = None;
    let mut seen: HashMap<Vec<u8>, usize> = HashMap::new();
    for row in &mut rows {
        let Row {
            line,
            fields,
            record,
        } = match row {
            Ok(row) => row,
            Err(warning) => {
                file.warn(warning.line, 0, warning.message);
                break;
            }
        };
        let Some(columns) = &columns else {
            let mut found = HashMap::new();
            for (i, name) in fields.iter().enumerate() {
                match COLUMNS.iter().find(|(n, _)| n.eq_ignore_ascii_case(name)) {
                    Some(&(_, column)) => {
                        found.entry(column).or_insert(i);
                    }
                    None => file.warn(line, i + 1, format!("unknown column '{name}' ignored (name, address, type, unit, description, access, min, max, decimals)")),
                }
            }
            if !(found.contains_key(&Column::Name) && found.contains_key(&Column::Address)) {
                file.warn(line, 0, "the header lacks the column name or address (expected name,address,type,unit,description,access); no tag loaded".to_string());
                return file;
            }
            columns = Some(found);
            continue;
        };
        if fields.iter().all(String::is_empty) {
            continue;
        }
        let field = |c: Column| -> (&str, usize) {
            columns.get(&c).map_or(("", 0), |&i| {
                (fields.get(i).map_or("", String::as_str), i + 1)
            })
        };
        let raw_name = record.get(columns[&Column::Name]);
        let tags = match line_tags(&field, line, utf8, raw_name.unwrap_or_default()) {
            Ok(tags) => tags,
            Err((column, message)) => {
                file.warn(line, column, message);
                continue;
            }
        };
        for tag in tags {
            let folded = cp1250::to_upper(&tag.name);
            if let Some(&first) = seen.get(&folded) {
                let message = format!(
                    "duplicate name '{}' (first defined on line {first}); skipped",
                    cp1250::decode(&tag.name)
                );
                file.warn(line, field(Column::Name).1, message);
                break;
            }
            if file.tags.len() == crate::pubfile::MAX_VARS {
                file.too_many = Some(line);
                return file;
            }
            seen.insert(folded, line);
            file.tags.push(tag);
        }
    }
    if columns.is_none() {
        file.warn(
            1,
            0,
            "no header line (expected name,address,type,...)".to_string(),
        );
    }
    file
}

type Field<'a> = dyn Fn(Column) -> (&'a str, usize) + 'a;

/// The tags of one line (several for an array), or the column at fault
/// and why.
fn line_tags(
    field: &Field<'_>,
    line: usize,
    utf8: bool,
    raw_name: &[u8],
) -> Result<Vec<Tag>, (usize, String)> {
    let (name_text, name_col) = field(Column::Name);
    let name = name_bytes(name_text, utf8, raw_name).map_err(|m| (name_col, m))?;
    let (address_text, address_col) = field(Column::Address);
    let address = parse_address(address_text).map_err(|m| (address_col, m))?;
    let (type_text, type_col) = field(Column::Type);
    let (array, element) = match parse_array(type_text) {
        Some(Ok((lo, hi, element))) => (Some((lo, hi)), element),
        Some(Err(m)) => return Err((type_col, m)),
        None => (None, type_text),
    };
    let bool_type = element.eq_ignore_ascii_case("BOOL");
    let layout = match (element.is_empty(), address.width) {
        (true, Width::Bit(_)) => None,
        (true, Width::Bytes(1)) => Some(Layout::Plain(IecType::Byte)),
        (true, Width::Bytes(2)) => Some(Layout::Plain(IecType::Word)),
        (true, Width::Bytes(_)) => Some(Layout::Plain(IecType::Dword)),
        (true, Width::String(n)) => Some(Layout::String(n)),
        (false, _) if bool_type => None,
        (false, _) => Some(Layout::parse(element).ok_or_else(|| {
            (
                type_col,
                format!("unknown type '{element}' (an IEC type, STRING[n], WSTRING[n], DATE_AND_TIME, DTL, S5TIME or ARRAY[lo..hi] OF one)"),
            )
        })?),
    };
    // The address's width and the type agree.
    match (layout, address.width) {
        (None, Width::Bit(_)) => {}
        (None, _) => {
            return Err((
                address_col,
                format!("a BOOL needs a bit address (DB1.DBX0.0, M0.0), not '{address_text}'"),
            ))
        }
        (Some(_), Width::Bit(_)) => {
            return Err((
                type_col,
                format!("'{address_text}' is a bit: its type is BOOL, not {element}"),
            ))
        }
        (Some(Layout::String(n)), Width::String(m)) if n != m => {
            return Err((
                type_col,
                format!("'{address_text}' is a STRING[{m}], not STRING[{n}]"),
            ))
        }
        (Some(Layout::String(_)), Width::String(_)) => {}
        (Some(_), Width::String(_)) => {
            return Err((
                type_col,
                format!("'{address_text}' is a string; its type is STRING[n], not {element}"),
            ))
        }
        (Some(layout), Width::Bytes(w)) if layout.len() <= 4 && layout.len() != w => {
            let letter = match layout.len() {
                1 => "B",
                2 => "W",
                _ => "D",
            };
            return Err((
                address_col,
                format!(
                    "{element} is {} byte(s); '{address_text}' is {w}: address it with {letter} (e.g. DB1.DB{letter}0, M{letter}0)",
                    layout.len()
                ),
            ));
        }
        (Some(_), Width::Bytes(_)) => {}
    }

    let (access_text, access_col) = field(Column::Access);
    let writable = match access_text.to_ascii_lowercase().as_str() {
        "" => address.region != Region::Inputs,
        "rw" => true,
        "ro" => false,
        _ => {
            return Err((
                access_col,
                format!("unknown access '{access_text}' (ro or rw)"),
            ))
        }
    };
    let number = |c: Column| -> Result<Option<f64>, (usize, String)> {
        let (text, col) = field(c);
        if text.is_empty() {
            return Ok(None);
        }
        text.parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .map(Some)
            .ok_or_else(|| (col, format!("'{text}' is not a number")))
    };
    let (decimals_text, decimals_col) = field(Column::Decimals);
    let decimals = match decimals_text {
        "" => None,
        text => Some(
            text.parse::<u8>()
                .ok()
                .filter(|&n| n <= 15)
                .ok_or_else(|| {
                    (
                        decimals_col,
                        format!("decimals '{text}' is not a whole number 0-15"),
                    )
                })?,
        ),
    };
    let info = crate::VarInfo {
        unit: field(Column::Unit).0.to_string(),
        description: field(Column::Description).0.to_string(),
        min: number(Column::Min)?,
        max: number(Column::Max)?,
        decimals,
    };
    let one = |name: Box<[u8]>, byte: u32, bit: Option<u8>| Tag {
        name,
        region: address.region,
        byte,
        bit,
        layout: layout.unwrap_or(Layout::Plain(IecType::Bool)),
        writable,
        info: info.clone(),
        line,
    };
    let start_bit = match address.width {
        Width::Bit(bit) => Some(bit),
        _ => None,
    };
    let Some((lo, hi)) = array else {
        let len = layout.map_or(1, Layout::len);
        if address.byte + len > BLOCK {
            return Err((
                address_col,
                format!("'{address_text}' runs past the block's end (byte 65535)"),
            ));
        }
        return Ok(vec![one(name, address.byte, start_bit)]);
    };
    let count = (hi - lo + 1) as u32;
    // Elements one after another; a string or anything of two bytes or more on
    // an even byte, as STEP 7 lays arrays out.
    let stride = layout.map_or(0, |l| l.len() + l.len() % 2 * u32::from(l.len() > 1));
    let last_byte = match start_bit {
        Some(bit) => address.byte + (u32::from(bit) + count - 1) / 8,
        None => address.byte + stride * (count - 1) + layout.map_or(1, Layout::len) - 1,
    };
    if last_byte >= BLOCK {
        return Err((
            address_col,
            format!("ARRAY[{lo}..{hi}] at '{address_text}' runs past the block's end (byte 65535)"),
        ));
    }
    let mut tags = Vec::with_capacity(count as usize);
    for (i, index) in (lo..=hi).enumerate() {
        let mut element_name = name.to_vec();
        element_name.extend_from_slice(format!("[{index}]").as_bytes());
        if element_name.len() > crate::pubfile::MAX_NAME {
            return Err((
                name_col,
                format!(
                    "element names of '{name_text}' are longer than {} characters",
                    crate::pubfile::MAX_NAME
                ),
            ));
        }
        let i = i as u32;
        let (byte, bit) = match start_bit {
            Some(bit) => {
                let at = u32::from(bit) + i;
                (address.byte + at / 8, Some((at % 8) as u8))
            }
            None => (address.byte + stride * i, None),
        };
        tags.push(one(element_name.into_boxed_slice(), byte, bit));
    }
    Ok(tags)
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_protocol::Area;

    const HEADER: &str = "name,address,type,unit,description,access\n";

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
    fn addresses_in_both_mnemonics() {
        let a = |t: &str| parse_address(t).unwrap();
        assert_eq!(
            a("DB1.DBX0.7"),
            Address {
                region: Region::Db(1),
                byte: 0,
                width: Width::Bit(7)
            }
        );
        assert_eq!(a("db10.dbw2").width, Width::Bytes(2));
        assert_eq!(
            a("DB1.DBS10.20"),
            Address {
                region: Region::Db(1),
                byte: 10,
                width: Width::String(20)
            }
        );
        assert_eq!(
            a("M10.1"),
            Address {
                region: Region::Merkers,
                byte: 10,
                width: Width::Bit(1)
            }
        );
        assert_eq!(a("MD10").width, Width::Bytes(4));
        assert_eq!(a("E0.0"), a("I0.0"));
        assert_eq!(a("EW64"), a("IW64"));
        assert_eq!(a("A0.0"), a("Q0.0"));
        assert_eq!(a("AW2").region, Region::Outputs);
        for bad in [
            "DB0.DBB0",
            "DB1.DBX0",
            "DB1.DBX0.8",
            "M10",
            "MX1.0",
            "T5",
            "DB1.DBS0.0",
            "DB1.DBS0.255",
            "X1",
            "DB1.DBB65536",
            "",
            "DB1DBB0",
            "MB-1",
        ] {
            let e = parse_address(bad).unwrap_err();
            assert!(e.contains("expected e.g."), "{bad}: {e}");
        }
        assert!(parse_address("T5")
            .unwrap_err()
            .contains("timers and counters"));
    }

    #[test]
    fn types_and_places() {
        let t = one("Speed,DB1.DBW2,INT,rpm,Conveyor speed,").unwrap();
        let var = t.var();
        assert_eq!(
            (var.area, var.offset, var.ty),
            (Area::R, 65_536 + 2, IecType::Int)
        );
        assert_eq!(var.byte_len(), 2);
        assert!(var.writable);
        let bit = one("Run,I0.3,BOOL").unwrap().var();
        assert_eq!(
            (bit.area, bit.offset, bit.bit, bit.ty, bit.writable),
            (Area::X, 0, Some(3), IecType::Bool, false)
        );
        let s = one("Recipe,DB1.DBS10.20").unwrap().var();
        assert_eq!((s.ty, s.byte_len()), (IecType::String(20), 22));
        let stamp = one("Stamp,DB2.DBB4,DTL").unwrap().var();
        assert_eq!((stamp.ty, stamp.byte_len()), (IecType::Dt, 12));
        assert_eq!(one("Plain,MW4").unwrap().var().ty, IecType::Word);
        assert!(!one("Q,QB0,,,,ro").unwrap().writable);
    }

    #[test]
    fn mismatches_name_line_column_and_the_fix() {
        let e = one("X,DB1.DBW2,DINT").unwrap_err();
        assert_eq!((e.line, e.column), (2, Some(2)));
        assert!(e.message.contains("address it with D"), "{e}");
        let e = one("X,DB1.DBB2,BOOL").unwrap_err();
        assert!(e.message.contains("needs a bit address"), "{e}");
        let e = one("X,DB1.DBX2.0,INT").unwrap_err();
        assert_eq!(e.column, Some(3));
        let e = one("X,DB1.DBS2.10,STRING[9]").unwrap_err();
        assert!(e.message.contains("STRING[10]"), "{e}");
        let e = one("X,DB1.DBW2,FLOAT").unwrap_err();
        assert!(e.message.contains("unknown type 'FLOAT'"), "{e}");
        let e = one("X,DB1.DBB65530,LREAL").unwrap_err();
        assert!(e.message.contains("past the block's end"), "{e}");
        let e = one("X,ZZ,INT").unwrap_err();
        assert_eq!(e.to_string().split(':').next(), Some("line 2, column 2"));
    }

    #[test]
    fn arrays_expand_to_elements() {
        let file = parse(format!("{HEADER}L,DB3.DBW0,ARRAY[1..3] OF INT\nB,M0.6,ARRAY[0..3] OF BOOL\nS,DB4.DBB0,Array[0..1] of STRING[3]\n").as_bytes());
        assert!(file.warnings.is_empty(), "{:?}", file.warnings);
        let places: Vec<(String, u32, Option<u8>)> = file
            .tags
            .iter()
            .map(|t| (cp1250::decode(&t.name).into_owned(), t.byte, t.bit))
            .collect();
        assert_eq!(
            places,
            [
                ("L[1]".into(), 0, None),
                ("L[2]".into(), 2, None),
                ("L[3]".into(), 4, None),
                ("B[0]".into(), 0, Some(6)),
                ("B[1]".into(), 0, Some(7)),
                ("B[2]".into(), 1, Some(0)),
                ("B[3]".into(), 1, Some(1)),
                ("S[0]".into(), 0, None),
                ("S[1]".into(), 6, None),
            ]
        );
        let e = one("L,DB3.DBW0,ARRAY[3..1] OF INT").unwrap_err();
        assert!(e.message.contains("1 to 65536 elements"), "{e}");
    }

    #[test]
    fn header_and_duplicates() {
        let file = parse(b"name,type\nA,INT\n");
        assert!(file.tags.is_empty());
        assert!(file.warnings[0].message.contains("lacks the column"));
        let file = parse(format!("{HEADER}A,MB0\na,MB1\n").as_bytes());
        assert_eq!(file.tags.len(), 1);
        assert!(file.warnings[0].message.contains("duplicate name"));
    }
}
