//! Which nodes a section serves: browsed from `OPCUA_BROWSE` (named by
//! browse path, see [`plccoms_plc::opcua::path_name`]) or listed in
//! `OPCUA_TAGS`, then typed and given their access from the server's
//! DataType, ValueRank and UserAccessLevel attributes. The outcome is a tag
//! file with every type filled in ([`plccoms_plc::opcua::tags::write`]),
//! the one list both the backend and the section's variable table use.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;

use opcua::client::Session;
use opcua::types::{
    BrowseDescription, BrowseDirection, BrowseResultMask, ByteString, Guid, NodeClass,
    NodeClassMask, NodeId, ReadValueId, ReferenceDescription, Variant,
};
use tracing::warn;

use plccoms_core::driver::PlcError;
use plccoms_plc::opcua::nodeid::{Identifier, Namespace, NodeRef};
use plccoms_plc::opcua::structure::{element_suffix, elements};
use plccoms_plc::opcua::tags::Tag;
use plccoms_plc::opcua::{path_name, unique_names};
use plccoms_plc::VarInfo;
use plccoms_protocol::cp1250;

use crate::convert::Builtin;
use crate::structure::{Definition, Layout};
use crate::Limits;

/// Deepest browse path followed: PLC models are a few levels deep; a
/// deeper one is a loop through references the visited set cannot see.
const MAX_DEPTH: usize = 32;

/// References one Browse answer carries per node, and nodes one Browse
/// asks for: a folder of 10,000 variables comes in pages (BrowseNext), each
/// answer well inside the message size limits, not as one refused answer
/// (BadEncodingLimitsExceeded, as asyncua's server answered).
const REFERENCES_PER_NODE: u32 = 1000;
const BROWSE_BATCH: usize = 10;
/// Most variables browsed (for a structure's fields) in one Browse: most
/// have no children, so their answers are small; 10 a request made a
/// rebrowse of 100,000 variables 10,000 round trips.
const VARIABLE_BATCH: usize = 1000;

/// Most nodes a browse visits (objects and variables): a server that
/// shows endless folders is browsed this far, not until memory runs out.
const MAX_NODES: usize = 4 * plccoms_plc::pubfile::MAX_VARS;

/// The Server object (i=2253): its diagnostics are not the PLC's variables.
const SERVER_OBJECT: u32 = 2253;
/// HasProperty (i=46): a variable's properties (EURange, EngineeringUnits)
/// are not variables of their own.
const HAS_PROPERTY: u32 = 46;
/// HierarchicalReferences (i=33), followed with their subtypes.
const HIERARCHICAL: u32 = 33;
/// UserAccessLevel's CurrentWrite bit.
const CURRENT_WRITE: u8 = 0x02;
/// Most elements of an array served as variables (`NAME[0]` ...); a longer
/// array is skipped.
pub const MAX_ELEMENTS: u32 = 1024;

/// What a list's nodes are written and read as, by node id text: a
/// node's built-in type, or the layout of its structure type.
#[derive(Clone, Default)]
pub struct Types {
    /// Those not of their IEC type's ([`Builtin::of_iec`]) only: a map of
    /// 100,000 node ids was 7 MB of a list that needs none of them.
    pub builtins: HashMap<String, Builtin>,
    pub layouts: HashMap<String, Arc<Layout>>,
}

/// The list built: tags with their type and access, and how each node is
/// written.
pub struct Built {
    pub tags: Vec<Tag>,
    pub types: Types,
    /// What was left out, for the log when the list is new.
    pub skipped: Vec<String>,
}

/// A node id of the server's for `node`; `nsu=` through its NamespaceArray.
pub async fn node_id(session: &Session, node: &NodeRef) -> Result<NodeId, String> {
    let namespace = match &node.namespace {
        Namespace::Index(i) => *i,
        Namespace::Uri(uri) => session
            .get_namespace_index(uri)
            .await
            .map_err(|e| format!("namespace {uri} not on the server: {e}"))?,
    };
    Ok(match &node.identifier {
        Identifier::Numeric(n) => NodeId::new(namespace, *n),
        Identifier::String(s) => NodeId::new(namespace, s.clone()),
        Identifier::Guid(g) => NodeId::new(
            namespace,
            g.parse::<Guid>().map_err(|_| format!("bad GUID {g}"))?,
        ),
        Identifier::Opaque(b) => NodeId::new(
            namespace,
            ByteString::from_base64(b).ok_or_else(|| format!("bad base64 {b}"))?,
        ),
    })
}

