//! A TwinCAT PLC's symbol table and data types as uploaded (index groups
//! SYM_UPLOAD and SYM_DT_UPLOAD), expanded into the variables a client
//! sees: structures to their fields (`MAIN.st.x`), arrays to their elements
//! (`MAIN.arr[3]`), each with the ADS name to ask a handle for, its index
//! group/offset and its type. [`Layout`] places them in R one after another
//! and writes the public file that names them.
//!
//! Every parser bounds what it reads by the entry's own length and by
//! [`MAX_VARS`]: a device sending garbage costs an error naming the entry
//! and byte, never a panic or memory beyond its bytes.

use std::collections::HashMap;
use std::fmt::Write as _;

use bytes::Buf;
use plccoms_protocol::IecType;

use crate::pubfile::{crc_of, MAX_NAME, MAX_VARS};

/// One entry of the symbol table.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Symbol {
    pub name: String,
    pub group: u32,
    pub offset: u32,
    pub size: u32,
    /// ADS data type id (ADST_*).
    pub data_type: u32,
    pub type_name: String,
    pub comment: String,
}

/// One data type (a structure, an array type, an alias or an enum).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DataType {
    pub name: String,
    /// What it is built on (an alias's or an array's element type).
    pub type_name: String,
    pub size: u32,
    /// Within its parent, for a structure's field.
    pub offset: u32,
    pub data_type: u32,
    /// (lower bound, elements) per dimension.
    pub array: Vec<(i32, u32)>,
    pub fields: Vec<DataType>,
}

/// An upload that does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{what} entry {entry} at byte {at}: {message}")]
pub struct UploadError {
    pub what: &'static str,
    pub entry: usize,
    pub at: usize,
    pub message: String,
}

struct Cursor<'a> {
    what: &'static str,
    entry: usize,
    base: usize,
    all: &'a [u8],
    rest: &'a [u8],
}

impl<'a> Cursor<'a> {
    fn error(&self, message: String) -> UploadError {
        UploadError {
            what: self.what,
            entry: self.entry,
            at: self.base + self.all.len() - self.rest.len(),
            message,
        }
    }

    fn need(&self, n: usize, field: &str) -> Result<(), UploadError> {
        if self.rest.len() < n {
            return Err(self.error(format!("{field} needs {n} bytes, {} left", self.rest.len())));
        }
        Ok(())
    }

    fn u16(&mut self, field: &str) -> Result<u16, UploadError> {
        self.need(2, field)?;
        Ok(self.rest.get_u16_le())
    }

    fn u32(&mut self, field: &str) -> Result<u32, UploadError> {
        self.need(4, field)?;
        Ok(self.rest.get_u32_le())
    }

    /// `len` bytes of text and the NUL after them; the entry's last text
    /// may end with the entry (pyads's server leaves the comment's NUL out).
    fn text(&mut self, len: u16, field: &str) -> Result<String, UploadError> {
        let len = usize::from(len);
        self.need(len, field)?;
        let text = String::from_utf8_lossy(&self.rest[..len]).into_owned();
        self.rest = self.rest.get(len + 1..).unwrap_or_default();
        Ok(text)
    }
}

/// Splits `bytes` into entries, each led by its own u32 length.
fn entries<'a>(
    what: &'static str,
    bytes: &'a [u8],
    base: usize,
    count: Option<usize>,
) -> impl Iterator<Item = Result<Cursor<'a>, UploadError>> + 'a {
    let mut at = 0usize;
    let mut entry = 0usize;
    std::iter::from_fn(move || {
        if at >= bytes.len() || count.is_some_and(|c| entry >= c) {
            return None;
        }
        let start = at;
        let fail = |message: String| UploadError {
            what,
            entry,
            at: base + start,
            message,
        };
        let result = match bytes.get(at..at + 4) {
            None => Err(fail(format!(
                "{} bytes left, no entry length",
                bytes.len() - at
            ))),
            Some(head) => {
                let len = u32::from_le_bytes([head[0], head[1], head[2], head[3]]) as usize;
                if len < 4 || len > bytes.len() - at {
                    Err(fail(format!(
                        "entry length {len} where {} bytes are left",
                        bytes.len() - at
                    )))
                } else {
                    at += len;
                    Ok(Cursor {
                        what,
                        entry,
                        base: base + start + 4,
                        all: &bytes[start + 4..start + len],
                        rest: &bytes[start + 4..start + len],
                    })
                }
            }
        };
        if result.is_err() {
            at = bytes.len();
        }
        entry += 1;
        Some(result)
    })
}

