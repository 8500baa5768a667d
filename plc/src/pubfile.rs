//! Public files: the list of PLC variables with their addresses and types.
//!
//! One variable a line:
//!
//! ```text
//!  NAME AREA KIND OFFSET [.BIT] TYPE [PUB_IN|PUB_OUT|PUB_INOUT]
//!  __PLC_RUN S B 2 .2 BOOL PUB_INOUT
//!  TEXT R B 100 STRING[80]
//! ```
//!
//! Fields are separated by spaces or tabs; lines end in LF or CRLF. Blank
//! lines, `;` comment lines and trailing `;` comments are ignored. The bit may
//! also be glued to the offset (`2.2`); it is allowed for BOOL only, and a BOOL
//! without one is bit 0. KIND (`B` byte-addressed, `F` float) and the `PUB_`
//! flag are checked but not kept: the address is the area and byte offset.
//! A line that does not fit is skipped with a [`PubWarning`]; the rest loads.
//!
//! Names are kept exactly as written (cp1250 bytes, mixed case); whoever
//! builds the name table upper-cases them. Duplicates within one file are
//! found case-insensitively (ASCII and cp1250 letters): the first definition
//! stays, later ones are skipped with a warning.
//!
//! # CRC
//!
//! A file may end with a trailer line `;* Crc="xxxx"` (hex). Nothing public
//! says which CRC it is. This project's choice: CRC-32/ISO-HDLC (the zlib/PNG
//! CRC-32) over every byte of the file that precedes the trailer line, as
//! computed by [`crc_of`] on [`crc_content`]. The simulated PLC reports the
//! same value in `__PF_CRC`.

use std::collections::HashMap;
use std::fmt;
use std::hash::{Hash, Hasher};
use std::path::Path;

use plccoms_protocol::{Area, IecType};

use crate::value_codec::Codec;
use crate::var::{Var, VarDef};

/// A parsed public file.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PubFile {
    /// Variables in file order.
    pub vars: Vec<VarDef>,
    /// The value of the `;* Crc="xxxx"` trailer, if the file has one.
    pub crc: Option<u32>,
    /// Skipped lines and other problems, in file order: the first
    /// [`MAX_WARNINGS`] of them.
    pub warnings: Vec<PubWarning>,
    /// Problems beyond [`MAX_WARNINGS`], counted only (a file of garbage
    /// must not become megabytes of messages).
    pub more_warnings: usize,
    /// The line of the first variable past [`MAX_VARS`]: the file is too
    /// large, and its parse stopped there.
    pub too_many: Option<usize>,
}

/// Warnings a parsed file keeps; the rest are counted.
pub const MAX_WARNINGS: usize = 100;

/// Most variables a file (and a section's table) takes: real public files
/// have tens of thousands. A table costs about 1.3 KiB a variable at names of
/// [`MAX_NAME`] bytes (RSS growth, `tests/memory_bounds.rs`), so 130 MB at
/// most. A file with more is refused whole: the parse stops at the first
/// variable past the bound ([`PubFile::too_many`]).
pub const MAX_VARS: usize = 100_000;

/// Longest name accepted, in bytes (as a Modbus tag file's); a line with a
/// longer one is skipped with a warning.
pub const MAX_NAME: usize = 255;

impl PubFile {
    fn warn(&mut self, line: usize, message: String) {
        if self.warnings.len() < MAX_WARNINGS {
            self.warnings.push(PubWarning { line, message });
        } else {
            self.more_warnings += 1;
        }
    }
}

/// A problem on one line of a public file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PubWarning {
    /// 1-based line.
    pub line: usize,
    pub message: String,
}

impl fmt::Display for PubWarning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "line {}: {}", self.line, self.message)
    }
}

const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// CRC-32/ISO-HDLC of `bytes`. For a public file's CRC, pass
/// [`crc_content`] of the file.
pub fn crc_of(bytes: &[u8]) -> u32 {
    CRC32.checksum(bytes)
}

/// The part of a public file that its CRC covers: every byte before the last
/// `;* Crc="..."` trailer line, or the whole file when there is none.
pub fn crc_content(bytes: &[u8]) -> &[u8] {
    let mut content = bytes;
    for (start, line) in lines(bytes) {
        if parse_crc_line(trim_start(line)).is_some() {
            content = &bytes[..start];
        }
    }
    content
}

