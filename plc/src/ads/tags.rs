//! `ADS_TAGS`: a CSV file naming the variables of an ADS device that has
//! no symbol table to upload (a BC/BX controller, a TwinCAT 2 PLC without
//! symbol download), or a chosen few of one that has.
//!
//! ```text
//! name,address,type,unit,description
//! temp,MAIN.rTemp,REAL,°C,"kitchen, north"
//! count,0x4020:16,DINT
//! ```
//!
//! `address` is a symbol name (read by handle) or `group:offset` (index
//! group and offset, decimal or `0x` hex, read as such); `type` a TwinCAT
//! type (`STRING(80)`) or the server's (`STRING[80]`); unit and description
//! are optional. A header line (its first field `name`) and `#` comment lines
//! are skipped. A line that does not fit is skipped with a warning naming
//! its line and what was wrong; at most [`MAX_VARS`] tags are taken.

use std::collections::HashSet;

use plccoms_protocol::IecType;

use super::symbols::basic_type;
use crate::pubfile::{PubWarning, MAX_NAME, MAX_VARS, MAX_WARNINGS};

/// Where a tag is on the device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Address {
    /// A symbol, by handle.
    Symbol(String),
    /// An index group and offset.
    Group { group: u32, offset: u32 },
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Tag {
    pub name: String,
    pub address: Address,
    pub ty: IecType,
    pub unit: String,
    pub description: String,
    /// 1-based line in the file.
    pub line: usize,
}

#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TagFile {
    pub tags: Vec<Tag>,
    /// The first [`MAX_WARNINGS`] problems, in file order.
    pub warnings: Vec<PubWarning>,
    /// Problems beyond those, counted.
    pub more_warnings: usize,
}

impl TagFile {
    fn warn(&mut self, line: usize, message: String) {
        if self.warnings.len() < MAX_WARNINGS {
            self.warnings.push(PubWarning { line, message });
        } else {
            self.more_warnings += 1;
        }
    }
}

/// Parses a tag file. Never fails: bad lines become warnings.
pub fn parse(bytes: &[u8]) -> TagFile {
    let mut file = TagFile::default();
    let mut seen = HashSet::new();
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .from_reader(bytes);
    for record in reader.byte_records() {
        let record = match record {
            Ok(record) => record,
            Err(e) => {
                let line = e.position().map_or(0, |p| p.line() as usize);
                file.warn(line, format!("unreadable CSV: {e}"));
                // The reader cannot go on past a broken record reliably.
                break;
            }
        };
        let line = record.position().map_or(0, |p| p.line() as usize);
        let field =
            |i: usize| String::from_utf8_lossy(record.get(i).unwrap_or_default()).into_owned();
        if record.iter().all(|f| f.is_empty()) {
            continue;
        }
        if file.tags.is_empty() && field(0).eq_ignore_ascii_case("name") {
            continue;
        }
        if file.tags.len() == MAX_VARS {
            file.warn(
                line,
                format!("more than {MAX_VARS} tags: the rest is skipped"),
            );
            break;
        }
        match tag(&field, record.len(), line) {
            Ok(tag) => {
                if seen.insert(tag.name.to_ascii_uppercase()) {
                    file.tags.push(tag);
                } else {
                    file.warn(line, format!("duplicate name '{}'; skipped", tag.name));
                }
            }
            Err(message) => file.warn(line, message),
        }
    }
    file
}

const GRAMMAR: &str = "name,address,type[,unit[,description]]";

