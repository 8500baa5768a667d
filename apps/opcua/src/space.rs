//! Our namespace: Objects / plccoms / <Section> / <Variable>. The root
//! folder and section objects are built into the stack's address space;
//! the variables are served from each section's variable table
//! ([`crate::vars`]), so a new table (a new public or tag file) shows at
//! once. Each section's [`View`]
//! says which variables are shown, which may be written, which the
//! historian records, and which monitored items watch, by name, so that a
//! new table keeps them.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, MutexGuard};

use opcua::nodes::{ObjectBuilder, VariableBuilder};
use opcua::server::address_space::AddressSpace;
use opcua::types::{
    DataValue, DateTime, LocalizedText, NodeId, ObjectTypeId, QualifiedName, StatusCode,
    VariableTypeId, Variant,
};
use plccoms_core::changes::Interest;
use plccoms_core::changes::{Quality, Snapshot};
use plccoms_core::section::Section;
use plccoms_core::vars::{VarId, VarTable};
use plccoms_protocol::cp1250;
use plccoms_protocol::value::Value;

use crate::convert;
use crate::ids;

/// A variable a monitored item watches: what was last given to the stack.
///
/// One per monitored variable (100,000 with a SCADA's items): kept small,
/// its NodeId made when a change is given (a change is rarer than a
/// variable watched).
#[derive(Debug, Clone)]
pub struct Watched {
    /// Its monitored items, over every session.
    pub count: u32,
    /// `changed_seq` of the value given, and its quality.
    pub seq: u64,
    pub quality: Option<Quality>,
    /// The longest sampling interval of its monitored items (ms), and when
    /// its last change is to be given again (see [`View::enable`]).
    pub resample_ms: f32,
    pub due: Option<std::time::Instant>,
}

/// One section's part of the address space.
pub struct View {
    /// The table the nodes were built from.
    pub table: Arc<VarTable>,
    /// Its interest (what the poll reads).
    pub interest: Arc<Interest>,
    /// Per variable of `table`: shown, writable (OPCUA_WRITE), recorded.
    pub shown: Vec<bool>,
    pub writable: Vec<bool>,
    pub historized: Vec<bool>,
    /// The monitored variables of `table`, in order (the feed walks them a
    /// slice at a time).
    pub watched: BTreeMap<VarId, Watched>,
    /// Monitored items on names `table` lacks (a later table may have
    /// them), over every session.
    pub absent: HashMap<String, u32>,
    /// Last link state and poll shown on the section object.
    pub link_shown: Option<(&'static str, i64)>,
    /// HISTORY_STAMP: value variable -> the variable holding the PLC's time
    /// of it (its SourceTimestamp).
    pub stamp_of: HashMap<VarId, VarId>,
}

pub struct SectionNodes {
    pub section: Arc<Section>,
    pub name: String,
    pub view: Mutex<View>,
}

impl SectionNodes {
    pub fn lock(&self) -> MutexGuard<'_, View> {
        self.view.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The sections served now, in configuration order.
pub type NodesList = Arc<[Arc<SectionNodes>]>;

/// What the node manager, the feed tasks and the authenticator share.
pub struct Shared {
    pub ns: std::sync::OnceLock<u16>,
    /// Replaced whole by a reload (under the address space's write lock,
    /// taken first), so a service sees one list throughout.
    sections: std::sync::RwLock<NodesList>,
    /// Monitored item counts of removed sections, by section name: items
    /// outlive their nodes, and a section of that name added back later
    /// enables their variables again.
    orphans: Mutex<HashMap<String, HashMap<String, u32>>>,
    pub history: Option<Arc<dyn plccoms_core::history_source::HistorySource>>,
    pub users: Arc<crate::users::Users>,
    /// The longest sampling interval of any monitored item made (ms, as
    /// f64 bits): the [`View::enable`] interval of items whose own is not
    /// known (after a new table or a reload).
    resample_ms: std::sync::atomic::AtomicU64,
}

impl SectionNodes {
    pub fn new(section: &Arc<Section>, recorded: bool) -> SectionNodes {
        let snapshot = section.latest();
        SectionNodes {
            section: section.clone(),
            name: section.name().to_string(),
            view: Mutex::new(View::new(section, &snapshot, recorded)),
        }
    }

