//! Our node manager for the variables: every variable node and its
//! property nodes (EngineeringUnits, EURange) served from the sections'
//! tables, nothing of them copied into the stack's address space. A node
//! is its NodeId's text parsed back ([`crate::ids`]) against a section's
//! [`View`]; its attributes and references are made when asked. Per
//! variable the view keeps a few bits (shown, writable, recorded) beside
//! the core's table, so a table of 100,000 variables costs no node memory.
//!
//! Registered before the in-memory manager of the root folder and section
//! objects ([`crate::manager`]), so the stack asks this one first for the
//! nodes it owns (`owns_node`), and in Browse adds a section object's
//! variables before the in-memory manager adds the object's other
//! references.
//!
//! The services that reach the PLC or the historian: Read of a value (the
//! poll's, else a read from the PLC as GET does), Write through the core's
//! one write path, monitored items that enable their variable in the poll
//! as EN does, HistoryRead from the historian.

use std::collections::{HashSet, VecDeque};
use std::sync::Arc;

use async_trait::async_trait;
use futures::StreamExt;
use opcua::nodes::{DefaultTypeTree, TypeTree};
use opcua::server::address_space::AccessLevel;
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::{
    BrowseNode, BrowsePathItem, HistoryNode, MonitoredItemRef, MonitoredItemUpdateRef, NodeManager,
    ReadNode, RequestContext, ServerContext, WriteNode,
};
use opcua::server::{ContinuationPoint, CreateMonitoredItem, MonitoredItemHandle};
use opcua::types::{
    AttributeId, DataEncoding, DataValue, EUInformation, ExpandedNodeId, HistoryData,
    LocalizedText, MonitoringMode, NodeClass, NodeId, NumericRange, ObjectTypeId, QualifiedName,
    Range, ReadRawModifiedDetails, ReferenceDescription, ReferenceTypeId, RelativePathElement,
    StatusCode, TimestampsToReturn, UAString, VariableTypeId, Variant,
};
use plccoms_core::driver::ReadRequest;
use plccoms_core::history_source::HistoryQuery;
use plccoms_core::vars::VarId;
use plccoms_protocol::IecType;

use crate::auth;
use crate::convert;
use crate::ids;
use crate::manager::{self, bad, unwatch, watch, Cursor, BOUND_LOOKBACK_MS, HISTORY_PAGE};
use crate::space::{self, SectionNodes, Shared, View};

/// A variable's property node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Prop {
    Units,
    Range,
}

impl Prop {
    pub fn name(self) -> &'static str {
        match self {
            Prop::Units => "EngineeringUnits",
            Prop::Range => "EURange",
        }
    }

    fn parse(name: &str) -> Option<Prop> {
        match name {
            "EngineeringUnits" => Some(Prop::Units),
            "EURange" => Some(Prop::Range),
            _ => None,
        }
    }
}

/// What one of our NodeIds names, in the sections served now (whether the
/// variable is in its table is for the caller to look up).
pub enum Named {
    Section(Arc<SectionNodes>),
    Variable(Arc<SectionNodes>, String),
    Property(Arc<SectionNodes>, String, Prop),
}

impl Shared {
    /// The section and variable a NodeId of ours names (a section served
    /// now; whether its table has the variable is for the caller).
    pub fn variable(&self, node: &NodeId) -> Option<(Arc<SectionNodes>, String)> {
        match self.named(node)? {
            Named::Variable(nodes, name) => Some((nodes, name)),
            _ => None,
        }
    }

    pub fn named(&self, node: &NodeId) -> Option<Named> {
        if node.namespace != self.ns() {
            return None;
        }
        let opcua::types::Identifier::String(text) = &node.identifier else {
            return None;
        };
        let list = self.list();
        let names: Vec<&str> = list.iter().map(|s| s.name.as_str()).collect();
        Some(match ids::parse(text.as_ref(), &names).ok()? {
            ids::Ours::Section { section } => Named::Section(list[section].clone()),
            ids::Ours::Variable { section, variable } => {
                Named::Variable(list[section].clone(), variable.to_string())
            }
            ids::Ours::VariableProperty {
                section,
                variable,
                property,
            } => Named::Property(
                list[section].clone(),
                variable.to_string(),
                Prop::parse(property)?,
            ),
            _ => return None,
        })
    }
}

/// What a variable's attributes and references are made of, read from
/// its section's view.
pub struct Facts {
    pub id: VarId,
    pub ty: IecType,
    pub access: AccessLevel,
    pub historized: bool,
    pub description: Option<String>,
    pub unit: Option<String>,
    pub range: Option<(f64, f64)>,
}

impl Facts {
    pub fn of(view: &View, name: &str) -> Option<Facts> {
        let id = view.id_of(name)?;
        Some(Facts::of_id(view, id))
    }