/// The text form of a server's node id, as the tag file writes it.
pub fn node_ref(id: &NodeId) -> NodeRef {
    let identifier = match &id.identifier {
        opcua::types::Identifier::Numeric(n) => Identifier::Numeric(*n),
        opcua::types::Identifier::String(s) => {
            Identifier::String(s.value().clone().unwrap_or_default())
        }
        opcua::types::Identifier::Guid(g) => Identifier::Guid(g.to_string().to_ascii_uppercase()),
        opcua::types::Identifier::ByteString(b) => Identifier::Opaque(b.as_base64()),
    };
    NodeRef {
        namespace: Namespace::Index(id.namespace),
        identifier,
    }
}

/// The standard fixed file's variables: served by the backend itself.
const FIXED_NAMES: [&str; 2] = ["__PLC_RUN", "__PF_CRC"];

/// A variable found, before its attributes are read.
#[derive(Clone, PartialEq)]
pub struct Found {
    name: String,
    node: NodeId,
    /// From a tag file: what it says (boxed: a browse finds 100,000
    /// variables without one).
    tag: Option<Box<Tag>>,
}

/// What [`find`] found, in 128 bits, fed a variable at a time: the
/// rebrowse keeps this, not the list, to tell whether the server's
/// variables changed. Fed the names as browsed (before collisions are
/// resolved, which depends on nothing else), so that a rebrowse needs no
/// list of what it found.
pub(crate) struct Print([std::hash::DefaultHasher; 2], usize);

impl Print {
    fn new() -> Print {
        use std::hash::Hash;
        let mut halves = [
            std::hash::DefaultHasher::new(),
            std::hash::DefaultHasher::new(),
        ];
        for (seed, h) in halves.iter_mut().enumerate() {
            (seed as u8).hash(h);
        }
        Print(halves, 0)
    }

    fn add(&mut self, name: &str, node: &NodeId, tag: Option<&Tag>) {
        use std::hash::Hash;
        let tag = tag.map(|t| format!("{t:?}"));
        for h in &mut self.0 {
            name.hash(h);
            node.hash(h);
            tag.hash(h);
        }
        self.1 += 1;
    }

    fn finish(self) -> u128 {
        use std::hash::{Hash, Hasher};
        let [mut a, mut b] = self.0;
        self.1.hash(&mut a);
        self.1.hash(&mut b);
        (u128::from(a.finish()) << 64) | u128::from(b.finish())
    }
}

/// A node's key in a walk's visited set (and a list's map of sources):
/// 16 bytes, not a NodeId and its string (at 100,000 variables 4 MB
/// against 11).
pub(crate) fn visit_key(node: &NodeId) -> u128 {
    use std::hash::{Hash, Hasher};
    let half = |seed: u8| {
        let mut h = std::hash::DefaultHasher::new();
        seed.hash(&mut h);
        node.hash(&mut h);
        h.finish()
    };
    (u128::from(half(0)) << 64) | u128::from(half(1))
}

/// What a look keeps until the next: the print of the variables it found
/// (see [`Print`]) and the [`visit_key`]s of those browsed with children
/// of their own (a structure's fields): a look that only compares browses
/// these and no other variable.
pub(crate) struct Known {
    pub print: u128,
    pub parents: HashSet<u128>,
}

/// What [`find`] found.
pub(crate) struct Finding {
    pub known: Known,
    /// The variables, where kept.
    pub found: Option<Vec<Found>>,
}

