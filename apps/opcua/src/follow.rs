//! Follows the running sections through reloads (SIGHUP), as CONTRIBUTING
//! "Adding a north app" asks: by pointer, a section added gets its nodes
//! and a feed, a removed one loses both (its monitored items told so), a
//! restarted one (same name, new `Section`) gets its nodes again under the
//! same NodeIds with its monitored items carried over; the others are left
//! alone.

use std::sync::Arc;

use opcua::server::node_manager::memory::InMemoryNodeManager;
use opcua::server::SubscriptionCache;
use opcua::types::{AttributeId, StatusCode};
use plccoms_core::section::Section;
use plccoms_core::sections::{self, SectionList};
use tokio::runtime::Handle;
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::feed::{self, Feed, Verb};
use crate::manager::Manager;
use crate::space::{self, SectionNodes, Shared};

pub struct Follow {
    pub shared: Arc<Shared>,
    pub manager: Arc<InMemoryNodeManager<Manager>>,
    pub subscriptions: Arc<SubscriptionCache>,
    pub stop: CancellationToken,
}

/// A served section's feed.
struct Running {
    nodes: Arc<SectionNodes>,
    stop: CancellationToken,
    task: JoinHandle<()>,
}

impl Follow {
    /// Feeds the sections served now (`old`, the list `Shared` was made
    /// from), then follows `rx` until stopped.
    pub async fn run(self, mut old: SectionList, mut rx: watch::Receiver<SectionList>) {
        // Shut down with this task, however it ends.
        let runtime = FeedRuntime::new();
        let feeds = runtime.handle();
        let mut running: Vec<Running> = self
            .shared
            .list()
            .iter()
            .map(|nodes| self.spawn(&feeds, nodes.clone()))
            .collect();
        loop {
            tokio::select! {
                changed = rx.changed() => if changed.is_err() { break },
                () = self.stop.cancelled() => break,
            }
            let new = rx.borrow_and_update().clone();
            let (added, removed) = sections::diff(&old, &new);
            if !added.is_empty() || !removed.is_empty() {
                self.apply(&feeds, &mut running, &new, &added, &removed)
                    .await;
            }
            old = new;
        }
        for feed in running {
            feed.stop.cancel();
            feed.task.abort();
        }
    }

    fn spawn(&self, feeds: &Handle, nodes: Arc<SectionNodes>) -> Running {
        let stop = self.stop.child_token();
        let task = feeds.spawn(
            Feed {
                shared: self.shared.clone(),
                nodes: nodes.clone(),
                manager: self.manager.clone(),
                subscriptions: self.subscriptions.clone(),
                stop: stop.clone(),
            }
            .run(),
        );
        Running { nodes, stop, task }
    }