    pub fn of_id(view: &View, id: VarId) -> Facts {
        let var = view.table.var(id);
        let historized = view.historized[id as usize];
        let mut access = AccessLevel::CURRENT_READ;
        if view.writable[id as usize] {
            access |= AccessLevel::CURRENT_WRITE;
        }
        if historized {
            access |= AccessLevel::HISTORY_READ;
        }
        let info = var.info.as_deref();
        let text = |t: Option<&str>| t.filter(|t| !t.is_empty()).map(str::to_string);
        Facts {
            id,
            ty: var.ty,
            access,
            historized,
            description: text(info.map(|i| i.description.as_str())),
            unit: text(info.map(|i| i.unit.as_str())),
            range: info.and_then(|i| Some((i.min?, i.max?))),
        }
    }

    fn has(&self, prop: Prop) -> bool {
        match prop {
            Prop::Units => self.unit.is_some(),
            Prop::Range => self.range.is_some(),
        }
    }

    fn type_definition(&self) -> VariableTypeId {
        if self.range.is_some() {
            VariableTypeId::AnalogItemType
        } else {
            VariableTypeId::BaseDataVariableType
        }
    }

    fn property_value(&self, prop: Prop) -> Option<Variant> {
        match prop {
            Prop::Units => self.unit.as_deref().map(|unit| {
                Variant::from(EUInformation {
                    namespace_uri: UAString::from(
                        "http://www.opcfoundation.org/UA/units/un/cefact",
                    ),
                    unit_id: -1,
                    display_name: LocalizedText::from(unit),
                    description: LocalizedText::from(unit),
                })
            }),
            Prop::Range => self
                .range
                .map(|(low, high)| Variant::from(Range { low, high })),
        }
    }
}

/// Where a Browse of ours stopped: at a section's variable `next`, or
/// with the references left over.
enum Cont {
    Section { name: String, next: VarId },
    Rest(VecDeque<ReferenceDescription>),
}

/// A variable read: its value now, or to be read from the PLC.
enum Ours {
    Value(DataValue),
    Read(VarId),
}

/// A write checked: its section, the variable's name and the SET text.
type Checked = (Arc<SectionNodes>, Vec<u8>, Vec<u8>);

pub struct Vars {
    pub shared: Arc<Shared>,
    pub loop_delay_ms: f64,
    /// Monitored items of ours in MonitoringMode Disabled: they do not
    /// keep their variable enabled in the poll.
    disabled: std::sync::Mutex<HashSet<MonitoredItemHandle>>,
}

fn type_ref(
    reference: ReferenceTypeId,
    forward: bool,
    node: NodeId,
    browse_name: QualifiedName,
    class: NodeClass,
    type_definition: NodeId,
) -> ReferenceDescription {
    ReferenceDescription {
        reference_type_id: reference.into(),
        is_forward: forward,
        node_id: node.into(),
        display_name: LocalizedText::from(browse_name.name.as_ref()),
        browse_name,
        node_class: class,
        type_definition: if type_definition.is_null() {
            ExpandedNodeId::null()
        } else {
            type_definition.into()
        },
    }
}

/// A standard type's node as a reference target.
fn to_type(id: impl Into<NodeId>, name: &str) -> ReferenceDescription {
    type_ref(
        ReferenceTypeId::HasTypeDefinition,
        true,
        id.into(),
        QualifiedName::new(0, name),
        NodeClass::VariableType,
        NodeId::null(),
    )
}

/// Whether `reference` passes a filter of type `wanted` (null: any).
fn passes(
    tree: &dyn TypeTree,
    wanted: &NodeId,
    subtypes: bool,
    reference: ReferenceTypeId,
) -> bool {
    let reference: NodeId = reference.into();
    wanted.is_null() || *wanted == reference || subtypes && tree.is_subtype_of(&reference, wanted)
}

impl Vars {
    pub fn new(shared: Arc<Shared>, loop_delay_ms: f64) -> Vars {
        Vars {
            shared,
            loop_delay_ms,
            disabled: Default::default(),
        }
    }

    fn disabled_set(&self) -> std::sync::MutexGuard<'_, HashSet<MonitoredItemHandle>> {
        self.disabled.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn node(&self, text: String) -> NodeId {
        self.shared.node(text)
    }

    /// The reference to variable `name` of `section` (forward, from the
    /// section object; inverse, from a property).
    fn variable_ref(
        &self,
        section: &str,
        name: &str,
        facts: &Facts,
        reference: ReferenceTypeId,
        forward: bool,
    ) -> ReferenceDescription {
        type_ref(
            reference,
            forward,
            self.node(ids::variable(section, name)),
            QualifiedName::new(self.shared.ns(), name),
            NodeClass::Variable,
            facts.type_definition().into(),
        )
    }