/// The variables: the tag file's tags, or those found by browsing
/// `starts`, and their [`Print`]; [`build`] reads their attributes. With
/// `keep` false a browse only hashes what it finds (a rebrowse that
/// compares): no list of 100,000 names and node ids is held. With
/// `parents` given, only those variables are browsed for children; the
/// others are taken to have none (a look at 100,000 variables is then a
/// Browse of their folders, not of each of them).
pub(crate) async fn find(
    section: &str,
    session: &Session,
    limits: &Limits,
    tags: Option<Vec<Tag>>,
    starts: &[NodeRef],
    keep: bool,
    parents: Option<&HashSet<u128>>,
) -> Result<Finding, PlcError> {
    Ok(match tags {
        Some(tags) => {
            let mut print = Print::new();
            let mut found = Vec::with_capacity(tags.len());
            for tag in tags {
                match node_id(session, &tag.node).await {
                    Ok(node) => {
                        let name = cp1250::decode(&tag.name).into_owned();
                        print.add(&name, &node, Some(&tag));
                        found.push(Found {
                            name,
                            node,
                            tag: Some(Box::new(tag)),
                        });
                    }
                    Err(e) => warn!(section, "tag file line {}: {e}; skipped", tag.line),
                }
            }
            Finding {
                known: Known {
                    print: print.finish(),
                    parents: HashSet::new(),
                },
                found: Some(found),
            }
        }
        None => {
            let mut sink = Sink {
                print: Print::new(),
                found: keep.then(Vec::new),
                parents: HashSet::new(),
            };
            browse(section, session, limits, starts, parents, &mut sink).await?;
            Finding {
                known: Known {
                    print: sink.print.finish(),
                    parents: sink.parents,
                },
                found: sink.found.map(|found| named(section, found)),
            }
        }
    })
}

/// Where a browse puts the variables it finds.
struct Sink {
    print: Print,
    /// Kept for [`build`], or only hashed.
    found: Option<Vec<Found>>,
    /// See [`Known::parents`].
    parents: HashSet<u128>,
}

impl Sink {
    fn add(&mut self, name: String, node: &NodeId) {
        self.print.add(&name, node, None);
        if let Some(found) = &mut self.found {
            found.push(Found {
                name,
                node: node.clone(),
                tag: None,
            });
        }
    }
}

/// Most variables one node is served as (an array's elements times its
/// structure's fields); a larger node is skipped.
pub const MAX_PER_NODE: u64 = 4096;

