//! A subscription to a section's changes, for in-process consumers (the
//! historian, MQTT, the web page): the variables matching a set of masks,
//! polled for as long as the subscription lives, delivered as batches of
//! the variables that changed since the previous batch.
//!
//! It is the mechanism sessions use: the latest [`Snapshot`] on a `watch`
//! channel, interest counted in the snapshot's [`Interest`] so the link polls
//! what is subscribed, and change sequence numbers per variable. Memory is
//! bounded whatever the consumer does. By default a consumer that falls
//! behind is not queued for: its next batch compares against the latest
//! snapshot and says how many publishes it `missed` (their intermediate
//! values are gone, the latest are in the batch). One that follows
//! ([`Subscription::every_change`]) gets every publish in order while it
//! lags within [`super::FOLLOW_BOUND`] publishes and
//! [`super::FOLLOW_BYTES`]; past that, the same catch-up and `missed`.

use std::sync::Arc;

use tokio::sync::watch;

use super::{FollowQueue, Followers, Interest, Popped, Snapshot};
use crate::vars::{VarId, VarTable};

/// The link to the PLC changed state between two batches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkEvent {
    Lost,
    Restored,
}

/// What changed since the previous batch.
#[derive(Debug, Clone)]
pub struct ChangeBatch {
    /// The snapshot the values are read from (`snapshot.slot(id)`,
    /// `snapshot.quality(id)`, `snapshot.table.var(id)`).
    pub snapshot: Arc<Snapshot>,
    /// Publishes between the previous batch and this one that the consumer
    /// did not see: a variable that changed more than once meanwhile shows
    /// only its latest value.
    pub missed: u64,
    /// A new variable table (a new public file): `changes` holds every
    /// subscribed variable of it that has a value.
    pub table_changed: bool,
    pub link: Option<LinkEvent>,
    /// Subscribed variables whose value or quality changed, in table order.
    pub changes: Vec<VarId>,
}

pub struct Subscription {
    rx: watch::Receiver<Arc<Snapshot>>,
    followers: Arc<Followers>,
    /// Every publish, queued, once [`Subscription::every_change`] asked.
    follow: Option<Arc<FollowQueue>>,
    masks: Vec<Vec<u8>>,
    /// `masks` match names of the project only (`VarTable::matching_names`).
    names_only: bool,
    table: Arc<VarTable>,
    interest: Arc<Interest>,
    /// Subscribed variables of `table`, ascending.
    wanted: Vec<VarId>,
    /// Per entry of `wanted`: change sequence of the value last delivered,
    /// shifted left, and whether it was uncertain in the low bit (8 bytes
    /// a variable, not 16: a sequence never reaches 2^63).
    delivered: Vec<u64>,
    seen_seq: u64,
    online: Option<bool>,
    /// Also a batch for every poll cycle, changes or not.
    every_poll: bool,
    seen_poll: u64,
}

impl Subscription {
    pub(super) fn new<M: AsRef<[u8]>>(
        mut rx: watch::Receiver<Arc<Snapshot>>,
        followers: Arc<Followers>,
        masks: &[M],
        names_only: bool,
    ) -> Subscription {
        let snapshot = rx.borrow_and_update().clone();
        let mut subscription = Subscription {
            rx,
            followers,
            follow: None,
            masks: masks.iter().map(|m| m.as_ref().to_vec()).collect(),
            names_only,
            table: snapshot.table.clone(),
            interest: snapshot.interest.clone(),
            wanted: Vec::new(),
            delivered: Vec::new(),
            // Everything known now is owed in the first batch.
            seen_seq: 0,
            online: None,
            every_poll: false,
            seen_poll: 0,
        };
        subscription.resolve(&snapshot);
        subscription
    }

    /// Also delivers a batch for every completed poll cycle, with no changes
    /// if none: for consumers that act per cycle (heartbeats, the
    /// historian's event capture). A batch that skipped cycles says so in
    /// `missed`.
    pub fn every_poll(mut self) -> Subscription {
        self.every_poll = true;
        self
    }

    /// Follows every publish: no change is missed while the consumer lags
    /// within [`super::FOLLOW_BOUND`] publishes and [`super::FOLLOW_BYTES`]
    /// (for the historian and MQTT, which promise every change). Call
    /// before the first [`Subscription::next`].
    pub fn every_change(self) -> Subscription {
        self.every_change_within(super::FOLLOW_BOUND, super::FOLLOW_BYTES)
    }

    /// [`Subscription::every_change`] with other bounds.
    pub(crate) fn every_change_within(mut self, max: usize, max_bytes: usize) -> Subscription {
        self.follow = Some(self.followers.follow(max, max_bytes));
        self
    }