    /// A variable's references: to its section object, its type and its
    /// properties.
    fn variable_refs(
        &self,
        nodes: &SectionNodes,
        name: &str,
        facts: &Facts,
    ) -> Vec<ReferenceDescription> {
        let text = ids::variable(&nodes.name, name);
        let mut refs = vec![
            type_ref(
                ReferenceTypeId::HasComponent,
                false,
                self.node(nodes.name.clone()),
                QualifiedName::new(self.shared.ns(), nodes.name.as_str()),
                NodeClass::Object,
                ObjectTypeId::BaseObjectType.into(),
            ),
            match facts.type_definition() {
                VariableTypeId::AnalogItemType => {
                    to_type(VariableTypeId::AnalogItemType, "AnalogItemType")
                }
                _ => to_type(VariableTypeId::BaseDataVariableType, "BaseDataVariableType"),
            },
        ];
        for prop in [Prop::Units, Prop::Range] {
            if facts.has(prop) {
                refs.push(type_ref(
                    ReferenceTypeId::HasProperty,
                    true,
                    self.node(ids::property(&text, prop.name())),
                    QualifiedName::new(0, prop.name()),
                    NodeClass::Variable,
                    VariableTypeId::PropertyType.into(),
                ));
            }
        }
        refs
    }

    fn property_refs(
        &self,
        nodes: &SectionNodes,
        name: &str,
        facts: &Facts,
    ) -> Vec<ReferenceDescription> {
        vec![
            self.variable_ref(
                &nodes.name,
                name,
                facts,
                ReferenceTypeId::HasProperty,
                false,
            ),
            to_type(VariableTypeId::PropertyType, "PropertyType"),
        ]
    }

    /// Adds `refs` that pass the node's filter, as many as fit; the rest
    /// to a continuation point.
    fn add_all(
        node: &mut BrowseNode,
        tree: &dyn TypeTree,
        refs: impl IntoIterator<Item = ReferenceDescription>,
    ) {
        let mut rest = VecDeque::new();
        for reference in refs {
            if !rest.is_empty() || node.remaining() == 0 {
                if node.matches_filter(tree, &reference) && direction_ok(node, reference.is_forward)
                {
                    rest.push_back(reference);
                }
                continue;
            }
            if direction_ok(node, reference.is_forward) {
                let _ = node.add(tree, reference);
            }
        }
        if !rest.is_empty() {
            // The next page adds them (filtered again, to the same result).
            node.set_next_continuation_point(Box::new(Cont::Rest(rest)));
        }
    }

    /// A section object's variables from `start` on, as many as fit.
    fn browse_section(
        &self,
        node: &mut BrowseNode,
        tree: &dyn TypeTree,
        nodes: &SectionNodes,
        start: VarId,
    ) {
        if !node.allows_forward()
            || !node.allows_node_class(NodeClass::Variable)
            || !node.allows_reference_type(&ReferenceTypeId::HasComponent.into(), tree)
        {
            return;
        }
        let view = nodes.lock();
        for id in start..view.table.len() as VarId {
            if !view.shown[id as usize] {
                continue;
            }
            if node.remaining() == 0 {
                node.set_next_continuation_point(Box::new(Cont::Section {
                    name: nodes.name.clone(),
                    next: id,
                }));
                return;
            }
            let name = space::shown_name(&view.table, id);
            let facts = Facts::of_id(&view, id);
            let reference = self.variable_ref(
                &nodes.name,
                &name,
                &facts,
                ReferenceTypeId::HasComponent,
                true,
            );
            let _ = node.add(tree, reference);
        }
    }

    /// One step of a browse path from `from`.
    fn step(
        &self,
        tree: &DefaultTypeTree,
        from: &NodeId,
        element: &RelativePathElement,
    ) -> Option<NodeId> {
        let ns = self.shared.ns();
        let target = &element.target_name;
        let via = |reference: ReferenceTypeId, inverse: bool| {
            element.is_inverse == inverse
                && passes(
                    tree,
                    &element.reference_type_id,
                    element.include_subtypes,
                    reference,
                )
        };
        match self.shared.named(from)? {
            Named::Section(nodes) => {
                if target.namespace_index != ns || !via(ReferenceTypeId::HasComponent, false) {
                    return None;
                }
                let name = target.name.as_ref();
                nodes
                    .lock()
                    .id_of(name)
                    .is_some()
                    .then(|| self.node(ids::variable(&nodes.name, name)))
            }
            Named::Variable(nodes, name) => {
                let facts = Facts::of(&nodes.lock(), &name)?;
                if target.namespace_index == 0 && via(ReferenceTypeId::HasProperty, false) {
                    let prop = Prop::parse(target.name.as_ref()).filter(|p| facts.has(*p))?;
                    return Some(self.node(ids::property(
                        &ids::variable(&nodes.name, &name),
                        prop.name(),
                    )));
                }
                (target.namespace_index == ns
                    && target.name.as_ref() == nodes.name
                    && via(ReferenceTypeId::HasComponent, true))
                .then(|| self.node(nodes.name.clone()))
            }
            Named::Property(nodes, name, prop) => {
                let facts = Facts::of(&nodes.lock(), &name)?;
                (facts.has(prop)
                    && target.namespace_index == ns
                    && target.name.as_ref() == name
                    && via(ReferenceTypeId::HasProperty, true))
                .then(|| self.node(ids::variable(&nodes.name, &name)))
            }
        }
    }