/// Builds the list of `found`, typed from their attributes; structures
/// expanded into their fields by their DataTypeDefinition.
pub async fn build(
    section: &str,
    session: &Session,
    limits: &Limits,
    found: Vec<Found>,
) -> Result<Built, PlcError> {
    let attributes = read_attributes(session, limits, &found).await?;
    // The structure types among them, and their layouts.
    let mut structured: Vec<NodeId> = found
        .iter()
        .zip(&attributes)
        .filter(|(f, a)| {
            a.data_type
                .as_ref()
                .and_then(Builtin::of_data_type)
                .is_none()
                && f.tag.as_ref().is_none_or(|t| t.field.is_some())
        })
        .filter_map(|(_, a)| a.data_type.clone())
        .filter(may_be_structure)
        .collect();
    structured.sort_unstable_by_key(|n| n.to_string());
    structured.dedup();
    let layouts = layouts(session, limits, structured).await?;
    // Variables with child variables: a structure whose fields the server
    // shows as its children (S7-1500, TwinCAT) is served by those.
    let parents: HashSet<String> = found
        .iter()
        .filter_map(|f| Some(f.name.rsplit_once('.')?.0.to_uppercase()))
        .collect();
    let mut shown = 0usize;
    let mut types = Types::default();
    let mut tags = Vec::with_capacity(found.len());
    let (mut arrays, mut unknown) = (0usize, 0usize);
    let mut structures: HashMap<String, (usize, String)> = HashMap::new();
    let most = plccoms_plc::pubfile::MAX_VARS;
    for (found, attrs) in found.into_iter().zip(attributes) {
        // Arrays and structures multiply: the list stays a table's size.
        if tags.len() >= most {
            warn!(section, "more than {most} variables with arrays and structures expanded: the rest is left out");
            break;
        }
        let builtin = attrs.data_type.as_ref().and_then(Builtin::of_data_type);
        let node = node_ref(&found.node);
        let text = node.to_string();
        let layout = attrs.data_type.as_ref().and_then(|d| layouts.get(d));
        if let Some(tag) = found.tag {
            let mut tag = *tag;
            // A structure's field: typed by its definition.
            if let Some(path) = &tag.field {
                let leaf = match layout {
                    Some(Ok(layout)) => layout.leaf(path).map(|i| (layout, i)),
                    _ => None,
                };
                let Some((layout, i)) = leaf else {
                    let why = match layout {
                        Some(Err(e)) => e.clone(),
                        _ => format!("no field {path} in its DataType"),
                    };
                    warn!(
                        section,
                        "tag file line {}: node {}: {why}; skipped", tag.line, tag.node
                    );
                    continue;
                };
                let Some(leaf_builtin) = layout.builtin(i) else {
                    warn!(section, "tag file line {}: field {path} is of a type plccoms does not serve; skipped", tag.line);
                    continue;
                };
                tag.node = node;
                tag.ty = tag.ty.or(Some(leaf_builtin.iec()));
                tag.writable = tag.writable.or(Some(attrs.writable(leaf_builtin)));
                types.layouts.insert(text, layout.clone());
                tags.push(tag);
                continue;
            }
            // A tag file's type wins; its node's DataType writes it.
            let builtin = match (tag.ty, builtin) {
                (_, Some(b)) => b,
                (Some(ty), None) => Builtin::of_iec(ty),
                (None, None) => {
                    warn!(section, "tag file line {}: node {} has no type plccoms serves (DataType {}); give one in the type column", tag.line, tag.node, attrs.data_type.map_or_else(|| "unreadable".to_string(), |d| d.to_string()));
                    continue;
                }
            };
            // nsu= resolved: the list names nodes by the server's indexes.
            tag.node = node;
            tag.ty = tag.ty.or(Some(builtin.iec()));
            tag.writable = tag.writable.or(Some(attrs.writable(builtin)));
            if tag.ty.map(Builtin::of_iec) != Some(builtin) {
                types.builtins.insert(text, builtin);
            }
            tags.push(tag);
            continue;
        }
        // Its elements (one for a scalar), each named `[i]` or `[i][j]`.
        let dims = match (attrs.value_rank, &attrs.dims) {
            (None | Some(-1), _) => None,
            (Some(rank), Some(dims)) if rank >= 1 && dims.len() == rank as usize => {
                Some(dims.clone())
            }
            _ => {
                arrays += 1;
                continue;
            }
        };
        let count = match &dims {
            None => Some(1),
            Some(dims) => elements(dims, u64::from(MAX_ELEMENTS)),
        };
        let Some(count) = count else {
            arrays += 1;
            continue;
        };
        let name_of = |i: u64| match &dims {
            None => found.name.clone(),
            Some(dims) => format!("{}{}", found.name, element_suffix(dims, i)),
        };
        let index_of = |i: u64| dims.as_ref().map(|_| i as u32);
        let tag = |name: &str, index, field: Option<&str>, builtin: Builtin| Tag {
            // path_name keeps cp1250's characters only.
            name: cp1250::encode(name).into_owned().into_boxed_slice(),
            node: node.clone(),
            ty: Some(builtin.iec()),
            writable: Some(attrs.writable(builtin)),
            index,
            field: field.map(str::to_string),
            info: VarInfo::default(),
            line: 0,
        };
        if let Some(builtin) = builtin {
            if Builtin::of_iec(builtin.iec()) != builtin {
                types.builtins.insert(text, builtin);
            }
            for i in 0..count.min((most - tags.len()) as u64) {
                tags.push(tag(&name_of(i), index_of(i), None, builtin));
            }
            continue;
        }
        let Some(data_type) = &attrs.data_type else {
            unknown += 1;
            continue;
        };
        if parents.contains(&found.name.to_uppercase()) {
            shown += 1;
            continue;
        }
        let layout = match layouts.get(data_type) {
            Some(Ok(layout)) => layout,
            Some(Err(e)) => {
                structures
                    .entry(data_type.to_string())
                    .or_insert((0, e.clone()))
                    .0 += 1;
                continue;
            }
            None => {
                unknown += 1;
                continue;
            }
        };
        let served: Vec<(usize, Builtin)> = (0..layout.leaves.len())
            .filter_map(|i| Some((i, layout.builtin(i)?)))
            .collect();
        if count.saturating_mul(served.len() as u64) > MAX_PER_NODE {
            structures
                .entry(data_type.to_string())
                .or_insert((
                    0,
                    format!("more than {MAX_PER_NODE} fields in one variable"),
                ))
                .0 += 1;
            continue;
        }
        if tags.len() as u64 + count * served.len() as u64 > most as u64 {
            warn!(section, "more than {most} variables with arrays and structures expanded: the rest is left out");
            break;
        }
        types.layouts.insert(text, layout.clone());
        for i in 0..count {
            let base = name_of(i);
            for &(leaf, builtin) in &served {
                let path = &layout.leaves[leaf].path;
                tags.push(tag(
                    &format!("{base}.{path}"),
                    index_of(i),
                    Some(path),
                    builtin,
                ));
            }
        }
    }
    let mut skipped = Vec::new();
    if shown > 0 {
        skipped.push(format!("{shown} structured variables skipped (their fields are served as the child variables the server shows)"));
    }
    let mut kinds: Vec<_> = structures.into_iter().collect();
    kinds.sort();
    for (data_type, (n, why)) in kinds.iter().take(5) {
        skipped.push(format!(
            "{n} structured variables of DataType {data_type} skipped: {why}"
        ));
    }
    if kinds.len() > 5 {
        skipped.push(format!("{} more structure types skipped", kinds.len() - 5));
    }
    if arrays > 0 {
        skipped.push(format!(
            "{arrays} array variables skipped (more than {MAX_ELEMENTS} elements, or dimensions the server does not tell)"
        ));
    }
    if unknown > 0 {
        skipped.push(format!("{unknown} variables of types plccoms does not serve skipped (ByteString, Guid, NodeId, ...)"));
    }
    Ok(Built {
        tags,
        types,
        skipped,
    })
}

