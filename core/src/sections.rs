//! The sections that are running now. The binary replaces the list when a
//! reload adds, removes or restarts sections; north apps hold a
//! [`Sections`] and either read [`Sections::current`] when they serve (the
//! web page) or follow [`Sections::watch`] to start and stop their work per
//! section (MQTT, the historian), leaving the sections that stayed alone.
//! A restarted section is a new [`Section`]: tell them apart by pointer
//! ([`Arc::ptr_eq`]), not by name.

use std::sync::Arc;

use tokio::sync::watch;

use crate::section::Section;

/// The running sections, in configuration order.
pub type SectionList = Arc<[Arc<Section>]>;

/// A shared, watchable list of the running sections.
#[derive(Clone)]
pub struct Sections {
    tx: Arc<watch::Sender<SectionList>>,
}

impl Sections {
    pub fn new(sections: Vec<Arc<Section>>) -> Self {
        let (tx, _) = watch::channel(sections.into());
        Sections { tx: Arc::new(tx) }
    }

    /// The sections now.
    pub fn current(&self) -> SectionList {
        self.tx.borrow().clone()
    }

    /// The running section named `name`.
    pub fn find(&self, name: &str) -> Option<Arc<Section>> {
        self.tx.borrow().iter().find(|s| s.name() == name).cloned()
    }

    /// Replaces the list; every watcher wakes.
    pub fn set(&self, sections: Vec<Arc<Section>>) {
        self.tx.send_replace(sections.into());
    }

    /// Follows the list: the receiver's current value is the list now, and
    /// `changed()` resolves at each replacement.
    pub fn watch(&self) -> watch::Receiver<SectionList> {
        self.tx.subscribe()
    }
}

/// What changed between two lists, by pointer: sections in `new` that are
/// not in `old` (`added`: new or restarted) and sections of `old` that are
/// not in `new` (`removed`: gone or replaced).
pub fn diff(old: &[Arc<Section>], new: &[Arc<Section>]) -> (Vec<Arc<Section>>, Vec<Arc<Section>>) {
    let added = new
        .iter()
        .filter(|n| !old.iter().any(|o| Arc::ptr_eq(o, n)))
        .cloned()
        .collect();
    let removed = old
        .iter()
        .filter(|o| !new.iter().any(|n| Arc::ptr_eq(o, n)))
        .cloned()
        .collect();
    (added, removed)
}
