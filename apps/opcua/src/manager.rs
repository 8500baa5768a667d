//! Our node manager: the stack's in-memory address space for browsing and
//! the attributes, with the services that touch the PLC done here: Read of
//! a value (the poll's, else a read from the PLC as GET does), Write
//! through the core's one write path, monitored items that enable their
//! variable in the poll as EN does, and HistoryRead from the historian.

use std::collections::HashSet;
use std::sync::Arc;

use async_trait::async_trait;
use futures::StreamExt;
use opcua::core::sync::RwLock;
use opcua::server::address_space::{AccessLevel, AddressSpace};
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{
    InMemoryNodeManagerImpl, InMemoryNodeManagerImplBuilder,
};
use opcua::server::node_manager::{
    HistoryNode, MonitoredItemRef, MonitoredItemUpdateRef, ParsedReadValueId, RequestContext,
    ServerContext, WriteNode,
};
use opcua::server::{ContinuationPoint, CreateMonitoredItem, MonitoredItemHandle};
use opcua::types::{
    AttributeId, DataValue, DateTime, HistoryData, MonitoringMode, ReadRawModifiedDetails,
    StatusCode, TimestampsToReturn,
};
use plccoms_core::driver::ReadRequest;
use plccoms_core::history_source::{HistoryQuery, RowQuality};
use plccoms_core::present;
use plccoms_core::vars::VarId;

use crate::auth;
use crate::convert;
use crate::space::{self, SectionNodes, Shared, View};

/// Our namespace's URI.
pub const NAMESPACE: &str = "urn:plccoms";

/// Most values one HistoryRead returns per node, whatever the client asks:
/// past it, a continuation point.
pub const HISTORY_PAGE: usize = 10_000;

pub struct Builder {
    pub shared: Arc<Shared>,
    pub loop_delay_ms: f64,
}

impl InMemoryNodeManagerImplBuilder for Builder {
    type Impl = Manager;

    fn build(self, context: ServerContext, space: &mut AddressSpace) -> Manager {
        let ns = context
            .type_tree
            .write()
            .namespaces_mut()
            .add_namespace(NAMESPACE);
        space.add_namespace(NAMESPACE, ns);
        let _ = self.shared.ns.set(ns);
        space::build_root(space, ns);
        for nodes in self.shared.list().iter() {
            let view = nodes.lock();
            space::build_section(space, &self.shared, nodes, None, &view, self.loop_delay_ms);
        }
        Manager {
            shared: self.shared,
            ns,
            disabled: Default::default(),
        }
    }
}

pub struct Manager {
    pub shared: Arc<Shared>,
    ns: u16,
    /// Monitored items of ours in MonitoringMode Disabled: they do not
    /// keep their variable enabled in the poll.
    disabled: std::sync::Mutex<HashSet<MonitoredItemHandle>>,
}

/// Where a HistoryRead stopped: the time of the last value returned and
/// how many values of that millisecond were returned (several samples may
/// share one). Kept by the stack, per session; never parsed from a client.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cursor {
    pub from_ms: i64,
    pub skip: usize,
    /// The request's end, so a continuation of another range is refused.
    pub to_ms: i64,
}

impl Manager {
    fn disabled_set(&self) -> std::sync::MutexGuard<'_, HashSet<MonitoredItemHandle>> {
        self.disabled.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn read_ours(&self, node: &ParsedReadValueId) -> Option<(Arc<SectionNodes>, VarId, Ours)> {
        if node.attribute_id != AttributeId::Value {
            return None;
        }
        let (nodes, name) = self.shared.variable(&node.node_id)?;
        let snapshot = nodes.section.latest();
        let view = nodes.lock();
        let &id = view.by_name.get(&name)?;
        if !Arc::ptr_eq(&view.table, &snapshot.table) {
            return None;
        }
        let now = tokio::time::Instant::now();
        // The poll's value while it is fresh; the last value with its bad
        // quality while the link is lost; else a read, as GET makes one.
        if snapshot.fresh(id, now).is_some() || !snapshot.online || view.table.is_fixed(id) {
            let stamp = view.stamp_of.get(&id).copied();
            let value = space::data_value(&snapshot, id, stamp, nodes.section.format());
            drop(view);
            return Some((nodes, id, Ours::Value(value)));
        }
        drop(view);
        Some((nodes, id, Ours::Read))
    }
}

/// A write checked: its section, the variable's name and the SET text.
type Checked = (Arc<SectionNodes>, Vec<u8>, Vec<u8>);

