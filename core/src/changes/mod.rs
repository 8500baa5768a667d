//! The change stream of a section: the link publishes what it read as an
//! immutable [`Snapshot`]; every consumer (client sessions, and in-process
//! consumers through [`Subscription`]) holds the latest one and picks what it
//! owes from it.
//!
//! A snapshot never blocks the link: it goes out on a `watch` channel, so a
//! slow consumer simply sees a later snapshot and catches up by comparing
//! change sequence numbers, instead of an ever-growing queue. A consumer
//! that must see every change (the historian, MQTT) follows the stream
//! instead ([`Subscription::every_change`]): each snapshot is also queued
//! for it, within [`FOLLOW_BOUND`] publishes and [`FOLLOW_BYTES`], so it
//! loses nothing while it lags by less; past that the queue drops what it
//! cannot hold and the consumer sees the jump as `missed`. Values are
//! formatted once per change here, not once per consumer. Each snapshot
//! carries the poll's time (monotonic, for freshness, and UTC, for records)
//! and the link's state, so every value has a [`Quality`].

pub mod interest;
pub mod subscription;

use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use plccoms_protocol::value::{FormatOptions, Value};
use plccoms_protocol::IecType;
use tokio::sync::watch;
use tokio::time::Instant;

use crate::vars::{Var, VarId, VarTable};
pub use interest::Interest;
pub use subscription::{ChangeBatch, LinkEvent, Subscription};

/// Slots per copy-on-write chunk: a publish copies only the chunks it changed.
const CHUNK: usize = 256;

/// How far a following subscription (the historian, MQTT) may lag before
/// it misses changes: this many publishes, or [`FOLLOW_BYTES`] of the
/// slots its queued snapshots hold that no other snapshot shares, whichever
/// comes first. A poll that changes a few variables costs one chunk of
/// slots (256 of 56 bytes: 14 KiB, their texts inline; what it read
/// unchanged costs nothing, but 2 KiB of read stamps for a chunk it read in
/// part), so the bytes allow minutes of polls or seconds of a client's
/// rapid SETs; a poll that changes every variable of a 10,000 variable
/// table costs about 560 KiB, so 58 of them (STRINGs longer than 20
/// characters beyond). The queue holds
/// snapshots only while its consumer lags.
pub const FOLLOW_BOUND: usize = 10_000;
/// See [`FOLLOW_BOUND`].
pub const FOLLOW_BYTES: usize = 32 << 20;

/// One following subscription's queue.
pub(crate) struct FollowQueue {
    state: std::sync::Mutex<Queued>,
    ready: tokio::sync::Notify,
    /// Publishes and bytes it may hold.
    max: usize,
    max_bytes: usize,
}

#[derive(Default)]
struct Queued {
    snapshots: std::collections::VecDeque<(Arc<Snapshot>, usize)>,
    bytes: usize,
    /// The newest publish the bounds made it drop (0: none); the consumer
    /// takes it from the watch once the queue is drained.
    dropped_up_to: u64,
    /// The publisher is gone.
    closed: bool,
}

/// What a following subscription takes from its queue.
pub(crate) enum Popped {
    Snapshot(Arc<Snapshot>),
    /// Nothing queued; the newest publish dropped meanwhile (0: none).
    Drained {
        dropped_up_to: u64,
    },
}

impl FollowQueue {
    fn lock(&self) -> std::sync::MutexGuard<'_, Queued> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The oldest queued snapshot, or word that none is queued; `Err` once
    /// the publisher is gone and the queue is empty.
    pub(crate) fn pop(&self) -> Result<Popped, ()> {
        let mut queued = self.lock();
        match queued.snapshots.pop_front() {
            Some((snapshot, cost)) => {
                queued.bytes -= cost;
                Ok(Popped::Snapshot(snapshot))
            }
            None if queued.closed => Err(()),
            None => Ok(Popped::Drained {
                dropped_up_to: queued.dropped_up_to,
            }),
        }
    }

    /// Waits until something may have been queued (or the end).
    pub(crate) async fn wait(&self) {
        self.ready.notified().await;
    }

    /// Queues `snapshot` if the bounds allow; else it is missed (the
    /// consumer sees the jump in `seq`).
    fn offer(&self, snapshot: &Arc<Snapshot>, cost: usize) {
        let mut queued = self.lock();
        if queued.snapshots.len() < self.max && queued.bytes + cost <= self.max_bytes {
            queued.snapshots.push_back((snapshot.clone(), cost));
            queued.bytes += cost;
        } else {
            queued.dropped_up_to = snapshot.seq;
        }
        drop(queued);
        self.ready.notify_one();
    }

    fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_one();
    }
}

/// What `snapshot` holds that the one before (`before`) does not share:
/// the chunks of slots and of read stamps copied since, and the lists of
/// them.
fn unshared_bytes(snapshot: &Snapshot, before: &Snapshot) -> usize {
    let (chunks, reads) = (&snapshot.chunks, &snapshot.reads);
    let copied = chunks
        .iter()
        .zip(&before.chunks)
        .filter(|(now, before)| !Arc::ptr_eq(now, before))
        .count()
        + chunks.len().saturating_sub(before.chunks.len());
    let stamps: usize = reads
        .iter()
        .enumerate()
        .map(|(i, now)| match (now, before.reads.get(i)) {
            (ReadChunk::Each(now), Some(ReadChunk::Each(old))) if Arc::ptr_eq(now, old) => 0,
            (ReadChunk::Each(now), _) => std::mem::size_of_val(&now[..]),
            (ReadChunk::All(_), _) => 0,
        })
        .sum();
    copied * CHUNK * std::mem::size_of::<Slot>()
        + stamps
        + std::mem::size_of_val(&chunks[..])
        + std::mem::size_of_val(&reads[..])
}