/// Reads and parses a public file.
pub fn load(path: &Path) -> Result<PubFile, std::io::Error> {
    Ok(parse(&std::fs::read(path)?))
}

/// The CRC trailer's value as [`parse`] reads it (the last good CRC line
/// counts), without parsing the variables: what a link keeps to check
/// `__PF_CRC` instead of the file.
pub fn crc_trailer(bytes: &[u8]) -> Option<u32> {
    lines(bytes)
        .filter_map(|(_, raw)| {
            let line = trim_start(raw);
            if line.first() != Some(&b';') {
                return None;
            }
            parse_crc_line(line)?.ok()
        })
        .last()
}

/// Parses a public file. Never fails: bad lines become warnings.
pub fn parse(bytes: &[u8]) -> PubFile {
    let mut file = PubFile::default();
    let mut seen: HashMap<FoldedName<'_>, usize> = HashMap::new();
    let mut seen_crc_line: Option<usize> = None;
    for (index, (_, raw)) in lines(bytes).enumerate() {
        let line_no = index + 1;
        let line = trim_start(raw);
        if line.first() == Some(&b';') {
            if let Some(crc) = parse_crc_line(line) {
                match crc {
                    Ok(value) => {
                        if let Some(previous) = seen_crc_line {
                            file.warn(
                                line_no,
                                format!(
                                    "second CRC line (the first is on line {previous}); this one counts"
                                ),
                            );
                        }
                        seen_crc_line = Some(line_no);
                        file.crc = Some(value);
                    }
                    Err(message) => file.warn(line_no, message),
                }
            }
            continue;
        }
        let line = match line.iter().position(|&b| b == b';') {
            Some(comment) => &line[..comment],
            None => line,
        };
        let mut fields = [&[][..]; MAX_FIELDS];
        let mut count = 0;
        let mut too_many = false;
        for field in line
            .split(|&b| b == b' ' || b == b'\t')
            .filter(|f| !f.is_empty())
        {
            if count == MAX_FIELDS {
                too_many = true;
                break;
            }
            fields[count] = field;
            count += 1;
        }
        if count == 0 {
            continue;
        }
        let result = if too_many {
            Err(format!("too many fields; expected {GRAMMAR}"))
        } else {
            parse_var(&fields[..count], line_no)
        };
        match result {
            Ok(var) => {
                let name = &fields[0];
                if let Some(&first_line) = seen.get(&FoldedName(name)) {
                    file.warn(
                        line_no,
                        format!(
                            "duplicate name '{}' (first defined on line {first_line}); skipped",
                            show(name)
                        ),
                    );
                } else if file.vars.len() == MAX_VARS {
                    file.too_many = Some(line_no);
                    break;
                } else {
                    seen.insert(FoldedName(name), line_no);
                    file.vars.push(var);
                }
            }
            Err(message) => file.warn(line_no, message),
        }
    }
    file
}

const GRAMMAR: &str = "NAME AREA KIND OFFSET [.BIT] TYPE [PUB_IN|PUB_OUT|PUB_INOUT]";
/// NAME AREA KIND OFFSET .BIT TYPE FLAG
const MAX_FIELDS: usize = 7;