    async fn apply(
        &self,
        feeds: &Handle,
        running: &mut Vec<Running>,
        new: &[Arc<Section>],
        added: &[Arc<Section>],
        removed: &[Arc<Section>],
    ) {
        // The feeds of removed sections stop first: none may rebuild nodes
        // being removed.
        let mut gone = Vec::new();
        for section in removed {
            let Some(i) = running
                .iter()
                .position(|r| Arc::ptr_eq(&r.nodes.section, section))
            else {
                continue;
            };
            let feed = running.remove(i);
            feed.stop.cancel();
            let _ = feed.task.await;
            gone.push(feed.nodes);
        }
        let replaced = |name: &str| added.iter().any(|s| s.name() == name);
        let recorded = self.shared.history.is_some();
        let mut fresh = Vec::new();
        for section in added {
            fresh.push(Arc::new(SectionNodes::new(section, recorded)));
        }
        let ns = self.shared.ns();
        let mut unknown = Vec::new();
        let mut waiting = Vec::new();
        {
            let mut space = self.manager.address_space().write();
            for old in &gone {
                let view = old.lock();
                let ids = space::remove_section(&mut space, ns, &old.name, &view);
                if replaced(&old.name) {
                    // Values of the old section no more, none of the new
                    // one yet (its feed gives them; a variable its table
                    // lacks until the public file comes stays so).
                    waiting.extend(view.shown_ids().map(|id| {
                        let name = space::shown_name(&view.table, id);
                        self.shared.node(crate::ids::variable(&old.name, &name))
                    }));
                } else {
                    unknown.extend(ids);
                }
            }
            for nodes in &fresh {
                space::build_section(&mut space, &self.shared, nodes);
            }
            let list = new
                .iter()
                .filter_map(|section| {
                    running
                        .iter()
                        .map(|r| &r.nodes)
                        .chain(&fresh)
                        .find(|n| Arc::ptr_eq(&n.section, section))
                        .cloned()
                })
                .collect();
            self.shared.set_list(list);
            // Monitored item counts move once services see the new list,
            // so that none is counted on a section that went: a restarted
            // section's carry over by name, a removed one's wait for a
            // section of its name.
            for old in &gone {
                let monitored = old.lock().take_monitored();
                match fresh.iter().find(|f| f.name == old.name) {
                    Some(new) => new.adopt(&self.shared, monitored),
                    None => self.shared.orphan(&old.name, monitored),
                }
            }
            for nodes in &fresh {
                if !gone.iter().any(|g| g.name == nodes.name) {
                    nodes.adopt(&self.shared, self.shared.adopt_orphans(&nodes.name));
                }
            }
        }
        // Monitored items on nodes that went: a Bad value, as a read gets.
        for (ids, status) in [
            (&unknown, StatusCode::BadNodeIdUnknown),
            (&waiting, StatusCode::BadWaitingForInitialData),
        ] {
            let value = crate::manager::bad(status);
            self.subscriptions
                .notify_data_change(ids.iter().map(|id| (value.clone(), id, AttributeId::Value)));
        }
        for old in &gone {
            if !replaced(&old.name) {
                info!(section = %old.name, "OPC UA: section removed from the address space");
                feed::model_changed(&self.shared, &self.subscriptions, &old.name, Verb::Removed);
            }
        }
        for nodes in fresh {
            let restarted = gone.iter().any(|g| g.name == nodes.name);
            info!(
                section = %nodes.name,
                "OPC UA: section {} in the address space ({} variables shown)",
                if restarted { "restarted" } else { "added" },
                nodes.lock().shown_ids().count()
            );
            let verb = if restarted {
                Verb::Changed
            } else {
                Verb::Added
            };
            feed::model_changed(&self.shared, &self.subscriptions, &nodes.name, verb);
            running.push(self.spawn(feeds, nodes));
        }
    }
}

/// The feeds' runtime: threads of their own. A feed's walk of a snapshot
/// and the stack's notify of its changes (100,000 a second: a few hundred
/// ms) run without yielding; on the server's workers they held one of
/// them, and a Write or Read waited for it (SET p99 at 100,000 through
/// plccoms's server: 149 ms). On threads of their own the OS shares the
/// cores between them and the requests. The current runtime when those
/// threads cannot be made.
struct FeedRuntime(Option<tokio::runtime::Runtime>);

impl FeedRuntime {
    fn new() -> FeedRuntime {
        let built = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(FEED_THREADS)
            .thread_name("opcua-feed")
            .enable_all()
            .build();
        match built {
            Ok(runtime) => FeedRuntime(Some(runtime)),
            Err(e) => {
                warn!("OPC UA: the feeds run on the server's threads ({e})");
                FeedRuntime(None)
            }
        }
    }

    fn handle(&self) -> Handle {
        self.0
            .as_ref()
            .map_or_else(Handle::current, |runtime| runtime.handle().clone())
    }
}

impl Drop for FeedRuntime {
    fn drop(&mut self) {
        // Inside another runtime a plain drop would panic (it blocks).
        if let Some(runtime) = self.0.take() {
            runtime.shutdown_background();
        }
    }
}

/// The feeds' threads: more than one, so a section's long walk does not
/// hold every other section's feed.
const FEED_THREADS: usize = 2;

#[cfg(test)]
mod tests {
    use super::*;

    /// Dropped on a runtime's worker (as the follow task ends), the feeds'
    /// runtime ends and drops its tasks; a plain drop there would panic.
    #[tokio::test(flavor = "multi_thread", worker_threads = 1)]
    async fn the_feed_runtime_ends_its_feeds_when_dropped_inside_a_runtime() {
        let runtime = FeedRuntime::new();
        assert!(runtime.0.is_some(), "threads of its own");
        let (alive, ended) = tokio::sync::oneshot::channel::<()>();
        let (started_tx, started) = tokio::sync::oneshot::channel();
        runtime.handle().spawn(async move {
            let _alive = alive;
            let name = std::thread::current().name().map(str::to_owned);
            let _ = started_tx.send(name);
            std::future::pending::<()>().await;
        });
        let name = started.await.expect("the feed ran");
        assert_eq!(name.as_deref(), Some("opcua-feed"));
        drop(runtime);
        let ended = tokio::time::timeout(std::time::Duration::from_secs(10), ended).await;
        assert!(
            matches!(ended, Ok(Err(_))),
            "the feed's task is dropped with its runtime"
        );
    }
}