/// When the variables of one chunk were last read from the PLC, as a
/// snapshot holds it. Apart from the slots: a poll reads every polled
/// variable again, changed or not, and a read stamp in the slot made every
/// poll copy every polled chunk (64 bytes a variable per poll at rest,
/// `tests/memory_per_var.rs`). A chunk read whole in one publish (what a
/// poll does) is its one sequence, without an allocation.
#[derive(Debug, Clone)]
enum ReadChunk {
    All(u64),
    Each(Arc<[u64]>),
}

impl ReadChunk {
    fn of(seqs: &[u64]) -> ReadChunk {
        match seqs.first() {
            Some(&first) if seqs.iter().any(|&seq| seq != first) => ReadChunk::Each(seqs.into()),
            first => ReadChunk::All(first.copied().unwrap_or(0)),
        }
    }

    fn get(&self, index: usize) -> u64 {
        match self {
            ReadChunk::All(seq) => *seq,
            ReadChunk::Each(seqs) => seqs[index],
        }
    }
}

/// The queues of the subscriptions that follow every publish.
#[derive(Default)]
pub(crate) struct Followers {
    queues: std::sync::Mutex<Vec<Arc<FollowQueue>>>,
}

impl Followers {
    pub(crate) fn follow(&self, max: usize, max_bytes: usize) -> Arc<FollowQueue> {
        let queue = Arc::new(FollowQueue {
            state: std::sync::Mutex::default(),
            ready: tokio::sync::Notify::new(),
            max,
            max_bytes,
        });
        self.lock().push(queue.clone());
        queue
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<Arc<FollowQueue>>> {
        self.queues.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Whether any subscription follows (the link skips the cost otherwise).
    fn any(&self) -> bool {
        !self.lock().is_empty()
    }

    /// Queues `snapshot` (whose own slots cost `cost` bytes) for every
    /// follower that has room. Never waits.
    fn offer(&self, snapshot: &Arc<Snapshot>, cost: usize) {
        let mut queues = self.lock();
        // A dropped subscription leaves its queue to us alone.
        queues.retain(|queue| Arc::strong_count(queue) > 1);
        for queue in queues.iter() {
            queue.offer(snapshot, cost);
        }
    }

    /// The publisher is gone: followers see the end.
    fn close(&self) {
        for queue in self.lock().drain(..) {
            queue.close();
        }
    }
}

/// Public-file notices kept for clients that missed snapshots: reloads come
/// one per SETCONF or file change, so a session is never this far behind.
const NOTICE_HISTORY: usize = 32;

/// Bytes of text a slot holds in itself.
const INLINE: usize = 22;

/// A value as the protocol prints it: in the slot when it fits (every
/// number, BOOL, date and time), shared on the heap when longer (STRINGs).
/// An `Arc` for each was 32 bytes of malloc beside every slot, and one
/// more per change in a poll (`tests/memory_per_var.rs`).
#[derive(Debug, Clone, Default)]
enum Text {
    /// Not read yet.
    #[default]
    None,
    Inline {
        len: u8,
        bytes: [u8; INLINE],
    },
    Shared(Arc<[u8]>),
}

const _: () = assert!(std::mem::size_of::<Text>() == 24);

impl Text {
    fn of(text: &[u8]) -> Text {
        if text.len() > INLINE {
            return Text::Shared(Arc::from(text));
        }
        let mut bytes = [0; INLINE];
        bytes[..text.len()].copy_from_slice(text);
        Text::Inline {
            len: text.len() as u8,
            bytes,
        }
    }

    fn get(&self) -> Option<&[u8]> {
        match self {
            Text::None => None,
            Text::Inline { len, bytes } => Some(&bytes[..usize::from(*len)]),
            Text::Shared(text) => Some(text),
        }
    }

    fn is_some(&self) -> bool {
        !matches!(self, Text::None)
    }
}

/// The last known value of one variable.
#[derive(Debug, Clone, Default)]
pub struct Slot {
    /// Scalar value: the first 8 bytes as read, as a little-endian number (a
    /// BOOL as 0/1); unused for STRING, whose bytes are in `text`.
    raw: u64,
    /// The value as the protocol prints it; `None` until first read.
    text: Text,
    /// Snapshot sequence at which the value last changed (when it was last
    /// read: [`Snapshot::read_seq`], [`Publisher::read_seq`]).
    pub changed_seq: u64,
    /// UTC milliseconds of the poll (or SET read-back) that read the value
    /// as it is now, or of the device's last change of its quality.
    pub changed_ms: i64,
    /// The device marked the value uncertain (OPC UA's Uncertain status):
    /// served, but as [`Quality::Stale`]. A change of it alone is listed in
    /// [`Snapshot::requalified`], not in `changed_seq` (no DIFF line: the
    /// line protocol has no quality).
    uncertain: bool,
}

impl Slot {
    pub fn text(&self) -> Option<&[u8]> {
        self.text.get()
    }

    /// The text to keep beyond the snapshot: shared when long, a copy of
    /// a short one.
    pub fn shared_text(&self) -> Option<Arc<[u8]>> {
        match &self.text {
            Text::Shared(text) => Some(text.clone()),
            text => text.get().map(Arc::from),
        }
    }

    /// The device marked the value uncertain.
    pub fn uncertain(&self) -> bool {
        self.uncertain
    }

    /// The value, decoded (for delta comparisons).
    pub fn value(&self, var: &Var) -> Option<Value> {
        let text = self.text.get()?;
        Some(if var.ty.is_string() {
            // text is `"..."`; the quotes are ours.
            Value::Str(text[1..text.len() - 1].to_vec())
        } else if var.ty == IecType::Bool {
            Value::Bool(self.raw != 0)
        } else {
            let len = (var.byte_len() as usize).min(8);
            var.codec.decode(var.ty, &self.raw.to_le_bytes()[..len])
        })
    }
}

/// How far a value can be trusted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Quality {
    /// Read by the last poll, with the link up.
    Good,
    /// The link is up but the last poll did not read it (not polled, or its
    /// read refused): the value is an older one; or the device marked it
    /// uncertain.
    Stale,
    /// The link to the PLC is lost: the value is the last one known.
    LinkLost,
}

impl Quality {
    pub fn as_str(self) -> &'static str {
        match self {
            Quality::Good => "good",
            Quality::Stale => "stale",
            Quality::LinkLost => "link_lost",
        }
    }
}

