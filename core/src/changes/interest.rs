//! Which variables the clients of a section enabled: a count per variable,
//! raised and lowered by sessions, read by the poller to decide what to poll.

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use crate::vars::VarId;

#[derive(Debug)]
pub struct Interest {
    counts: Vec<AtomicU32>,
    dirty: AtomicBool,
}

impl Interest {
    pub fn new(len: usize) -> Self {
        Interest {
            counts: (0..len).map(|_| AtomicU32::new(0)).collect(),
            dirty: AtomicBool::new(true),
        }
    }

    /// One more client enabled `id`.
    pub fn add(&self, id: VarId) {
        if self.counts[id as usize].fetch_add(1, Ordering::Relaxed) == 0 {
            self.dirty.store(true, Ordering::Release);
        }
    }

    /// One client fewer has `id` enabled.
    pub fn remove(&self, id: VarId) {
        let previous = self.counts[id as usize].fetch_sub(1, Ordering::Relaxed);
        debug_assert!(previous > 0, "interest underflow for variable {id}");
        if previous == 1 {
            self.dirty.store(true, Ordering::Release);
        }
    }

    pub fn is_wanted(&self, id: VarId) -> bool {
        self.counts[id as usize].load(Ordering::Relaxed) > 0
    }

    /// Whether the set changed since the last call (and clears the flag).
    pub fn take_dirty(&self) -> bool {
        self.dirty.swap(false, Ordering::Acquire)
    }

    pub fn len(&self) -> usize {
        self.counts.len()
    }

    pub fn is_empty(&self) -> bool {
        self.counts.is_empty()
    }
}
