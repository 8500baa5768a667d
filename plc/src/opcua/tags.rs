//! The OPC UA tag file (`OPCUA_TAGS`): which nodes of a server a section
//! serves, under which names. CSV with a header line naming the columns
//! (any order, any case):
//!
//! ```text
//! name,node,type,access,unit,description
//! Line1.Speed,"ns=3;s=""DB_Line1"".""Speed""",REAL,,rpm,Main drive
//! Line1.Running,ns=3;i=1001
//! Recipe,ns=3;s=Recipe,STRING[80],ro
//! ```
//!
//! - `name` and `node` are required (node id syntax in [`super::nodeid`]).
//! - `type`: an IEC type as in a public file; empty: the node's DataType,
//!   read from the server when the section connects.
//! - `access`: `ro` or `rw`; empty: as the node's AccessLevel says.
//! - `index`: an element of an array node (0-based); the backend names a
//!   browsed array's elements `NAME[0]`, `NAME[1]`, ... as public files
//!   name array elements.
//! - `field`: a field of a structure node, by its path in the structure
//!   (`TEMP`, `STEPS[2]`, `INNER.X`): the backend reads the structure and
//!   serves that field (see [`super::structure`]).
//! - `unit`, `description`: for people (MQTT, the web page), as a Modbus
//!   tag file's.
//!
//! The backend also writes this form for the variables it found by
//! browsing ([`write`]), every type and access filled in: the one list the
//! section's variable table is built from ([`vars`] places them). Lines
//! that do not fit are skipped with a warning naming line and column; the
//! rest loads. Pure: bytes in, tags out.

use plccoms_protocol::{cp1250, Area, IecType};

use super::nodeid::{self, NodeRef};
use crate::modbus::tags::TagWarning;
use crate::tag_csv::{self, name_bytes};
use crate::value_codec::Codec;
use crate::var::{Var, VarDef, VarInfo};

/// One tag.
#[derive(Debug, Clone, PartialEq)]
pub struct Tag {
    /// cp1250 bytes, case as written.
    pub name: Box<[u8]>,
    pub node: NodeRef,
    /// `None`: the node's DataType decides.
    pub ty: Option<IecType>,
    /// `None`: the node's AccessLevel decides.
    pub writable: Option<bool>,
    /// The element of an array node, when the variable is one.
    pub index: Option<u32>,
    /// The field of a structure node (after `index`'s element), by path.
    pub field: Option<String>,
    pub info: VarInfo,
    /// 1-based line in the file.
    pub line: usize,
}

/// A parsed tag file.
pub type TagFile = tag_csv::TagFile<Tag>;

impl TagFile {
    /// The section's variables: every typed tag, placed by [`vars`].
    pub fn var_defs(&self) -> Vec<VarDef> {
        let placed = vars(&self.tags);
        self.tags
            .iter()
            .filter(|t| t.ty.is_some())
            .zip(placed)
            .map(|(tag, var)| VarDef {
                var,
                line: tag.line,
            })
            .collect()
    }
}