/// The symbol table as SYM_UPLOAD answers it.
pub fn parse_symbols(bytes: &[u8]) -> Result<Vec<Symbol>, UploadError> {
    let mut symbols = Vec::new();
    for cursor in entries("symbol", bytes, 0, None) {
        let mut c = cursor?;
        if symbols.len() == MAX_VARS {
            return Err(c.error(format!("more than {MAX_VARS} symbols")));
        }
        let group = c.u32("index group")?;
        let offset = c.u32("index offset")?;
        let size = c.u32("size")?;
        let data_type = c.u32("data type")?;
        let _flags = c.u32("flags")?;
        let (name_len, type_len, comment_len) = (
            c.u16("name length")?,
            c.u16("type length")?,
            c.u16("comment length")?,
        );
        let name = c.text(name_len, "name")?;
        let type_name = c.text(type_len, "type")?;
        let comment = c.text(comment_len, "comment")?;
        symbols.push(Symbol {
            name,
            group,
            offset,
            size,
            data_type,
            type_name,
            comment,
        });
    }
    Ok(symbols)
}

/// One symbol table entry as a device writes it (SYM_UPLOAD).
pub fn encode_symbol(symbol: &Symbol) -> Vec<u8> {
    let (name, ty, comment) = (
        symbol.name.as_bytes(),
        symbol.type_name.as_bytes(),
        symbol.comment.as_bytes(),
    );
    let len = 30 + name.len() + ty.len() + comment.len() + 3;
    let mut entry = Vec::with_capacity(len);
    entry.extend_from_slice(&(len as u32).to_le_bytes());
    for field in [
        symbol.group,
        symbol.offset,
        symbol.size,
        symbol.data_type,
        0,
    ] {
        entry.extend_from_slice(&field.to_le_bytes());
    }
    for text in [name, ty, comment] {
        entry.extend_from_slice(&(text.len() as u16).to_le_bytes());
    }
    for text in [name, ty, comment] {
        entry.extend_from_slice(text);
        entry.push(0);
    }
    entry
}

/// The data types as SYM_DT_UPLOAD answers them.
pub fn parse_data_types(bytes: &[u8]) -> Result<Vec<DataType>, UploadError> {
    let mut types = Vec::new();
    let mut budget = MAX_VARS;
    for cursor in entries("data type", bytes, 0, None) {
        types.push(parse_data_type(cursor?, 0, &mut budget)?);
    }
    Ok(types)
}

/// Deepest nesting of fields taken.
const MAX_DEPTH: usize = 16;

fn parse_data_type(
    mut c: Cursor<'_>,
    depth: usize,
    budget: &mut usize,
) -> Result<DataType, UploadError> {
    if depth > MAX_DEPTH {
        return Err(c.error(format!("fields nested deeper than {MAX_DEPTH}")));
    }
    if *budget == 0 {
        return Err(c.error(format!("more than {MAX_VARS} data types and fields")));
    }
    *budget -= 1;
    let _version = c.u32("version")?;
    let _hash = c.u32("hash")?;
    let _type_hash = c.u32("type hash")?;
    let size = c.u32("size")?;
    let offset = c.u32("offset")?;
    let data_type = c.u32("data type")?;
    let _flags = c.u32("flags")?;
    let (name_len, type_len, comment_len) = (
        c.u16("name length")?,
        c.u16("type length")?,
        c.u16("comment length")?,
    );
    let dims = c.u16("array dimensions")?;
    let fields_count = c.u16("field count")?;
    let name = c.text(name_len, "name")?;
    let type_name = c.text(type_len, "type")?;
    let _comment = c.text(comment_len, "comment")?;
    let mut array = Vec::new();
    for _ in 0..dims {
        array.push((c.u32("lower bound")? as i32, c.u32("elements")?));
    }
    let mut fields = Vec::new();
    let base = c.base + c.all.len() - c.rest.len();
    for sub in entries("field", c.rest, base, Some(usize::from(fields_count))) {
        fields.push(parse_data_type(sub?, depth + 1, budget)?);
    }
    if fields.len() < usize::from(fields_count) {
        return Err(c.error(format!(
            "{fields_count} fields announced, {} present",
            fields.len()
        )));
    }
    Ok(DataType {
        name,
        type_name,
        size,
        offset,
        data_type,
        array,
        fields,
    })
}

