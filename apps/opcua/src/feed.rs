//! One task per section: each new snapshot of the change stream gives the
//! stack the values of the monitored variables that changed (value or
//! quality), which it hands to every monitored item on them through its
//! filters (deadbands) and queues; a new variable table is served at once
//! (a new view), keeping every monitored item's variable enabled.

use std::sync::Arc;
use std::time::Duration;

use opcua::server::node_manager::memory::InMemoryNodeManager;
use opcua::server::SubscriptionCache;
use opcua::types::{AttributeId, DataValue, DateTime, NodeId, Variant};
use tokio_util::sync::CancellationToken;
use tracing::info;

use plccoms_core::changes::Snapshot;
use plccoms_core::vars::VarId;

use crate::ids;
use crate::manager::Manager;
use crate::space::{self, SectionNodes, Shared, View};

pub struct Feed {
    pub shared: Arc<Shared>,
    pub nodes: Arc<SectionNodes>,
    pub manager: Arc<InMemoryNodeManager<Manager>>,
    pub subscriptions: Arc<SubscriptionCache>,
    pub stop: CancellationToken,
}

impl Feed {
    pub async fn run(self) {
        let nodes = &self.nodes;
        let mut rx = nodes.section.snapshots();
        loop {
            let snapshot = rx.borrow_and_update().clone();
            let stale_table = !Arc::ptr_eq(&nodes.lock().table, &snapshot.table);
            if stale_table {
                self.rebuild(&snapshot);
            }
            let due = self.push(&snapshot);
            // A change to give again (see View::enable) wakes it without a
            // new snapshot (none comes while the link is lost).
            let resample = async {
                match due {
                    Some(due) => tokio::time::sleep_until(due.into()).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                changed = rx.changed() => if changed.is_err() { break },
                () = resample => {}
                () = self.stop.cancelled() => break,
            }
        }
    }

    /// A new table: the section's nodes again, and the monitored variables
    /// enabled in it.
    fn rebuild(&self, snapshot: &Snapshot) {
        let shared = &self.shared;
        let nodes = &self.nodes;
        let mut view = View::new(&nodes.section, snapshot, shared.history.is_some());
        {
            let mut current = nodes.lock();
            view.adopt(current.take_monitored(), shared.resample_ms());
            *current = view;
        }
        // Served from the view: the new nodes are there now.
        info!(
            section = %nodes.name,
            "OPC UA: variables of the new variable table served ({} shown)",
            nodes.lock().shown_ids().count()
        );
        model_changed(
            &self.shared,
            &self.subscriptions,
            &nodes.name,
            Verb::Changed,
        );
    }

    /// Gives the stack what changed for the monitored variables, and the
    /// section object's link state and last poll. When a change is next to
    /// be given again.
    ///
    /// The view's lock is taken a slice of [`SLICE`] variables at a time: a
    /// Read or Write of the section's nodes (which take it too, on another
    /// thread) waits for one slice, not for a walk of 100,000. The walk is
    /// all of one snapshot and does not yield: a subscriber gets every
    /// polled value of a variable, in order, as long as the feed keeps up
    /// with the polls.
    fn push(&self, snapshot: &Snapshot) -> Option<std::time::Instant> {
        let nodes = &self.nodes;
        let opts = nodes.section.format();
        let now = std::time::Instant::now();
        let stamp_now = DateTime::now();
        let mut next_due = None;
        let mut updates: Vec<(NodeId, DataValue)> = Vec::new();
        // The first variable of the next slice (`watched` is ordered).
        let mut from: Option<VarId> = Some(0);
        while let Some(first) = from.take() {
            let mut view = nodes.lock();
            // A new table (before the walk or meanwhile): the run loop
            // rebuilds and gives every monitored variable again.
            if !Arc::ptr_eq(&view.table, &snapshot.table) {
                return None;
            }
            let view = &mut *view;
            for (n, (&id, watched)) in view.watched.range_mut(first..).enumerate() {
                if n == SLICE {
                    from = Some(id);
                    break;
                }
                let slot = snapshot.slot(id);
                let quality = snapshot.quality(id);
                let changed = slot.changed_seq != watched.seq || Some(quality) != watched.quality;
                // Given again one sampling interval after its change:
                // see View::enable.
                if !changed && watched.due.is_none_or(|due| due > now) {
                    next_due = earliest(next_due, watched.due);
                    continue;
                }
                watched.due = (changed && watched.resample_ms > 0.0).then(|| {
                    now + Duration::from_secs_f64(
                        f64::from(watched.resample_ms.min(3.6e6)) / 1000.0,
                    )
                });
                next_due = earliest(next_due, watched.due);
                watched.seq = slot.changed_seq;
                watched.quality = Some(quality);
                let stamp = view.stamp_of.get(&id).copied();
                let node = ids::variable(&nodes.name, &space::shown_name(&view.table, id));
                updates.push((
                    self.shared.node(node),
                    space::data_value_at(snapshot, id, stamp, opts, stamp_now),
                ));
            }
        }
        // The variables straight to their monitored items (they have no
        // node in the address space), in one call: each call takes every
        // subscribed session's lock, which its publishes hold while they
        // are built (a call a slice made the poll -> stack p50 6 -> 17 ms).
        if !updates.is_empty() {
            let (ids, values): (Vec<NodeId>, Vec<DataValue>) = updates.into_iter().unzip();
            self.subscriptions.notify_data_change(
                ids.iter()
                    .zip(values)
                    .map(|(node, value)| (space::notified(value), node, AttributeId::Value)),
            );
        }
        self.push_link_state(snapshot);
        next_due
    }

    /// The section object's link state and last poll, through the
    /// in-memory manager, which keeps their values.
    fn push_link_state(&self, snapshot: &Snapshot) {
        let nodes = &self.nodes;
        let mut link_updates: Vec<(NodeId, DataValue)> = Vec::new();
        {
            let mut view = nodes.lock();
            let link = nodes.section.link_state().as_str();
            let polled = snapshot.polled.map_or(0, |p| p.unix_ms);
            if view.link_shown != Some((link, polled)) {
                let link_changed = view.link_shown.map(|(l, _)| l) != Some(link);
                view.link_shown = Some((link, polled));
                if link_changed {
                    link_updates.push((
                        self.shared.node(ids::property(&nodes.name, "LinkState")),
                        space::good_now(Variant::from(link)),
                    ));
                }
                if let Some(time) =
                    chrono::DateTime::from_timestamp_millis(polled).filter(|_| polled > 0)
                {
                    link_updates.push((
                        self.shared.node(ids::property(&nodes.name, "LastPoll")),
                        space::good_now(Variant::from(DateTime::from(time))),
                    ));
                }
            }
        }
        if !link_updates.is_empty() {
            let (ids, values): (Vec<NodeId>, Vec<DataValue>) = link_updates.into_iter().unzip();
            let _ = self.manager.set_values(
                &self.subscriptions,
                ids.iter()
                    .zip(values)
                    .map(|(node, value)| (node, None, value)),
            );
        }
    }
}

/// Monitored variables the feed walks under the view's lock at a time.
const SLICE: usize = 2_000;

/// The earlier of two times, if any.
fn earliest(
    a: Option<std::time::Instant>,
    b: Option<std::time::Instant>,
) -> Option<std::time::Instant> {
    match (a, b) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// What a model change did to a section's nodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verb {
    /// A section added by a reload.
    Added,
    /// A section removed by a reload.
    Removed,
    /// A new variable table, or the section restarted by a reload.
    Changed,
}

/// A GeneralModelChangeEvent from the Server object: section `name`'s
/// nodes were added or removed, for clients that cache the tree.
pub fn model_changed(shared: &Shared, subscriptions: &SubscriptionCache, name: &str, verb: Verb) {
    use opcua::core_namespace::events::{BaseModelChangeEventType, GeneralModelChangeEventType};
    use opcua::nodes::{BaseEventType, Event};
    use opcua::types::{ByteString, ModelChangeStructureDataType, ObjectId, ObjectTypeId};
    let section = shared.node(name.to_string());
    let id = format!(
        "plccoms:{name}:{}",
        chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0)
    );
    // NodeAdded 1, NodeDeleted 2, ReferenceAdded 4, ReferenceDeleted 8.
    let (message, verb) = match verb {
        Verb::Added => ("section added", 0b0101),
        Verb::Removed => ("section removed", 0b1010),
        Verb::Changed => ("variables added and removed", 0b1111),
    };
    let mut base = BaseEventType::new_now(
        ObjectTypeId::GeneralModelChangeEventType,
        ByteString::from(id.into_bytes()),
        format!("[{name}]: {message}"),
    );
    base.source_node = section.clone();
    base.source_name = name.into();
    base.severity = 100;
    let event = GeneralModelChangeEventType {
        base: BaseModelChangeEventType { base },
        changes: ModelChangeStructureDataType {
            affected: section,
            affected_type: ObjectTypeId::BaseObjectType.into(),
            verb,
        },
    };
    let server: NodeId = ObjectId::Server.into();
    subscriptions.notify_events([(&event as &dyn Event, &server)].into_iter());
}