/// Where the variables live: R, from 0, one after another in file order,
/// each its type's size (a BOOL a byte, bit 0). The backend answers reads
/// of these bytes with its nodes' values in the PLC's own layout.
pub fn vars(tags: &[Tag]) -> Vec<Var> {
    let mut offset = 0u32;
    tags.iter()
        .filter_map(|tag| {
            let ty = tag.ty?;
            let var = Var {
                name: tag.name.clone(),
                area: Area::R,
                offset,
                bit: (ty == IecType::Bool).then_some(0),
                ty,
                codec: Codec::Native,
                writable: tag.writable.unwrap_or(true),
                info: tag.info.clone().boxed(),
            };
            offset += ty.size() as u32;
            Some(var)
        })
        .collect()
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Column {
    Name,
    Node,
    Type,
    Access,
    Unit,
    Description,
    Index,
    Field,
}

const COLUMNS: tag_csv::Columns<Column> = tag_csv::Columns {
    all: &[
        ("name", Column::Name),
        ("node", Column::Node),
        ("type", Column::Type),
        ("access", Column::Access),
        ("unit", Column::Unit),
        ("description", Column::Description),
        ("index", Column::Index),
        ("field", Column::Field),
    ],
    required: &[Column::Name, Column::Node],
    expected: "name,node,type,access,...",
};

/// Parses a tag file. Never fails: bad lines become warnings.
pub fn parse(bytes: &[u8]) -> TagFile {
    let mut file = TagFile::default();
    tag_csv::read(bytes, &COLUMNS, &mut file, TagFile::warn, |file, row| {
        let line = row.line;
        match tag(&|c| row.field(c), line, row.utf8, row.raw(Column::Name)) {
            Ok(tag) => {
                let name = tag.name.clone();
                if file
                    .add(&name, line, row.field(Column::Name).1, tag)
                    .is_none()
                {
                    return false;
                }
            }
            Err((column, message)) => file.warn(TagWarning {
                line,
                column: (column > 0).then_some(column),
                message,
            }),
        }
        true
    });
    file
}

type Field<'a> = dyn Fn(Column) -> (&'a str, usize) + 'a;

fn tag(
    field: &Field<'_>,
    line: usize,
    utf8: bool,
    raw_name: &[u8],
) -> Result<Tag, (usize, String)> {
    let (name, name_col) = field(Column::Name);
    let name = name_bytes(name, utf8, raw_name).map_err(|e| (name_col, e))?;
    let (node, node_col) = field(Column::Node);
    let node = nodeid::parse(node).map_err(|e| (node_col, e))?;
    let (ty, ty_col) = field(Column::Type);
    let ty = match ty {
        "" => None,
        ty => Some(
            IecType::parse(ty.as_bytes())
                .ok_or_else(|| (ty_col, format!("unknown type '{ty}'")))?,
        ),
    };
    let (access, access_col) = field(Column::Access);
    let writable = match access.to_ascii_lowercase().as_str() {
        "" => None,
        "ro" => Some(false),
        "rw" => Some(true),
        _ => return Err((access_col, format!("access '{access}' is not ro or rw"))),
    };
    let (index, index_col) = field(Column::Index);
    let index = match index {
        "" => None,
        index => Some(
            index
                .parse::<u32>()
                .map_err(|_| (index_col, format!("index '{index}' is not 0-4294967295")))?,
        ),
    };
    let field_path = match field(Column::Field).0.trim() {
        "" => None,
        path => Some(path.to_string()),
    };
    let info = VarInfo {
        unit: field(Column::Unit).0.to_string(),
        description: field(Column::Description).0.to_string(),
        ..VarInfo::default()
    };
    Ok(Tag {
        name,
        node,
        ty,
        writable,
        index,
        field: field_path,
        info,
        line,
    })
}