/// The type a TwinCAT type name stands for, where it is a basic one.
/// TwinCAT's DATE and DT are 4-byte seconds since 1970 (the server's are
/// 8 bytes): they are served as UDINT. LTIME (8-byte ns) as ULINT.
pub fn basic_type(name: &str) -> Option<IecType> {
    let upper = name.trim().to_ascii_uppercase();
    if let Some(rest) = upper.strip_prefix("STRING") {
        let rest = rest.trim();
        if rest.is_empty() {
            return Some(IecType::String(80));
        }
        let n = rest
            .strip_prefix(['(', '['])?
            .strip_suffix([')', ']'])?
            .trim()
            .parse()
            .ok()?;
        return Some(IecType::String(n));
    }
    Some(match upper.as_str() {
        "BOOL" | "BIT" => IecType::Bool,
        "BYTE" => IecType::Byte,
        "WORD" => IecType::Word,
        "DWORD" => IecType::Dword,
        "LWORD" => IecType::Lword,
        "SINT" => IecType::Sint,
        "USINT" => IecType::Usint,
        "INT" => IecType::Int,
        "UINT" => IecType::Uint,
        "DINT" => IecType::Dint,
        "UDINT" => IecType::Udint,
        "LINT" => IecType::Lint,
        "ULINT" | "LTIME" => IecType::Ulint,
        "REAL" => IecType::Real,
        "LREAL" => IecType::Lreal,
        "TIME" => IecType::Time,
        "TOD" | "TIME_OF_DAY" => IecType::Tod,
        "DATE" | "DT" | "DATE_AND_TIME" => IecType::Udint,
        _ => return None,
    })
}

/// The type of an ADS data type id of `size` bytes, for a symbol whose type
/// name is not known (ADST_* of the ADS specification).
fn type_of_id(id: u32, size: u32) -> Option<IecType> {
    let ty = match id {
        2 => IecType::Int,
        3 => IecType::Dint,
        4 => IecType::Real,
        5 => IecType::Lreal,
        16 => IecType::Sint,
        17 => IecType::Usint,
        18 => IecType::Uint,
        19 => IecType::Udint,
        20 => IecType::Lint,
        21 => IecType::Ulint,
        30 if (2..=256).contains(&size) => IecType::String(size as u16 - 1),
        33 => IecType::Bool,
        _ => return None,
    };
    (ty.size() as u32 == size).then_some(ty)
}

/// `ARRAY [0..9, 1..2] OF INT` as its dimensions and element type.
fn array_type(name: &str) -> Option<(Vec<(i32, u32)>, String)> {
    let upper = name.trim().to_ascii_uppercase();
    let rest = upper
        .strip_prefix("ARRAY")?
        .trim_start()
        .strip_prefix('[')?;
    let close = rest.find(']')?;
    let of = rest[close + 1..].trim_start().strip_prefix("OF")?;
    let mut dims = Vec::new();
    for range in rest[..close].split(',') {
        let (low, high) = range.split_once("..")?;
        let (low, high): (i32, i32) = (low.trim().parse().ok()?, high.trim().parse().ok()?);
        dims.push((
            low,
            u32::try_from(i64::from(high) - i64::from(low) + 1).ok()?,
        ));
    }
    // The element type as written (its case kept for the data type lookup).
    let element = name.trim()[name.trim().len() - of.len()..]
        .trim()
        .to_string();
    Some((dims, element))
}

/// One variable a client sees.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Leaf {
    /// As the public file lists it (`MAIN.arr[1][2]`).
    pub name: String,
    /// As the PLC takes it for a handle (`MAIN.arr[1,2]`).
    pub ads_name: String,
    pub group: u32,
    pub offset: u32,
    pub ty: IecType,
    /// Its place in R.
    pub at: u32,
}

impl Leaf {
    pub fn size(&self) -> u32 {
        self.ty.size() as u32
    }
}

/// Symbols that could not be served, said once each.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Skipped {
    pub first: Vec<String>,
    pub count: usize,
}

impl Skipped {
    fn add(&mut self, message: String) {
        self.count += 1;
        if self.first.len() < 20 {
            self.first.push(message);
        }
    }
}

/// The symbols expanded and placed.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Layout {
    pub leaves: Vec<Leaf>,
    pub skipped: Skipped,
    end: u32,
}