/// Whether a DataType may be a structure: the server's own types, and the
/// standard ones past the built-in and abstract types (Range, EUInformation).
fn may_be_structure(data_type: &NodeId) -> bool {
    data_type.namespace != 0
        || matches!(data_type.identifier, opcua::types::Identifier::Numeric(id) if id > 29)
}

/// The layouts of structure types `types`, from their DataTypeDefinition
/// attributes (and those of the types their fields name); a type whose
/// definition cannot be had is the reason why.
async fn layouts(
    session: &Session,
    limits: &Limits,
    types: Vec<NodeId>,
) -> Result<HashMap<NodeId, Result<Arc<Layout>, String>>, PlcError> {
    let mut defs: HashMap<NodeId, Result<Definition, String>> = HashMap::new();
    let mut pending = types.clone();
    for _ in 0..plccoms_plc::opcua::structure::MAX_DEPTH {
        pending.retain(|t| !defs.contains_key(t));
        pending.dedup();
        if pending.is_empty() {
            break;
        }
        // DataTypeDefinition (23, OPC UA 1.04).
        let values = read_all(session, limits, &pending, &[23]).await?;
        for (t, v) in pending.iter().zip(values) {
            let def = match v.status {
                Some(status) if status.is_bad() => {
                    Err(format!("its DataTypeDefinition is not readable ({status})"))
                }
                _ => v
                    .value
                    .ok_or_else(|| "no DataTypeDefinition".to_string())
                    .and_then(Definition::of),
            };
            defs.insert(t.clone(), def);
        }
        pending = defs
            .values()
            .flatten()
            .flat_map(Definition::needs)
            .filter(|t| !defs.contains_key(t))
            .collect();
        pending.sort_unstable_by_key(|n| n.to_string());
    }
    Ok(types
        .into_iter()
        .map(|t| {
            let layout = crate::structure::resolve(&t, &defs, 0)
                .and_then(|s| Layout::new(t.clone(), s))
                .map(Arc::new);
            (t, layout)
        })
        .collect())
}

/// A node waiting to be browsed: its browse path, whether a variable, and
/// a variable's children when [`prefetch`] browsed them already.
struct Queued {
    node: NodeId,
    path: Vec<String>,
    variable: bool,
    children: Option<Vec<ReferenceDescription>>,
}

impl Queued {
    fn new(node: NodeId, path: Vec<String>, variable: bool) -> Queued {
        Queued {
            node,
            path,
            variable,
            children: None,
        }
    }
}

/// The Browse of a node's children: hierarchical references to objects
/// and variables.
fn describe(node: &NodeId) -> BrowseDescription {
    BrowseDescription {
        node_id: node.clone(),
        browse_direction: BrowseDirection::Forward,
        reference_type_id: NodeId::new(0, HIERARCHICAL),
        include_subtypes: true,
        node_class_mask: (NodeClassMask::OBJECT | NodeClassMask::VARIABLE).bits(),
        // What is used only: a DisplayName and a TypeDefinition are a
        // third of each reference, 100,000 times.
        result_mask: (BrowseResultMask::ReferenceTypeId as u32)
            | (BrowseResultMask::NodeClass as u32)
            | (BrowseResultMask::BrowseName as u32),
    }
}