fn parse_var(fields: &[&[u8]], line: usize) -> Result<VarDef, String> {
    if fields.len() < 5 {
        return Err(format!(
            "too few fields ({}); expected {GRAMMAR}",
            fields.len()
        ));
    }
    let name = fields[0];
    if name.len() > MAX_NAME {
        return Err(format!(
            "name of {} bytes '{}' is longer than the {MAX_NAME} accepted",
            name.len(),
            show(name)
        ));
    }
    if let Some(&bad) = name
        .iter()
        .find(|&&b| b < 0x20 || b == 0x7f || matches!(b, b',' | b':' | b'*' | b'"'))
    {
        return Err(format!(
            "invalid character '{}' in name '{}'",
            show(&[bad]),
            show(name)
        ));
    }
    let area = match fields[1] {
        [letter] => Area::from_letter(*letter),
        _ => None,
    }
    .ok_or_else(|| format!("unknown area '{}' (expected X, Y, S or R)", show(fields[1])))?;
    if !matches!(fields[2], [b'B' | b'b' | b'F' | b'f']) {
        return Err(format!(
            "unknown address kind '{}' (expected B or F)",
            show(fields[2])
        ));
    }

    let (offset_text, mut bit_text) = match fields[3].iter().position(|&b| b == b'.') {
        Some(dot) => (&fields[3][..dot], Some(&fields[3][dot + 1..])),
        None => (fields[3], None),
    };
    let offset = parse_u32(offset_text).ok_or_else(|| {
        format!(
            "bad offset '{}' (expected a decimal byte offset)",
            show(fields[3])
        )
    })?;
    let mut next = 4;
    if let Some(separate) = fields[next].strip_prefix(b".") {
        if bit_text.is_some() {
            return Err(format!(
                "bit given twice ('{}' and '{}')",
                show(fields[3]),
                show(fields[next])
            ));
        }
        bit_text = Some(separate);
        next += 1;
    }
    let bit = match bit_text {
        None => None,
        Some([digit @ b'0'..=b'7']) => Some(digit - b'0'),
        Some(text) => {
            return Err(format!("bad bit '.{}' (expected .0 to .7)", show(text)));
        }
    };

    let type_text = fields
        .get(next)
        .ok_or_else(|| format!("missing type; expected {GRAMMAR}"))?;
    let ty =
        IecType::parse(type_text).ok_or_else(|| format!("unknown type '{}'", show(type_text)))?;
    next += 1;
    if let Some(flag) = fields.get(next) {
        if !(flag.eq_ignore_ascii_case(b"PUB_IN")
            || flag.eq_ignore_ascii_case(b"PUB_OUT")
            || flag.eq_ignore_ascii_case(b"PUB_INOUT"))
        {
            return Err(format!(
                "unexpected '{}' after the type (expected PUB_IN, PUB_OUT or PUB_INOUT)",
                show(flag)
            ));
        }
        next += 1;
    }
    if next < fields.len() {
        return Err(format!("too many fields; expected {GRAMMAR}"));
    }

    let bit = match (ty, bit) {
        (IecType::Bool, bit) => Some(bit.unwrap_or(0)),
        (_, None) => None,
        (_, Some(b)) => {
            return Err(format!(
                "bit .{b} given for a {ty} variable (only BOOL has a bit)"
            ));
        }
    };
    if u64::from(offset) + ty.size() as u64 > u64::from(u32::MAX) + 1 {
        return Err(format!("offset {offset} is too large for a {ty}"));
    }
    // `bit`: Some for a BOOL (bit 0 when the file gives none), else None.
    Ok(VarDef {
        var: Var {
            name: name.into(),
            area,
            offset,
            bit,
            ty,
            codec: Codec::Native,
            writable: true,
            info: None,
        },
        line,
    })
}

/// `;* Crc="xxxx"` with optional spaces around each token and the keyword in
/// any case. `None` if the line is not a CRC line at all, `Some(Err)` if it is
/// one but the value is unreadable.
fn parse_crc_line(line: &[u8]) -> Option<Result<u32, String>> {
    let rest = trim_start(line.strip_prefix(b";")?);
    let rest = trim_start(rest.strip_prefix(b"*")?);
    if rest.len() < 3 || !rest[..3].eq_ignore_ascii_case(b"crc") {
        return None;
    }
    let rest = trim_start(&rest[3..]);
    let rest = trim_start(rest.strip_prefix(b"=")?);
    let bad = || {
        Some(Err(format!(
            "bad CRC line '{}' (expected ;* Crc=\"<hex>\")",
            show(trim_end(line))
        )))
    };
    let Some(rest) = rest.strip_prefix(b"\"") else {
        return bad();
    };
    let Some(close) = rest.iter().position(|&b| b == b'"') else {
        return bad();
    };
    if !trim_end(&rest[close + 1..]).is_empty() {
        return bad();
    }
    let digits = trim_end(trim_start(&rest[..close]));
    if digits.is_empty() || digits.len() > 8 {
        return bad();
    }
    let mut value = 0u32;
    for &d in digits {
        let Some(v) = (d as char).to_digit(16) else {
            return bad();
        };
        value = value << 4 | v;
    }
    Some(Ok(value))
}

/// Lines with their start offsets, without the line end (`\n` or `\r\n`).
fn lines(bytes: &[u8]) -> impl Iterator<Item = (usize, &[u8])> {
    let mut start = 0;
    std::iter::from_fn(move || {
        if start >= bytes.len() {
            return None;
        }
        let line_start = start;
        let rest = &bytes[start..];
        let (line, advance) = match rest.iter().position(|&b| b == b'\n') {
            Some(nl) => (&rest[..nl], nl + 1),
            None => (rest, rest.len()),
        };
        start += advance;
        Some((line_start, line.strip_suffix(b"\r").unwrap_or(line)))
    })
}