    /// The browse name of a node of ours.
    fn browse_name(&self, node: &NodeId) -> Option<QualifiedName> {
        match self.shared.named(node)? {
            Named::Section(nodes) => {
                Some(QualifiedName::new(self.shared.ns(), nodes.name.as_str()))
            }
            Named::Variable(nodes, name) => nodes
                .lock()
                .id_of(&name)
                .is_some()
                .then(|| QualifiedName::new(self.shared.ns(), name.as_str())),
            Named::Property(nodes, name, prop) => Facts::of(&nodes.lock(), &name)
                .filter(|f| f.has(prop))
                .map(|_| QualifiedName::new(0, prop.name())),
        }
    }

    /// A variable's value now: the poll's while fresh, the last one with
    /// its bad quality while the link is lost; else to be read, as GET
    /// makes a read. `None`: not a variable of its table.
    fn read_value(&self, nodes: &SectionNodes, name: &str) -> Option<Ours> {
        let snapshot = nodes.section.latest();
        let view = nodes.lock();
        let id = view.id_of(name)?;
        if !Arc::ptr_eq(&view.table, &snapshot.table) {
            // A new table the feed has not taken yet (a moment).
            return Some(Ours::Value(bad(StatusCode::BadWaitingForInitialData)));
        }
        let now = tokio::time::Instant::now();
        if snapshot.fresh(id, now).is_some() || !snapshot.online || view.table.is_fixed(id) {
            let stamp = view.stamp_of.get(&id).copied();
            return Some(Ours::Value(space::data_value(
                &snapshot,
                id,
                stamp,
                nodes.section.format(),
            )));
        }
        Some(Ours::Read(id))
    }

    /// Attribute `attribute` of a node of ours other than a variable's
    /// Value (a property's Value is one of these).
    fn attribute(
        &self,
        context: &RequestContext,
        node_id: &NodeId,
        attribute: AttributeId,
    ) -> Result<DataValue, StatusCode> {
        let unknown = StatusCode::BadNodeIdUnknown;
        let (nodes, name, prop) = match self.shared.named(node_id).ok_or(unknown)? {
            Named::Variable(nodes, name) => (nodes, name, None),
            Named::Property(nodes, name, prop) => (nodes, name, Some(prop)),
            Named::Section(_) => return Err(unknown),
        };
        let facts = Facts::of(&nodes.lock(), &name).ok_or(unknown)?;
        if prop.is_some_and(|p| !facts.has(p)) {
            return Err(unknown);
        }
        let (browse, access) = match prop {
            None => (
                QualifiedName::new(self.shared.ns(), name.as_str()),
                facts.access,
            ),
            Some(p) => (QualifiedName::new(0, p.name()), AccessLevel::CURRENT_READ),
        };
        let value = match attribute {
            AttributeId::NodeId => Variant::from(node_id.clone()),
            AttributeId::NodeClass => Variant::from(NodeClass::Variable as i32),
            AttributeId::DisplayName => Variant::from(LocalizedText::from(browse.name.as_ref())),
            AttributeId::BrowseName => Variant::from(browse),
            AttributeId::Description => match (prop, &facts.description) {
                (None, Some(text)) => Variant::from(LocalizedText::from(text.as_str())),
                _ => return Err(StatusCode::BadAttributeIdInvalid),
            },
            AttributeId::WriteMask | AttributeId::UserWriteMask => Variant::from(0u32),
            AttributeId::DataType => Variant::from(NodeId::from(match prop {
                None => convert::data_type(facts.ty),
                Some(Prop::Units) => opcua::types::DataTypeId::EUInformation,
                Some(Prop::Range) => opcua::types::DataTypeId::Range,
            })),
            AttributeId::ValueRank => Variant::from(-1i32),
            AttributeId::AccessLevel => Variant::from(access.bits()),
            AttributeId::UserAccessLevel => Variant::from(
                context
                    .authenticator
                    .effective_user_access_level(&context.token, access, node_id)
                    .bits(),
            ),
            AttributeId::Historizing => Variant::from(prop.is_none() && facts.historized),
            AttributeId::MinimumSamplingInterval if prop.is_none() => {
                Variant::from(self.loop_delay_ms)
            }
            AttributeId::Value => match prop.and_then(|p| facts.property_value(p)) {
                Some(value) => return Ok(space::good_now(value)),
                None => return Err(StatusCode::BadAttributeIdInvalid),
            },
            _ => return Err(StatusCode::BadAttributeIdInvalid),
        };
        Ok(DataValue {
            value: Some(value),
            status: Some(StatusCode::Good),
            ..Default::default()
        })
    }
}