/// Browses from `starts` down hierarchical references (not properties),
/// breadth first: every Variable with a served type becomes a variable
/// named by its browse path below its start node, given to `sink`. With
/// `parents`, a variable not among them is not browsed (see [`find`]).
async fn browse(
    section: &str,
    session: &Session,
    limits: &Limits,
    starts: &[NodeRef],
    parents: Option<&HashSet<u128>>,
    sink: &mut Sink,
) -> Result<(), PlcError> {
    let mut queue: VecDeque<Queued> = VecDeque::new();
    let mut visited: HashSet<u128> = HashSet::new();
    for start in starts {
        match node_id(session, start).await {
            Ok(node) => {
                visited.insert(visit_key(&node));
                queue.push_back(Queued::new(node, Vec::new(), false));
            }
            Err(e) => warn!(section, "OPCUA_BROWSE {start}: {e}"),
        }
    }
    let mut variables = 0usize;
    let most = limits.per_browse.clamp(1, VARIABLE_BATCH);
    while !queue.is_empty() {
        // In queue order (the names' order): up to BROWSE_BATCH objects,
        // whose answers may be long, and variables up to VARIABLE_BATCH.
        let mut objects = 0;
        let take = queue
            .iter()
            .take(most)
            .take_while(|q| {
                objects += usize::from(!q.variable);
                objects <= BROWSE_BATCH.min(most)
            })
            .count()
            .max(1);
        let batch: Vec<Queued> = queue.drain(..take).collect();
        let descriptions: Vec<BrowseDescription> = batch
            .iter()
            .filter(|q| q.children.is_none())
            .map(|q| describe(&q.node))
            .collect();
        let mut results = if descriptions.is_empty() {
            Vec::new()
        } else {
            crate::rebrowse::browse_nodes(session, limits, descriptions, REFERENCES_PER_NODE)
                .await?
        }
        .into_iter();
        for item in batch {
            let (mut references, mut point) = match item.children {
                Some(children) => (children, ByteString::null()),
                None => match results.next() {
                    Some(mut result) => (
                        result.references.take().unwrap_or_default(),
                        std::mem::take(&mut result.continuation_point),
                    ),
                    None => continue,
                },
            };
            let path = item.path;
            let parent = item.variable.then(|| visit_key(&item.node));
            // Continuation points bring the rest of a long list: each page
            // taken as it comes (a folder of 100,000 variables held at
            // once was the largest peak of a rebrowse).
            let (mut pages, mut seen) = (0, 0);
            loop {
                seen += references.len();
                let mut fresh = Vec::new();
                for reference in references.drain(..) {
                    // Properties, and nodes on other servers, are not served.
                    if reference.reference_type_id == NodeId::new(0, HAS_PROPERTY)
                        || reference.node_id.server_index != 0
                    {
                        continue;
                    }
                    let node = reference.node_id.node_id;
                    if let Some(parent) = parent {
                        sink.parents.insert(parent);
                    }
                    if node == NodeId::new(0, SERVER_OBJECT) || !visited.insert(visit_key(&node)) {
                        continue;
                    }
                    if visited.len() > MAX_NODES {
                        warn!(
                            section,
                            "more than {MAX_NODES} nodes below OPCUA_BROWSE: the rest is left out"
                        );
                        return Ok(());
                    }
                    let mut child = path.clone();
                    child.push(
                        reference
                            .browse_name
                            .name
                            .value()
                            .clone()
                            .unwrap_or_default(),
                    );
                    let variable = reference.node_class == NodeClass::Variable;
                    if variable {
                        if variables == plccoms_plc::pubfile::MAX_VARS {
                            warn!(
                                section,
                                "more than {} variables found by browsing: the rest is left out",
                                plccoms_plc::pubfile::MAX_VARS
                            );
                            return Ok(());
                        }
                        let name = path_name(&child);
                        // Another plccoms's section (loopback) shows the fixed
                        // file's variables, which every table has already.
                        if FIXED_NAMES.iter().any(|f| f.eq_ignore_ascii_case(&name)) {
                            continue;
                        }
                        variables += 1;
                        sink.add(name, &node);
                    }
                    // Variables have fields (a structure's) as components too.
                    if child.len() < MAX_DEPTH {
                        fresh.push(Queued::new(node, child, variable));
                    }
                }
                prefetch(session, limits, parents, &mut fresh).await?;
                queue.extend(fresh);
                if point.is_null() || pages >= 10_000 || seen >= MAX_NODES {
                    break;
                }
                pages += 1;
                let next = crate::rebrowse::browse_next(session, limits, point).await?;
                let Some(mut next) = next.into_iter().next() else {
                    break;
                };
                references = next.references.take().unwrap_or_default();
                point = next.continuation_point;
            }
        }
    }
    Ok(())
}

