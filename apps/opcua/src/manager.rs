//! The in-memory part of our namespace: the root folder and the section
//! objects with their properties (a few nodes per section), in the stack's
//! address space. The variables are not there: [`crate::vars::Vars`]
//! serves them from the sections' tables. Also the helpers both share:
//! HistoryRead's cursor and rows, and the monitored item counts.

use std::sync::Arc;

use async_trait::async_trait;
use futures::StreamExt;
use opcua::server::address_space::AddressSpace;
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{
    InMemoryNodeManagerImpl, InMemoryNodeManagerImplBuilder,
};
use opcua::server::node_manager::ServerContext;
use opcua::types::{DataValue, DateTime, StatusCode};
use plccoms_core::history_source::{HistoryQuery, RowQuality};
use plccoms_core::present;
use plccoms_core::vars::VarId;

use crate::convert;
use crate::space::{self, Shared, View};

/// Our namespace's URI.
pub const NAMESPACE: &str = "urn:plccoms";

/// Most values one HistoryRead returns per node, whatever the client asks:
/// past it, a continuation point.
pub const HISTORY_PAGE: usize = 10_000;

pub struct Builder {
    pub shared: Arc<Shared>,
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
            space::build_section(space, &self.shared, nodes);
        }
        Manager { ns }
    }
}

/// The root folder and the section objects.
pub struct Manager {
    ns: u16,
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

/// UTC milliseconds of an OPC UA time; `unset` for a null one.
pub(crate) fn time_ms(time: &DateTime, unset: i64) -> i64 {
    if time.is_null() {
        unset
    } else {
        time.as_chrono().timestamp_millis()
    }
}

/// A history row as a DataValue: its value with the row's quality as
/// StatusCode; a marker row (an outage, the server stopped, a gap) without
/// a value, Bad.
pub(crate) fn history_value(
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
pub(crate) async fn bound(
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
pub(crate) fn bound_not_found(at_ms: i64) -> DataValue {
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
    match view.id_of(name) {
        Some(id) => {
            view.enable(id, sampling_ms, 1);
            Some(id)
        }
        None => {
            *view.absent.entry(name.to_string()).or_default() += 1;
            None
        }
    }
}

/// One monitored item fewer on `name`: the last disables it.
pub fn unwatch(view: &mut View, name: &str) {
    if let Some(id) = view.id_of(name) {
        let Some(watched) = view.watched.get_mut(&id) else {
            return;
        };
        watched.count = watched.count.saturating_sub(1);
        if watched.count == 0 {
            view.disable(id);
        }
        return;
    }
    let Some(count) = view.absent.get_mut(name) else {
        return;
    };
    *count -= 1;
    if *count == 0 {
        view.absent.remove(name);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::changes::Interest;
    use plccoms_core::vars::table_of;

    fn view() -> View {
        let table = Arc::new(table_of(&[("A", "INT"), ("B", "REAL")]));
        View {
            interest: Arc::new(Interest::new(table.len())),
            shown: vec![true; table.len()],
            writable: vec![false; table.len()],
            historized: vec![false; table.len()],
            table,
            absent: Default::default(),
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
        assert!(view.watched.is_empty() && view.absent.is_empty());
        // A name the table lacks is counted, and enables nothing.
        assert_eq!(watch(&mut view, "GONE", 0.0), None);
        assert_eq!(view.absent.get("GONE"), Some(&1));
        unwatch(&mut view, "GONE");
        assert!(view.absent.is_empty());
        // More removals than items are harmless.
        unwatch(&mut view, "A");
        assert!(!view.interest.is_wanted(a));
    }
}