/// Whether the node's browse direction takes a reference of this one.
fn direction_ok(node: &BrowseNode, forward: bool) -> bool {
    if forward {
        node.allows_forward()
    } else {
        node.allows_inverse()
    }
}

fn stamp(mut value: DataValue, which: TimestampsToReturn) -> DataValue {
    match which {
        TimestampsToReturn::Source => value.server_timestamp = None,
        TimestampsToReturn::Server => value.source_timestamp = None,
        TimestampsToReturn::Neither => {
            value.server_timestamp = None;
            value.source_timestamp = None;
        }
        _ => {}
    }
    value
}

#[async_trait]
impl NodeManager for Vars {
    /// Variables and their properties of the sections served now.
    fn owns_node(&self, id: &NodeId) -> bool {
        matches!(
            self.shared.named(id),
            Some(Named::Variable(..) | Named::Property(..))
        )
    }

    fn name(&self) -> &str {
        "plccoms-variables"
    }

    /// The namespace is the in-memory manager's (it registers it).
    fn namespaces_for_user(&self, _context: &RequestContext) -> Vec<NamespaceMetadata> {
        Vec::new()
    }

    async fn init(&self, _type_tree: &mut DefaultTypeTree, _context: ServerContext) {}

    async fn browse(
        &self,
        context: &RequestContext,
        nodes_to_browse: &mut [BrowseNode],
    ) -> Result<(), StatusCode> {
        let tree = context.get_type_tree_for_user();
        let tree = tree.get();
        for node in nodes_to_browse.iter_mut() {
            let cont = node.take_continuation_point::<Cont>().map(|c| *c);
            if cont.is_some() {
                node.set_status(StatusCode::Good);
            }
            match cont {
                Some(Cont::Rest(rest)) => Self::add_all(node, tree, rest),
                Some(Cont::Section { name, next }) => {
                    let list = self.shared.list();
                    if let Some(nodes) = list.iter().find(|s| s.name == name) {
                        self.browse_section(node, tree, nodes, next);
                    }
                }
                None => match self.shared.named(node.node_id()) {
                    Some(Named::Section(nodes)) => {
                        node.set_status(StatusCode::Good);
                        self.browse_section(node, tree, &nodes, 0);
                    }
                    Some(Named::Variable(nodes, name)) => {
                        let Some(facts) = Facts::of(&nodes.lock(), &name) else {
                            continue;
                        };
                        node.set_status(StatusCode::Good);
                        let refs = self.variable_refs(&nodes, &name, &facts);
                        Self::add_all(node, tree, refs);
                    }
                    Some(Named::Property(nodes, name, prop)) => {
                        let Some(facts) = Facts::of(&nodes.lock(), &name).filter(|f| f.has(prop))
                        else {
                            continue;
                        };
                        node.set_status(StatusCode::Good);
                        let refs = self.property_refs(&nodes, &name, &facts);
                        Self::add_all(node, tree, refs);
                    }
                    None => {}
                },
            }
        }
        Ok(())
    }

    async fn translate_browse_paths_to_node_ids(
        &self,
        context: &RequestContext,
        nodes: &mut [&mut BrowsePathItem],
    ) -> Result<(), StatusCode> {
        let tree = context.type_tree.read();
        for item in nodes.iter_mut() {
            if let Some(wanted) = item.unmatched_browse_name() {
                if self.browse_name(item.node_id()).as_ref() != Some(wanted) {
                    continue;
                }
                item.set_browse_name_matched(context.current_node_manager_index);
            }
            let mut at = item.node_id().clone();
            let mut found = Vec::new();
            for (depth, element) in item.path().iter().enumerate() {
                let Some(next) = self.step(&tree, &at, element) else {
                    break;
                };
                found.push((next.clone(), depth + 1));
                at = next;
            }
            for (node, depth) in found {
                item.add_element(node, depth, None);
            }
        }
        Ok(())
    }

