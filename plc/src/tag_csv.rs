//! The CSV every tag file is written in (Modbus `MODBUS_TAGS`, OPC UA
//! `OPCUA_TAGS`): a header line naming the columns in any order and case,
//! `#` comment lines, quoted fields, UTF-8 (or else cp1250), and each
//! problem reported with the line (and column) an editor shows. Each file
//! format says which columns it has and what a line means ([`read`]).

use std::collections::HashMap;
use std::hash::Hash;

use plccoms_protocol::cp1250;

use crate::modbus::tags::{text, LineCounter, TagWarning};

/// A file's columns: (header name, column), and those a file must have.
pub struct Columns<C: 'static> {
    pub all: &'static [(&'static str, C)],
    pub required: &'static [C],
    /// What the header should look like, for a file without one.
    pub expected: &'static str,
}

/// One line of values, its fields by column.
pub struct Row<'a, C> {
    /// 1-based line in the file.
    pub line: usize,
    /// The file is UTF-8 (else cp1250).
    pub utf8: bool,
    fields: &'a [String],
    columns: &'a HashMap<C, usize>,
    record: &'a csv::ByteRecord,
}

impl<C: Copy + Eq + Hash> Row<'_, C> {
    /// The text of column `c` ("" when absent) and its 1-based column (0
    /// when the header lacks it).
    pub fn field(&self, c: C) -> (&str, usize) {
        self.columns.get(&c).map_or(("", 0), |&i| {
            (self.fields.get(i).map_or("", String::as_str), i + 1)
        })
    }

    /// The bytes of column `c` as in the file.
    pub fn raw(&self, c: C) -> &[u8] {
        self.columns
            .get(&c)
            .and_then(|&i| self.record.get(i))
            .unwrap_or_default()
    }
}

/// A parsed tag file: its tags in file order and its problems.
#[derive(Debug, Clone, PartialEq)]
pub struct TagFile<T> {
    pub tags: Vec<T>,
    /// The first [`crate::pubfile::MAX_WARNINGS`] problems, in file order.
    pub warnings: Vec<TagWarning>,
    /// Problems beyond those, counted only (a file of garbage must not
    /// become megabytes of messages).
    pub more_warnings: usize,
    /// The line of the first tag past [`crate::pubfile::MAX_VARS`]: the file
    /// is too large, and its parse stopped there.
    pub too_many: Option<usize>,
    /// Folded names seen, and their lines.
    seen: HashMap<Vec<u8>, usize>,
}

impl<T> Default for TagFile<T> {
    fn default() -> Self {
        TagFile {
            tags: Vec::new(),
            warnings: Vec::new(),
            more_warnings: 0,
            too_many: None,
            seen: HashMap::new(),
        }
    }
}

impl<T> TagFile<T> {
    pub fn warn(&mut self, warning: TagWarning) {
        if self.warnings.len() < crate::pubfile::MAX_WARNINGS {
            self.warnings.push(warning);
        } else {
            self.more_warnings += 1;
        }
    }

    /// Adds `tag`, named `name` (cp1250) on `line`, unless a tag of that
    /// name (ignoring case) came before: then a warning at `column`, and
    /// `Some(false)`. `None` when the file already has
    /// [`crate::pubfile::MAX_VARS`] tags: the reading stops.
    pub fn add(&mut self, name: &[u8], line: usize, column: usize, tag: T) -> Option<bool> {
        let folded = cp1250::to_upper(name);
        if let Some(&first) = self.seen.get(&folded) {
            self.warn(TagWarning {
                line,
                column: Some(column),
                message: format!(
                    "duplicate name '{}' (first defined on line {first}); skipped",
                    cp1250::decode(name)
                ),
            });
            return Some(false);
        }
        if self.tags.len() == crate::pubfile::MAX_VARS {
            self.too_many = Some(line);
            return None;
        }
        self.seen.insert(folded, line);
        self.tags.push(tag);
        Some(true)
    }
}