/// When a poll read its values: a monotonic instant (freshness) and UTC
/// milliseconds (records).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PollStamp {
    pub at: Instant,
    pub unix_ms: i64,
}

impl PollStamp {
    pub fn now() -> PollStamp {
        PollStamp {
            at: Instant::now(),
            unix_ms: unix_ms(SystemTime::now()),
        }
    }
}

/// UTC milliseconds since 1970 of `time`.
pub fn unix_ms(time: SystemTime) -> i64 {
    match time.duration_since(UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_millis()).unwrap_or(i64::MAX),
        Err(e) => -i64::try_from(e.duration().as_millis()).unwrap_or(i64::MAX),
    }
}

/// A change of public file, announced to every client of the section.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Notice {
    /// Increases with every notice.
    pub seq: u64,
    /// The new file differs: WARNING:250 (else 251, content unchanged).
    pub changed: bool,
    /// The file's name as the warning shows it.
    pub name: String,
}

/// Everything a session needs to know about the PLC's variables, as of one
/// moment.
#[derive(Debug)]
pub struct Snapshot {
    /// Increases with every publish.
    pub seq: u64,
    /// Sequence of the last completed poll cycle: a slot read at or after it
    /// is current.
    pub poll_seq: u64,
    /// The link to the PLC answered the last poll.
    pub online: bool,
    /// The last poll cycle that completed, if any.
    pub polled: Option<PollStamp>,
    /// How long after its poll a value may still be served as current.
    pub fresh_for: Duration,
    pub table: Arc<VarTable>,
    /// Which variables the clients of this table enabled.
    pub interest: Arc<Interest>,
    /// Variables whose value changed in this publish.
    pub changed: Vec<VarId>,
    /// Variables whose quality alone the device changed in this publish
    /// (not in `changed`: no DIFF line).
    pub requalified: Vec<VarId>,
    /// The latest public-file notices, oldest first: a session that missed
    /// snapshots still tells its client of every reload, in order.
    pub notices: Arc<[Arc<Notice>]>,
    /// The section's default line end, where it has a DIFF block.
    block_eol: Option<&'static [u8]>,
    /// See [`Snapshot::diff_block`].
    diff_block: std::sync::OnceLock<Option<DiffBlock>>,
    chunks: Vec<Arc<Vec<Slot>>>,
    reads: Vec<ReadChunk>,
}

#[derive(Debug, Clone)]
pub struct DiffBlock {
    pub eol: &'static [u8],
    pub bytes: Arc<[u8]>,
    /// DIFF lines in `bytes`.
    pub lines: usize,
}

impl Snapshot {
    /// The DIFF lines of every variable in `changed`, with the section's
    /// default line end: what a client that enabled everything is owed, so
    /// a thousand such clients copy one block instead of each picking
    /// lines. Made by the first client that asks, not by the link at each
    /// publish: at 100,000 changes a second that was 3 MB of lines a
    /// second, 5 % of an OPC UA section's CPU, with no such client.
    pub fn diff_block(&self) -> Option<&DiffBlock> {
        self.diff_block
            .get_or_init(|| {
                let eol = self.block_eol?;
                if self.changed.is_empty() {
                    return None;
                }
                let mut bytes = Vec::with_capacity(self.changed.len() * 32);
                let mut lines = 0;
                for &id in &self.changed {
                    if let Some(text) = self.slot(id).text() {
                        lines += 1;
                        bytes.extend_from_slice(b"DIFF:");
                        bytes.extend_from_slice(&self.table.var(id).name);
                        bytes.push(b',');
                        bytes.extend_from_slice(text);
                        bytes.extend_from_slice(eol);
                    }
                }
                Some(DiffBlock {
                    eol,
                    bytes: bytes.into(),
                    lines,
                })
            })
            .as_ref()
    }