/// The file of `tags` in this form (UTF-8), as [`parse`] reads it back.
pub fn write(tags: &[Tag]) -> Vec<u8> {
    let mut out = csv::WriterBuilder::new()
        .terminator(csv::Terminator::Any(b'\n'))
        .from_writer(Vec::new());
    // Writing to a Vec cannot fail.
    let _ = out.write_record([
        "name",
        "node",
        "type",
        "access",
        "unit",
        "description",
        "index",
        "field",
    ]);
    for tag in tags {
        let ty = tag.ty.map(|t| t.to_string()).unwrap_or_default();
        let access = match tag.writable {
            Some(true) => "rw",
            Some(false) => "ro",
            None => "",
        };
        let index = tag.index.map(|i| i.to_string()).unwrap_or_default();
        let _ = out.write_record([
            cp1250::decode(&tag.name).as_ref(),
            tag.node.to_string().as_str(),
            ty.as_str(),
            access,
            tag.info.unit.as_str(),
            tag.info.description.as_str(),
            index.as_str(),
            tag.field.as_deref().unwrap_or(""),
        ]);
    }
    out.into_inner().unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_loads_in_order_with_its_warnings() {
        let file = parse(
            b"Name,Node,Type,Access,Unit\n\
              Speed,\"ns=3;s=\"\"DB\"\".\"\"Speed\"\"\",REAL,,rpm\n\
              # a comment\n\
              Run,ns=3;i=1001\n\
              bad name,i=1\n\
              Other,ns=x;i=1\n\
              speed,i=2\n\
              Text,ns=2;s=T,STRING[80],ro\n\
              Odd,i=3,FLOAT\n",
        );
        let names: Vec<_> = file.tags.iter().map(|t| t.name.to_vec()).collect();
        assert_eq!(
            names,
            [b"Speed".to_vec(), b"Run".to_vec(), b"Text".to_vec()]
        );
        assert_eq!(file.tags[0].node.to_string(), "ns=3;s=\"DB\".\"Speed\"");
        assert_eq!(file.tags[0].info.unit, "rpm");
        assert_eq!(file.tags[1].ty, None);
        assert_eq!(file.tags[2].writable, Some(false));
        let said: Vec<String> = file.warnings.iter().map(|w| w.to_string()).collect();
        assert_eq!(said.len(), 4, "{said:?}");
        assert!(
            said[0].starts_with("line 5, column 1: invalid character"),
            "{said:?}"
        );
        assert!(said[1].starts_with("line 6, column 2: node id"), "{said:?}");
        assert!(said[2].contains("duplicate name"), "{said:?}");
        assert!(
            said[3].contains("line 9, column 3: unknown type 'FLOAT'"),
            "{said:?}"
        );
    }

    #[test]
    fn typed_tags_are_placed_one_after_another_and_written_back() {
        let file =
            parse(b"name,node,type,index,field\nA,i=1,BOOL\nB,i=2\nC,i=3,LREAL\nD,i=4,STRING[10]\nE[1],i=5,INT,1\nR.S[1].X,i=6,INT,,S[1].X\n");
        let defs = file.var_defs();
        let placed: Vec<_> = defs
            .iter()
            .map(|d| (d.var.offset, d.var.bit, d.line))
            .collect();
        assert_eq!(
            placed,
            [
                (0, Some(0), 2),
                (1, None, 4),
                (9, None, 5),
                (20, None, 6),
                (22, None, 7)
            ]
        );
        let again = parse(&write(&file.tags));
        assert!(again.warnings.is_empty(), "{:?}", again.warnings);
        assert_eq!(
            again.tags.iter().map(|t| &t.node).collect::<Vec<_>>(),
            file.tags.iter().map(|t| &t.node).collect::<Vec<_>>()
        );
        assert_eq!(vars(&again.tags), vars(&file.tags));
        assert_eq!(again.tags[4].index, Some(1));
        assert_eq!(again.tags[5].field.as_deref(), Some("S[1].X"));
        assert_eq!(again.tags[4].field, None);
        assert!(parse(b"name,node,index\nA,i=1,-1\n").warnings[0]
            .to_string()
            .contains("column 3: index '-1'"));
    }

    /// The README's example tag file loads without a warning.
    #[test]
    fn the_readme_example_loads() {
        let readme = include_str!("../../../README.md");
        let section = readme
            .split("## OPC UA client (PROTOCOL = OPCUA)")
            .nth(1)
            .unwrap();
        let block = section
            .split("```text\n")
            .nth(1)
            .and_then(|rest| rest.split("```").next())
            .unwrap();
        let file = parse(block.as_bytes());
        assert!(file.warnings.is_empty(), "{:?}", file.warnings);
        assert_eq!(file.tags.len(), 3);
    }

    #[test]
    fn a_header_without_node_loads_nothing() {
        let file = parse(b"name,type\nA,BOOL\n");
        assert!(file.tags.is_empty());
        assert!(file.warnings[0].message.contains("lacks the column"));
        assert!(parse(b"").warnings[0].message.contains("no header"));
    }
}
