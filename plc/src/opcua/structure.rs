//! A structured value's binary body (OPC 10000-6, 5.2.6) read by its
//! DataTypeDefinition: the backend serves a structure as its scalar fields
//! ("leaves": `TEMP`, `STEPS[2]`, `INNER.X`) when the server shows no child
//! variables for them. [`Structure::spans`] finds where each leaf's bytes lie
//! in a body; the backend decodes a leaf's bytes with the stack's own
//! codecs, and writes one leaf by replacing its bytes in the body it read.
//! Pure and bounds checked: bytes from a server never panic, and every
//! error names the field and the byte offset.

use std::fmt;
use std::ops::Range;
use std::sync::Arc;

/// Deepest nesting of structures served (a definition that refers to itself
/// is cut here, not followed forever).
pub const MAX_DEPTH: usize = 8;
/// Most leaves one structure is served as; a larger one is skipped.
pub const MAX_LEAVES: usize = 4096;
/// Most elements an array field in a body may claim: more is an error, not
/// an allocation.
const MAX_ELEMENTS: u64 = 1 << 20;

/// The built-in types (OPC 10000-6, 5.1.2) a field may have, by their id.
pub mod builtin {
    pub const BOOLEAN: u8 = 1;
    pub const SBYTE: u8 = 2;
    pub const BYTE: u8 = 3;
    pub const INT16: u8 = 4;
    pub const UINT16: u8 = 5;
    pub const INT32: u8 = 6;
    pub const UINT32: u8 = 7;
    pub const INT64: u8 = 8;
    pub const UINT64: u8 = 9;
    pub const FLOAT: u8 = 10;
    pub const DOUBLE: u8 = 11;
    pub const STRING: u8 = 12;
    pub const DATE_TIME: u8 = 13;
    pub const GUID: u8 = 14;
    pub const BYTE_STRING: u8 = 15;
    pub const XML_ELEMENT: u8 = 16;
    pub const NODE_ID: u8 = 17;
    pub const EXPANDED_NODE_ID: u8 = 18;
    pub const STATUS_CODE: u8 = 19;
    pub const QUALIFIED_NAME: u8 = 20;
    pub const LOCALIZED_TEXT: u8 = 21;
}

/// Whether a field of built-in type `id` can be walked over.
pub fn walkable(id: u8) -> bool {
    (builtin::BOOLEAN..=builtin::LOCALIZED_TEXT).contains(&id)
}

/// A field's type.
#[derive(Debug, Clone, PartialEq)]
pub enum Kind {
    /// A built-in type, by id ([`builtin`]); enumerations are Int32.
    Builtin(u8),
    Structure(Arc<Structure>),
}

/// A field's shape.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    Scalar,
    /// An array of these dimensions (row-major), each element a leaf.
    Fixed(Vec<u32>),
    /// An array whose length the definition leaves open (of `rank`
    /// dimensions): walked over, not served.
    Open(u32),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub name: String,
    pub kind: Kind,
    pub shape: Shape,
}

/// A structure's fields in encoding order (StructureType Structure only:
/// optional fields and unions are not served).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Structure {
    pub fields: Vec<Field>,
}

/// One scalar inside a structure: its path below the variable (`TEMP`,
/// `STEPS[2]`, `GRID[1][0]`, `INNER.X`) and its built-in type.
#[derive(Debug, Clone, PartialEq)]
pub struct Leaf {
    pub path: String,
    pub builtin: u8,
}

/// What was wrong in a body, and where.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodeError {
    /// The field's path (empty: the body itself).
    pub field: String,
    pub offset: usize,
    pub what: String,
}

impl fmt::Display for DecodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.field.is_empty() {
            write!(f, "at byte {}: {}", self.offset, self.what)
        } else {
            write!(
                f,
                "field {} at byte {}: {}",
                self.field, self.offset, self.what
            )
        }
    }
}

impl std::error::Error for DecodeError {}

/// The indexes of element `i` of an array of `dims`, as public files name
/// them: `[1][0]` (row-major: the last index runs fastest).
pub fn element_suffix(dims: &[u32], i: u64) -> String {
    let mut rest = i;
    let mut index = vec![0u64; dims.len()];
    for (slot, &n) in index.iter_mut().zip(dims).rev() {
        let n = u64::from(n.max(1));
        *slot = rest % n;
        rest /= n;
    }
    index.iter().map(|i| format!("[{i}]")).collect()
}