    /// The line end of [`Snapshot::diff_block`], without making it.
    pub fn diff_block_eol(&self) -> Option<&'static [u8]> {
        self.block_eol
    }

    /// Sequence of the latest notice (0: none yet).
    pub fn notice_seq(&self) -> u64 {
        self.notices.last().map_or(0, |n| n.seq)
    }

    /// The notices after `seq`, oldest first.
    pub fn notices_after(&self, seq: u64) -> impl Iterator<Item = &Arc<Notice>> {
        self.notices.iter().filter(move |n| n.seq > seq)
    }

    pub fn slot(&self, id: VarId) -> &Slot {
        let id = id as usize;
        &self.chunks[id / CHUNK][id % CHUNK]
    }

    /// Snapshot sequence at which the value was last read from the PLC.
    pub fn read_seq(&self, id: VarId) -> u64 {
        let id = id as usize;
        self.reads[id / CHUNK].get(id % CHUNK)
    }

    /// The slot if its value is current: read in the last poll cycle or later,
    /// with the PLC online. What DIFF lines are made of.
    pub fn current(&self, id: VarId) -> Option<&Slot> {
        let slot = self.slot(id);
        (self.online
            && slot.text.is_some()
            && self.read_seq(id) >= self.poll_seq
            && self.poll_seq > 0)
            .then_some(slot)
    }

    /// The slot if its value may be served as live at `now`: current, and
    /// its poll completed no longer ago than `fresh_for`. A link that went
    /// silent stops this within the bound, long before it is declared lost.
    pub fn fresh(&self, id: VarId, now: Instant) -> Option<&Slot> {
        let polled = self.polled?;
        if now.saturating_duration_since(polled.at) > self.fresh_for {
            return None;
        }
        self.current(id)
    }

    /// The quality at `now`, for a face that reads the snapshot later than
    /// its publish (the web page): `Good` only while GET would serve the
    /// value from this poll ([`Snapshot::fresh`]); past that, with the link
    /// not yet declared lost, `Stale`.
    pub fn quality_at(&self, id: VarId, now: Instant) -> Quality {
        match self.quality(id) {
            Quality::Good if self.fresh(id, now).is_none() => Quality::Stale,
            quality => quality,
        }
    }

    /// The quality as published (fresh by construction).
    pub fn quality(&self, id: VarId) -> Quality {
        if !self.online {
            Quality::LinkLost
        } else if self.current(id).is_some_and(|slot| !slot.uncertain) {
            Quality::Good
        } else {
            Quality::Stale
        }
    }
}

impl Drop for Publisher {
    fn drop(&mut self) {
        self.followers.close();
    }
}

/// The consumers' side: the latest snapshot, and subscriptions.
#[derive(Clone)]
pub struct ChangeStream {
    rx: watch::Receiver<Arc<Snapshot>>,
    followers: Arc<Followers>,
    /// Set by [`ChangeStream::woken_by_relay`]: what wakes sessions.
    relay: Option<watch::Receiver<()>>,
}

impl ChangeStream {
    /// The same stream, its sessions woken by a task of the current runtime
    /// instead of by the publisher. The link publishes from a thread of its
    /// own; waking 1,000 sessions from there meant a worker wake-up (an
    /// eventfd write and a context switch) every few sessions, the link
    /// thread preempted by the workers it woke on its own core for the
    /// whole burst (perf sched timehist: 12 ms of a 100 ms cycle). The
    /// relay is woken once and wakes the sessions from a worker, into its
    /// own run queue. Sessions still read the publisher's latest snapshot,
    /// so what they see is never older than before.
    pub fn woken_by_relay(mut self) -> ChangeStream {
        let (tx, relay) = watch::channel(());
        let mut upstream = self.rx.clone();
        tokio::spawn(async move {
            while upstream.changed().await.is_ok() {
                tx.send_replace(());
            }
            // Dropping `tx` tells the sessions the link is gone.
        });
        self.relay = Some(relay);
        self
    }

    /// A receiver of every snapshot (what sessions hold).
    pub fn receiver(&self) -> Snapshots {
        Snapshots {
            rx: self.rx.clone(),
            relay: self.relay.clone(),
        }
    }

    pub fn latest(&self) -> Arc<Snapshot> {
        self.rx.borrow().clone()
    }

    /// The changes of the variables matching `masks` (`*` wildcards, case
    /// insensitive), polled for as long as the subscription lives.
    pub fn subscribe<M: AsRef<[u8]>>(&self, masks: &[M]) -> Subscription {
        Subscription::new(self.rx.clone(), self.followers.clone(), masks, false)
    }

    /// Like [`Changes::subscribe`], with masks that mean the project's
    /// variables: system variables only for masks beginning with `__`
    /// (`Mask::matches_name`).
    pub fn subscribe_names<M: AsRef<[u8]>>(&self, masks: &[M]) -> Subscription {
        Subscription::new(self.rx.clone(), self.followers.clone(), masks, true)
    }
}

/// A session's view of the stream: the publisher's latest snapshot, and
/// the wait for the next one (through the relay, when there is one).
pub struct Snapshots {
    rx: watch::Receiver<Arc<Snapshot>>,
    relay: Option<watch::Receiver<()>>,
}

impl Snapshots {
    /// Waits for a snapshot not seen yet; an error once the publisher is
    /// gone and its last snapshot was seen. Cancel safe.
    pub async fn changed(&mut self) -> Result<(), watch::error::RecvError> {
        let Some(relay) = &mut self.relay else {
            return self.rx.changed().await;
        };
        loop {
            match self.rx.has_changed() {
                Ok(true) => return Ok(()),
                Ok(false) => {}
                // Closed: the last snapshot, if unseen, then the error.
                Err(_) => return self.rx.changed().await,
            }
            if relay.changed().await.is_err() {
                return self.rx.changed().await;
            }
        }
    }

    pub fn has_changed(&self) -> bool {
        self.rx.has_changed().unwrap_or(false)
    }

    pub fn borrow(&self) -> watch::Ref<'_, Arc<Snapshot>> {
        self.rx.borrow()
    }

    pub fn borrow_and_update(&mut self) -> watch::Ref<'_, Arc<Snapshot>> {
        self.rx.borrow_and_update()
    }
}

/// The link's side: owns the master copy of the slots and publishes.
pub struct Publisher {
    tx: watch::Sender<Arc<Snapshot>>,
    followers: Arc<Followers>,
    seq: u64,
    poll_seq: u64,
    online: bool,
    polled: Option<PollStamp>,
    fresh_for: Duration,
    table: Arc<VarTable>,
    interest: Arc<Interest>,
    chunks: Vec<Arc<Vec<Slot>>>,
    /// When each variable was last read: the truth, which a publish turns
    /// into the snapshot's `reads` for the chunks marked in `reads_dirty`.
    read_seq: Vec<u64>,
    reads: Vec<ReadChunk>,
    reads_dirty: Vec<bool>,
    changed: Vec<VarId>,
    requalified: Vec<VarId>,
    format: FormatOptions,
    scratch: Vec<u8>,
    notices: Arc<[Arc<Notice>]>,
    /// Line end of the shared DIFF block; `None`: no block (DIFF lines off).
    block_eol: Option<&'static [u8]>,
}