    async fn read(
        &self,
        context: &RequestContext,
        _max_age: f64,
        timestamps_to_return: TimestampsToReturn,
        nodes_to_read: &mut [&mut ReadNode],
    ) -> Result<(), StatusCode> {
        // Per section: (node index, variable) to read from the PLC.
        let mut reads: Vec<(Arc<SectionNodes>, Vec<(usize, VarId)>)> = Vec::new();
        for (i, node) in nodes_to_read.iter_mut().enumerate() {
            let read = node.node();
            if read.attribute_id != AttributeId::Value && read.index_range != NumericRange::None {
                node.set_error(StatusCode::BadIndexRangeDataMismatch);
                continue;
            }
            if !matches!(read.data_encoding, DataEncoding::Binary) {
                node.set_error(StatusCode::BadDataEncodingInvalid);
                continue;
            }
            let variable = match self.shared.named(&read.node_id) {
                Some(Named::Variable(nodes, name)) if read.attribute_id == AttributeId::Value => {
                    Some((nodes, name))
                }
                _ => None,
            };
            let Some((section, name)) = variable else {
                let result = self.attribute(context, &read.node_id, read.attribute_id);
                match result {
                    Ok(value) => node.set_result(stamp(value, timestamps_to_return)),
                    Err(status) => node.set_error(status),
                }
                continue;
            };
            match self.read_value(&section, &name) {
                Some(Ours::Value(value)) => node.set_result(stamp(value, timestamps_to_return)),
                Some(Ours::Read(id)) => {
                    match reads.iter_mut().find(|(s, _)| Arc::ptr_eq(s, &section)) {
                        Some((_, wanted)) => wanted.push((i, id)),
                        None => reads.push((section, vec![(i, id)])),
                    }
                }
                None => node.set_error(StatusCode::BadNodeIdUnknown),
            }
        }
        for (nodes, wanted) in reads {
            let table = nodes.lock().table.clone();
            let requests = wanted
                .iter()
                .map(|&(_, id)| {
                    let var = table.var(id);
                    ReadRequest {
                        area: var.area,
                        offset: var.offset,
                        len: var.byte_len(),
                    }
                })
                .collect();
            let answers = match nodes.section.read(requests).await {
                Ok(Ok(answers)) => answers,
                // The link is down or failed: nothing read.
                _ => {
                    for &(i, _) in &wanted {
                        nodes_to_read[i].set_result(stamp(
                            bad(StatusCode::BadCommunicationError),
                            timestamps_to_return,
                        ));
                    }
                    continue;
                }
            };
            for (&(i, id), answer) in wanted.iter().zip(answers) {
                let var = table.var(id);
                let value = match answer {
                    Ok(bytes) => match convert::variant(var.ty, &var.decode(&bytes)) {
                        Some(value) => space::good_now(value),
                        None => bad(StatusCode::BadDataEncodingInvalid),
                    },
                    Err(_) => bad(StatusCode::BadNotReadable),
                };
                nodes_to_read[i].set_result(stamp(value, timestamps_to_return));
            }
        }
        Ok(())
    }

    async fn create_monitored_items(
        &self,
        context: &RequestContext,
        items: &mut [&mut CreateMonitoredItem],
    ) -> Result<(), StatusCode> {
        for item in items.iter_mut() {
            let node = item.item_to_monitor();
            let variable = match self.shared.named(&node.node_id) {
                Some(Named::Variable(nodes, name)) if node.attribute_id == AttributeId::Value => {
                    Some((nodes, name))
                }
                _ => None,
            };
            let Some((nodes, name)) = variable else {
                // Another attribute, or a property: its value as read now.
                match self.attribute(context, &node.node_id, node.attribute_id) {
                    Ok(value) => {
                        item.set_initial_value(value);
                        item.set_status(StatusCode::Good);
                    }
                    Err(StatusCode::BadAttributeIdInvalid) => item.set_status(StatusCode::Good),
                    Err(status) => item.set_status(status),
                }
                continue;
            };
            if item.monitoring_mode() == MonitoringMode::Disabled {
                self.disabled_set().insert(item.handle());
                item.set_status(StatusCode::Good);
                continue;
            }
            let snapshot = nodes.section.latest();
            let mut view = nodes.lock();
            let sampling = item.sampling_interval();
            self.shared.sampled(sampling);
            match watch(&mut view, &name, sampling) {
                Some(id) if Arc::ptr_eq(&view.table, &snapshot.table) => {
                    let stamp = view.stamp_of.get(&id).copied();
                    let value = space::data_value(&snapshot, id, stamp, nodes.section.format());
                    if let Some(w) = view.watched.get_mut(&id) {
                        w.seq = snapshot.slot(id).changed_seq;
                        w.quality = Some(snapshot.quality(id));
                    }
                    item.set_initial_value(space::notified(value));
                    item.set_status(StatusCode::Good);
                }
                Some(_) => item.set_status(StatusCode::Good),
                None => {
                    // Not a variable of this table (any more): nothing to watch.
                    unwatch(&mut view, &name);
                    item.set_status(StatusCode::BadNodeIdUnknown);
                }
            }
        }
        Ok(())
    }

    /// A sampling interval modified counts for giving held-back changes
    /// again (see View::enable).
    async fn modify_monitored_items(
        &self,
        _context: &RequestContext,
        items: &[&MonitoredItemUpdateRef],
    ) {
        for item in items {
            if item.attribute() != AttributeId::Value || !item.status_code().is_good() {
                continue;
            }
            let sampling = item.update().revised_sampling_interval;
            self.shared.sampled(sampling);
            let Some((nodes, name)) = self.shared.variable(item.node_id()) else {
                continue;
            };
            let view = &mut *nodes.lock();
            let Some(id) = view.id_of(&name) else {
                continue;
            };
            if let Some(watched) = view.watched.get_mut(&id) {
                watched.resample_ms = watched.resample_ms.max(sampling as f32);
            }
        }
    }

