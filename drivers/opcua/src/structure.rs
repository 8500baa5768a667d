//! Structured values served field by field: a DataTypeDefinition as a
//! [`Structure`] ([`plccoms_plc::opcua::structure`] walks the bodies), and
//! one field of an ExtensionObject read, or written into a copy of it.
//!
//! A body is taken as the stack holds it: a type it does not know (every
//! PLC's own) is its raw bytes; one it knows is encoded again, the same
//! bytes. Each field's bytes are then decoded with the stack's codec of
//! its built-in type.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, LazyLock};

use opcua::types::{
    BinaryDecodable, BinaryEncodable, ByteString, ByteStringBody, ContextOwned, DataTypeDefinition,
    DateTime, ExtensionObject, Identifier, LocalizedText, NodeId, StructureType, UAString, Variant,
};
use plccoms_plc::opcua::structure::{builtin, walkable, Field, Kind, Leaf, Shape, Structure};

use crate::convert::Builtin;

static CONTEXT: LazyLock<ContextOwned> = LazyLock::new(ContextOwned::default);

/// A structure type as served: its fields' layout and its leaves by path.
#[derive(Debug)]
pub struct Layout {
    pub data_type: NodeId,
    pub structure: Structure,
    pub leaves: Vec<Leaf>,
    paths: HashMap<String, usize>,
    /// A body that did not fit is logged once per list, not per read.
    warned: AtomicBool,
}

impl Layout {
    pub fn new(data_type: NodeId, structure: Structure) -> Result<Layout, String> {
        let leaves = structure.leaves()?;
        let paths = leaves
            .iter()
            .enumerate()
            .map(|(i, l)| (l.path.to_ascii_uppercase(), i))
            .collect();
        Ok(Layout {
            data_type,
            structure,
            leaves,
            paths,
            warned: AtomicBool::new(false),
        })
    }

    /// The leaf at `path` (ignoring case, as names are).
    pub fn leaf(&self, path: &str) -> Option<usize> {
        self.paths.get(&path.to_ascii_uppercase()).copied()
    }

    /// The served type of leaf `i`: `None` for those not served (Guid,
    /// ByteString, NodeId, ...).
    pub fn builtin(&self, i: usize) -> Option<Builtin> {
        let id = self.leaves.get(i)?.builtin;
        Builtin::of_data_type(&NodeId::new(0, u32::from(id)))
    }

    /// Leaf `i`'s value in `value` (an ExtensionObject of this type).
    pub fn read(&self, value: &Variant, i: usize) -> Result<Variant, String> {
        Fields::default().read((0, None), self, value, i)
    }

    /// `value` (an ExtensionObject of this type) with leaf `i` set to `new`.
    pub fn write(&self, value: &Variant, i: usize, new: &Variant) -> Result<Variant, String> {
        let (body, encoding) = body_of(value)?;
        let spans = self.spans(&body)?;
        let span = spans.get(i).ok_or("no such field")?.clone();
        let bytes = encode_scalar(new)?;
        let body = plccoms_plc::opcua::structure::replace(&body, span, &bytes)
            .ok_or("field outside the body")?;
        Ok(Variant::ExtensionObject(ExtensionObject::new(
            ByteStringBody::new(ByteString::from(body), encoding),
        )))
    }

    fn spans(&self, body: &[u8]) -> Result<Vec<std::ops::Range<usize>>, String> {
        self.structure.spans(body).map_err(|e| {
            let text = format!("a value of DataType {}: {e}", self.data_type);
            if !self.warned.swap(true, Ordering::Relaxed) {
                tracing::warn!("{text}; its fields are refused (BadDecodingError)");
            }
            text
        })
    }
}

/// Bodies decoded once for all the fields served from them: a structure
/// of n fields is walked once per value, not n times.
#[derive(Default)]
pub struct Fields {
    /// The last value's key (the caller's: one per value) and its body
    /// with its leaves' spans.
    last: Option<(FieldsKey, DecodedBody)>,
}

/// A value's key: its source and element.
pub type FieldsKey = (usize, Option<u32>);

type DecodedBody = Result<(Vec<u8>, Vec<std::ops::Range<usize>>), String>;

impl Fields {
    /// Leaf `i` of `value`, a structure of `layout`; `key` names `value`
    /// among those this cache sees.
    pub fn read(
        &mut self,
        key: FieldsKey,
        layout: &Layout,
        value: &Variant,
        i: usize,
    ) -> Result<Variant, String> {
        if self.last.as_ref().is_none_or(|(k, _)| *k != key) {
            let decoded = body_of(value).and_then(|(body, _)| {
                let spans = layout.spans(&body)?;
                Ok((body, spans))
            });
            self.last = Some((key, decoded));
        }
        let Some((_, decoded)) = &self.last else {
            return Err("no value".into());
        };
        let (body, spans) = decoded.as_ref().map_err(Clone::clone)?;
        let span = spans.get(i).ok_or("no such field")?.clone();
        decode_scalar(layout.leaves[i].builtin, &body[span])
    }
}