impl Publisher {
    /// A publisher of values of `table` whose polls are fresh for
    /// `fresh_for`.
    pub fn new(
        table: Arc<VarTable>,
        format: FormatOptions,
        fresh_for: Duration,
    ) -> (Publisher, ChangeStream) {
        let interest = Arc::new(Interest::new(table.len()));
        let chunks = empty_chunks(table.len());
        let reads = vec![ReadChunk::All(0); chunks.len()];
        let len = table.len();
        let snapshot = Arc::new(Snapshot {
            seq: 0,
            poll_seq: 0,
            online: false,
            polled: None,
            fresh_for,
            table: table.clone(),
            interest: interest.clone(),
            changed: Vec::new(),
            requalified: Vec::new(),
            notices: Arc::new([]),
            block_eol: None,
            diff_block: std::sync::OnceLock::new(),
            chunks: chunks.clone(),
            reads: reads.clone(),
        });
        let (tx, rx) = watch::channel(snapshot);
        let followers = Arc::new(Followers::default());
        let publisher = Publisher {
            tx,
            followers: followers.clone(),
            seq: 0,
            poll_seq: 0,
            online: false,
            polled: None,
            fresh_for,
            table,
            interest,
            read_seq: vec![0; len],
            reads_dirty: vec![false; chunks.len()],
            reads,
            chunks,
            changed: Vec::new(),
            requalified: Vec::new(),
            format,
            scratch: Vec::new(),
            notices: Arc::new([]),
            block_eol: None,
        };
        (
            publisher,
            ChangeStream {
                rx,
                followers,
                relay: None,
            },
        )
    }

    /// Changes the freshness bound (a new link with another timeout).
    pub fn set_fresh_for(&mut self, fresh_for: Duration) {
        self.fresh_for = fresh_for;
    }

    pub fn table(&self) -> &Arc<VarTable> {
        &self.table
    }

    /// Publishes each change also as one block of DIFF lines ending in `eol`.
    pub fn with_diff_block(mut self, eol: &'static [u8]) -> Self {
        self.block_eol = Some(eol);
        self
    }

    pub fn interest(&self) -> &Arc<Interest> {
        &self.interest
    }

    pub fn stream(&self) -> ChangeStream {
        ChangeStream {
            rx: self.tx.subscribe(),
            followers: self.followers.clone(),
            relay: None,
        }
    }

    /// Sequence the next publish will carry; updates are stamped with it.
    pub fn next_seq(&self) -> u64 {
        self.seq + 1
    }

    pub fn slot(&self, id: VarId) -> &Slot {
        let id = id as usize;
        &self.chunks[id / CHUNK][id % CHUNK]
    }

    /// Sequence at which `id` was last read (the next one's for a read
    /// since the last publish).
    pub fn read_seq(&self, id: VarId) -> u64 {
        self.read_seq[id as usize]
    }

    /// Counts `id` as read for the next publish, its value as it is: after
    /// a poll's publish, only a variable read since that poll began is
    /// current ([`Snapshot::current`]). [`Publisher::update`] marks what it
    /// records; a poll marks so a value read back between its slices (a
    /// SET's), newer than what it read itself.
    pub fn mark_read(&mut self, id: VarId) {
        let index = id as usize;
        self.read_seq[index] = self.seq + 1;
        self.reads_dirty[index / CHUNK] = true;
    }

    /// Records a value read from the PLC at `unix_ms` (`bytes` as read for
    /// the variable; the bit of a BOOL is extracted here). Returns whether it
    /// changed.
    pub fn update(&mut self, id: VarId, bytes: &[u8], unix_ms: i64) -> bool {
        self.mark_read(id);
        let var = self.table.var(id);
        let seq = self.seq + 1;
        let ty = var.ty;
        let value = (!ty.is_string()).then(|| var.decode(bytes));
        let raw = match &value {
            Some(Value::Bool(on)) => u64::from(*on),
            Some(_) => {
                let mut le = [0u8; 8];
                let n = bytes.len().min(8);
                le[..n].copy_from_slice(&bytes[..n]);
                u64::from_le_bytes(le)
            }
            None => 0,
        };
        let index = id as usize;
        let slot = &self.chunks[index / CHUNK][index % CHUNK];
        let changed = match slot.text.get() {
            None => true,
            Some(old) if ty.is_string() => !string_equals(old, bytes),
            Some(_) => slot.raw != raw,
        };
        if changed {
            self.scratch.clear();
            // Through the variable: a tag file's decimals and scale count.
            let value = value.unwrap_or_else(|| var.decode(bytes));
            var.format(&value, &self.format, &mut self.scratch);
            let chunk = Arc::make_mut(&mut self.chunks[index / CHUNK]);
            let slot = &mut chunk[index % CHUNK];
            slot.raw = raw;
            slot.text = Text::of(&self.scratch);
            slot.changed_seq = seq;
            slot.changed_ms = unix_ms;
            self.changed.push(id);
        }
        changed
    }