fn parse_u32(text: &[u8]) -> Option<u32> {
    if text.is_empty() || !text.iter().all(u8::is_ascii_digit) {
        return None;
    }
    text.iter().try_fold(0u32, |n, &d| {
        n.checked_mul(10)?.checked_add(u32::from(d - b'0'))
    })
}

fn trim_start(bytes: &[u8]) -> &[u8] {
    let skip = bytes
        .iter()
        .take_while(|&&b| b == b' ' || b == b'\t')
        .count();
    &bytes[skip..]
}

fn trim_end(bytes: &[u8]) -> &[u8] {
    let keep = bytes.len()
        - bytes
            .iter()
            .rev()
            .take_while(|&&b| b == b' ' || b == b'\t' || b == b'\r')
            .count();
    &bytes[..keep]
}

/// Bytes for a message: printable ASCII as is, everything else as `\xNN`
/// (names are cp1250, messages are UTF-8).
/// `bytes` for a message: printable ASCII, the rest escaped, cut after
/// [`SHOWN`] bytes (a warning quotes a field, and a field may be megabytes).
fn show(bytes: &[u8]) -> String {
    let (bytes, cut) = match bytes.get(..SHOWN) {
        Some(head) if bytes.len() > SHOWN => (head, true),
        _ => (bytes, false),
    };
    let mut out = String::with_capacity(bytes.len() + 3);
    for &b in bytes {
        if (0x20..0x7f).contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("\\x{b:02X}"));
        }
    }
    if cut {
        out.push_str("...");
    }
    out
}

/// Bytes of a field a message quotes.
const SHOWN: usize = 64;

use plccoms_protocol::cp1250::upper as cp1250_upper;

/// A name compared and hashed case-insensitively (cp1250).
struct FoldedName<'a>(&'a [u8]);

impl PartialEq for FoldedName<'_> {
    fn eq(&self, other: &Self) -> bool {
        self.0.len() == other.0.len()
            && self
                .0
                .iter()
                .zip(other.0)
                .all(|(&a, &b)| cp1250_upper(a) == cp1250_upper(b))
    }
}

impl Eq for FoldedName<'_> {}