    /// The subscribed variables of the current table.
    pub fn wanted(&self) -> &[VarId] {
        &self.wanted
    }

    pub fn table(&self) -> &Arc<VarTable> {
        &self.table
    }

    /// The latest snapshot, without waiting.
    pub fn latest(&self) -> Arc<Snapshot> {
        self.rx.borrow().clone()
    }

    /// Registers interest in what the masks match in `snapshot`'s table.
    fn resolve(&mut self, snapshot: &Snapshot) {
        self.release();
        self.table = snapshot.table.clone();
        self.interest = snapshot.interest.clone();
        self.wanted = if self.names_only {
            self.table.matching_names(&self.masks)
        } else {
            self.table.matching(&self.masks)
        };
        for &id in &self.wanted {
            if !self.table.is_fixed(id) {
                self.interest.add(id);
            }
        }
        self.delivered = vec![0; self.wanted.len()];
    }

    fn release(&mut self) {
        for &id in &self.wanted {
            if !self.table.is_fixed(id) {
                self.interest.remove(id);
            }
        }
        self.wanted.clear();
    }

    /// The next batch with something in it: changes, a new table or a link
    /// event. `None` once the section stopped.
    pub async fn next(&mut self) -> Option<ChangeBatch> {
        if self.follow.is_some() {
            return self.next_followed().await;
        }
        loop {
            let snapshot = self.rx.borrow_and_update().clone();
            if let Some(batch) = self.batch(snapshot) {
                return Some(batch);
            }
            self.rx.changed().await.ok()?;
        }
    }

    /// [`Subscription::next`] of a following subscription: the first batch
    /// from the latest snapshot (everything known), then each queued
    /// publish in order. A publish the full queue could not take shows as a
    /// jump in `seq`: the batch after it compares everything and counts it
    /// in `missed`.
    async fn next_followed(&mut self) -> Option<ChangeBatch> {
        if self.seen_seq == 0 {
            let snapshot = self.rx.borrow_and_update().clone();
            if let Some(batch) = self.batch(snapshot) {
                return Some(batch);
            }
        }
        loop {
            let follow = self.follow.clone()?;
            let snapshot = match follow.pop().ok()? {
                Popped::Snapshot(snapshot) => snapshot,
                // Drained, and the newest publishes were dropped: the watch
                // has them (or will: a publish is offered to the queue
                // before the watch shows it). Only then: while the link
                // publishes, the watch runs ahead of a queue that holds
                // every publish, and taking it would skip them.
                Popped::Drained { dropped_up_to } if dropped_up_to > self.seen_seq => {
                    let latest = self.rx.borrow_and_update().clone();
                    if latest.seq >= dropped_up_to {
                        latest
                    } else {
                        self.rx.changed().await.ok()?;
                        continue;
                    }
                }
                Popped::Drained { .. } => {
                    // Seen (its seq is ours already): wait for a newer one.
                    self.rx.borrow_and_update();
                    // A gone publisher closed the queue before its watch:
                    // the next pop drains what is left, then ends.
                    tokio::select! {
                        biased;
                        _ = follow.wait() => {}
                        _ = self.rx.changed() => {}
                    }
                    continue;
                }
            };
            // Queued before the first batch read the latest, or taken from
            // the watch already: seen.
            if snapshot.seq <= self.seen_seq {
                continue;
            }
            if let Some(batch) = self.batch(snapshot) {
                return Some(batch);
            }
        }
    }

    /// The batch `snapshot` makes, if it holds anything new.
    fn batch(&mut self, snapshot: Arc<Snapshot>) -> Option<ChangeBatch> {
        let table_changed = !Arc::ptr_eq(&snapshot.table, &self.table);
        if snapshot.seq == self.seen_seq && !table_changed {
            return None;
        }
        let first = self.seen_seq == 0;
        // The first batch owes everything known: nothing was missed before it.
        let missed = if first {
            0
        } else {
            snapshot.seq.saturating_sub(self.seen_seq + 1)
        };
        let consecutive = snapshot.seq == self.seen_seq + 1;
        self.seen_seq = snapshot.seq;
        if table_changed {
            self.resolve(&snapshot);
        }
        let link = match (self.online, snapshot.online) {
            (Some(true), false) => Some(LinkEvent::Lost),
            (Some(false), true) => Some(LinkEvent::Restored),
            _ => None,
        };
        self.online = Some(snapshot.online);
        let mut changes = Vec::new();
        if consecutive && !table_changed && !first {
            // Only what this publish changed; `changed` is short.
            for &id in snapshot.changed.iter().chain(&snapshot.requalified) {
                if let Ok(index) = self.wanted.binary_search(&id) {
                    self.offer(&snapshot, index, &mut changes);
                }
            }
            changes.sort_unstable();
        } else {
            for index in 0..self.wanted.len() {
                self.offer(&snapshot, index, &mut changes);
            }
        }
        let new_poll = snapshot.poll_seq > self.seen_poll;
        self.seen_poll = snapshot.poll_seq;
        if changes.is_empty() && link.is_none() && !table_changed && !(self.every_poll && new_poll)
        {
            return None;
        }
        Some(ChangeBatch {
            snapshot,
            missed,
            table_changed,
            link,
            changes,
        })
    }