enum Ours {
    Value(DataValue),
    Read,
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

/// A value-less DataValue of `status`, stamped now.
pub(crate) fn bad(status: StatusCode) -> DataValue {
    DataValue {
        value: None,
        status: Some(status),
        source_timestamp: None,
        source_picoseconds: None,
        server_timestamp: Some(DateTime::now()),
        server_picoseconds: None,
    }
}

#[async_trait]
impl InMemoryNodeManagerImpl for Manager {
    async fn init(&self, _space: &mut AddressSpace, _context: ServerContext) {}

    fn name(&self) -> &str {
        "plccoms"
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        vec![NamespaceMetadata {
            namespace_uri: NAMESPACE.to_string(),
            namespace_index: self.ns,
            ..Default::default()
        }]
    }

    async fn read_values(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        nodes: &[&ParsedReadValueId],
        max_age: f64,
        timestamps_to_return: TimestampsToReturn,
    ) -> Vec<DataValue> {
        let mut results: Vec<Option<DataValue>> = vec![None; nodes.len()];
        // Per section: (result index, variable) to read from the PLC.
        let mut reads: Vec<(Arc<SectionNodes>, Vec<(usize, VarId)>)> = Vec::new();
        let mut from_space = Vec::new();
        for (i, node) in nodes.iter().enumerate() {
            match self.read_ours(node) {
                Some((_, _, Ours::Value(value))) => results[i] = Some(value),
                Some((section, id, Ours::Read)) => {
                    match reads.iter_mut().find(|(s, _)| Arc::ptr_eq(s, &section)) {
                        Some((_, wanted)) => wanted.push((i, id)),
                        None => reads.push((section, vec![(i, id)])),
                    }
                }
                None => from_space.push(i),
            }
        }
        if !from_space.is_empty() {
            let space = address_space.read();
            for i in from_space {
                results[i] = Some(space.read(context, nodes[i], max_age, timestamps_to_return));
            }
        }
        for (nodes, wanted) in reads {
            let table = nodes.section.latest().table.clone();
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
            let reply = nodes.section.read(requests).await;
            let answers = match reply {
                Ok(Ok(answers)) => answers,
                // The link is down or failed: nothing read.
                _ => {
                    for &(i, _) in &wanted {
                        results[i] = Some(bad(StatusCode::BadCommunicationError));
                    }
                    continue;
                }
            };
            for (&(i, id), answer) in wanted.iter().zip(answers) {
                let var = table.var(id);
                results[i] = Some(match answer {
                    Ok(bytes) => match convert::variant(var.ty, &var.decode(&bytes)) {
                        Some(value) => space::good_now(value),
                        None => bad(StatusCode::BadDataEncodingInvalid),
                    },
                    Err(_) => bad(StatusCode::BadNotReadable),
                });
            }
        }
        results
            .into_iter()
            .map(|v| {
                stamp(
                    v.unwrap_or_else(|| bad(StatusCode::BadInternalError)),
                    timestamps_to_return,
                )
            })
            .collect()
    }