impl Hash for FoldedName<'_> {
    fn hash<H: Hasher>(&self, state: &mut H) {
        // In chunks: one hasher call per byte dominated loading big files.
        state.write_usize(self.0.len());
        let mut folded = [0u8; 64];
        for chunk in self.0.chunks(folded.len()) {
            for (dst, &src) in folded.iter_mut().zip(chunk) {
                *dst = cp1250_upper(src);
            }
            state.write(&folded[..chunk.len()]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(line: &str) -> Var {
        let file = parse(line.as_bytes());
        assert_eq!(file.warnings, vec![], "{line}");
        assert_eq!(file.vars.len(), 1, "{line}");
        file.vars.into_iter().next().unwrap().var
    }

    fn warning(line: &str) -> String {
        let file = parse(line.as_bytes());
        assert!(file.vars.is_empty(), "{line} loaded");
        assert_eq!(file.warnings.len(), 1, "{line}");
        file.warnings[0].to_string()
    }

    #[test]
    fn vendor_fixed_file() {
        let file = parse(include_bytes!("../../tests/data/vendor/FIXED_Foxtrot.pub"));
        assert!(file.warnings.is_empty(), "{:?}", file.warnings);
        assert_eq!(file.crc, None);
        assert_eq!(
            file.vars,
            vec![
                VarDef {
                    var: Var {
                        name: (*b"__PLC_RUN").into(),
                        area: Area::S,
                        offset: 2,
                        bit: Some(2),
                        ty: IecType::Bool,
                        codec: Codec::Native,
                        writable: true,
                        info: None,
                    },
                    line: 1,
                },
                VarDef {
                    var: Var {
                        name: (*b"__PF_CRC").into(),
                        area: Area::S,
                        offset: 70,
                        bit: None,
                        ty: IecType::Dword,
                        codec: Codec::Native,
                        writable: true,
                        info: None,
                    },
                    line: 2,
                },
            ]
        );
    }

    #[test]
    fn the_documented_examples() {
        let v = one(" TEPLOTA_TERIK X F 5 REAL PUB_INOUT");
        assert_eq!(
            (v.area, v.offset, v.bit, v.ty),
            (Area::X, 5, None, IecType::Real)
        );
        let v = one(" UserBits R B 17112 UDINT PUB_INOUT");
        assert_eq!(&*v.name, b"UserBits");
        assert_eq!((v.area, v.offset, v.ty), (Area::R, 17112, IecType::Udint));
        let v = one(" TEXT R B 100 STRING[80]");
        assert_eq!(v.ty, IecType::String(80));
        let v = one(" T_ZONES_SET[0].TOPIT_TC R B 8 INT PUB_IN");
        assert_eq!(&*v.name, b"T_ZONES_SET[0].TOPIT_TC");
        let v = one(" Meteo.WindDirection r b 12 uint pub_out");
        assert_eq!(
            (&*v.name, v.area, v.ty),
            (&b"Meteo.WindDirection"[..], Area::R, IecType::Uint)
        );
    }

    #[test]
    fn cp1250_names_are_kept_as_bytes() {
        let file = parse(b" Teplota_kuchyn\xec R B 4 REAL\r\n");
        assert!(file.warnings.is_empty());
        assert_eq!(&*file.vars[0].var.name, b"Teplota_kuchyn\xec");
    }

    #[test]
    fn bits() {
        assert_eq!(one(" A S B 2 .2 BOOL").bit, Some(2));
        assert_eq!(one(" A S B 2.7 BOOL").bit, Some(7));
        assert_eq!(one(" A S B 2 BOOL").bit, Some(0));
        assert_eq!(one(" A S B 2 .0 BOOL").bit, Some(0));
        assert_eq!(
            warning(" A S B 2 .8 BOOL"),
            "line 1: bad bit '.8' (expected .0 to .7)"
        );
        assert_eq!(
            warning(" A S B 2. BOOL"),
            "line 1: bad bit '.' (expected .0 to .7)"
        );
        assert_eq!(
            warning(" A S B 2 .x BOOL"),
            "line 1: bad bit '.x' (expected .0 to .7)"
        );
        assert_eq!(
            warning(" A S B 2.1 .2 BOOL"),
            "line 1: bit given twice ('2.1' and '.2')"
        );
        assert_eq!(
            warning(" A S B 2 .2 BYTE"),
            "line 1: bit .2 given for a BYTE variable (only BOOL has a bit)"
        );
    }

    #[test]
    fn bad_lines_are_skipped_with_a_warning() {
        assert_eq!(warning(" X R B 1 FLOAT"), "line 1: unknown type 'FLOAT'");
        assert_eq!(
            warning(" X Q B 1 INT"),
            "line 1: unknown area 'Q' (expected X, Y, S or R)"
        );
        assert_eq!(
            warning(" X RR B 1 INT"),
            "line 1: unknown area 'RR' (expected X, Y, S or R)"
        );
        assert_eq!(
            warning(" X R W 1 INT"),
            "line 1: unknown address kind 'W' (expected B or F)"
        );
        assert_eq!(
            warning(" X R B -1 INT"),
            "line 1: bad offset '-1' (expected a decimal byte offset)"
        );
        assert_eq!(
            warning(" X R B 4294967296 INT"),
            "line 1: bad offset '4294967296' (expected a decimal byte offset)"
        );
        assert_eq!(
            warning(" X R B 4294967295 INT"),
            "line 1: offset 4294967295 is too large for a INT"
        );
        assert_eq!(
            warning(" X R B 1"),
            "line 1: too few fields (4); expected NAME AREA KIND OFFSET [.BIT] TYPE [PUB_IN|PUB_OUT|PUB_INOUT]"
        );
        assert_eq!(
            warning(" X R B 1 .1"),
            "line 1: missing type; expected NAME AREA KIND OFFSET [.BIT] TYPE [PUB_IN|PUB_OUT|PUB_INOUT]"
        );
        assert_eq!(
            warning(" X R B 1 INT PUB_INOUT extra"),
            "line 1: too many fields; expected NAME AREA KIND OFFSET [.BIT] TYPE [PUB_IN|PUB_OUT|PUB_INOUT]"
        );
        assert_eq!(
            warning(" X R B 1 .1 BOOL PUB_INOUT a b c"),
            "line 1: too many fields; expected NAME AREA KIND OFFSET [.BIT] TYPE [PUB_IN|PUB_OUT|PUB_INOUT]"
        );
        assert_eq!(
            warning(" X R B 1 INT PUB_ALL"),
            "line 1: unexpected 'PUB_ALL' after the type (expected PUB_IN, PUB_OUT or PUB_INOUT)"
        );
        assert_eq!(
            warning(" TEXT R B 1 STRING [80]"),
            "line 1: unexpected '[80]' after the type (expected PUB_IN, PUB_OUT or PUB_INOUT)"
        );
        assert_eq!(
            warning(" A,B R B 1 INT"),
            "line 1: invalid character ',' in name 'A,B'"
        );
    }

    #[test]
    fn blank_lines_comments_and_line_ends() {
        let text = b"\r\n\n; a comment\r\n   ; indented comment\n A R B 0 INT ; trailing\r\n\t B\tR\tB\t2\tINT;glued\n\n C R B 4 INT";
        let file = parse(text);
        assert!(file.warnings.is_empty(), "{:?}", file.warnings);
        let names: Vec<_> = file.vars.iter().map(|v| (&*v.var.name, v.line)).collect();
        assert_eq!(names, vec![(&b"A"[..], 5), (&b"B"[..], 6), (&b"C"[..], 8)]);
        assert_eq!(file.crc, None);
    }

    #[test]
    fn the_rest_loads_around_a_bad_line() {
        let file = parse(b" A R B 0 INT\n B R B 2 FLOAT\n C R B 4 INT\n");
        assert_eq!(file.vars.len(), 2);
        assert_eq!(
            file.warnings,
            vec![PubWarning {
                line: 2,
                message: "unknown type 'FLOAT'".into()
            }]
        );
    }

    #[test]
    fn duplicates_are_case_insensitive_and_the_first_wins() {
        let file = parse(b" Teplota_kuchyn\xec R B 0 INT\n TEPLOTA_KUCHYN\xcc R B 2 INT\n");
        assert_eq!(file.vars.len(), 1);
        assert_eq!(file.vars[0].var.offset, 0);
        assert_eq!(
            file.warnings[0].to_string(),
            "line 2: duplicate name 'TEPLOTA_KUCHYN\\xCC' (first defined on line 1); skipped"
        );
    }

    #[test]
    fn crc_trailer() {
        let body = b" A R B 0 INT\r\n B R B 2 REAL PUB_INOUT\r\n";
        let crc = crc_of(body);
        for trailer in [
            format!(";* Crc=\"{crc:08x}\"\r\n"),
            format!(";* Crc=\"{crc:08X}\""),
            format!(" ; * CRC = \" {crc:x} \" \n"),
        ] {
            let mut text = body.to_vec();
            text.extend_from_slice(trailer.as_bytes());
            let file = parse(&text);
            assert!(file.warnings.is_empty(), "{trailer}: {:?}", file.warnings);
            assert_eq!(file.crc, Some(crc), "{trailer}");
            assert_eq!(super::crc_trailer(&text), Some(crc), "{trailer}");
            assert_eq!(crc_content(&text), body, "{trailer}");
            assert_eq!(file.vars.len(), 2);
        }
        assert_eq!(crc_content(body), body);
        let file = parse(b" A R B 0 INT\n;* Crc=\"12G4\"\n");
        assert_eq!(file.crc, None);
        assert_eq!(super::crc_trailer(b" A R B 0 INT\n;* Crc=\"12G4\"\n"), None);
        // The last good line counts, a bad one after it changes nothing.
        let two = b";* Crc=\"1\"\n;* Crc=\"2\"\n;* Crc=\"x\"\n";
        assert_eq!(
            (parse(two).crc, super::crc_trailer(two)),
            (Some(2), Some(2))
        );
        assert_eq!(
            file.warnings[0].to_string(),
            "line 2: bad CRC line ';* Crc=\"12G4\"' (expected ;* Crc=\"<hex>\")"
        );
        // Other ;* comments are plain comments.
        let file = parse(b";* Created by Mosaic\n A R B 0 INT\n");
        assert!(file.warnings.is_empty());
        assert_eq!(file.crc, None);
    }

    proptest::proptest! {
        /// The trailer alone reads what the whole parse reads, for lines of
        /// CRC trailers good and bad, variables and junk in any order.
        #[test]
        fn crc_trailer_agrees_with_parse(
            lines in proptest::collection::vec(
                proptest::prop_oneof![
                    "[ ;*]{0,3}[cC][rR][cC] ?= ?\"[0-9a-fA-FxG ]{0,10}\"?",
                    " [A-Z]{1,4} R B [0-9]{1,3} (INT|BOOL|REAL)",
                    "[ -~\t;]{0,20}",
                ],
                0..12,
            ),
            eol in "(\r\n|\n|\r)",
        ) {
            let text = lines.join(&eol);
            proptest::prop_assert_eq!(super::crc_trailer(text.as_bytes()), parse(text.as_bytes()).crc);
        }
    }

    #[test]
    fn crc_is_crc32_iso_hdlc() {
        assert_eq!(crc_of(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn never_panics_on_junk() {
        let junk: Vec<u8> = (0..4096u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
            .collect();
        let _ = parse(&junk);
        let _ = parse(b";");
        let _ = parse(b";*crc=\"");
        let _ = parse(b"\r");
        let _ = parse(b" . . . . . . . . . .");
        let _ = parse(b" A R B .");
        let _ = parse(b" A R B . BOOL");
    }

    #[test]
    fn fifty_thousand_lines() {
        let mut text = Vec::new();
        text.extend_from_slice(
            b"\r\n __PLC_RUN S B 2 .2 BOOL PUB_INOUT\r\n __PF_CRC S B 70 DWORD PUB_INOUT\r\n",
        );
        for i in 0..50_000u32 {
            let line = match i % 4 {
                0 => format!(" VAR_{i}.BIT R B {} .{} BOOL PUB_INOUT\r\n", i / 8, i % 8),
                1 => format!(" T_ZONES[{i}].TEMP R F {} REAL PUB_INOUT\r\n", 4 * i),
                2 => format!(" COUNTER_{i} R B {} UDINT\r\n", 4 * i),
                _ => format!(" TEXT_{i} R B {} STRING[40] PUB_OUT ; comment\r\n", 41 * i),
            };
            text.extend_from_slice(line.as_bytes());
        }
        let crc = crc_of(&text);
        text.extend_from_slice(format!(";* Crc=\"{crc:08X}\"\r\n").as_bytes());
        let file = parse(&text);
        assert!(file.warnings.is_empty(), "{:?}", &file.warnings[..1]);
        assert_eq!(file.vars.len(), 50_002);
        assert_eq!(file.crc, Some(crc));
        assert_eq!(crc_of(crc_content(&text)), crc);
        assert_eq!(file.vars[50_001].line, 50_003);
    }

    #[test]
    fn a_file_past_the_variable_bound_stops_at_its_line_and_long_names_are_skipped() {
        let mut text = b" ; a comment line\r\n".to_vec();
        for i in 0..=MAX_VARS {
            text.extend_from_slice(format!(" V{i} R B {} BYTE\r\n", i % 1000).as_bytes());
        }
        let file = parse(&text);
        assert_eq!(file.vars.len(), MAX_VARS);
        assert_eq!(file.too_many, Some(MAX_VARS + 2));
        text.truncate(text.len() - b" V100000 R B 0 BYTE\r\n".len());
        assert_eq!(parse(&text).too_many, None);

        let long = "N".repeat(MAX_NAME + 1);
        let file =
            parse(format!(" {long} R B 0 BYTE\r\n {} R B 0 BYTE\r\n", &long[1..]).as_bytes());
        assert_eq!(file.vars.len(), 1);
        assert_eq!(file.vars[0].var.name.len(), MAX_NAME);
        let warning = file.warnings[0].to_string();
        assert!(
            warning.starts_with("line 1: name of 256 bytes 'NNN"),
            "{warning}"
        );
        // The message quotes the start of the name only.
        assert!(warning.len() < 150, "{warning}");
    }

    #[test]
    fn warnings_are_kept_up_to_a_bound_and_counted_beyond() {
        let text = " bad line\r\n".repeat(MAX_WARNINGS + 900);
        let file = parse(text.as_bytes());
        assert_eq!(file.warnings.len(), MAX_WARNINGS);
        assert_eq!(file.more_warnings, 900);
        assert!(file.vars.is_empty());
    }
}