    /// Takes over monitored item counts by variable name (from the section
    /// this one replaces, or one removed earlier), enabling what its
    /// table has.
    pub fn adopt(&self, shared: &Shared, monitored: HashMap<String, u32>) {
        self.lock().adopt(monitored, shared.resample_ms());
    }
}

impl Shared {
    pub fn new(
        sections: &[Arc<Section>],
        history: Option<Arc<dyn plccoms_core::history_source::HistorySource>>,
        users: Arc<crate::users::Users>,
    ) -> Shared {
        let sections: Vec<Arc<SectionNodes>> = sections
            .iter()
            .map(|section| Arc::new(SectionNodes::new(section, history.is_some())))
            .collect();
        Shared {
            ns: Default::default(),
            sections: std::sync::RwLock::new(sections.into()),
            orphans: Default::default(),
            history,
            users,
            resample_ms: Default::default(),
        }
    }

    /// The sections served now.
    pub fn list(&self) -> NodesList {
        self.sections
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Serves `list` from now on.
    pub fn set_list(&self, list: Vec<Arc<SectionNodes>>) {
        *self.sections.write().unwrap_or_else(|p| p.into_inner()) = list.into();
    }

    /// Keeps the monitored item counts of a removed section.
    pub fn orphan(&self, name: &str, monitored: HashMap<String, u32>) {
        if monitored.is_empty() {
            return;
        }
        self.orphans
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(name.to_string(), monitored);
    }

    /// The counts kept for a section named `name`, taken.
    pub fn adopt_orphans(&self, name: &str) -> HashMap<String, u32> {
        self.orphans
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(name)
            .unwrap_or_default()
    }

    /// See the field.
    pub fn resample_ms(&self) -> f64 {
        f64::from_bits(self.resample_ms.load(std::sync::atomic::Ordering::Relaxed))
    }

    /// A monitored item of sampling interval `ms` made.
    pub fn sampled(&self, ms: f64) {
        // Positive f64s order as their bits.
        if ms > 0.0 && ms.is_finite() {
            self.resample_ms
                .fetch_max(ms.to_bits(), std::sync::atomic::Ordering::Relaxed);
        }
    }

    pub fn ns(&self) -> u16 {
        self.ns.get().copied().unwrap_or(0)
    }

    pub fn node(&self, text: String) -> NodeId {
        NodeId::new(self.ns(), text)
    }
}

/// A variable's name as shown (UTF-8): borrowed where it is ASCII (the
/// feed makes one for every change it gives).
pub fn shown_name(table: &VarTable, id: VarId) -> std::borrow::Cow<'_, str> {
    cp1250::decode(&table.var(id).name)
}

impl View {
    pub fn new(section: &Section, snapshot: &Snapshot, recorded: bool) -> View {
        let mut view = View {
            table: snapshot.table.clone(),
            interest: snapshot.interest.clone(),
            shown: Vec::new(),
            writable: Vec::new(),
            historized: Vec::new(),
            absent: HashMap::new(),
            watched: BTreeMap::new(),
            link_shown: None,
            stamp_of: HashMap::new(),
        };
        view.classify(section, recorded);
        view
    }

    /// A shown variable by its name as shown (exactly; the table's own
    /// index, so no map of names is kept per view).
    pub fn id_of(&self, name: &str) -> Option<VarId> {
        let encoded;
        let bytes: &[u8] = if name.is_ascii() {
            name.as_bytes()
        } else {
            encoded = cp1250::try_encode(name)?;
            &encoded
        };
        let id = self.table.lookup(bytes)?;
        (self.shown[id as usize] && *self.table.var(id).name == *bytes).then_some(id)
    }

    /// The shown variables, in the table's order.
    pub fn shown_ids(&self) -> impl Iterator<Item = VarId> + '_ {
        (0..self.table.len() as VarId).filter(|&id| self.shown[id as usize])
    }

    /// Enables `id` in the poll (with its HISTORY_STAMP variable) and hands
    /// its changes to its monitored items.
    ///
    /// `resample_ms`: the longest sampling interval of those items. The
    /// stack holds back a change that comes sooner than that after the last
    /// one reported (moving its SourceTimestamp to the interval's end), and
    /// reports it only when it looks at the item again, which it does on
    /// the item's next change (async-opcua 0.19 drops the item from its
    /// list of items to look at on the publish before that end): a last
    /// change would never arrive. The feed gives such a change again one
    /// interval after it, which makes the stack report it.
    ///
    /// `count`: the monitored items it gains.
    pub fn enable(&mut self, id: VarId, resample_ms: f64, count: u32) {
        if let Some(watched) = self.watched.get_mut(&id) {
            watched.count += count;
            watched.resample_ms = watched.resample_ms.max(resample_ms as f32);
            return;
        }
        for enabled in [Some(id), self.stamp_of.get(&id).copied()]
            .into_iter()
            .flatten()
        {
            if !self.table.is_fixed(enabled) {
                self.interest.add(enabled);
            }
        }
        self.watched.insert(
            id,
            Watched {
                count,
                seq: u64::MAX,
                quality: None,
                resample_ms: resample_ms as f32,
                due: None,
            },
        );
    }