/// The binary body of an ExtensionObject and its encoding's node id.
fn body_of(value: &Variant) -> Result<(Vec<u8>, NodeId), String> {
    let Variant::ExtensionObject(object) = value else {
        return Err(format!("not a structure: {:?}", value.type_id()));
    };
    let Some(body) = &object.body else {
        return Err("a null structure".into());
    };
    let mut bytes = Vec::new();
    body.encode_binary(&mut bytes, &CONTEXT.context())
        .map_err(|e| format!("structure body: {e}"))?;
    Ok((bytes, body.binary_type_id().node_id))
}

/// A scalar of built-in type `id` from exactly `bytes`.
pub fn decode_scalar(id: u8, bytes: &[u8]) -> Result<Variant, String> {
    let ctx = CONTEXT.context();
    let mut stream = std::io::Cursor::new(bytes);
    let s = &mut stream;
    let value = match id {
        builtin::BOOLEAN => bool::decode(s, &ctx).map(Variant::Boolean),
        builtin::SBYTE => i8::decode(s, &ctx).map(Variant::SByte),
        builtin::BYTE => u8::decode(s, &ctx).map(Variant::Byte),
        builtin::INT16 => i16::decode(s, &ctx).map(Variant::Int16),
        builtin::UINT16 => u16::decode(s, &ctx).map(Variant::UInt16),
        builtin::INT32 => i32::decode(s, &ctx).map(Variant::Int32),
        builtin::UINT32 => u32::decode(s, &ctx).map(Variant::UInt32),
        builtin::INT64 => i64::decode(s, &ctx).map(Variant::Int64),
        builtin::UINT64 => u64::decode(s, &ctx).map(Variant::UInt64),
        builtin::FLOAT => f32::decode(s, &ctx).map(Variant::Float),
        builtin::DOUBLE => f64::decode(s, &ctx).map(Variant::Double),
        builtin::STRING => UAString::decode(s, &ctx).map(Variant::String),
        builtin::DATE_TIME => DateTime::decode(s, &ctx).map(|t| Variant::DateTime(Box::new(t))),
        builtin::LOCALIZED_TEXT => {
            LocalizedText::decode(s, &ctx).map(|t| Variant::LocalizedText(Box::new(t)))
        }
        other => return Err(format!("built-in type {other} is not served")),
    };
    value.map_err(|e| format!("built-in type {id}: {e}"))
}

/// The bytes of a scalar Variant.
pub fn encode_scalar(value: &Variant) -> Result<Vec<u8>, String> {
    let ctx = CONTEXT.context();
    let mut out = Vec::new();
    let o = &mut out;
    let done = match value {
        Variant::Boolean(v) => v.encode(o, &ctx),
        Variant::SByte(v) => v.encode(o, &ctx),
        Variant::Byte(v) => v.encode(o, &ctx),
        Variant::Int16(v) => v.encode(o, &ctx),
        Variant::UInt16(v) => v.encode(o, &ctx),
        Variant::Int32(v) => v.encode(o, &ctx),
        Variant::UInt32(v) => v.encode(o, &ctx),
        Variant::Int64(v) => v.encode(o, &ctx),
        Variant::UInt64(v) => v.encode(o, &ctx),
        Variant::Float(v) => v.encode(o, &ctx),
        Variant::Double(v) => v.encode(o, &ctx),
        Variant::String(v) => v.encode(o, &ctx),
        Variant::DateTime(v) => v.encode(o, &ctx),
        other => {
            return Err(format!(
                "{:?} is not written into a structure",
                other.type_id()
            ))
        }
    };
    done.map_err(|e| e.to_string())?;
    Ok(out)
}

/// A DataTypeDefinition read, before the types its fields name are known.
pub enum Definition {
    Structure(opcua::types::StructureDefinition),
    /// Enumerations are Int32 on the wire.
    Enumeration,
}

impl Definition {
    /// The definition in a DataTypeDefinition attribute's value.
    pub fn of(value: Variant) -> Result<Definition, String> {
        let Variant::ExtensionObject(object) = value else {
            return Err("no DataTypeDefinition".into());
        };
        match DataTypeDefinition::from_extension_object(object) {
            Ok(DataTypeDefinition::Structure(s)) => Ok(Definition::Structure(s)),
            Ok(DataTypeDefinition::Enum(_)) => Ok(Definition::Enumeration),
            Err(status) => Err(format!("DataTypeDefinition: {status}")),
        }
    }

    /// The data types its fields name that are not built in.
    pub fn needs(&self) -> Vec<NodeId> {
        match self {
            Definition::Structure(s) => s
                .fields
                .iter()
                .flatten()
                .filter(|f| builtin_of(&f.data_type).is_none())
                .map(|f| f.data_type.clone())
                .collect(),
            Definition::Enumeration => Vec::new(),
        }
    }
}