    async fn create_value_monitored_items(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        items: &mut [&mut &mut CreateMonitoredItem],
    ) {
        let mut rest = Vec::new();
        for (i, item) in items.iter_mut().enumerate() {
            let node = item.item_to_monitor();
            let Some((nodes, name)) = (node.attribute_id == AttributeId::Value)
                .then(|| self.shared.variable(&node.node_id))
                .flatten()
            else {
                rest.push(i);
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
        if !rest.is_empty() {
            let space = address_space.read();
            for i in rest {
                let value = space.read(
                    context,
                    items[i].item_to_monitor(),
                    0.0,
                    TimestampsToReturn::Both,
                );
                if value.status() != StatusCode::BadAttributeIdInvalid {
                    items[i].set_initial_value(value);
                }
                items[i].set_status(StatusCode::Good);
            }
        }
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
            let Some(&id) = view.by_name.get(&name) else {
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
        address_space: &RwLock<AddressSpace>,
        nodes_to_write: &mut [&mut WriteNode],
    ) -> Result<(), StatusCode> {
        let writer = auth::may_write(&self.shared.users, &context.token);
        let mut pending = Vec::new();
        {
            let space = address_space.read();
            for (i, write) in nodes_to_write.iter_mut().enumerate() {
                match self.check_write(&space, write, writer) {
                    Ok((section, name, text)) => pending.push((i, section, name, text)),
                    Err(status) => write.set_status(status),
                }
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
        _context: &RequestContext,
        details: &ReadRawModifiedDetails,
        nodes: &mut [&mut &mut HistoryNode],
        _timestamps_to_return: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        if details.is_read_modified {
            return Err(StatusCode::BadHistoryOperationUnsupported);
        }
        let Some(history) = self.shared.history.clone() else {
            return Err(StatusCode::BadHistoryOperationUnsupported);
        };
        let from = time_ms(&details.start_time, i64::MIN);
        let to = time_ms(&details.end_time, i64::MAX);
        let page = match details.num_values_per_node {
            0 => HISTORY_PAGE,
            n => (n as usize).min(HISTORY_PAGE),
        };
        let bounds = details.return_bounds;
        for node in nodes.iter_mut() {
            let status = self
                .history_node(&*history, node, (from, to), page, bounds)
                .await;
            node.set_status(status);
        }
        Ok(())
    }
}

/// UTC milliseconds of an OPC UA time; `unset` for a null one.
fn time_ms(time: &DateTime, unset: i64) -> i64 {
    if time.is_null() {
        unset
    } else {
        time.as_chrono().timestamp_millis()
    }
}

impl Manager {
    /// Checks a write and makes its SET text: the node must be one of our
    /// variables, writable (BadNotWritable), by this user
    /// (BadUserAccessDenied), with a value of its type (BadTypeMismatch).
    fn check_write(
        &self,
        space: &AddressSpace,
        write: &WriteNode,
        writer: bool,
    ) -> Result<Checked, StatusCode> {
        let value = write.value();
        let Some(node) = space.find(&value.node_id) else {
            return Err(StatusCode::BadNodeIdUnknown);
        };
        let Some((nodes, name)) = self.shared.variable(&value.node_id) else {
            return Err(StatusCode::BadNotWritable);
        };
        let opcua::server::address_space::NodeType::Variable(variable) = node else {
            return Err(StatusCode::BadNotWritable);
        };
        if value.attribute_id != AttributeId::Value || value.index_range.has_range() {
            return Err(StatusCode::BadNotWritable);
        }
        if !variable.access_level().contains(AccessLevel::CURRENT_WRITE) {
            return Err(StatusCode::BadNotWritable);
        }
        if !writer {
            return Err(StatusCode::BadUserAccessDenied);
        }
        let Some(variant) = value.value.value.as_ref() else {
            return Err(StatusCode::BadTypeMismatch);
        };
        let view = nodes.lock();
        let &id = view
            .by_name
            .get(&name)
            .ok_or(StatusCode::BadNodeIdUnknown)?;
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
        history: &dyn plccoms_core::history_source::HistorySource,
        node: &mut HistoryNode,
        (from, to): (i64, i64),
        page: usize,
        bounds: bool,
    ) -> StatusCode {
        let Some((nodes, name)) = self.shared.variable(node.node_id()) else {
            return StatusCode::BadNodeIdUnknown;
        };
        let (ty, recorded) = {
            let view = nodes.lock();
            match view.by_name.get(&name) {
                Some(&id) => (view.table.var(id).ty, view.historized[id as usize]),
                None => return StatusCode::BadNodeIdUnknown,
            }
        };
        if !recorded {
            return StatusCode::BadHistoryOperationUnsupported;
        }
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
            bound(history, query, &name, first)
        };
        // The bound before the start: on the first page only.
        if bounds && node.continuation_point().is_none() && from != i64::MIN {
            let found = find_bound(from.saturating_sub(BOUND_LOOKBACK_MS), from - 1, false).await;
            values.push(match found {
                Some(sample) => history_value(&sample, ty, opts),
                None => bound_not_found(from),
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
            values.push(history_value(&sample, ty, opts));
            last = Some(match last {
                Some((ms, n)) if ms == sample.unix_ms => (ms, n + 1),
                _ => (sample.unix_ms, 1),
            });
        }
        // The bound after the end: on the last page.
        if bounds && !more && to != i64::MAX {
            let found = find_bound(to + 1, to.saturating_add(BOUND_LOOKBACK_MS), true).await;
            values.push(match found {
                Some(sample) => history_value(&sample, ty, opts),
                None => bound_not_found(to),
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

/// A history row as a DataValue: its value with the row's quality as
/// StatusCode; a marker row (an outage, the server stopped, a gap) without
/// a value, Bad.
fn history_value(
    sample: &plccoms_core::history_source::Sample,
    ty: plccoms_protocol::IecType,
    opts: &plccoms_protocol::value::FormatOptions,
) -> DataValue {
    let source = chrono::DateTime::from_timestamp_millis(sample.unix_ms).map(DateTime::from);
    let value = sample.value.as_ref().and_then(|p| {
        let user = p.text();
        let text = present::protocol_text(ty, user.as_bytes(), opts).ok()?;
        convert::variant_of_text(ty, &text, opts)
    });
    let status = match sample.quality {
        RowQuality::Good => StatusCode::Good,
        RowQuality::Stale => StatusCode::UncertainLastUsableValue,
        RowQuality::LinkLost => StatusCode::BadNoCommunication,
        RowQuality::Stopped => StatusCode::BadOutOfService,
        RowQuality::Damaged | RowQuality::Missed => StatusCode::BadDataLost,
        RowQuality::Error => StatusCode::BadUnexpectedError,
    };
    DataValue {
        status: Some(if value.is_none() && status.is_good() {
            StatusCode::BadDataEncodingInvalid
        } else {
            status
        }),
        value,
        source_timestamp: source,
        source_picoseconds: None,
        server_timestamp: source,
        server_picoseconds: None,
    }
}

/// The first (`first`) or last sample of `name` in `query`'s range.
async fn bound(
    history: &dyn plccoms_core::history_source::HistorySource,
    query: HistoryQuery,
    name: &str,
    first: bool,
) -> Option<plccoms_core::history_source::Sample> {
    let mut stream = history.samples(query).ok()?;
    let mut found = None;
    while let Some(Ok(sample)) = stream.next().await {
        if sample.value.is_some() && *sample.name != *name {
            continue;
        }
        found = Some(sample);
        if first {
            break;
        }
    }
    found
}

/// A bound with no sample within [`BOUND_LOOKBACK_MS`].
fn bound_not_found(at_ms: i64) -> DataValue {
    let at = chrono::DateTime::from_timestamp_millis(at_ms).map(DateTime::from);
    DataValue {
        value: None,
        status: Some(StatusCode::BadBoundNotFound),
        source_timestamp: at,
        source_picoseconds: None,
        server_timestamp: at,
        server_picoseconds: None,
    }
}

/// How far before the start and after the end a bound is looked for.
pub const BOUND_LOOKBACK_MS: i64 = 24 * 3_600_000;

/// One more monitored item on `name`, of sampling interval `sampling_ms`:
/// the first enables it in the poll. The variable's id in the view's
/// table, if it has it.
pub fn watch(view: &mut View, name: &str, sampling_ms: f64) -> Option<VarId> {
    let count = view.monitored.entry(name.to_string()).or_default();
    *count += 1;
    let first = *count == 1;
    let &id = view.by_name.get(name)?;
    if first {
        view.enable(id, sampling_ms);
    } else if let Some(watched) = view.watched.get_mut(&id) {
        watched.resample_ms = watched.resample_ms.max(sampling_ms as f32);
    }
    Some(id)
}

/// One monitored item fewer on `name`: the last disables it.
pub fn unwatch(view: &mut View, name: &str) {
    let Some(count) = view.monitored.get_mut(name) else {
        return;
    };
    *count -= 1;
    if *count > 0 {
        return;
    }
    view.monitored.remove(name);
    if let Some(&id) = view.by_name.get(name) {
        view.disable(id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::changes::Interest;
    use plccoms_core::vars::table_of;

    fn view() -> View {
        let table = Arc::new(table_of(&[("A", "INT"), ("B", "REAL")]));
        let by_name = (0..table.len() as VarId)
            .map(|id| (space::shown_name(&table, id), id))
            .collect();
        View {
            interest: Arc::new(Interest::new(table.len())),
            shown: vec![true; table.len()],
            writable: vec![false; table.len()],
            historized: vec![false; table.len()],
            table,
            by_name,
            monitored: Default::default(),
            watched: Default::default(),
            link_shown: None,
            stamp_of: Default::default(),
        }
    }

    /// As EN: the first monitored item enables the variable in the poll,
    /// the last to go disables it.
    #[test]
    fn monitored_items_enable_their_variable_until_the_last_goes() {
        let mut view = view();
        let a = view.table.lookup(b"A").unwrap();
        assert_eq!(watch(&mut view, "A", 0.0), Some(a));
        assert_eq!(watch(&mut view, "A", 0.0), Some(a));
        assert!(view.interest.is_wanted(a));
        unwatch(&mut view, "A");
        assert!(view.interest.is_wanted(a));
        assert!(view.watched.contains_key(&a));
        unwatch(&mut view, "A");
        assert!(!view.interest.is_wanted(a));
        assert!(view.watched.is_empty() && view.monitored.is_empty());
        // A name the table lacks is counted, and enables nothing.
        assert_eq!(watch(&mut view, "GONE", 0.0), None);
        assert_eq!(view.monitored.get("GONE"), Some(&1));
        unwatch(&mut view, "GONE");
        assert!(view.monitored.is_empty());
        // More removals than items are harmless.
        unwatch(&mut view, "A");
        assert!(!view.interest.is_wanted(a));
    }
}