    /// Marks the value of `id` uncertain or good again, as the device said
    /// at `unix_ms`; [`Publisher::update`] leaves the mark as it is. A change
    /// of the mark alone is published in [`Snapshot::requalified`], for the
    /// faces that show quality. Returns whether it changed.
    pub fn set_uncertain(&mut self, id: VarId, uncertain: bool, unix_ms: i64) -> bool {
        let index = id as usize;
        if self.slot(id).uncertain == uncertain {
            return false;
        }
        let seq = self.seq + 1;
        let chunk = Arc::make_mut(&mut self.chunks[index / CHUNK]);
        let slot = &mut chunk[index % CHUNK];
        slot.uncertain = uncertain;
        if slot.changed_seq != seq {
            slot.changed_ms = unix_ms;
            self.requalified.push(id);
        }
        true
    }

    /// A poll cycle completed at `stamp`: every slot it read is current.
    pub fn publish_poll(&mut self, stamp: PollStamp) {
        self.polled = Some(stamp);
        self.publish_state(true, true);
    }

    /// Publishes what changed outside a poll (SET read-backs, a new table),
    /// the link as it is.
    pub fn publish(&mut self) {
        let online = self.online;
        self.publish_state(false, online);
    }

    /// The link is lost: every value becomes [`Quality::LinkLost`].
    pub fn publish_offline(&mut self) {
        self.publish_state(false, false);
    }

    fn publish_state(&mut self, polled: bool, online: bool) {
        self.seq += 1;
        if polled {
            self.poll_seq = self.seq;
        }
        self.online = online;
        for (index, dirty) in self.reads_dirty.iter_mut().enumerate() {
            if std::mem::take(dirty) {
                let start = index * CHUNK;
                let end = (start + CHUNK).min(self.read_seq.len());
                self.reads[index] = ReadChunk::of(&self.read_seq[start..end]);
            }
        }
        let snapshot = Snapshot {
            seq: self.seq,
            poll_seq: self.poll_seq,
            online,
            polled: self.polled,
            fresh_for: self.fresh_for,
            table: self.table.clone(),
            interest: self.interest.clone(),
            changed: std::mem::take(&mut self.changed),
            requalified: std::mem::take(&mut self.requalified),
            notices: self.notices.clone(),
            block_eol: self.block_eol,
            diff_block: std::sync::OnceLock::new(),
            chunks: self.chunks.clone(),
            reads: self.reads.clone(),
        };
        let snapshot = Arc::new(snapshot);
        if self.followers.any() {
            let cost = unshared_bytes(&snapshot, &self.tx.borrow());
            self.followers.offer(&snapshot, cost);
        }
        self.tx.send_replace(snapshot);
    }

    pub fn online(&self) -> bool {
        self.online
    }

    /// Switches to a new variable table (a new public file): every value is
    /// unknown again and the clients' interest starts anew. Takes effect with
    /// the next publish.
    pub fn replace_table(&mut self, table: Arc<VarTable>) {
        self.interest = Arc::new(Interest::new(table.len()));
        self.chunks = empty_chunks(table.len());
        self.read_seq = vec![0; table.len()];
        self.reads = vec![ReadChunk::All(0); self.chunks.len()];
        self.reads_dirty = vec![false; self.chunks.len()];
        self.changed.clear();
        self.requalified.clear();
        self.table = table;
    }

    /// Announces a public-file load to every client with the next publish.
    pub fn announce(&mut self, changed: bool, name: String) -> Arc<Notice> {
        let seq = self.notices.last().map_or(1, |n| n.seq + 1);
        let notice = Arc::new(Notice { seq, changed, name });
        let skip = (self.notices.len() + 1).saturating_sub(NOTICE_HISTORY);
        self.notices = self.notices[skip..]
            .iter()
            .cloned()
            .chain([notice.clone()])
            .collect();
        notice
    }
}

fn empty_chunks(len: usize) -> Vec<Arc<Vec<Slot>>> {
    (0..len.div_ceil(CHUNK))
        .map(|i| Arc::new(vec![Slot::default(); CHUNK.min(len - i * CHUNK)]))
        .collect()
}