impl Layout {
    /// Expands `symbols` with `types`, in table order.
    pub fn expand(symbols: &[Symbol], types: &[DataType]) -> Layout {
        let by_name: HashMap<String, &DataType> = types
            .iter()
            .map(|t| (t.name.to_ascii_uppercase(), t))
            .collect();
        let mut layout = Layout::default();
        for symbol in symbols {
            let place = Place {
                name: symbol.name.clone(),
                ads_name: symbol.name.clone(),
                group: symbol.group,
                offset: symbol.offset,
            };
            layout.add(
                &by_name,
                place,
                &symbol.type_name,
                symbol.size,
                symbol.data_type,
                0,
            );
        }
        layout
    }

    /// A leaf of `ty`, placed after the last one.
    pub fn push(&mut self, name: String, ads_name: String, group: u32, offset: u32, ty: IecType) {
        if self.leaves.len() >= MAX_VARS {
            self.skipped
                .add(format!("{name}: more than {MAX_VARS} variables"));
            return;
        }
        if let Err(why) = check_name(&name) {
            self.skipped.add(format!("{name}: {why}"));
            return;
        }
        let size = ty.size() as u32;
        if u64::from(self.end) + u64::from(size)
            > u64::from(super::MAP.size(plccoms_protocol::Area::R))
        {
            self.skipped
                .add(format!("{name}: the symbols fill the 16 MiB served"));
            return;
        }
        self.leaves.push(Leaf {
            name,
            ads_name,
            group,
            offset,
            ty,
            at: self.end,
        });
        self.end += size;
    }

    fn add(
        &mut self,
        types: &HashMap<String, &DataType>,
        place: Place,
        type_name: &str,
        size: u32,
        data_type: u32,
        depth: usize,
    ) {
        if depth > MAX_DEPTH || self.leaves.len() >= MAX_VARS {
            self.skipped
                .add(format!("{}: nested too deep or too many", place.name));
            return;
        }
        if let Some(ty) = basic_type(type_name) {
            if ty.size() as u32 == size {
                return self.push(place.name, place.ads_name, place.group, place.offset, ty);
            }
            return self.skipped.add(format!(
                "{}: {type_name} of {size} bytes (expected {})",
                place.name,
                ty.size()
            ));
        }
        if let Some((dims, element)) = array_type(type_name) {
            return self.array(types, place, &dims, &element, size, depth);
        }
        match types.get(&type_name.trim().to_ascii_uppercase()) {
            Some(dt) if !dt.array.is_empty() => {
                let (dims, element) = (dt.array.clone(), dt.type_name.clone());
                self.array(types, place, &dims, &element, dt.size, depth)
            }
            Some(dt) if !dt.fields.is_empty() => {
                for field in &dt.fields {
                    let inner = Place {
                        name: format!("{}.{}", place.name, field.name),
                        ads_name: format!("{}.{}", place.ads_name, field.name),
                        group: place.group,
                        offset: place.offset.wrapping_add(field.offset),
                    };
                    let field_type = if field.type_name.is_empty() {
                        &field.name
                    } else {
                        &field.type_name
                    };
                    // An array field's type reads `ARRAY [..] OF X` (expanded
                    // from that) or names the element type alone.
                    if !field.array.is_empty() && array_type(field_type).is_none() {
                        self.array(
                            types,
                            inner,
                            &field.array,
                            field_type,
                            field.size,
                            depth + 1,
                        );
                    } else {
                        self.add(
                            types,
                            inner,
                            field_type,
                            field.size,
                            field.data_type,
                            depth + 1,
                        );
                    }
                }
            }
            // An alias or an enum: what it is built on.
            Some(dt) if !dt.type_name.is_empty() && dt.type_name != dt.name => {
                let (inner, size, id) = (dt.type_name.clone(), dt.size, dt.data_type);
                self.add(types, place, &inner, size, id, depth + 1)
            }
            _ => match type_of_id(data_type, size) {
                Some(ty) => self.push(place.name, place.ads_name, place.group, place.offset, ty),
                None => self.skipped.add(format!(
                    "{}: type {type_name} ({size} bytes) has no counterpart here",
                    place.name
                )),
            },
        }
    }