    async fn delete_monitored_items(&self, _context: &RequestContext, items: &[&MonitoredItemRef]) {
        for item in items {
            if item.attribute() != AttributeId::Value || self.disabled_set().remove(&item.handle())
            {
                continue;
            }
            if let Some((nodes, name)) = self.shared.variable(item.node_id()) {
                unwatch(&mut nodes.lock(), &name);
            }
        }
    }

    /// Disabled items stop keeping their variable in the poll, as DI: does;
    /// enabled again, they keep it again.
    async fn set_monitoring_mode(
        &self,
        _context: &RequestContext,
        mode: MonitoringMode,
        items: &[&MonitoredItemRef],
    ) {
        for item in items {
            if item.attribute() != AttributeId::Value {
                continue;
            }
            let Some((nodes, name)) = self.shared.variable(item.node_id()) else {
                continue;
            };
            let was_disabled = self.disabled_set().contains(&item.handle());
            let view = &mut nodes.lock();
            match (mode == MonitoringMode::Disabled, was_disabled) {
                (true, false) => {
                    self.disabled_set().insert(item.handle());
                    unwatch(view, &name);
                }
                (false, true) => {
                    self.disabled_set().remove(&item.handle());
                    // Counted by name even if this table lacks it: a
                    // later table may have it.
                    let resample = self.shared.resample_ms();
                    let _ = watch(view, &name, resample);
                }
                _ => {}
            }
        }
    }

    async fn write(
        &self,
        context: &RequestContext,
        nodes_to_write: &mut [&mut WriteNode],
    ) -> Result<(), StatusCode> {
        let writer = auth::may_write(&self.shared.users, &context.token);
        let mut pending = Vec::new();
        for (i, write) in nodes_to_write.iter_mut().enumerate() {
            match self.check_write(write, writer) {
                Ok((section, name, text)) => pending.push((i, section, name, text)),
                Err(status) => write.set_status(status),
            }
        }
        // Each write waits for the PLC's read-back (or its refusal) before
        // answering: a refused write is never applied later.
        let outcomes =
            futures::future::join_all(pending.into_iter().map(|(i, nodes, name, text)| {
                let section = nodes.section.clone();
                async move { (i, section.write(&name, &text).await) }
            }))
            .await;
        for (i, outcome) in outcomes {
            nodes_to_write[i].set_status(match outcome {
                Ok(_) => StatusCode::Good,
                Err(refusal) => convert::refusal(&refusal),
            });
        }
        Ok(())
    }

    async fn history_read_raw_modified(
        &self,
        context: &RequestContext,
        details: &ReadRawModifiedDetails,
        nodes: &mut [&mut HistoryNode],
        _timestamps_to_return: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        if details.is_read_modified {
            return Err(StatusCode::BadHistoryOperationUnsupported);
        }
        let Some(history) = self.shared.history.clone() else {
            return Err(StatusCode::BadHistoryOperationUnsupported);
        };
        let from = manager::time_ms(&details.start_time, i64::MIN);
        let to = manager::time_ms(&details.end_time, i64::MAX);
        let page = match details.num_values_per_node {
            0 => HISTORY_PAGE,
            n => (n as usize).min(HISTORY_PAGE),
        };
        let bounds = details.return_bounds;
        for node in nodes.iter_mut() {
            let status = self
                .history_node(context, &*history, node, (from, to), page, bounds)
                .await;
            node.set_status(status);
        }
        Ok(())
    }
}

impl Vars {
    /// Checks a write and makes its SET text: the node must be one of our
    /// variables, writable (BadNotWritable), by this user
    /// (BadUserAccessDenied), with a value of its type (BadTypeMismatch).
    fn check_write(&self, write: &WriteNode, writer: bool) -> Result<Checked, StatusCode> {
        let value = write.value();
        let (nodes, name) = match self.shared.named(&value.node_id) {
            Some(Named::Variable(nodes, name)) => (nodes, name),
            Some(Named::Property(nodes, name, prop)) => {
                return match Facts::of(&nodes.lock(), &name) {
                    Some(f) if f.has(prop) => Err(StatusCode::BadNotWritable),
                    _ => Err(StatusCode::BadNodeIdUnknown),
                };
            }
            _ => return Err(StatusCode::BadNodeIdUnknown),
        };
        let view = nodes.lock();
        let id = view.id_of(&name).ok_or(StatusCode::BadNodeIdUnknown)?;
        if value.attribute_id != AttributeId::Value || value.index_range.has_range() {
            return Err(StatusCode::BadNotWritable);
        }
        if !view.writable[id as usize] {
            return Err(StatusCode::BadNotWritable);
        }
        if !writer {
            return Err(StatusCode::BadUserAccessDenied);
        }
        let Some(variant) = value.value.value.as_ref() else {
            return Err(StatusCode::BadTypeMismatch);
        };
        let var = view.table.var(id);
        let opts = nodes.section.format();
        let text = convert::write_text(var.ty, variant, opts)?;
        // The tag file's range is the range a writer may set (EURange).
        if let Some(info) = var.info.as_deref() {
            let value = plccoms_protocol::value::Value::parse(var.ty, &text, opts)
                .map(|v| v.as_f64())
                .unwrap_or(f64::NAN);
            if info.min.is_some_and(|min| value < min) || info.max.is_some_and(|max| value > max) {
                return Err(StatusCode::BadOutOfRange);
            }
        }
        let name = var.name.to_vec();
        drop(view);
        Ok((nodes, name, text))
    }