/// The built-in type id of a field's DataType: the built-in types and the
/// standard subtypes that keep their encoding.
fn builtin_of(data_type: &NodeId) -> Option<u8> {
    if data_type.namespace != 0 {
        return None;
    }
    let Identifier::Numeric(id) = data_type.identifier else {
        return None;
    };
    Some(match id {
        1..=21 => id as u8,
        29 => builtin::INT32,         // Enumeration
        288 | 289 => builtin::UINT32, // IntegerId, Counter
        290 => builtin::DOUBLE,       // Duration
        291 | 295 => builtin::STRING, // NumericRange, LocaleId
        294 => builtin::DATE_TIME,    // UtcTime
        _ => return None,
    })
    .filter(|&b| walkable(b))
}

/// The structure of `data_type` from the definitions read (`defs`);
/// nested structures resolved, a cycle or a missing definition an error.
pub fn resolve(
    data_type: &NodeId,
    defs: &HashMap<NodeId, Result<Definition, String>>,
    depth: usize,
) -> Result<Structure, String> {
    if depth >= plccoms_plc::opcua::structure::MAX_DEPTH {
        return Err(format!(
            "{data_type}: nested too deep (or refers to itself)"
        ));
    }
    let def = match defs.get(data_type) {
        Some(Ok(def)) => def,
        Some(Err(e)) => return Err(format!("{data_type}: {e}")),
        None => return Err(format!("{data_type}: no definition read")),
    };
    let Definition::Structure(def) = def else {
        return Err(format!("{data_type}: an enumeration, not a structure"));
    };
    if def.structure_type != StructureType::Structure {
        return Err(format!(
            "{data_type}: {:?} (optional fields and unions are not served)",
            def.structure_type
        ));
    }
    let mut fields = Vec::new();
    for f in def.fields.iter().flatten() {
        let name = f.name.value().clone().unwrap_or_default();
        let name = plccoms_plc::opcua::path_name(&[name]);
        let kind = match builtin_of(&f.data_type) {
            Some(id) => Kind::Builtin(id),
            None => match defs.get(&f.data_type) {
                Some(Ok(Definition::Enumeration)) => Kind::Builtin(builtin::INT32),
                _ => Kind::Structure(Arc::new(resolve(&f.data_type, defs, depth + 1)?)),
            },
        };
        let dims: Vec<u32> = f.array_dimensions.clone().unwrap_or_default();
        let shape = match f.value_rank {
            -1 => Shape::Scalar,
            rank if rank >= 1 && dims.len() == rank as usize && dims.iter().all(|&d| d > 0) => {
                Shape::Fixed(dims)
            }
            rank if rank >= 1 => Shape::Open(rank as u32),
            rank => {
                return Err(format!(
                    "{data_type}: field {name} of ValueRank {rank} (no fixed shape)"
                ))
            }
        };
        fields.push(Field { name, kind, shape });
    }
    Ok(Structure { fields })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_field_read_and_written_by_the_stacks_codecs() {
        let structure = Structure {
            fields: vec![
                Field {
                    name: "TEMP".into(),
                    kind: Kind::Builtin(builtin::DOUBLE),
                    shape: Shape::Scalar,
                },
                Field {
                    name: "NAME".into(),
                    kind: Kind::Builtin(builtin::STRING),
                    shape: Shape::Scalar,
                },
            ],
        };
        let layout = Layout::new(NodeId::new(2, 7u32), structure).unwrap();
        let mut body = 21.5f64.to_le_bytes().to_vec();
        body.extend(2i32.to_le_bytes());
        body.extend(b"ab");
        let value = Variant::ExtensionObject(ExtensionObject::new(ByteStringBody::new(
            ByteString::from(body),
            NodeId::new(2, 9u32),
        )));
        assert_eq!(layout.read(&value, 0), Ok(Variant::Double(21.5)));
        assert_eq!(layout.read(&value, 1), Ok(Variant::String("ab".into())));
        assert_eq!(layout.leaf("name"), Some(1));
        let written = layout
            .write(&value, 1, &Variant::String("longer".into()))
            .unwrap();
        assert_eq!(
            layout.read(&written, 1),
            Ok(Variant::String("longer".into()))
        );
        assert_eq!(layout.read(&written, 0), Ok(Variant::Double(21.5)));
        let Variant::ExtensionObject(object) = &written else {
            panic!("{written:?}");
        };
        assert_eq!(object.binary_type_id().node_id, NodeId::new(2, 9u32));
        assert!(layout
            .read(&Variant::Double(1.0), 0)
            .unwrap_err()
            .contains("not a structure"));
        // A body the definition does not fit: the field and offset named.
        let short = Variant::ExtensionObject(ExtensionObject::new(ByteStringBody::new(
            ByteString::from(vec![0u8; 10]),
            NodeId::new(2, 9u32),
        )));
        assert_eq!(
            layout.read(&short, 0).unwrap_err(),
            "a value of DataType ns=2;i=7: field NAME at byte 8: needs 4 bytes, 2 left"
        );
    }
}