/// The number of elements of `dims`, `None` past `limit`.
pub fn elements(dims: &[u32], limit: u64) -> Option<u64> {
    dims.iter()
        .try_fold(1u64, |n, &d| n.checked_mul(u64::from(d)))
        .filter(|&n| n <= limit)
}

impl Structure {
    /// Its leaves in encoding order; an error past [`MAX_LEAVES`] or
    /// [`MAX_DEPTH`].
    pub fn leaves(&self) -> Result<Vec<Leaf>, String> {
        let mut out = Vec::new();
        self.leaves_into("", 0, &mut out)?;
        Ok(out)
    }

    fn leaves_into(&self, prefix: &str, depth: usize, out: &mut Vec<Leaf>) -> Result<(), String> {
        if depth >= MAX_DEPTH {
            return Err(format!("{prefix}: nested deeper than {MAX_DEPTH}"));
        }
        for field in &self.fields {
            let path = if prefix.is_empty() {
                field.name.clone()
            } else {
                format!("{prefix}.{}", field.name)
            };
            let one = |path: &str, out: &mut Vec<Leaf>| -> Result<(), String> {
                match &field.kind {
                    Kind::Builtin(id) => {
                        if out.len() >= MAX_LEAVES {
                            return Err(format!("more than {MAX_LEAVES} fields"));
                        }
                        out.push(Leaf {
                            path: path.to_string(),
                            builtin: *id,
                        });
                        Ok(())
                    }
                    Kind::Structure(inner) => inner.leaves_into(path, depth + 1, out),
                }
            };
            match &field.shape {
                Shape::Scalar => one(&path, out)?,
                Shape::Open(_) => {}
                Shape::Fixed(dims) => {
                    let n = elements(dims, MAX_LEAVES as u64)
                        .ok_or_else(|| format!("{path}: more than {MAX_LEAVES} elements"))?;
                    let before = out.len();
                    for i in 0..n {
                        one(&format!("{path}{}", element_suffix(dims, i)), out)?;
                        // Elements without leaves (empty structures): the
                        // rest have none either, however many.
                        if out.len() == before {
                            break;
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Where each leaf ([`Structure::leaves`], same order) lies in `body`.
    /// The whole body must be the structure: bytes left over are an error
    /// (the definition is not the one the value was encoded by).
    pub fn spans(&self, body: &[u8]) -> Result<Vec<Range<usize>>, DecodeError> {
        let mut walker = Walker {
            body,
            at: 0,
            spans: Vec::new(),
            steps: 0,
        };
        walker.structure(self, &Path::Root, 0)?;
        if walker.at != body.len() {
            return Err(DecodeError {
                field: String::new(),
                offset: walker.at,
                what: format!("{} bytes after the last field", body.len() - walker.at),
            });
        }
        Ok(walker.spans)
    }
}

/// `body` with the bytes of `span` replaced by `new` (a leaf written).
pub fn replace(body: &[u8], span: Range<usize>, new: &[u8]) -> Option<Vec<u8>> {
    let (head, tail) = (body.get(..span.start)?, body.get(span.end..)?);
    let mut out = Vec::with_capacity(head.len() + new.len() + tail.len());
    out.extend_from_slice(head);
    out.extend_from_slice(new);
    out.extend_from_slice(tail);
    Some(out)
}

/// Where the walker is: named only when an error needs it, as a body is
/// walked for every value (no string per field and value).
enum Path<'a> {
    Root,
    Field(&'a Path<'a>, &'a str),
    Element(&'a Path<'a>, &'a [u32], u64),
}

impl fmt::Display for Path<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Path::Root => Ok(()),
            Path::Field(Path::Root, name) => f.write_str(name),
            Path::Field(parent, name) => write!(f, "{parent}.{name}"),
            Path::Element(parent, dims, i) => write!(f, "{parent}{}", element_suffix(dims, *i)),
        }
    }
}

struct Walker<'a> {
    body: &'a [u8],
    at: usize,
    spans: Vec<Range<usize>>,
    /// Values walked: bounded, as elements of empty structures take no
    /// bytes (a definition's dimensions alone would not stop a walk).
    steps: usize,
}

impl Walker<'_> {
    fn error(&self, field: &Path<'_>, what: impl Into<String>) -> DecodeError {
        DecodeError {
            field: field.to_string(),
            offset: self.at,
            what: what.into(),
        }
    }

    fn take(&mut self, field: &Path<'_>, n: usize) -> Result<&[u8], DecodeError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&end| end <= self.body.len())
            .ok_or_else(|| {
                self.error(
                    field,
                    format!("needs {n} bytes, {} left", self.body.len() - self.at),
                )
            })?;
        let bytes = &self.body[self.at..end];
        self.at = end;
        Ok(bytes)
    }

    fn i32(&mut self, field: &Path<'_>) -> Result<i32, DecodeError> {
        let b = self.take(field, 4)?;
        Ok(i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u8(&mut self, field: &Path<'_>) -> Result<u8, DecodeError> {
        Ok(self.take(field, 1)?[0])
    }

    /// An Int32 length (-1: null) and that many bytes.
    fn bytes(&mut self, field: &Path<'_>) -> Result<(), DecodeError> {
        let at = self.at;
        let n = self.i32(field)?;
        if n < -1 {
            self.at = at;
            return Err(self.error(field, format!("length {n}")));
        }
        if n > 0 {
            self.take(field, n as usize)?;
        }
        Ok(())
    }

    fn structure(
        &mut self,
        s: &Structure,
        prefix: &Path<'_>,
        depth: usize,
    ) -> Result<(), DecodeError> {
        if depth >= MAX_DEPTH {
            return Err(self.error(prefix, format!("nested deeper than {MAX_DEPTH}")));
        }
        for field in &s.fields {
            let path = Path::Field(prefix, &field.name);
            match &field.shape {
                Shape::Scalar => self.one(field, &path, depth, true)?,
                Shape::Fixed(dims) if dims.len() == 1 => {
                    let at = self.at;
                    let n = self.i32(&path)?;
                    if i64::from(n) != i64::from(dims[0]) {
                        self.at = at;
                        return Err(self.error(
                            &path,
                            format!("{n} elements, the definition says {}", dims[0]),
                        ));
                    }
                    for i in 0..u64::from(dims[0]) {
                        let name = Path::Element(&path, dims, i);
                        self.one(field, &name, depth, true)?;
                    }
                }
                Shape::Fixed(dims) => {
                    let at = self.at;
                    let got = self.dimensions(&path)?;
                    if got != *dims {
                        self.at = at;
                        return Err(self.error(
                            &path,
                            format!("dimensions {got:?}, the definition says {dims:?}"),
                        ));
                    }
                    let n = elements(dims, MAX_ELEMENTS).unwrap_or(0);
                    for i in 0..n {
                        let name = Path::Element(&path, dims, i);
                        self.one(field, &name, depth, true)?;
                    }
                }
                Shape::Open(rank) => {
                    let n = if *rank <= 1 {
                        let at = self.at;
                        let n = self.i32(&path)?;
                        if n < -1 {
                            self.at = at;
                            return Err(self.error(&path, format!("{n} elements")));
                        }
                        u64::try_from(n).unwrap_or(0)
                    } else {
                        let dims = self.dimensions(&path)?;
                        elements(&dims, MAX_ELEMENTS).unwrap_or(0)
                    };
                    if n > MAX_ELEMENTS {
                        return Err(self.error(&path, format!("{n} elements")));
                    }
                    for _ in 0..n {
                        self.one(field, &path, depth, false)?;
                    }
                }
            }
        }
        Ok(())
    }

    /// A multi-dimensional array's dimensions: an Int32 array.
    fn dimensions(&mut self, path: &Path<'_>) -> Result<Vec<u32>, DecodeError> {
        let at = self.at;
        let n = self.i32(path)?;
        if !(0..=32).contains(&n) {
            self.at = at;
            return Err(self.error(path, format!("{n} dimensions")));
        }
        let mut dims = Vec::with_capacity(n as usize);
        for _ in 0..n {
            let at = self.at;
            let d = self.i32(path)?;
            let d = u32::try_from(d).map_err(|_| {
                self.at = at;
                self.error(path, format!("dimension {d}"))
            })?;
            dims.push(d);
        }
        if elements(&dims, MAX_ELEMENTS).is_none() {
            return Err(self.error(path, format!("dimensions {dims:?}: too many elements")));
        }
        Ok(dims)
    }

    /// One value of `field`'s type; its span kept when it is a leaf.
    fn one(
        &mut self,
        field: &Field,
        path: &Path<'_>,
        depth: usize,
        leaf: bool,
    ) -> Result<(), DecodeError> {
        self.steps += 1;
        if self.steps > self.body.len() + MAX_LEAVES {
            return Err(self.error(path, "more values than the body can hold"));
        }
        match &field.kind {
            Kind::Structure(inner) => {
                if leaf {
                    self.structure(inner, path, depth + 1)
                } else {
                    // Walked over only: its leaves are not served.
                    let kept = self.spans.len();
                    self.structure(inner, path, depth + 1)?;
                    self.spans.truncate(kept);
                    Ok(())
                }
            }
            Kind::Builtin(id) => {
                let start = self.at;
                self.scalar(*id, path)?;
                if leaf {
                    self.spans.push(start..self.at);
                }
                Ok(())
            }
        }
    }

    fn scalar(&mut self, id: u8, path: &Path<'_>) -> Result<(), DecodeError> {
        use builtin::*;
        let fixed = match id {
            BOOLEAN | SBYTE | BYTE => 1,
            INT16 | UINT16 => 2,
            INT32 | UINT32 | FLOAT | STATUS_CODE => 4,
            INT64 | UINT64 | DOUBLE | DATE_TIME => 8,
            GUID => 16,
            STRING | BYTE_STRING | XML_ELEMENT => return self.bytes(path),
            NODE_ID => return self.node_id(path).map(|_| ()),
            EXPANDED_NODE_ID => {
                let flags = self.node_id(path)?;
                if flags & 0x80 != 0 {
                    self.bytes(path)?;
                }
                if flags & 0x40 != 0 {
                    self.take(path, 4)?;
                }
                return Ok(());
            }
            QUALIFIED_NAME => {
                self.take(path, 2)?;
                return self.bytes(path);
            }
            LOCALIZED_TEXT => {
                let mask = self.u8(path)?;
                if mask & 0x01 != 0 {
                    self.bytes(path)?;
                }
                if mask & 0x02 != 0 {
                    self.bytes(path)?;
                }
                return Ok(());
            }
            other => return Err(self.error(path, format!("built-in type {other} not decoded"))),
        };
        self.take(path, fixed).map(|_| ())
    }

    /// A NodeId; returns its encoding byte (an ExpandedNodeId's flags).
    fn node_id(&mut self, path: &Path<'_>) -> Result<u8, DecodeError> {
        let at = self.at;
        let encoding = self.u8(path)?;
        match encoding & 0x3F {
            0 => self.take(path, 1).map(|_| ()),
            1 => self.take(path, 3).map(|_| ()),
            2 => self.take(path, 6).map(|_| ()),
            3 | 5 => {
                self.take(path, 2)?;
                self.bytes(path)
            }
            4 => self.take(path, 18).map(|_| ()),
            other => {
                self.at = at;
                Err(self.error(path, format!("NodeId encoding {other}")))
            }
        }?;
        Ok(encoding)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(name: &str, kind: Kind, shape: Shape) -> Field {
        Field {
            name: name.into(),
            kind,
            shape,
        }
    }

    fn sample() -> Structure {
        let inner = Arc::new(Structure {
            fields: vec![
                field("X", Kind::Builtin(builtin::INT16), Shape::Scalar),
                field("NAME", Kind::Builtin(builtin::STRING), Shape::Scalar),
            ],
        });
        Structure {
            fields: vec![
                field("TEMP", Kind::Builtin(builtin::DOUBLE), Shape::Scalar),
                field(
                    "STEPS",
                    Kind::Builtin(builtin::UINT16),
                    Shape::Fixed(vec![2]),
                ),
                field("LOG", Kind::Builtin(builtin::BYTE), Shape::Open(1)),
                field("INNER", Kind::Structure(inner.clone()), Shape::Scalar),
                field(
                    "GRID",
                    Kind::Builtin(builtin::BOOLEAN),
                    Shape::Fixed(vec![2, 2]),
                ),
            ],
        }
    }

    fn body() -> Vec<u8> {
        let mut b = Vec::new();
        b.extend(21.5f64.to_le_bytes());
        b.extend(2i32.to_le_bytes());
        b.extend(7u16.to_le_bytes());
        b.extend(8u16.to_le_bytes());
        b.extend(3i32.to_le_bytes());
        b.extend([1, 2, 3]);
        b.extend((-4i16).to_le_bytes());
        b.extend(2i32.to_le_bytes());
        b.extend(b"ab");
        b.extend(2i32.to_le_bytes());
        b.extend(2i32.to_le_bytes());
        b.extend(2i32.to_le_bytes());
        b.extend([1, 0, 0, 1]);
        b
    }

    #[test]
    fn leaves_are_named_as_public_files_name_them() {
        let paths: Vec<String> = sample()
            .leaves()
            .unwrap()
            .into_iter()
            .map(|l| l.path)
            .collect();
        assert_eq!(
            paths,
            [
                "TEMP",
                "STEPS[0]",
                "STEPS[1]",
                "INNER.X",
                "INNER.NAME",
                "GRID[0][0]",
                "GRID[0][1]",
                "GRID[1][0]",
                "GRID[1][1]"
            ]
        );
    }

    #[test]
    fn spans_lie_where_the_leaves_are() {
        let b = body();
        let spans = sample().spans(&b).unwrap();
        assert_eq!(spans.len(), 9);
        assert_eq!(&b[spans[0].clone()], 21.5f64.to_le_bytes());
        assert_eq!(&b[spans[2].clone()], 8u16.to_le_bytes());
        assert_eq!(&b[spans[3].clone()], (-4i16).to_le_bytes());
        assert_eq!(&b[spans[4].clone()], [2, 0, 0, 0, b'a', b'b']);
        assert_eq!(&b[spans[8].clone()], [1]);
        // A leaf replaced: a longer string moves what follows.
        let mut name = 3i32.to_le_bytes().to_vec();
        name.extend(b"xyz");
        let new = replace(&b, spans[4].clone(), &name).unwrap();
        let again = sample().spans(&new).unwrap();
        assert_eq!(&new[again[4].clone()], name.as_slice());
        assert_eq!(&new[again[8].clone()], [1]);
    }

    /// Arrays of empty structures nested deep: no leaves, found at once,
    /// and a body of them refused, not walked forever.
    #[test]
    fn empty_structures_in_large_arrays_end_quickly() {
        let mut s = Structure::default();
        for _ in 0..MAX_DEPTH - 1 {
            s = Structure {
                fields: vec![field(
                    "A",
                    Kind::Structure(Arc::new(s)),
                    Shape::Fixed(vec![2, 2048]),
                )],
            };
        }
        assert_eq!(s.leaves(), Ok(Vec::new()));
        let mut body = 2i32.to_le_bytes().to_vec();
        body.extend(2i32.to_le_bytes());
        body.extend(2048i32.to_le_bytes());
        body.resize(4096, 0);
        assert!(s.spans(&body).is_err());
    }

    #[test]
    fn errors_name_elements_and_nested_fields() {
        let b = body();
        assert_eq!(
            sample().spans(&b[..15]).unwrap_err().to_string(),
            "field STEPS[1] at byte 14: needs 2 bytes, 1 left"
        );
        assert_eq!(
            sample().spans(&b[..27]).unwrap_err().to_string(),
            "field INNER.NAME at byte 25: needs 4 bytes, 2 left"
        );
    }

    #[test]
    fn errors_name_the_field_and_the_offset() {
        let b = body();
        let e = sample().spans(&b[..20]).unwrap_err();
        assert_eq!(e.to_string(), "field LOG at byte 20: needs 1 bytes, 0 left");
        let mut wrong = b.clone();
        wrong[8] = 3;
        let e = sample().spans(&wrong).unwrap_err();
        assert_eq!(
            e.to_string(),
            "field STEPS at byte 8: 3 elements, the definition says 2"
        );
        let mut long = b.clone();
        long.push(0);
        assert_eq!(
            sample().spans(&long).unwrap_err().to_string(),
            format!("at byte {}: 1 bytes after the last field", b.len())
        );
        let mut huge = b.clone();
        huge[16..20].copy_from_slice(&i32::MAX.to_le_bytes());
        assert!(sample()
            .spans(&huge)
            .unwrap_err()
            .to_string()
            .starts_with("field LOG"));
    }
}