    async fn history_node(
        &self,
        context: &RequestContext,
        history: &dyn plccoms_core::history_source::HistorySource,
        node: &mut HistoryNode,
        (from, to): (i64, i64),
        page: usize,
        bounds: bool,
    ) -> StatusCode {
        let (nodes, name) = match self.shared.named(node.node_id()) {
            Some(Named::Variable(nodes, name)) => (nodes, name),
            Some(Named::Property(..)) => return StatusCode::BadHistoryOperationUnsupported,
            _ => return StatusCode::BadNodeIdUnknown,
        };
        let Some(facts) = Facts::of(&nodes.lock(), &name) else {
            return StatusCode::BadNodeIdUnknown;
        };
        // As the stack's check of a node's user access level.
        let access = context.authenticator.effective_user_access_level(
            &context.token,
            facts.access,
            node.node_id(),
        );
        if !access.contains(AccessLevel::HISTORY_READ) {
            return StatusCode::BadUserAccessDenied;
        }
        let ty = facts.ty;
        // Oldest first; a range given backwards is read forwards.
        let (from, to) = (from.min(to), from.max(to));
        let cursor = match node.continuation_point() {
            None => Cursor {
                from_ms: from,
                skip: 0,
                to_ms: to,
            },
            Some(point) => match point.get::<Cursor>() {
                Some(cursor) if cursor.to_ms == to => *cursor,
                _ => return StatusCode::BadContinuationPointInvalid,
            },
        };
        let query = HistoryQuery {
            section: nodes.name.clone(),
            masks: vec![name.clone()],
            from_ms: cursor.from_ms,
            to_ms: to,
        };
        let mut stream = match history.samples(query) {
            Ok(stream) => stream,
            Err(_) => return StatusCode::BadHistoryOperationUnsupported,
        };
        let opts = nodes.section.format();
        let mut values = Vec::new();
        let find_bound = |from_ms: i64, to_ms: i64, first: bool| {
            let query = HistoryQuery {
                section: nodes.name.clone(),
                masks: vec![name.clone()],
                from_ms,
                to_ms,
            };
            manager::bound(history, query, &name, first)
        };
        // The bound before the start: on the first page only.
        if bounds && node.continuation_point().is_none() && from != i64::MIN {
            let found = find_bound(from.saturating_sub(BOUND_LOOKBACK_MS), from - 1, false).await;
            values.push(match found {
                Some(sample) => manager::history_value(&sample, ty, opts),
                None => manager::bound_not_found(from),
            });
        }
        let mut skip = cursor.skip;
        let mut last: Option<(i64, usize)> = None;
        let mut more = false;
        while let Some(row) = stream.next().await {
            let sample = match row {
                Ok(sample) => sample,
                Err(_) => {
                    values.push(bad(StatusCode::BadUnexpectedError));
                    break;
                }
            };
            let marker = sample.value.is_none();
            if !marker && *sample.name != *name {
                continue;
            }
            if sample.unix_ms == cursor.from_ms && skip > 0 {
                skip -= 1;
                continue;
            }
            if values.len() == page {
                more = true;
                break;
            }
            values.push(manager::history_value(&sample, ty, opts));
            last = Some(match last {
                Some((ms, n)) if ms == sample.unix_ms => (ms, n + 1),
                _ => (sample.unix_ms, 1),
            });
        }
        // The bound after the end: on the last page.
        if bounds && !more && to != i64::MAX {
            let found = find_bound(to + 1, to.saturating_add(BOUND_LOOKBACK_MS), true).await;
            values.push(match found {
                Some(sample) => manager::history_value(&sample, ty, opts),
                None => manager::bound_not_found(to),
            });
        }
        let next = match (more, last) {
            (true, Some((ms, n))) => Some(Cursor {
                from_ms: ms,
                // Values of that millisecond given before this page too.
                skip: if ms == cursor.from_ms {
                    n + cursor.skip
                } else {
                    n
                },
                to_ms: to,
            }),
            _ => None,
        };
        node.set_next_continuation_point(next.map(|c| ContinuationPoint::new(Box::new(c))));
        let empty = values.is_empty();
        node.set_result(HistoryData {
            data_values: Some(values),
        });
        if empty {
            StatusCode::GoodNoData
        } else {
            StatusCode::Good
        }
    }
}