/// Whether a formatted STRING text (`"..."`) holds exactly the NUL-terminated
/// string in `raw`.
fn string_equals(text: &[u8], raw: &[u8]) -> bool {
    let end = raw.iter().position(|&b| b == 0).unwrap_or(raw.len());
    text.len() == end + 2 && text[1..text.len() - 1] == raw[..end]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn publisher() -> (Publisher, Snapshots) {
        let (publisher, stream) = Publisher::new(
            Arc::new(VarTable::default()),
            FormatOptions::default(),
            Duration::from_secs(1),
        );
        (publisher, stream.receiver())
    }

    fn told(snapshot: &Snapshot, after: u64) -> Vec<(u64, bool, &str)> {
        snapshot
            .notices_after(after)
            .map(|n| (n.seq, n.changed, n.name.as_str()))
            .collect()
    }

    #[tokio::test]
    async fn a_waiting_session_is_woken_by_the_relay_not_by_the_publish() {
        let (mut publisher, stream) = Publisher::new(
            Arc::new(VarTable::default()),
            FormatOptions::default(),
            Duration::from_secs(1),
        );
        // The relay's side in the test's hands.
        let (relay, relay_rx) = watch::channel(());
        let mut session = Snapshots {
            rx: stream.rx.clone(),
            relay: Some(relay_rx),
        };
        let mut waiting = Box::pin(session.changed());
        let quiet = Duration::from_millis(50);
        assert!(tokio::time::timeout(quiet, &mut waiting).await.is_err());
        publisher.publish_poll(PollStamp::now());
        let early = tokio::time::timeout(quiet, &mut waiting).await;
        assert!(early.is_err(), "woken by the publisher, not the relay");
        relay.send_replace(());
        tokio::time::timeout(Duration::from_secs(10), &mut waiting)
            .await
            .expect("woken by the relay")
            .expect("link up");
        drop(waiting);
        assert_eq!(session.borrow_and_update().seq, 1);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn sessions_woken_by_the_relay_see_every_publish_and_the_end() {
        let (mut publisher, stream) = Publisher::new(
            Arc::new(VarTable::default()),
            FormatOptions::default(),
            Duration::from_secs(1),
        );
        let stream = stream.woken_by_relay();
        let mut sessions: Vec<Snapshots> = (0..3).map(|_| stream.receiver()).collect();
        // The publisher on a thread of its own, as the link runs: `n`
        // publishes per request, 0 = a last publish and the end.
        let (requests, rx) = std::sync::mpsc::channel::<usize>();
        let link = std::thread::spawn(move || {
            while let Ok(n) = rx.recv() {
                for _ in 0..n.max(1) {
                    publisher.publish_poll(PollStamp::now());
                }
                if n == 0 {
                    return;
                }
            }
        });
        let within = Duration::from_secs(10);

        requests.send(1).unwrap();
        for session in &mut sessions {
            let changed = tokio::time::timeout(within, session.changed()).await;
            changed.expect("woken by the relay").expect("link up");
            assert_eq!(session.borrow_and_update().seq, 1);
        }
        // Seen: no wake-up without a newer snapshot.
        let idle = tokio::time::timeout(Duration::from_millis(50), sessions[0].changed()).await;
        assert!(idle.is_err(), "woken without a new snapshot");

        // Two publishes: whenever the wake comes, the latest is what is read.
        requests.send(2).unwrap();
        for session in &mut sessions {
            tokio::time::timeout(within, session.changed())
                .await
                .expect("woken")
                .expect("link up");
            while session.borrow_and_update().seq < 3 {
                tokio::time::timeout(within, session.changed())
                    .await
                    .expect("woken")
                    .expect("link up");
            }
        }

        // The end: the last snapshot first, then the error, for every session.
        requests.send(0).unwrap();
        link.join().unwrap();
        for session in &mut sessions {
            let last = tokio::time::timeout(within, session.changed()).await;
            last.expect("woken")
                .expect("the last snapshot before the end");
            assert_eq!(session.borrow_and_update().seq, 4);
            let end = tokio::time::timeout(within, session.changed()).await;
            assert!(end.expect("woken").is_err(), "the end is told");
        }
    }

    #[test]
    fn a_session_that_missed_snapshots_still_learns_of_every_reload() {
        let (mut publisher, rx) = publisher();
        assert_eq!(rx.borrow().notice_seq(), 0);
        publisher.announce(true, "other.pub".into());
        publisher.publish();
        publisher.announce(false, "other.pub".into());
        publisher.publish();
        publisher.publish_poll(PollStamp::now());
        // Only the latest snapshot is looked at: a "changed" reload followed
        // by an unchanged one must not read as "nothing changed".
        let latest = rx.borrow().clone();
        assert_eq!(latest.notice_seq(), 2);
        assert_eq!(
            told(&latest, 0),
            [(1, true, "other.pub"), (2, false, "other.pub")]
        );
        assert_eq!(told(&latest, 1), [(2, false, "other.pub")]);
        assert!(told(&latest, 2).is_empty());
    }

    #[test]
    fn an_uncertain_value_is_stale_until_the_device_says_good() {
        let table = Arc::new(crate::vars::table_of(&[("A", "INT"), ("B", "INT")]));
        let (publisher, stream) =
            Publisher::new(table, FormatOptions::default(), Duration::from_secs(60));
        let mut publisher = publisher.with_diff_block(b"\r\n");
        let a = publisher.table().fixed_count() as VarId;
        let b = a + 1;
        let poll = |publisher: &mut Publisher, value: i16| {
            let stamp = PollStamp::now();
            publisher.update(a, &value.to_le_bytes(), stamp.unix_ms);
            publisher.update(b, &value.to_le_bytes(), stamp.unix_ms);
            publisher.publish_poll(stamp);
        };
        poll(&mut publisher, 1);
        let first = stream.latest();
        assert_eq!(first.quality(a), Quality::Good);

        // Uncertain, same value: a change of quality only.
        assert!(publisher.set_uncertain(a, true, 1_000));
        assert!(!publisher.set_uncertain(a, true, 2_000), "no change");
        publisher.publish();
        let now = stream.latest();
        assert_eq!(now.quality(a), Quality::Stale);
        assert_eq!(now.quality_at(a, Instant::now()), Quality::Stale);
        assert_eq!(now.quality(b), Quality::Good);
        assert!(now.slot(a).uncertain());
        assert_eq!(now.slot(a).changed_seq, first.slot(a).changed_seq);
        assert_eq!(now.slot(a).changed_ms, 1_000, "the device's time of it");
        assert_eq!(now.requalified, [a]);
        assert!(now.changed.is_empty(), "no value changed");
        assert!(now.diff_block().is_none(), "no DIFF line for quality alone");
        // Still served as a value (GET and DIFF have no quality).
        assert_eq!(now.current(a).and_then(Slot::text), Some(&b"1"[..]));

        // The poll's update leaves the mark alone, changed value or not.
        poll(&mut publisher, 1);
        assert_eq!(stream.latest().quality(a), Quality::Stale);
        poll(&mut publisher, 2);
        let now = stream.latest();
        assert_eq!(now.quality(a), Quality::Stale);
        assert_eq!(now.changed, [a, b]);
        assert!(now.requalified.is_empty());

        // Good again.
        assert!(publisher.set_uncertain(a, false, 3_000));
        publisher.publish();
        let now = stream.latest();
        assert_eq!(now.quality(a), Quality::Good);
        assert_eq!(now.requalified, [a]);

        // A value and its quality changed in one publish: a value change.
        let stamp = PollStamp::now();
        publisher.update(a, &5i16.to_le_bytes(), stamp.unix_ms);
        publisher.set_uncertain(a, true, 4_000);
        publisher.publish_poll(stamp);
        let now = stream.latest();
        assert_eq!(
            (now.changed.as_slice(), now.requalified.as_slice()),
            (&[a][..], &[][..])
        );
        assert_eq!(now.slot(a).changed_ms, stamp.unix_ms);
        assert_eq!(now.quality(a), Quality::Stale);

        // Lost is lost, uncertain or not; a new table starts good.
        publisher.publish_offline();
        assert_eq!(stream.latest().quality(a), Quality::LinkLost);
        let table = Arc::new(crate::vars::table_of(&[("A", "INT"), ("B", "INT")]));
        publisher.replace_table(table);
        poll(&mut publisher, 7);
        assert_eq!(stream.latest().quality(a), Quality::Good);
    }

    /// A poll that reads values unchanged copies no slots and stamps its
    /// reads without an allocation; what a snapshot says is current stays
    /// as it was published, whatever later polls read.
    #[test]
    fn reads_are_stamped_apart_from_the_slots() {
        let names: Vec<String> = (0..CHUNK + 10).map(|i| format!("V{i}")).collect();
        let vars: Vec<(&str, &str)> = names.iter().map(|n| (n.as_str(), "INT")).collect();
        let table = Arc::new(crate::vars::table_of(&vars));
        let (publisher, stream) = Publisher::new(
            table.clone(),
            FormatOptions::default(),
            Duration::from_secs(60),
        );
        let mut publisher = publisher;
        let all: Vec<VarId> = (0..table.len() as VarId).collect();
        let poll = |publisher: &mut Publisher, ids: &[VarId]| {
            let stamp = PollStamp::now();
            for &id in ids {
                publisher.update(id, &7i16.to_le_bytes(), stamp.unix_ms);
            }
            publisher.publish_poll(stamp);
        };
        poll(&mut publisher, &all);
        let first = stream.latest();
        assert!(all.iter().all(|&id| first.current(id).is_some()));
        // The same values again: every slot shared, every chunk one stamp.
        poll(&mut publisher, &all);
        let second = stream.latest();
        for (now, before) in second.chunks.iter().zip(&first.chunks) {
            assert!(Arc::ptr_eq(now, before), "a slot chunk copied");
        }
        assert!(second
            .reads
            .iter()
            .all(|r| matches!(r, ReadChunk::All(seq) if *seq == second.seq)));
        assert!(all.iter().all(|&id| second.current(id).is_some()));
        // A poll that reads all but one: that one is not current now, and
        // still is in the snapshot before.
        let (left_out, rest) = all.split_last().unwrap();
        poll(&mut publisher, rest);
        let third = stream.latest();
        assert!(third.current(*left_out).is_none());
        assert!(rest.iter().all(|&id| third.current(id).is_some()));
        assert!(
            second.current(*left_out).is_some(),
            "an old snapshot changed"
        );
        assert!(matches!(third.reads.last(), Some(ReadChunk::Each(_))));
        // A SET's read-back after the poll makes it current until the next
        // poll that does not read it.
        publisher.update(*left_out, &7i16.to_le_bytes(), 1);
        assert_eq!(publisher.read_seq(*left_out), publisher.next_seq());
        publisher.publish();
        let fourth = stream.latest();
        assert_eq!(fourth.read_seq(*left_out), fourth.seq);
        assert!(fourth.current(*left_out).is_some());
        poll(&mut publisher, rest);
        assert!(stream.latest().current(*left_out).is_none());
    }

    /// Texts up to INLINE bytes live in the slot, longer ones on the heap:
    /// both read back whole, and a change across the bound is a change.
    #[test]
    fn short_and_long_texts_read_back_whole() {
        let table = Arc::new(crate::vars::table_of(&[("S", "STRING[40]")]));
        let (publisher, stream) =
            Publisher::new(table, FormatOptions::default(), Duration::from_secs(60));
        let mut publisher = publisher;
        let s = publisher.table().fixed_count() as VarId;
        // Quoted: 20 characters are 22 bytes of text, 21 are 23.
        for value in [
            "",
            "a",
            &"x".repeat(20),
            &"y".repeat(21),
            &"z".repeat(40),
            "b",
        ] {
            let mut bytes = value.as_bytes().to_vec();
            bytes.resize(41, 0);
            assert!(publisher.update(s, &bytes, 1), "{value}");
            assert!(!publisher.update(s, &bytes, 2), "{value} again");
            publisher.publish_poll(PollStamp::now());
            let quoted = format!("\"{value}\"").into_bytes();
            let latest = stream.latest();
            assert_eq!(latest.slot(s).text(), Some(&quoted[..]));
            assert_eq!(latest.slot(s).shared_text().as_deref(), Some(&quoted[..]));
            let table = latest.table.clone();
            assert_eq!(
                latest.slot(s).value(table.var(s)),
                Some(Value::Str(value.as_bytes().to_vec()))
            );
        }
    }

    #[test]
    fn the_notice_history_is_bounded() {
        let (mut publisher, rx) = publisher();
        for i in 0..NOTICE_HISTORY + 10 {
            publisher.announce(i % 2 == 0, format!("{i}.pub"));
        }
        publisher.publish();
        let latest = rx.borrow().clone();
        assert_eq!(latest.notices.len(), NOTICE_HISTORY);
        assert_eq!(latest.notice_seq(), (NOTICE_HISTORY + 10) as u64);
        assert_eq!(latest.notices[0].seq, 11);
    }
}