fn tag(field: &dyn Fn(usize) -> String, count: usize, line: usize) -> Result<Tag, String> {
    if count < 3 {
        return Err(format!("{count} fields; expected {GRAMMAR}"));
    }
    if count > 5 {
        return Err(format!("{count} fields; expected at most 5: {GRAMMAR}"));
    }
    let name = field(0);
    if name.is_empty() || name.len() > MAX_NAME {
        return Err(format!("name of {} bytes (1 to {MAX_NAME})", name.len()));
    }
    if let Some(bad) = name
        .chars()
        .find(|&c| !c.is_ascii_graphic() || matches!(c, ',' | ':' | '*' | '"' | ';'))
    {
        return Err(format!("character {bad:?} in name '{name}'"));
    }
    let text = field(1);
    let address = address(&text)?;
    let type_text = field(2);
    let ty = basic_type(&type_text)
        .or_else(|| IecType::parse(type_text.as_bytes()))
        .filter(|ty| !matches!(ty, IecType::Date | IecType::Dt))
        .ok_or_else(|| format!("unknown type '{type_text}' (BOOL, INT, REAL, STRING(80), ...)"))?;
    Ok(Tag {
        name,
        address,
        ty,
        unit: field(3),
        description: field(4),
        line,
    })
}

fn address(text: &str) -> Result<Address, String> {
    if let Some((group, offset)) = text.split_once(':') {
        let number = |t: &str| match t.trim().strip_prefix("0x").or(t.trim().strip_prefix("0X")) {
            Some(hex) => u32::from_str_radix(hex, 16).ok(),
            None => t.trim().parse().ok(),
        };
        return match (number(group), number(offset)) {
            (Some(group), Some(offset)) => Ok(Address::Group { group, offset }),
            _ => Err(format!(
                "address '{text}' is not group:offset (numbers, 0x for hex)"
            )),
        };
    }
    if text.is_empty() || text.contains(char::is_whitespace) || text.len() > MAX_NAME {
        return Err(format!(
            "address '{text}' is not a symbol name (MAIN.x) nor group:offset"
        ));
    }
    Ok(Address::Symbol(text.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The README's example tag file (the first block of its Beckhoff ADS
    /// section) loads without a warning.
    #[test]
    fn the_readme_example_loads() {
        let readme = include_str!("../../../README.md");
        let section = readme.split("## Beckhoff ADS").nth(1).unwrap();
        let block = section.split("```text\n").nth(1).unwrap();
        let file = parse(block.split("```").next().unwrap().as_bytes());
        assert!(file.warnings.is_empty(), "{:?}", file.warnings);
        assert_eq!(file.tags.len(), 3);
    }

    #[test]
    fn symbols_addresses_and_bad_lines() {
        let file = parse(
            "name,address,type,unit,description\n\
             # a comment\n\
             temp,MAIN.rTemp,REAL,°C,\"kitchen, north\"\n\
             count,0x4020:16,DINT\n\
             text,GVL.s,STRING(20)\n\
             old,16416:0,STRING[10]\n\
             bad,MAIN.x,FOO\n\
             worse,1:x,INT\n\
             short,MAIN.y\n\
             temp,MAIN.z,INT\n\
             day,MAIN.d,DT\n"
                .as_bytes(),
        );
        assert_eq!(file.tags.len(), 5);
        // TwinCAT's DT: 4-byte seconds, served as UDINT (as in a symbol table).
        assert_eq!(file.tags[4].ty, IecType::Udint);
        assert_eq!(file.tags[0].address, Address::Symbol("MAIN.rTemp".into()));
        assert_eq!(file.tags[0].unit, "°C");
        assert_eq!(file.tags[0].description, "kitchen, north");
        assert_eq!(
            file.tags[1].address,
            Address::Group {
                group: 0x4020,
                offset: 16
            }
        );
        assert_eq!(file.tags[2].ty, IecType::String(20));
        assert_eq!(file.tags[3].ty, IecType::String(10));
        let lines: Vec<String> = file.warnings.iter().map(|w| w.to_string()).collect();
        assert_eq!(
            lines,
            [
                "line 7: unknown type 'FOO' (BOOL, INT, REAL, STRING(80), ...)",
                "line 8: address '1:x' is not group:offset (numbers, 0x for hex)",
                "line 9: 2 fields; expected name,address,type[,unit[,description]]",
                "line 10: duplicate name 'temp'; skipped",
            ]
        );
    }
}