/// Browses the variables among `fresh` (a page's) for their children, a
/// structure's fields, now rather than at their turn: most have none and
/// are dropped, so the queue never holds the 100,000 variables of a
/// folder with their paths and node ids (a rebrowse's largest peak).
/// Those with children keep them for their turn (the names' order
/// stays); those whose answer was not plain (a refusal, more than a
/// page: its continuation point given back) are browsed at their turn.
/// With `parents`, a variable not among them is dropped unbrowsed.
async fn prefetch(
    session: &Session,
    limits: &Limits,
    parents: Option<&HashSet<u128>>,
    fresh: &mut Vec<Queued>,
) -> Result<(), PlcError> {
    let mut childless = vec![false; fresh.len()];
    let mut variables = Vec::new();
    for (i, queued) in fresh.iter().enumerate() {
        if !queued.variable {
            continue;
        }
        match parents {
            Some(parents) if !parents.contains(&visit_key(&queued.node)) => childless[i] = true,
            _ => variables.push(i),
        }
    }
    for chunk in variables.chunks(limits.per_browse.clamp(1, VARIABLE_BATCH)) {
        let descriptions = chunk.iter().map(|&i| describe(&fresh[i].node)).collect();
        let results =
            crate::rebrowse::browse_nodes(session, limits, descriptions, REFERENCES_PER_NODE)
                .await?;
        let mut points = Vec::new();
        for (&i, result) in chunk.iter().zip(results) {
            if !result.continuation_point.is_null() {
                points.push(result.continuation_point);
            } else if result.status_code.is_good() {
                match result.references {
                    Some(children) if !children.is_empty() => fresh[i].children = Some(children),
                    _ => childless[i] = true,
                }
            }
        }
        if !points.is_empty() {
            crate::rebrowse::release_points(session, limits, points).await?;
        }
    }
    let mut i = 0;
    fresh.retain(|_| {
        i += 1;
        !childless[i - 1]
    });
    Ok(())
}

/// Resolves name collisions (logged).
fn named(section: &str, mut found: Vec<Found>) -> Vec<Found> {
    let mut names: Vec<String> = found.iter().map(|f| f.name.clone()).collect();
    let renamed = unique_names(&mut names);
    for (old, new) in renamed.iter().take(5) {
        warn!(
            section,
            "two variables are named {old} by their browse paths: the later one is {new}"
        );
    }
    if renamed.len() > 5 {
        warn!(
            section,
            "{} more variables renamed for name collisions",
            renamed.len() - 5
        );
    }
    for (f, name) in found.iter_mut().zip(names) {
        f.name = name;
    }
    found
}

/// What a variable's attributes say.
struct Attributes {
    data_type: Option<NodeId>,
    value_rank: Option<i32>,
    user_access: Option<u8>,
    /// An array's dimensions (ArrayDimensions, else its value's).
    dims: Option<Vec<u32>>,
}

impl Attributes {
    fn writable(&self, builtin: Builtin) -> bool {
        builtin != Builtin::LocalizedText && self.user_access.is_none_or(|a| a & CURRENT_WRITE != 0)
    }
}

/// `attributes` of each of `nodes` (in that order), in as few Read calls
/// as MaxNodesPerRead allows, a node's attributes in one call; one value
/// each, or the failure.
async fn read_all(
    session: &Session,
    limits: &Limits,
    nodes: &[NodeId],
    attributes: &[u32],
) -> Result<Vec<opcua::types::DataValue>, PlcError> {
    let per_read = (limits.per_read / attributes.len().max(1)).max(1);
    let mut out = Vec::with_capacity(nodes.len() * attributes.len());
    for chunk in nodes.chunks(per_read) {
        let ids: Vec<ReadValueId> = chunk
            .iter()
            .flat_map(|node| {
                attributes.iter().map(|&attribute_id| ReadValueId {
                    node_id: node.clone(),
                    attribute_id,
                    ..Default::default()
                })
            })
            .collect();
        let values = crate::rebrowse::read_attributes(session, limits, &ids).await?;
        if values.len() != ids.len() {
            return Err(PlcError::Protocol(format!(
                "Read of {} attributes answered {}",
                ids.len(),
                values.len()
            )));
        }
        out.extend(values);
    }
    Ok(out)
}