/// Reads `bytes` as a tag file of `columns`: `row` gets every line of
/// values (returning `false` stops the reading), `warn` every problem of
/// the file itself (unreadable CSV, a bad header, a value under no column);
/// both get `state`. Returns without calling `row` when the header lacks a
/// required column.
pub fn read<C, S>(
    bytes: &[u8],
    columns: &Columns<C>,
    state: &mut S,
    warn: fn(&mut S, TagWarning),
    mut row: impl FnMut(&mut S, &Row<'_, C>) -> bool,
) where
    C: Copy + Eq + Hash + 'static,
{
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let utf8 = std::str::from_utf8(bytes).is_ok();
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .from_reader(bytes);
    let mut found: Option<HashMap<C, usize>> = None;
    let mut lines = LineCounter::default();
    let mut header_len = 0;
    for record in reader.byte_records() {
        let record = match record {
            Ok(record) => record,
            Err(e) => {
                let line = e
                    .position()
                    .map_or(0, |p| lines.line_of(bytes, p.byte() as usize));
                warn(
                    state,
                    TagWarning {
                        line,
                        column: None,
                        message: format!("unreadable CSV: {e}"),
                    },
                );
                break;
            }
        };
        let line = record
            .position()
            .map_or(0, |p| lines.line_of(bytes, p.byte() as usize));
        let fields: Vec<String> = record.iter().map(|f| text(f, utf8)).collect();
        let Some(by_column) = &found else {
            match header(columns, &fields, line, state, warn) {
                Some(header) => found = Some(header),
                None => return,
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
            warn(
                state,
                TagWarning {
                    line,
                    column: Some(extra + 1),
                    message: format!(
                        "'{}' is under no column (the header names {header_len}); line skipped",
                        fields[extra]
                    ),
                },
            );
            continue;
        }
        let values = Row {
            line,
            utf8,
            fields: &fields,
            columns: by_column,
            record: &record,
        };
        if !row(state, &values) {
            break;
        }
    }
    if found.is_none() {
        warn(
            state,
            TagWarning {
                line: 1,
                column: None,
                message: format!("no header line (expected {})", columns.expected),
            },
        );
    }
}

/// The header's columns by name; `None` (with a warning) when a required
/// one is missing.
fn header<C: Copy + Eq + Hash, S>(
    columns: &Columns<C>,
    fields: &[String],
    line: usize,
    state: &mut S,
    warn: fn(&mut S, TagWarning),
) -> Option<HashMap<C, usize>> {
    let mut found = HashMap::new();
    for (i, name) in fields.iter().enumerate() {
        let message = match columns
            .all
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
        {
            Some(&(_, column)) if !found.contains_key(&column) => {
                found.insert(column, i);
                continue;
            }
            Some(_) => format!("column '{name}' given twice; the first counts"),
            None => format!("unknown column '{name}' ignored"),
        };
        warn(
            state,
            TagWarning {
                line,
                column: Some(i + 1),
                message,
            },
        );
    }
    let missing: Vec<&str> = columns
        .required
        .iter()
        .filter(|c| !found.contains_key(c))
        .map(|c| {
            columns
                .all
                .iter()
                .find(|(_, k)| k == c)
                .map_or("", |(n, _)| *n)
        })
        .collect();
    if missing.is_empty() {
        return Some(found);
    }
    warn(
        state,
        TagWarning {
            line,
            column: None,
            message: format!(
                "the header lacks the column(s) {}; no tag loaded",
                missing.join(", ")
            ),
        },
    );
    None
}

/// Longest name accepted, as in a public file.
const MAX_NAME: usize = crate::pubfile::MAX_NAME;

/// The name in cp1250, checked as a public file's names are.
pub fn name_bytes(text: &str, utf8: bool, raw: &[u8]) -> Result<Box<[u8]>, String> {
    if text.is_empty() {
        return Err("empty name".to_string());
    }
    let bytes: Vec<u8> = if utf8 {
        cp1250::try_encode(text)
            .ok_or_else(|| format!("name '{text}' has characters cp1250 lacks"))?
    } else {
        raw.to_vec()
    };
    if bytes.len() > MAX_NAME {
        return Err(format!("name longer than {MAX_NAME} characters"));
    }
    if let Some(&bad) = bytes
        .iter()
        .find(|&&b| b <= 0x20 || b == 0x7f || matches!(b, b',' | b':' | b'*' | b'"' | b';'))
    {
        return Err(format!(
            "invalid character '{}' in name '{text}'",
            cp1250::decode(&[bad])
        ));
    }
    if bytes[0] == b'%' {
        return Err(format!(
            "name '{text}' starts with %, which marks direct addresses"
        ));
    }
    Ok(bytes.into_boxed_slice())
}