    fn array(
        &mut self,
        types: &HashMap<String, &DataType>,
        place: Place,
        dims: &[(i32, u32)],
        element: &str,
        size: u32,
        depth: usize,
    ) {
        let count = dims
            .iter()
            .try_fold(1u64, |n, &(_, e)| n.checked_mul(u64::from(e)))
            .unwrap_or(u64::MAX);
        if count == 0 || count > (MAX_VARS - self.leaves.len()) as u64 {
            return self.skipped.add(format!(
                "{}: array of {count} elements (at most {MAX_VARS} variables in all)",
                place.name
            ));
        }
        let element_size = size / count as u32;
        if u64::from(element_size) * count != u64::from(size) {
            return self.skipped.add(format!(
                "{}: {size} bytes do not divide into {count} elements",
                place.name
            ));
        }
        for i in 0..count {
            // Row-major: the last index runs fastest.
            let mut rest = i;
            let mut index = vec![0i64; dims.len()];
            for (slot, &(low, n)) in index.iter_mut().zip(dims).rev() {
                *slot = i64::from(low) + (rest % u64::from(n)) as i64;
                rest /= u64::from(n);
            }
            let listed: String = index.iter().map(|i| format!("[{i}]")).collect();
            let joined: Vec<String> = index.iter().map(i64::to_string).collect();
            let inner = Place {
                name: format!("{}{listed}", place.name),
                ads_name: format!("{}[{}]", place.ads_name, joined.join(",")),
                group: place.group,
                offset: place
                    .offset
                    .wrapping_add(element_size.wrapping_mul(i as u32)),
            };
            self.add(types, inner, element, element_size, 0, depth + 1);
        }
    }

    /// The leaves overlapping `[at, at + len)` of R, in order.
    pub fn covering(&self, at: u32, len: u32) -> &[Leaf] {
        let end = at.saturating_add(len);
        let first = self.leaves.partition_point(|l| l.at + l.size() <= at);
        let last = self.leaves.partition_point(|l| l.at < end);
        &self.leaves[first..last.max(first)]
    }

    /// The public file naming every leaf, with its CRC trailer.
    pub fn public_file(&self, device: &str) -> Vec<u8> {
        let mut text = String::new();
        let _ = writeln!(text, "; symbols of {device}, as plccoms serves them");
        for leaf in &self.leaves {
            match leaf.ty {
                IecType::Bool => {
                    let _ = writeln!(text, "{} R B {} .0 BOOL", leaf.name, leaf.at);
                }
                ty => {
                    let _ = writeln!(text, "{} R B {} {ty}", leaf.name, leaf.at);
                }
            }
        }
        let crc = crc_of(text.as_bytes());
        let _ = writeln!(text, ";* Crc=\"{crc:08X}\"");
        text.into_bytes()
    }
}

struct Place {
    name: String,
    ads_name: String,
    group: u32,
    offset: u32,
}