    /// The monitored item counts by variable name, taken (for a new
    /// table, or a section of this name added later).
    pub fn take_monitored(&mut self) -> HashMap<String, u32> {
        let mut names = std::mem::take(&mut self.absent);
        for (id, watched) in std::mem::take(&mut self.watched) {
            *names
                .entry(shown_name(&self.table, id).into_owned())
                .or_default() += watched.count;
        }
        names
    }

    /// Takes over monitored item counts by name, enabling what the table
    /// has.
    pub fn adopt(&mut self, monitored: HashMap<String, u32>, resample_ms: f64) {
        for (name, count) in monitored {
            match self.id_of(&name) {
                Some(id) => self.enable(id, resample_ms, count),
                None => *self.absent.entry(name).or_default() += count,
            }
        }
    }

    /// Undoes [`View::enable`].
    pub fn disable(&mut self, id: VarId) {
        if self.watched.remove(&id).is_none() {
            return;
        }
        for enabled in [Some(id), self.stamp_of.get(&id).copied()]
            .into_iter()
            .flatten()
        {
            if !self.table.is_fixed(enabled) {
                self.interest.remove(enabled);
            }
        }
    }

    /// Which variables of `self.table` are shown, writable and recorded.
    fn classify(&mut self, section: &Section, recorded: bool) {
        let config = section.state().config.clone();
        let table = &self.table;
        let len = table.len();
        let mark = |ids: Vec<VarId>| {
            let mut marks = vec![false; len];
            for id in ids {
                marks[id as usize] = true;
            }
            marks
        };
        self.shown = match &config.opcua.publish {
            None => vec![true; len],
            Some(masks) => mark(table.matching_names(masks)),
        };
        let writable = mark(table.matching_names(&config.opcua.write));
        self.writable = (0..len)
            .map(|i| {
                writable[i] && self.shown[i] && !config.read_only && table.var(i as VarId).writable
            })
            .collect();
        self.historized = if recorded && config.history.enabled() {
            mark(table.matching(&config.history.masks))
        } else {
            vec![false; len]
        };
        self.stamp_of = config
            .history
            .stamps
            .iter()
            .filter_map(|pair| {
                let value = table.lookup(pair.value.as_bytes())?;
                let stamp = table.lookup(pair.stamp.as_bytes())?;
                use plccoms_protocol::IecType::*;
                matches!(table.var(stamp).ty, Dt | Date | Lint | Ulint | Lword)
                    .then_some((value, stamp))
            })
            .collect();
    }
}

/// Builds the root folder (at start).
pub fn build_root(space: &mut AddressSpace, ns: u16) {
    let root = NodeId::new(ns, ids::ROOT);
    ObjectBuilder::new(
        &root,
        QualifiedName::new(ns, ids::ROOT),
        LocalizedText::from(ids::ROOT),
    )
    .description("Every PLC section of this plccoms server")
    .organized_by(NodeId::objects_folder_id())
    .has_type_definition(ObjectTypeId::FolderType)
    .insert(space);
}

/// Builds one section's object and its properties (its variables are
/// served by [`crate::vars::Vars`], from its table).
pub fn build_section(space: &mut AddressSpace, shared: &Shared, nodes: &SectionNodes) {
    let ns = shared.ns();
    let name = &nodes.name;
    let section_id = NodeId::new(ns, name.as_str());
    if space.find(&section_id).is_some() {
        return;
    }
    ObjectBuilder::new(
        &section_id,
        QualifiedName::new(ns, name.as_str()),
        LocalizedText::from(name.as_str()),
    )
    .description(format!("PLC section [{name}]"))
    .organized_by(NodeId::new(ns, ids::ROOT))
    .has_type_definition(ObjectTypeId::BaseObjectType)
    .insert(space);
    let protocol = nodes.section.state().config.protocol.to_string();
    for (property, value, ty) in [
        (
            "LinkState",
            Variant::from(""),
            opcua::types::DataTypeId::String,
        ),
        (
            "LastPoll",
            Variant::Empty,
            opcua::types::DataTypeId::DateTime,
        ),
        (
            "Backend",
            Variant::from(protocol.as_str()),
            opcua::types::DataTypeId::String,
        ),
    ] {
        let id = NodeId::new(ns, ids::property(name, property));
        VariableBuilder::new(
            &id,
            QualifiedName::new(ns, property),
            LocalizedText::from(property),
        )
        .data_type(ty)
        .value(value)
        .property_of(section_id.clone())
        .has_type_definition(VariableTypeId::PropertyType)
        .insert(space);
    }
}

/// Removes a section's object and its properties; the NodeIds removed
/// with those of the variables of `view`, for their monitored items.
pub fn remove_section(space: &mut AddressSpace, ns: u16, name: &str, view: &View) -> Vec<NodeId> {
    let mut gone: Vec<NodeId> = view
        .shown_ids()
        .map(|id| NodeId::new(ns, ids::variable(name, &shown_name(&view.table, id))))
        .collect();
    for property in SECTION_PROPERTIES {
        let id = NodeId::new(ns, ids::property(name, property));
        space.delete(&id, true);
        gone.push(id);
    }
    space.delete(&NodeId::new(ns, name), true);
    gone
}

/// The properties of a section object.
const SECTION_PROPERTIES: [&str; 3] = ["LinkState", "LastPoll", "Backend"];

/// The DataValue of variable `id` in `snapshot` (its value as last known,
/// its quality as StatusCode, as SourceTimestamp the PLC's time from its
/// HISTORY_STAMP variable `stamp` if it has one, else the poll's time).
pub fn data_value(
    snapshot: &Snapshot,
    id: VarId,
    stamp: Option<VarId>,
    opts: &plccoms_protocol::value::FormatOptions,
) -> DataValue {
    data_value_at(snapshot, id, stamp, opts, DateTime::now())
}

/// [`data_value`] with `now` as its ServerTimestamp: the feed's changes of
/// one walk share one (the clock read and converted for each of 100,000
/// was 3.5 % of the serving side's CPU).
pub fn data_value_at(
    snapshot: &Snapshot,
    id: VarId,
    stamp: Option<VarId>,
    opts: &plccoms_protocol::value::FormatOptions,
    now: DateTime,
) -> DataValue {
    let slot = snapshot.slot(id);
    let var = snapshot.table.var(id);
    let Some(text) = slot.text() else {
        return DataValue {
            value: None,
            status: Some(if snapshot.online {
                StatusCode::BadWaitingForInitialData
            } else {
                StatusCode::BadNoCommunication
            }),
            source_timestamp: None,
            source_picoseconds: None,
            server_timestamp: Some(now),
            server_picoseconds: None,
        };
    };
    let (value, status) = match convert::variant_of_text(var.ty, text, opts) {
        Some(v) => (Some(v), convert::status(snapshot.quality(id))),
        None => (None, StatusCode::BadDataEncodingInvalid),
    };
    let plc_ms =
        stamp.and_then(
            |stamp| match snapshot.slot(stamp).value(snapshot.table.var(stamp))? {
                Value::Date(secs) if secs.is_finite() => Some((secs * 1000.0).round() as i64),
                Value::Signed(ms) => Some(ms),
                Value::Unsigned(ms) => i64::try_from(ms).ok(),
                _ => None,
            },
        );
    let source_ms = plc_ms.unwrap_or(slot.changed_ms);
    DataValue {
        value,
        status: Some(status),
        source_timestamp: chrono::DateTime::from_timestamp_millis(source_ms).map(DateTime::from),
        source_picoseconds: None,
        server_timestamp: Some(now),
        server_picoseconds: None,
    }
}

/// `value` as monitored items get it: a Bad one without its value (Part 4,
/// DataValue: a Server sets the value of a Bad DataValue to null), which
/// is also what makes async-opcua 0.19 report a lost link to an item
/// without a DataChangeFilter: it compares only the values of those, not
/// the statuses (Part 4's default trigger is StatusValue). Read keeps the
/// last value with its Bad status. A value-less one gets an empty Variant:
/// the stack hands items the node's value as read back, which drops the
/// status of a value-less one (a variable not read yet would reach them as
/// Good).
pub fn notified(mut value: DataValue) -> DataValue {
    if value.status.is_some_and(|s| s.is_bad()) {
        value.value = Some(Variant::Empty);
    }
    value.value.get_or_insert(Variant::Empty);
    value
}

/// A good value read now.
pub fn good_now(value: Variant) -> DataValue {
    let now = DateTime::now();
    DataValue {
        value: Some(value),
        status: Some(StatusCode::Good),
        source_timestamp: Some(now),
        source_picoseconds: None,
        server_timestamp: Some(now),
        server_picoseconds: None,
    }
}