    fn offer(&mut self, snapshot: &Snapshot, index: usize, changes: &mut Vec<VarId>) {
        let id = self.wanted[index];
        let slot = snapshot.slot(id);
        let (seq, uncertain) = (self.delivered[index] >> 1, self.delivered[index] & 1 == 1);
        let news =
            slot.changed_seq > seq || (slot.changed_seq == seq && slot.uncertain() != uncertain);
        if slot.text().is_none() || !news {
            return;
        }
        self.delivered[index] = slot.changed_seq << 1 | u64::from(slot.uncertain());
        changes.push(id);
    }
}

impl Drop for Subscription {
    fn drop(&mut self) {
        self.release();
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use plccoms_protocol::value::FormatOptions;

    use super::*;
    use crate::changes::{PollStamp, Publisher};

    const CHUNK_BYTES: usize = super::super::CHUNK * std::mem::size_of::<crate::changes::Slot>();
    use crate::vars::table_of;

    fn setup() -> (Publisher, super::super::ChangeStream) {
        let table = Arc::new(table_of(&[("A", "INT"), ("B", "INT"), ("C", "REAL")]));
        Publisher::new(table, FormatOptions::default(), Duration::from_secs(1))
    }

    fn poll(publisher: &mut Publisher, values: &[(VarId, i16)]) {
        let stamp = PollStamp::now();
        for &(id, value) in values {
            publisher.update(id, &value.to_le_bytes(), stamp.unix_ms);
        }
        publisher.publish_poll(stamp);
    }

    fn names(batch: &ChangeBatch) -> Vec<String> {
        batch
            .changes
            .iter()
            .map(|&id| String::from_utf8_lossy(&batch.snapshot.table.var(id).name).into_owned())
            .collect()
    }

    #[tokio::test]
    async fn changes_of_subscribed_variables_with_interest_and_missed_counts() {
        let (mut publisher, stream) = setup();
        let fixed = publisher.table().fixed_count() as VarId;
        let (a, b) = (fixed, fixed + 1);
        let mut sub = stream.subscribe(&["a", "B"]);
        assert!(publisher.interest().is_wanted(a) && publisher.interest().is_wanted(b));
        assert!(!publisher.interest().is_wanted(fixed + 2));
        poll(&mut publisher, &[(a, 1), (b, 2)]);
        let batch = sub.next().await.unwrap();
        assert_eq!(names(&batch), ["A", "B"]);
        assert_eq!(batch.snapshot.quality(a), crate::changes::Quality::Good);
        // One change: only it.
        poll(&mut publisher, &[(a, 1), (b, 3)]);
        let batch = sub.next().await.unwrap();
        assert_eq!((names(&batch), batch.missed), (vec!["B".to_string()], 0));
        // Three publishes unseen: the latest values, and the count.
        poll(&mut publisher, &[(a, 5)]);
        poll(&mut publisher, &[(a, 6)]);
        poll(&mut publisher, &[(a, 7)]);
        let batch = sub.next().await.unwrap();
        assert_eq!((names(&batch), batch.missed), (vec!["A".to_string()], 2));
        assert_eq!(batch.snapshot.slot(a).text(), Some(&b"7"[..]));
        // Link loss and return are events.
        publisher.publish_offline();
        assert_eq!(sub.next().await.unwrap().link, Some(LinkEvent::Lost));
        poll(&mut publisher, &[(a, 7)]);
        assert_eq!(sub.next().await.unwrap().link, Some(LinkEvent::Restored));
        drop(sub);
        assert!(!publisher.interest().is_wanted(a), "interest released");
    }

    #[tokio::test]
    async fn a_change_of_quality_alone_is_a_change_of_the_slot() {
        use crate::changes::Quality;
        let (mut publisher, stream) = setup();
        let a = publisher.table().fixed_count() as VarId;
        let mut sub = stream.subscribe(&["A"]);
        let mut follower = stream.subscribe(&["A"]).every_change();
        poll(&mut publisher, &[(a, 1)]);
        assert_eq!(names(&sub.next().await.unwrap()), ["A"]);
        assert_eq!(names(&follower.next().await.unwrap()), ["A"]);
        // Same value, marked uncertain by the device, then good again: each
        // a change; polled again with the same value and mark, nothing new.
        let quiet = Duration::from_millis(50);
        for (uncertain, quality) in [(true, Quality::Stale), (false, Quality::Good)] {
            publisher.set_uncertain(a, uncertain, 5);
            publisher.publish();
            for sub in [&mut sub, &mut follower] {
                let batch = sub.next().await.unwrap();
                assert_eq!(names(&batch), ["A"]);
                assert_eq!(batch.snapshot.quality(a), quality);
            }
            poll(&mut publisher, &[(a, 1)]);
            assert!(tokio::time::timeout(quiet, sub.next()).await.is_err());
            assert!(tokio::time::timeout(quiet, follower.next()).await.is_err());
        }
        // A consumer that missed the publish compares the mark too.
        publisher.set_uncertain(a, true, 7);
        publisher.publish();
        poll(&mut publisher, &[(a, 1)]);
        let batch = sub.next().await.unwrap();
        assert_eq!((names(&batch), batch.missed), (vec!["A".to_string()], 1));
        assert_eq!(batch.snapshot.quality(a), Quality::Stale);
        publisher.set_uncertain(a, false, 8);
        publisher.publish();
        poll(&mut publisher, &[(a, 1)]);
        let batch = sub.next().await.unwrap();
        assert_eq!(batch.snapshot.quality(a), Quality::Good);
        // Marked and cleared unseen: nothing changed for it.
        publisher.set_uncertain(a, true, 9);
        publisher.publish();
        publisher.set_uncertain(a, false, 10);
        publisher.publish();
        poll(&mut publisher, &[(a, 1)]);
        assert!(tokio::time::timeout(quiet, sub.next()).await.is_err());
    }

    /// Publishes `values` of A, then reads until the last: the values seen
    /// and the publishes missed.
    async fn lag(
        publisher: &mut Publisher,
        sub: &mut Subscription,
        values: std::ops::Range<i16>,
    ) -> (Vec<i16>, u64) {
        let a = publisher.table().fixed_count() as VarId;
        let last = values.end - 1;
        for value in values {
            poll(publisher, &[(a, value)]);
        }
        let (mut seen, mut missed) = (Vec::new(), 0);
        while seen.last() != Some(&last) {
            let batch = sub.next().await.unwrap();
            missed += batch.missed;
            let text = batch.snapshot.slot(a).text().unwrap();
            seen.push(std::str::from_utf8(text).unwrap().parse::<i16>().unwrap());
        }
        assert!(seen.windows(2).all(|w| w[0] < w[1]), "in order: {seen:?}");
        (seen, missed)
    }

    #[tokio::test]
    async fn a_follower_gets_every_change_in_order_while_it_lags_within_the_bounds() {
        let (mut publisher, stream) = setup();
        let a = publisher.table().fixed_count() as VarId;
        poll(&mut publisher, &[(a, 1)]);
        let mut sub = stream.subscribe(&["A"]).every_change_within(50, usize::MAX);
        // The first batch is what is known; nothing was missed before it.
        let batch = sub.next().await.unwrap();
        assert_eq!((names(&batch), batch.missed), (vec!["A".to_string()], 0));
        // A consumer that does not read while the link publishes the
        // bound's worth of changes: every value, in order.
        let (seen, missed) = lag(&mut publisher, &mut sub, 2..52).await;
        assert_eq!((seen, missed), ((2..52).collect::<Vec<_>>(), 0));
        // Past it: the queue's 50, then the latest; the rest counted.
        let (seen, missed) = lag(&mut publisher, &mut sub, 52..112).await;
        assert_eq!((seen.len(), missed), (51, 9));
        // The link gone: the follower sees the end.
        drop(publisher);
        assert!(sub.next().await.is_none());
    }

    /// The link publishes on its own thread while the follower reads: a
    /// follower that drained its queue must not take the watch, which runs
    /// ahead of the queue while publishes go on (CI lost 8 of 20 ADS
    /// notifications in the historian so).
    #[test]
    fn a_follower_keeps_up_with_a_publisher_on_another_thread() {
        // The race is narrow: several rounds make it likely in each run.
        for _ in 0..8 {
            follow_a_publisher_on_another_thread(30_000);
        }
    }

    fn follow_a_publisher_on_another_thread(last: i16) {
        let (mut publisher, stream) = setup();
        let a = publisher.table().fixed_count() as VarId;
        poll(&mut publisher, &[(a, 0)]);
        let mut sub = stream.subscribe(&["A"]).every_change_within(64, usize::MAX);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        // The first batch: what is known when it subscribed.
        let first = runtime.block_on(sub.next()).unwrap();
        assert_eq!(first.snapshot.slot(a).text(), Some(&b"0"[..]));
        let seen = Arc::new(std::sync::atomic::AtomicI16::new(0));
        let link = std::thread::spawn({
            let seen = seen.clone();
            move || {
                let mut value = 0;
                while value < last {
                    // Within the queue's bound: nothing may be missed.
                    while value - seen.load(std::sync::atomic::Ordering::Acquire) >= 32 {
                        std::thread::yield_now();
                    }
                    value += 1;
                    publisher.update(a, &value.to_le_bytes(), i64::from(value));
                    publisher.publish();
                }
                publisher
            }
        });
        let (values, missed) = runtime.block_on(async {
            let (mut values, mut missed) = (Vec::new(), 0);
            while values.last() != Some(&last) {
                let batch = sub.next().await.unwrap();
                missed += batch.missed;
                for &id in &batch.changes {
                    let text = batch.snapshot.slot(id).text().unwrap();
                    let value = std::str::from_utf8(text).unwrap().parse::<i16>().unwrap();
                    values.push(value);
                    seen.store(value, std::sync::atomic::Ordering::Release);
                }
            }
            (values, missed)
        });
        drop(link.join().unwrap());
        assert_eq!(missed, 0);
        let skipped: Vec<_> = values
            .windows(2)
            .filter(|w| w[1] != w[0] + 1)
            .take(5)
            .collect();
        assert!(skipped.is_empty(), "skipped after: {skipped:?}");
        assert_eq!((values.first(), values.len()), (Some(&1), last as usize));
    }

    #[tokio::test]
    async fn a_follower_is_bounded_in_bytes_too() {
        let (mut publisher, stream) = setup();
        // FOLLOW_BYTES's doc and README count 14 KiB a chunk.
        assert_eq!(CHUNK_BYTES, 14 * 1024);
        // Each poll here copies one chunk of slots, and the read stamps of
        // the table's one chunk, read in part (5 variables).
        let one = CHUNK_BYTES
            + std::mem::size_of::<Arc<Vec<crate::changes::Slot>>>()
            + 5 * 8
            + std::mem::size_of::<super::super::ReadChunk>();
        let a = publisher.table().fixed_count() as VarId;
        poll(&mut publisher, &[(a, 0)]);
        let mut sub = stream
            .subscribe(&["A"])
            .every_change_within(usize::MAX, 10 * one);
        sub.next().await.unwrap();
        let (seen, missed) = lag(&mut publisher, &mut sub, 1..31).await;
        assert_eq!((seen.len(), missed), (11, 19), "{seen:?}");
    }

    #[tokio::test]
    async fn every_poll_delivers_cycles_without_changes() {
        let (mut publisher, stream) = setup();
        let a = publisher.table().fixed_count() as VarId;
        let mut sub = stream.subscribe(&["A"]).every_poll();
        poll(&mut publisher, &[(a, 1)]);
        assert_eq!(names(&sub.next().await.unwrap()), ["A"]);
        poll(&mut publisher, &[(a, 1)]);
        let batch = sub.next().await.unwrap();
        assert!(batch.changes.is_empty());
        assert_eq!(batch.snapshot.poll_seq, batch.snapshot.seq);
        // A publish outside a poll without subscribed changes: nothing.
        publisher.publish();
        poll(&mut publisher, &[(a, 2)]);
        let batch = sub.next().await.unwrap();
        assert_eq!((names(&batch), batch.missed), (vec!["A".to_string()], 1));
    }

    #[tokio::test]
    async fn a_new_table_is_resolved_again() {
        let (mut publisher, stream) = setup();
        let mut sub = stream.subscribe(&["*"]);
        let table = Arc::new(table_of(&[("A", "INT"), ("D", "INT")]));
        let d = table.lookup(b"D").unwrap();
        publisher.replace_table(table);
        publisher.publish();
        let batch = sub.next().await.unwrap();
        assert!(batch.table_changed);
        assert!(sub.wanted().contains(&d));
        assert!(publisher.interest().is_wanted(d));
        poll(&mut publisher, &[(d, 4)]);
        let batch = sub.next().await.unwrap();
        assert_eq!(names(&batch), ["D"]);
    }
}