async fn read_attributes(
    session: &Session,
    limits: &Limits,
    found: &[Found],
) -> Result<Vec<Attributes>, PlcError> {
    // DataType (14), ValueRank (15), ArrayDimensions (16), UserAccessLevel (18).
    const ATTRIBUTES: [u32; 4] = [14, 15, 16, 18];
    let mut out = Vec::with_capacity(found.len());
    let nodes: Vec<NodeId> = found.iter().map(|f| f.node.clone()).collect();
    let values = read_all(session, limits, &nodes, &ATTRIBUTES).await?;
    for four in values.chunks(ATTRIBUTES.len()) {
        let good = |i: usize| {
            four[i]
                .status
                .is_none_or(|s| s.is_good())
                .then(|| four[i].value.clone())
                .flatten()
        };
        out.push(Attributes {
            data_type: match good(0) {
                Some(Variant::NodeId(id)) => Some(*id),
                _ => None,
            },
            value_rank: match good(1) {
                Some(Variant::Int32(rank)) => Some(rank),
                _ => None,
            },
            dims: match good(2) {
                Some(Variant::Array(a)) => a
                    .values
                    .iter()
                    .map(|d| match d {
                        Variant::UInt32(n) if *n > 0 => Some(*n),
                        _ => None,
                    })
                    .collect::<Option<Vec<u32>>>()
                    .filter(|d| !d.is_empty()),
                _ => None,
            },
            user_access: match good(3) {
                Some(Variant::Byte(a)) => Some(a),
                _ => None,
            },
        });
    }
    // Arrays whose dimensions the server leaves open (ArrayDimensions 0):
    // those of their value now.
    let open: Vec<usize> = (0..out.len())
        .filter(|&i| out[i].value_rank.is_some_and(|r| r >= 1) && out[i].dims.is_none())
        .collect();
    for chunk in open.chunks(limits.per_read.max(1)) {
        let ids: Vec<ReadValueId> = chunk
            .iter()
            .map(|&i| found[i].node.clone().into())
            .collect();
        let values = crate::rebrowse::read_attributes(session, limits, &ids).await?;
        for (&i, value) in chunk.iter().zip(values) {
            if let Some(Variant::Array(a)) = value.value {
                out[i].dims = match a.dimensions {
                    Some(dims) if !dims.is_empty() => Some(dims),
                    _ => u32::try_from(a.values.len()).ok().map(|n| vec![n]),
                }
                .filter(|d| d.iter().all(|&n| n > 0));
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn print(found: &[(&str, u32)]) -> u128 {
        let mut print = Print::new();
        for (name, node) in found {
            print.add(name, &NodeId::new(2, *node), None);
        }
        print.finish()
    }

    /// The rebrowse keeps only this: a node added, removed, renamed or
    /// moved to another node id must change it.
    #[test]
    fn the_print_sees_a_node_added_removed_or_renamed() {
        let list = [("A", 1), ("B", 2), ("C", 3)];
        assert_eq!(print(&list), print(&list));
        for other in [
            &[("A", 1), ("B", 2), ("C", 3), ("D", 4)][..],
            &[("A", 1), ("C", 3)],
            &[("A", 1), ("B", 2)],
            &[("A", 1), ("X", 2), ("C", 3)],
            &[("A", 1), ("B", 5), ("C", 3)],
            &[("B", 2), ("A", 1), ("C", 3)],
            &[],
        ] {
            assert_ne!(print(&list), print(other), "{other:?}");
        }
    }

    #[test]
    fn visit_keys_tell_node_ids_apart() {
        let keys: HashSet<u128> = [
            NodeId::new(2, 1),
            NodeId::new(3, 1),
            NodeId::new(2, "1"),
            NodeId::new(2, "Sim.V1"),
            NodeId::new(2, "Sim.V10"),
        ]
        .iter()
        .map(visit_key)
        .collect();
        assert_eq!(keys.len(), 5);
        assert_eq!(
            visit_key(&NodeId::new(2, "a")),
            visit_key(&NodeId::new(2, "a"))
        );
    }
}