/// A name the public file can carry.
fn check_name(name: &str) -> Result<(), String> {
    if name.len() > MAX_NAME {
        return Err(format!("name longer than {MAX_NAME} bytes"));
    }
    if let Some(bad) = name
        .chars()
        .find(|&c| !c.is_ascii_graphic() || matches!(c, ',' | ':' | '*' | '"' | ';'))
    {
        return Err(format!("character {bad:?} in the name"));
    }
    if name.is_empty() {
        return Err("empty name".into());
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use bytes::BufMut;

    pub fn symbol_entry(
        name: &str,
        group: u32,
        offset: u32,
        size: u32,
        id: u32,
        ty: &str,
    ) -> Vec<u8> {
        let mut e = Vec::new();
        let len = 30 + name.len() + ty.len() + 3;
        e.put_u32_le(len as u32);
        for v in [group, offset, size, id, 8] {
            e.put_u32_le(v);
        }
        e.put_u16_le(name.len() as u16);
        e.put_u16_le(ty.len() as u16);
        e.put_u16_le(0);
        e.put_slice(name.as_bytes());
        e.put_u8(0);
        e.put_slice(ty.as_bytes());
        e.put_u8(0);
        e.put_u8(0);
        e
    }

    fn type_entry(
        name: &str,
        ty: &str,
        size: u32,
        offset: u32,
        array: &[(i32, u32)],
        fields: &[Vec<u8>],
    ) -> Vec<u8> {
        let mut body = Vec::new();
        for v in [1, 0, 0, size, offset, 65, 0] {
            body.put_u32_le(v);
        }
        body.put_u16_le(name.len() as u16);
        body.put_u16_le(ty.len() as u16);
        body.put_u16_le(0);
        body.put_u16_le(array.len() as u16);
        body.put_u16_le(fields.len() as u16);
        body.put_slice(name.as_bytes());
        body.put_u8(0);
        body.put_slice(ty.as_bytes());
        body.put_u8(0);
        body.put_u8(0);
        for &(low, n) in array {
            body.put_u32_le(low as u32);
            body.put_u32_le(n);
        }
        for f in fields {
            body.put_slice(f);
        }
        let mut e = Vec::new();
        e.put_u32_le(body.len() as u32 + 4);
        e.extend(body);
        e
    }

    #[test]
    fn structures_expand_to_fields_and_arrays_to_elements() {
        let mut table = symbol_entry("MAIN.st", 0x4040, 100, 7, 65, "ST_Pair");
        table.extend(symbol_entry(
            "MAIN.arr",
            0x4040,
            200,
            8,
            65,
            "ARRAY [1..2, 0..1] OF INT",
        ));
        table.extend(symbol_entry("MAIN.s", 0x4040, 300, 81, 30, "STRING(80)"));
        table.extend(symbol_entry("MAIN.fb", 0x4040, 400, 3, 65, "FB_Unknown"));
        let symbols = parse_symbols(&table).unwrap();
        assert_eq!(symbols.len(), 4);
        assert_eq!(symbols[1].type_name, "ARRAY [1..2, 0..1] OF INT");
        let pair = type_entry(
            "ST_Pair",
            "",
            7,
            0,
            &[],
            &[
                type_entry("on", "BOOL", 1, 0, &[], &[]),
                type_entry("n", "ARRAY [0..2] OF WORD", 6, 1, &[(0, 3)], &[]),
            ],
        );
        let types = parse_data_types(&pair).unwrap();
        let layout = Layout::expand(&symbols, &types);
        let names: Vec<_> = layout.leaves.iter().map(|l| l.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "MAIN.st.on",
                "MAIN.st.n[0]",
                "MAIN.st.n[1]",
                "MAIN.st.n[2]",
                "MAIN.arr[1][0]",
                "MAIN.arr[1][1]",
                "MAIN.arr[2][0]",
                "MAIN.arr[2][1]",
                "MAIN.s",
            ]
        );
        assert_eq!(layout.leaves[5].ads_name, "MAIN.arr[1,1]");
        assert_eq!(layout.leaves[5].offset, 202);
        assert_eq!(layout.leaves[3].offset, 105);
        assert_eq!(layout.skipped.count, 1);
        assert!(layout.skipped.first[0].contains("FB_Unknown"));
        // Placed one after another; the public file parses to the same.
        let file = crate::pubfile::parse(&layout.public_file("test"));
        assert_eq!(file.vars.len(), 9);
        assert!(file.warnings.is_empty(), "{:?}", file.warnings);
        assert_eq!(file.vars[8].var.offset, 1 + 6 + 8);
        assert_eq!(file.vars[8].var.ty, IecType::String(80));
        assert_eq!(
            file.crc,
            Some(crc_of(crate::pubfile::crc_content(
                &layout.public_file("test")
            )))
        );
        assert_eq!(layout.covering(1, 3).len(), 2);
        assert_eq!(layout.covering(15, 81)[0].name, "MAIN.s");
    }

    #[test]
    fn broken_uploads_name_the_entry() {
        let mut table = symbol_entry("A", 1, 2, 2, 2, "INT");
        table.extend([200, 0, 0, 0, 1, 2]);
        let err = parse_symbols(&table).unwrap_err();
        assert_eq!(err.entry, 1);
        assert!(err.to_string().contains("entry length 200"), "{err}");
        let mut short = symbol_entry("ABC", 1, 2, 2, 2, "INT");
        short[0] = 31;
        short.truncate(31);
        assert!(parse_symbols(&short)
            .unwrap_err()
            .to_string()
            .contains("name needs 3 bytes, 1 left"));
    }

    #[test]
    fn encoded_symbols_parse_back() {
        let symbol = Symbol {
            name: "MAIN.x".into(),
            group: 0x4020,
            offset: 4,
            size: 2,
            data_type: 2,
            type_name: "INT".into(),
            comment: "a comment".into(),
        };
        let mut table = encode_symbol(&symbol);
        table.extend(encode_symbol(&symbol));
        assert_eq!(parse_symbols(&table).unwrap(), [symbol.clone(), symbol]);
    }

    #[test]
    fn basic_types() {
        assert_eq!(basic_type("string(20)"), Some(IecType::String(20)));
        assert_eq!(basic_type("STRING"), Some(IecType::String(80)));
        assert_eq!(basic_type("DT"), Some(IecType::Udint));
        assert_eq!(basic_type("FB_X"), None);
    }
}
