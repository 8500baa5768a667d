//! The link: one task per PLC section, on a thread of its own, that owns the
//! section's backend. It polls on fixed deadlines, serves the clients' direct
//! reads, SETs, file transfers and SETCONF between polls, watches the link's
//! health, and publishes values ([`crate::changes`]) and the section's live
//! state ([`state`]).
//!
//! Its parts, each with one job: [`health`] (connected, lost, when to probe,
//! what to log), [`cycle`] (plan, read in slices with SETs served between
//! them, system variables), [`refusals`]
//! (what the PLC refuses to read, so one bad variable does not stop its
//! neighbours), [`jobs`] (batching
//! client reads and SETs), [`reconf`] (SETCONF), [`files`] (file transfers
//! and their cache), [`tables`] (public files and the variable table).
//!
//! Freshness: a polled value is served as current only while the poll that
//! read it completed no longer ago than `2 x COMM_LOOP_DELAY + EPSTOUT`
//! ([`fresh_for`]); past that a GET goes to the PLC. Loss is declared when an
//! exchange fails after its one retry; from then on requests are refused at
//! once by the [`LinkHandle`] and one probe at a time looks for the PLC. A
//! SET that could not be sent within EPSTOUT of its arrival is answered with
//! an error and never sent.

pub mod cycle;
pub mod files;
pub mod health;
pub mod jobs;
pub mod plan;
pub mod reconf;
pub mod refusals;
pub mod state;
pub mod tables;
pub mod traced;

use std::sync::Arc;
use std::time::{Duration, SystemTime};

use tokio::sync::{mpsc, oneshot, watch};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::changes::{unix_ms, Notice, Publisher};
use crate::config;
use crate::driver::{Answer, Drivers, PlcBackend, PlcError, PushedVar, ReadRequest};
use crate::metrics::SectionMetrics;
use cycle::{Cycle, SLICE_TIME};
use files::{FileJob, FileReply, Files};
pub use health::LinkState;
use health::{Connected, Failure, Health, SharedState};
pub use jobs::SetItem;
pub use reconf::ConfChange;
use state::{LinkStatus, SectionState};
use tables::{LoadError, Loaded, NamedBy, PubSource, UserFile, UserKind};

/// Why the link could not serve a request.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// No link to the PLC right now (none configured, or lost).
    #[error("no connection to the PLC")]
    Offline,
    /// A SET waited longer than EPSTOUT to be sent: it never will be.
    #[error("not sent within the PLC timeout")]
    Late,
    #[error(transparent)]
    Plc(#[from] PlcError),
}

impl LinkError {
    /// What a client of a failed exchange is told.
    pub fn from_failure(err: &PlcError) -> LinkError {
        LinkError::Plc(PlcError::Timeout(err.to_string()))
    }
}

pub type ReadReply = Result<Vec<Answer<Vec<u8>>>, LinkError>;

#[derive(Debug)]
pub struct SetOutcome {
    /// The bytes read back after the write, or the PLC's refusal.
    pub answer: Answer<Vec<u8>>,
    /// Snapshot sequence that carries the read-back value.
    pub seq: u64,
}

pub type SetReply = Result<SetOutcome, LinkError>;

/// A public-file load that SETCONF caused: the notice every client gets.
#[derive(Debug, Clone)]
pub struct ReconfOutcome {
    pub notice: Arc<Notice>,
}

#[derive(Debug, thiserror::Error)]
pub enum ReconfError {
    /// The PLC does not answer at the new address (ERROR:10).
    #[error("PLC not reachable: {0}")]
    Unreachable(String),
    /// The public file could not be loaded (ERROR:35).
    #[error("{0}")]
    PubFile(String),
}

pub type ReconfReply = Result<ReconfOutcome, ReconfError>;

/// Work the sessions hand to the link.
pub enum Job {
    Read {
        requests: Vec<ReadRequest>,
        reply: oneshot::Sender<ReadReply>,
    },
    Set {
        item: SetItem,
        /// When the client's request arrived (EPSTOUT counts from here).
        arrived: Instant,
        reply: oneshot::Sender<SetReply>,
    },
    /// SETCONF of a key that affects the whole section.
    Reconfigure {
        change: ConfChange,
        reply: oneshot::Sender<ReconfReply>,
    },
    File {
        job: FileJob,
        reply: oneshot::Sender<FileReply>,
    },
}

impl Job {
    /// Answers the job with the link error, unless it is a SETCONF (which
    /// must be served: it may be what brings the link back). Returns it then.
    fn refuse(self, err: LinkError) -> Option<Job> {
        match self {
            Job::Read { reply, .. } => drop(reply.send(Err(err))),
            Job::Set { reply, .. } => drop(reply.send(Err(err))),
            Job::File { reply, .. } => drop(reply.send(Err(err))),
            job @ Job::Reconfigure { .. } => return Some(job),
        }
        None
    }
}

/// The sessions' handle to their section's link. Requests are refused at
/// once, without queueing, while the link is lost or there is no PLC.
#[derive(Clone)]
pub struct LinkHandle {
    jobs: mpsc::UnboundedSender<Job>,
    state: SharedState,
    trace: crate::trace::FrameTrace,
}

impl LinkHandle {
    /// The section's frame trace, shared with the link.
    pub fn trace(&self) -> &crate::trace::FrameTrace {
        &self.trace
    }

    pub fn state(&self) -> LinkState {
        self.state.get()
    }

    /// Sends `job` to the link, or answers it with the link error at once.
    fn submit(&self, job: Job) {
        let job = if self.state.get().accepts_requests() {
            job
        } else {
            match job.refuse(LinkError::Offline) {
                Some(job) => job,
                None => return,
            }
        };
        // A closed channel drops the reply, which the receiver sees as
        // offline.
        let _ = self.jobs.send(job);
    }

    /// Queues direct reads; answers in request order.
    pub fn read(&self, requests: Vec<ReadRequest>) -> oneshot::Receiver<ReadReply> {
        let (reply, rx) = oneshot::channel();
        self.submit(Job::Read { requests, reply });
        rx
    }

    pub fn set(&self, item: SetItem) -> oneshot::Receiver<SetReply> {
        let (reply, rx) = oneshot::channel();
        self.submit(Job::Set {
            item,
            arrived: Instant::now(),
            reply,
        });
        rx
    }

    pub fn reconfigure(&self, change: ConfChange) -> oneshot::Receiver<ReconfReply> {
        let (reply, rx) = oneshot::channel();
        self.submit(Job::Reconfigure { change, reply });
        rx
    }

    pub fn file(&self, job: FileJob) -> oneshot::Receiver<FileReply> {
        let (reply, rx) = oneshot::channel();
        self.submit(Job::File { job, reply });
        rx
    }
}

/// How long after its poll a value may be served as current:
/// `2 x COMM_LOOP_DELAY + EPSTOUT` (a poll is due every COMM_LOOP_DELAY and
/// may take up to EPSTOUT to be answered).
pub fn fresh_for(loop_delay: Duration, answer_timeout: Duration) -> Duration {
    loop_delay * 2 + answer_timeout
}

/// How early the tokio timer wakes the link before a cycle's deadline.
const TIMER_SLACK: Duration = Duration::from_micros(1500);
/// Jobs taken into one batch at most.
const MAX_BATCH: usize = 1024;
/// Pushed values applied between two looks at the queue for a SET.
const PUSHED_PIECE: usize = 1000;

/// The first deadline of the schedule `previous + k * period` after `now`
/// (cycles that are already late are skipped, not bunched), and how many
/// were skipped.
fn next_deadline(previous: Instant, period: Duration, now: Instant) -> (Instant, u32) {
    let next = previous + period;
    if next > now {
        return (next, 0);
    }
    let period_ns = period.as_nanos().max(1);
    let missed = u32::try_from((now - next).as_nanos() / period_ns + 1).unwrap_or(u32::MAX);
    (next + period * missed, missed)
}

/// The public-file side of a section: where the files are, what was loaded.
pub struct Tables {
    pub source: PubSource,
    /// The user file loaded, without its bytes.
    pub user: Option<Loaded>,
    /// The user file must still be fetched from the PLC.
    pub pending_fetch: bool,
    /// The user file's CRC was compared with `__PF_CRC`.
    crc_checked: bool,
}

impl Tables {
    pub fn new(source: PubSource, user: Option<UserFile>, pending_fetch: bool) -> Tables {
        Tables {
            user: user.map(|user| Loaded::of(source.kind, &user)),
            source,
            pending_fetch,
            crc_checked: false,
        }
    }
}

/// Everything a link starts from.
pub struct LinkSetup {
    pub name: String,
    pub backend: Option<Box<dyn PlcBackend>>,
    /// Where a new backend comes from when SETCONF changes the link.
    pub drivers: Drivers,
    pub publisher: Publisher,
    pub config: config::Section,
    pub loop_delay: Duration,
    pub files: files::FileSettings,
    /// How to reload public files; `None` for a section built from a fixed
    /// table (tests).
    pub tables: Option<Tables>,
    pub metrics: Arc<SectionMetrics>,
    /// The section's frame trace (see [`crate::trace`]).
    pub trace: crate::trace::FrameTrace,
}

pub struct Link {
    name: String,
    backend: Option<Box<dyn PlcBackend>>,
    drivers: Drivers,
    health: Health,
    publisher: Publisher,
    state: watch::Sender<Arc<SectionState>>,
    jobs: mpsc::UnboundedReceiver<Job>,
    stop: CancellationToken,
    loop_delay: Duration,
    cycle: Cycle,
    files: Files,
    tables: Option<Tables>,
    metrics: Arc<SectionMetrics>,
    trace: crate::trace::FrameTrace,
    /// The next poll cycle is due then.
    deadline: Instant,
    /// Jobs that came in during a poll behind one that is not a SET: served
    /// when the poll ends, before newer ones.
    held: std::collections::VecDeque<Job>,
    /// The link has a thread of its own, so it may sleep the last stretch
    /// before a cycle precisely; on the shared pool it must not block.
    own_thread: bool,
    pushed_ids: PushedIds,
}

/// The ids of pushed values of [`PushedVar::Listed`] variables, for the
/// table and the backend's list they were found in.
#[derive(Default)]
struct PushedIds {
    /// Held weakly: a table reloaded since is freed, and its address is
    /// not taken by another while this is held.
    table: std::sync::Weak<crate::vars::VarTable>,
    list: u32,
    /// By index in the list; [`PushedIds::UNKNOWN`] where not looked up.
    ids: Vec<crate::vars::VarId>,
}

impl PushedIds {
    const UNKNOWN: crate::vars::VarId = crate::vars::VarId::MAX;

    /// The id of `var` in `table`; a listed one looked up once, by the
    /// name `name_of` gives for its list and index.
    fn id(
        &mut self,
        table: &Arc<crate::vars::VarTable>,
        var: &PushedVar,
        name_of: impl FnOnce(u32, u32) -> Option<Arc<[u8]>>,
    ) -> Option<crate::vars::VarId> {
        let (list, index) = match var {
            PushedVar::Named(name) => return table.lookup(name),
            &PushedVar::Listed { list, index } => (list, index),
        };
        let at = index as usize;
        // Bounded by the table: a list as long (arrays: their elements).
        if at >= table.len().saturating_mul(2) {
            return table.lookup(&name_of(list, index)?);
        }
        if self.list != list || !std::ptr::eq(self.table.as_ptr(), Arc::as_ptr(table)) {
            self.table = Arc::downgrade(table);
            self.list = list;
            self.ids.clear();
        }
        if at >= self.ids.len() {
            self.ids.resize(at + 1, Self::UNKNOWN);
        }
        match self.ids[at] {
            Self::UNKNOWN => {
                let id = table.lookup(&name_of(list, index)?)?;
                self.ids[at] = id;
                Some(id)
            }
            id => Some(id),
        }
    }
}

impl Link {
    /// Creates the link, the handle sessions use and the live state.
    pub fn new(setup: LinkSetup) -> (Link, LinkHandle, watch::Receiver<Arc<SectionState>>) {
        let (jobs_tx, jobs) = mpsc::unbounded_channel();
        let mut health = Health::new(setup.backend.is_some(), Instant::now());
        if let Some(backend) = &setup.backend {
            health.set_backoff(backend.probe_backoff());
        }
        let link_status = LinkStatus {
            state: health.state(),
            describe: describe(setup.backend.as_deref()),
            ident: None,
            source_address: setup.backend.as_ref().and_then(|b| b.source_address()),
            since_ms: unix_ms(SystemTime::now()),
        };
        let table_pending = setup.tables.as_ref().is_some_and(|t| t.pending_fetch);
        let (state, state_rx) = watch::channel(Arc::new(SectionState {
            config: setup.config,
            link: link_status,
            table_pending,
        }));
        let handle = LinkHandle {
            jobs: jobs_tx,
            state: health.shared(),
            trace: setup.trace.clone(),
        };
        let mut link = Link {
            cycle: Cycle::new(setup.name.clone()),
            name: setup.name,
            backend: setup.backend,
            drivers: setup.drivers,
            health,
            publisher: setup.publisher,
            state,
            jobs,
            stop: CancellationToken::new(),
            loop_delay: setup.loop_delay,
            files: Files::new(setup.files, setup.loop_delay),
            tables: setup.tables,
            metrics: setup.metrics,
            trace: setup.trace,
            deadline: Instant::now(),
            held: std::collections::VecDeque::new(),
            own_thread: false,
            pushed_ids: PushedIds::default(),
        };
        link.update_freshness();
        link.count_backend();
        (link, handle, state_rx)
    }

    /// Cancelling this token stops the link.
    pub fn stop_token(&self) -> CancellationToken {
        self.stop.clone()
    }

    fn config(&self) -> config::Section {
        self.state.borrow().config.clone()
    }

    /// The backend counts into the section's metrics, and its requests and
    /// answers go to the section's frame trace.
    fn count_backend(&mut self) {
        let counters = self.metrics.backend.clone();
        if let Some(backend) = self.backend.take() {
            let mut backend = traced::Traced::wrap(backend, self.trace.clone());
            backend.set_counters(counters);
            self.backend = Some(backend);
        }
    }

    fn update_freshness(&mut self) {
        let timeout = self
            .backend
            .as_ref()
            .map_or(Duration::from_secs(1), |b| b.answer_timeout());
        self.publisher
            .set_fresh_for(fresh_for(self.loop_delay, timeout));
    }

    /// Publishes the link's status in the live state.
    fn publish_status(&self, change: impl FnOnce(&mut LinkStatus)) {
        let state = self.health.state();
        let table_pending = self.tables.as_ref().is_some_and(|t| t.pending_fetch);
        self.metrics
            .link_up
            .set(u64::from(state == LinkState::Online));
        self.state.send_modify(|live| {
            let live = Arc::make_mut(live);
            live.table_pending = table_pending;
            if live.link.state != state {
                live.link.since_ms = unix_ms(SystemTime::now());
            }
            live.link.state = state;
            change(&mut live.link);
        });
    }

    /// Runs until stopped or every handle is dropped.
    pub async fn run(mut self) {
        // Fixed deadlines: a late cycle does not shift the ones after it.
        self.deadline = Instant::now();
        loop {
            let deadline = self.deadline;
            // A dedicated thread wakes early and sleeps the rest precisely.
            let wake = match self.own_thread {
                true => deadline.checked_sub(TIMER_SLACK).unwrap_or(deadline),
                false => deadline,
            };
            tokio::select! {
                biased;
                _ = self.stop.cancelled() => break,
                // A due cycle goes before queued requests, so a flood of
                // them cannot delay polling.
                _ = tokio::time::sleep_until(wake) => {
                    // tokio's timer has millisecond granularity: a dedicated
                    // thread sleeps the last stretch precisely. A pooled
                    // loop woke at the deadline (the timer is never early).
                    let now = Instant::now();
                    if self.own_thread && deadline > now {
                        std::thread::sleep(deadline - now);
                    }
                    self.metrics.poll_start_late.observe(Instant::now().saturating_duration_since(deadline));
                    self.tick().await;
                    if !self.held.is_empty() {
                        let held: Vec<Job> = self.held.drain(..).collect();
                        self.serve(held).await;
                    }
                    let missed;
                    (self.deadline, missed) = next_deadline(self.deadline, self.loop_delay, Instant::now());
                    self.metrics.overruns.add(u64::from(missed));
                }
                pushed = wait_pushed(self.backend.as_deref_mut()), if self.health.state() == LinkState::Online => {
                    match pushed {
                        Ok(()) => {
                            self.deliver_pushed().await;
                            // What was queued meanwhile, before the next
                            // take: a device that pushes without a pause
                            // must not keep clients waiting for the poll.
                            let batch = self.queued_batch(None);
                            if !batch.is_empty() {
                                self.serve(batch).await;
                            }
                        }
                        Err(err) => self.judge(&err),
                    }
                }
                job = self.jobs.recv() => {
                    let Some(job) = job else { break };
                    let batch = self.queued_batch(Some(job));
                    self.serve(batch).await;
                }
            }
        }
        debug!(section = %self.name, "link stopped");
    }

    /// The jobs held back, then `first`, then what is queued, up to
    /// [`MAX_BATCH`], in order.
    fn queued_batch(&mut self, first: Option<Job>) -> Vec<Job> {
        let mut batch: Vec<Job> = self.held.drain(..).collect();
        batch.extend(first);
        while batch.len() < MAX_BATCH {
            match self.jobs.try_recv() {
                Ok(job) => batch.push(job),
                Err(_) => break,
            }
        }
        batch
    }

    /// One cycle: connect or probe when due, else poll.
    async fn tick(&mut self) {
        if self.backend.is_none() {
            return;
        }
        if self.health.state() != LinkState::Online
            && (!self.health.probe_due(Instant::now()) || !self.probe().await)
        {
            return;
        }
        if self.files.polling_paused() {
            return;
        }
        self.poll().await;
    }

    /// One connection attempt. While the link is lost, requests that reach
    /// the queue meanwhile are refused at once rather than waiting for it.
    async fn probe(&mut self) -> bool {
        let Some(backend) = self.backend.as_mut() else {
            return false;
        };
        let lost = self.health.state() == LinkState::Lost;
        let mut deferred = Vec::new();
        self.health.probing(Instant::now());
        let result = {
            let connect = backend.probe();
            tokio::pin!(connect);
            loop {
                tokio::select! {
                    biased;
                    _ = self.stop.cancelled() => return false,
                    result = &mut connect => break result,
                    Some(job) = self.jobs.recv(), if lost => {
                        deferred.extend(job.refuse(LinkError::Offline));
                    }
                }
            }
        };
        let online = match result {
            Ok(ident) => {
                self.connected(ident).await;
                true
            }
            Err(err) => {
                self.failed(&err);
                false
            }
        };
        // SETCONFs that came in meanwhile.
        if !deferred.is_empty() {
            Box::pin(self.serve(deferred)).await;
        }
        online
    }

    async fn connected(&mut self, ident: String) {
        let away = self.health.connected(Instant::now());
        let backend = self.backend.as_deref().expect("connected to a backend");
        let describe = backend.describe();
        let source_address = backend.source_address();
        match away {
            Connected::Again(away) => {
                info!(section = %self.name, plc = %describe, ident = %ident, "PLC connected again after {:.1} s", away.as_secs_f64())
            }
            Connected::First => {
                info!(section = %self.name, plc = %describe, ident = %ident, "PLC connected")
            }
            Connected::Retrial => {
                debug!(section = %self.name, "flapping PLC connected once more")
            }
        }
        if self.tables.as_ref().is_some_and(|t| t.pending_fetch) {
            if let Err(err) = self.reload(NamedBy::Configuration).await {
                let serving = match self.user_kind() {
                    UserKind::PubFile | UserKind::DeviceSymbols => "the fixed variables",
                    UserKind::ModbusTags | UserKind::S7Tags | UserKind::Opcua => {
                        "__PLC_RUN and __PF_CRC"
                    }
                };
                warn!(section = %self.name, "{err}; serving {serving} only, tried again at the next connection");
            }
        }
        // After the table: sessions waiting for it see both at once.
        self.publish_status(|link| {
            link.ident = Some(ident);
            link.source_address = source_address;
        });
    }

    /// An exchange or a connection attempt failed: the link is lost (or
    /// stays lost). Everything queued is refused at once.
    fn failed(&mut self, err: &PlcError) {
        let describe = describe(self.backend.as_deref());
        match self.health.failed(Instant::now()) {
            Failure::Lost => {
                warn!(section = %self.name, plc = %describe, "PLC lost: {err}; retrying")
            }
            Failure::Unreachable => {
                warn!(section = %self.name, plc = %describe, "cannot reach PLC: {err}; retrying")
            }
            Failure::StillDown => debug!(section = %self.name, "PLC still not answering: {err}"),
            Failure::Unsteady => {
                let pause = self.health.next_probe_in(Instant::now());
                warn!(section = %self.name, plc = %describe, "PLC fails soon after connecting: {err}; reconnecting in {:.1} s, longer each time it fails again, counted in the log once a minute", pause.as_secs_f64())
            }
            Failure::Flapped => {
                debug!(section = %self.name, "flapping PLC failed again: {err}");
                if let Some(flaps) = self.health.flap_report(Instant::now()) {
                    let pause = self.health.next_probe_in(Instant::now());
                    warn!(section = %self.name, plc = %describe, "PLC failed soon after connecting {flaps} more times in the last minute, last: {err}; next try in {:.1} s", pause.as_secs_f64())
                }
            }
        }
        self.cycle.link_lost();
        if self.publisher.online() {
            self.publisher.publish_offline();
        }
        self.publish_status(|_| {});
    }

    /// A poll succeeded: a flapping link may be steady again.
    fn good_poll(&mut self) {
        if let Some(steady) = self.health.polled(Instant::now()) {
            let describe = describe(self.backend.as_deref());
            info!(section = %self.name, plc = %describe, "PLC connected again and steady after {} failures soon after connecting in {:.1} s", steady.flaps, steady.unsteady_for.as_secs_f64());
        }
    }

    /// A failed exchange with a link error means the PLC is lost; a garbled
    /// answer or a refusal does not.
    fn judge(&mut self, err: &PlcError) {
        if err.is_link_failure() && self.health.state() == LinkState::Online {
            self.failed(err);
        }
    }

    /// Publishes what the device pushed, each value with its own time: one
    /// publish per run of distinct variables, so a follower (the historian)
    /// sees every sample of a variable that changed twice. A SET queued
    /// meanwhile waits for [`PUSHED_PIECE`] values at most, not the whole
    /// take: what is applied so far is published and the SET served.
    async fn deliver_pushed(&mut self) {
        let Some(backend) = self.backend.as_deref_mut() else {
            return;
        };
        let started = Instant::now();
        let pushed = backend.take_pushed();
        if pushed.is_empty() {
            return;
        }
        let taken = Instant::now();
        let count = pushed.len();
        let table = self.publisher.table().clone();
        // Variables SET during this take: its values of them were sampled
        // before the Write (taken before it was sent), and would undo it.
        let mut set = std::collections::HashSet::new();
        for (n, value) in pushed.into_iter().enumerate() {
            if n % PUSHED_PIECE == PUSHED_PIECE - 1 && !self.jobs.is_empty() {
                self.publisher.publish();
                set.extend(self.sets_meanwhile().await);
                if self.health.state() != LinkState::Online
                    || !Arc::ptr_eq(&table, self.publisher.table())
                {
                    return;
                }
            }
            let name_of = |list, index| self.backend.as_deref()?.pushed_name(list, index);
            let Some(id) = self.pushed_ids.id(&table, &value.var, name_of) else {
                continue;
            };
            if set.contains(&id) {
                continue;
            }
            // Its second value since the last publish: that one first.
            if self.publisher.read_seq(id) == self.publisher.next_seq() {
                self.publisher.publish();
            }
            self.publisher.update(id, &value.bytes, value.unix_ms);
            self.publisher
                .set_uncertain(id, value.uncertain, value.unix_ms);
        }
        self.publisher.publish();
        debug!(
            target: jobs::SET_TIMING,
            section = %self.name,
            count,
            take_us = jobs::micros(taken - started),
            apply_us = jobs::micros(taken.elapsed()),
            "pushed"
        );
    }

    async fn poll(&mut self) {
        self.deliver_pushed().await;
        let Some(backend) = self.backend.as_deref_mut() else {
            return;
        };
        let started = Instant::now();
        let mut round = self.cycle.begin(backend, &self.publisher);
        loop {
            let backend = self.backend.as_deref_mut().expect("polling it");
            let slice = Instant::now();
            match self.cycle.read_slice(backend, &mut round).await {
                Ok(true) => {}
                Ok(false) => break,
                Err(err) => return self.failed(&err),
            }
            debug!(target: jobs::SET_TIMING, section = %self.name, slice_us = jobs::micros(slice.elapsed()), "poll slice");
            self.sets_meanwhile().await;
            if self.health.state() != LinkState::Online {
                return;
            }
        }
        // The values too are applied a slice's time at a time, with SETs
        // between (at 100,000 variables the whole was 6-19 ms).
        let backend = self.backend.as_deref_mut().expect("polling it");
        let mut finishing = self.cycle.finish_begin(backend, &self.publisher, round);
        loop {
            let piece = Instant::now();
            let more = self
                .cycle
                .finish_piece(&mut self.publisher, &mut finishing, SLICE_TIME);
            debug!(target: jobs::SET_TIMING, section = %self.name, finish_us = jobs::micros(piece.elapsed()), "poll finish");
            if !more {
                break;
            }
            self.sets_meanwhile().await;
            if self.health.state() != LinkState::Online {
                return;
            }
        }
        let backend = self.backend.as_deref_mut().expect("polling it");
        let ending = Instant::now();
        let polled = self
            .cycle
            .finish_end(backend, &mut self.publisher, finishing)
            .await;
        debug!(target: jobs::SET_TIMING, section = %self.name, finish_us = jobs::micros(ending.elapsed()), "poll finish");
        self.metrics.poll_cycle.observe(started.elapsed());
        if let Err(err) = polled {
            return self.failed(&err);
        }
        self.good_poll();
        let events = self.cycle.take_events();
        if events.halt_to_run {
            // After HALT -> RUN the PLC expects its clients to start anew.
            let backend = self.backend.as_deref_mut().expect("polled it");
            match backend.connect().await {
                Ok(_) => info!(section = %self.name, "HALT -> RUN: PLC link re-initialised"),
                Err(err) => return self.failed(&err),
            }
        }
        if let Some((last, now)) = events.crc_changed {
            let kind = self.user_kind();
            info!(section = %self.name, "{}", kind.changed(last, now));
            if let Some(tables) = self.tables.as_mut() {
                tables.crc_checked = false;
            }
            if let Err(err) = self.reload(NamedBy::Configuration).await {
                warn!(section = %self.name, "{} not reloaded: {err}", kind.what());
            }
            return;
        }
        if let Some(crc) = events.pf_crc {
            self.check_crc(crc);
        }
    }

    /// Serves the SETs that came in during a poll (between its slices) or
    /// a take of pushed values; the jobs queued after the first that is
    /// not a SET wait for the poll's or the take's end, in order. Returns
    /// the table variables the SETs were for.
    async fn sets_meanwhile(&mut self) -> Vec<crate::vars::VarId> {
        while let Ok(job) = self.jobs.try_recv() {
            self.held.push_back(job);
        }
        let mut sets = Vec::new();
        while matches!(self.held.front(), Some(Job::Set { .. })) {
            sets.extend(self.held.pop_front());
        }
        let table = self.publisher.table();
        let ids = sets
            .iter()
            .filter_map(|job| match job {
                Job::Set { item, .. } => item
                    .var
                    .as_ref()
                    .filter(|(of, _)| Arc::ptr_eq(of, table))
                    .map(|(_, id)| *id),
                _ => None,
            })
            .collect();
        if !sets.is_empty() {
            self.serve(sets).await;
        }
        ids
    }

    /// What describes this section's variables: a public file, or a tag
    /// file (its log lines say so).
    fn user_kind(&self) -> UserKind {
        self.tables
            .as_ref()
            .map_or_else(|| UserKind::of(&self.config()), |t| t.source.kind)
    }

    /// PUBFILE_CRC: the user file's CRC trailer must match `__PF_CRC`. A
    /// mismatch is logged once per file; the variables stay served. Not for
    /// a tag file: a Modbus section's `__PF_CRC` is that file's own CRC.
    fn check_crc(&mut self, pf_crc: u64) {
        let check = self.state.borrow().config.pubfile_crc && self.user_kind() == UserKind::PubFile;
        let Some(tables) = self.tables.as_mut() else {
            return;
        };
        if tables.crc_checked {
            return;
        }
        tables.crc_checked = true;
        let Some(user) = &tables.user else {
            return;
        };
        if !check {
            return;
        }
        match user.crc {
            Some(crc) if u64::from(crc) == pf_crc => {
                debug!(section = %self.name, "public file {} matches __PF_CRC {crc:08X}", user.name)
            }
            Some(crc) => warn!(
                section = %self.name,
                "public file {} has CRC {crc:08X} but the PLC's __PF_CRC is {pf_crc:08X}: the file does not describe the program in the PLC",
                user.name
            ),
            None => warn!(
                section = %self.name,
                "PUBFILE_CRC = Yes but public file {} has no CRC line",
                user.name
            ),
        }
    }

    /// Loads the public file again; when its content changed, switches every
    /// client to the new table. Announces the outcome (250 or 251). A local
    /// file is read and parsed off this thread while polling goes on; a file
    /// a client named with PUBFILE_CRC = Yes must carry the CRC of the
    /// program in the PLC.
    async fn reload(&mut self, by: NamedBy) -> Result<Arc<Notice>, String> {
        let config = self.config();
        let Some(tables) = self.tables.as_ref() else {
            return Err("this section has no public-file source".to_string());
        };
        let source = tables.source.clone();
        let loaded = {
            let (source, config, name) = (source.clone(), config.clone(), self.name.clone());
            self.poll_while(tokio::task::spawn_blocking(move || {
                let user = source.load_local(&config, by)?;
                let table = source
                    .build(&name, user.as_ref())
                    .map_err(LoadError::Failed)?;
                // Digesting a 60 MB file takes as long as parsing it: off
                // the link's thread too.
                Ok((user.map(|user| Loaded::of(source.kind, &user)), table))
            }))
            .await
            .unwrap_or_else(|e| Err(LoadError::Failed(format!("loading failed: {e}"))))
        };
        let online = self.health.state() == LinkState::Online;
        let loaded = match loaded {
            Ok(loaded) => Ok(loaded),
            Err(LoadError::Failed(message)) => Err(message),
            Err(LoadError::FromPlc) => {
                let backend = if online {
                    self.backend.as_deref_mut()
                } else {
                    None
                };
                match source.load_user(&config, by, backend).await {
                    Ok(user) => {
                        let name = self.name.clone();
                        let source = source.clone();
                        self.poll_while(tokio::task::spawn_blocking(move || {
                            let table = source.build(&name, user.as_ref())?;
                            Ok((user.map(|user| Loaded::of(source.kind, &user)), table))
                        }))
                        .await
                        .unwrap_or_else(|e| Err(format!("loading failed: {e}")))
                    }
                    Err(message) => Err(message),
                }
            }
        };
        // A PLC that cannot be asked now is asked at its next connection.
        self.tables.as_mut().expect("checked above").pending_fetch = loaded.is_err();
        let (user, table) = loaded?;
        if by == NamedBy::Client && config.pubfile_crc && source.kind == UserKind::PubFile {
            let file = user.as_ref().map_or("", |u| u.name.as_str());
            let Some(crc) = user.as_ref().and_then(|user| user.crc) else {
                return Err(format!(
                    "PUBFILE_CRC = Yes and public file {file} has no CRC line"
                ));
            };
            // The program in the PLC now, not as of the last poll.
            match self.read_pf_crc().await {
                Some(pf_crc) if u64::from(crc) == pf_crc => {}
                Some(pf_crc) => {
                    return Err(format!(
                        "PUBFILE_CRC = Yes and public file {file} has CRC {crc:08X}, the PLC's program {pf_crc:08X}"
                    ))
                }
                None => {
                    return Err(format!(
                        "PUBFILE_CRC = Yes and the PLC's __PF_CRC cannot be read to check {file}"
                    ))
                }
            }
        }
        let tables = self.tables.as_mut().expect("checked above");
        let name = user
            .as_ref()
            .map_or_else(|| tables.source.fixed_name.clone(), |u| u.name.clone());
        let changed = user != tables.user;
        let what = tables.source.kind.what();
        if changed {
            info!(section = %self.name, variables = table.len(), "{what} {name} loaded: new variable table");
            self.publisher.replace_table(Arc::new(table));
            self.metrics.pubfile_reloads.inc();
            self.cycle.reset();
            tables.user = user;
            tables.crc_checked = false;
        } else {
            info!(section = %self.name, "{what} {name} reloaded: content unchanged");
        }
        let notice = self.publisher.announce(changed, name);
        self.publisher.publish();
        Ok(notice)
    }

    /// `__PF_CRC` read from the PLC now, if it answers.
    async fn read_pf_crc(&mut self) -> Option<u64> {
        if self.health.state() != LinkState::Online {
            return None;
        }
        let table = self.publisher.table().clone();
        let var = table.var(table.pf_crc());
        let request = ReadRequest {
            area: var.area,
            offset: var.offset,
            len: var.byte_len(),
        };
        let backend = self.backend.as_deref_mut()?;
        match jobs::read_ranges(backend, &[request]).await {
            Ok(answers) => match answers.into_iter().next()? {
                Ok(bytes) => match var.decode(&bytes) {
                    plccoms_protocol::value::Value::Unsigned(crc) => Some(crc),
                    _ => None,
                },
                Err(_) => None,
            },
            Err(err) => {
                self.judge(&err);
                None
            }
        }
    }

    /// Waits for `job` (work on another thread), polling on schedule
    /// meanwhile: a long load never stops the values.
    async fn poll_while<T>(
        &mut self,
        job: tokio::task::JoinHandle<T>,
    ) -> Result<T, tokio::task::JoinError> {
        tokio::pin!(job);
        loop {
            let online = self.health.state() == LinkState::Online && self.backend.is_some();
            tokio::select! {
                biased;
                done = &mut job => return done,
                _ = tokio::time::sleep_until(self.deadline), if online => {
                    let backend = self.backend.as_deref_mut().expect("online");
                    let started = Instant::now();
                    let polled = self.cycle.poll(backend, &mut self.publisher).await;
                    self.metrics.poll_cycle.observe(started.elapsed());
                    match polled {
                        Ok(()) => self.good_poll(),
                        Err(err) => self.failed(&err),
                    }
                    (self.deadline, _) = next_deadline(self.deadline, self.loop_delay, Instant::now());
                }
            }
        }
    }

    /// SETCONF of a section key: apply it, reconnect when the link changed,
    /// reload the public file, and tell every client. A SETCONF that fails
    /// (the PLC does not answer, the public file cannot be loaded) is undone:
    /// the section keeps its settings and its link.
    async fn reconfigure(&mut self, change: ConfChange) -> ReconfReply {
        let Some(tables) = self.tables.as_ref() else {
            return Err(ReconfError::PubFile(
                "this section cannot be reconfigured".to_string(),
            ));
        };
        let pending_before = tables.pending_fetch;
        let before = self.config();
        let (config, relink) = reconf::apply(&before, &change);
        // A link this server cannot make is refused before anything
        // changes, so the section keeps its working link.
        let backend = if relink {
            Some(
                self.drivers
                    .open(&config, &tables.source.dir)
                    .map_err(ReconfError::Unreachable)?,
            )
        } else {
            None
        };
        let said = change.describe(tables.source.kind != UserKind::PubFile);
        info!(section = %self.name, "SETCONF: {said}");
        self.set_config(config);
        let mut old_backend = None;
        if let Some(backend) = backend {
            old_backend = Some(std::mem::replace(&mut self.backend, backend));
            if let Some(tables) = self.tables.as_mut() {
                // Loaded below once connected, not twice.
                tables.pending_fetch = false;
            }
            self.relinked();
            if self.backend.is_none() || !self.probe().await {
                let describe = describe(self.backend.as_deref());
                warn!(section = %self.name, "SETCONF {said} refused: the PLC at {describe} does not answer; the section keeps its settings");
                self.undo(before, old_backend, pending_before);
                return Err(ReconfError::Unreachable(describe));
            }
        }
        let by = match change {
            ConfChange::PubFile(_) => NamedBy::Client,
            _ => NamedBy::Configuration,
        };
        match self.reload(by).await {
            Ok(notice) => Ok(ReconfOutcome { notice }),
            Err(err) => {
                warn!(section = %self.name, "SETCONF {said} refused: {err}; the section keeps its settings");
                self.undo(before, old_backend, pending_before);
                Err(ReconfError::PubFile(err))
            }
        }
    }

    fn set_config(&mut self, config: config::Section) {
        self.state
            .send_modify(|live| Arc::make_mut(live).config = config);
    }

    /// A new backend is in place: connect to it from scratch.
    fn relinked(&mut self) {
        self.count_backend();
        if let Some(backend) = &self.backend {
            self.health.set_backoff(backend.probe_backoff());
        }
        self.health.reset(self.backend.is_some(), Instant::now());
        self.cycle.reset();
        self.update_freshness();
        if let Some(tables) = self.tables.as_mut() {
            tables.crc_checked = false;
        }
        let text = describe(self.backend.as_deref());
        self.publish_status(|link| {
            link.describe = text;
            link.ident = None;
        });
    }

    /// Puts back the settings (and the link, if it was replaced) a refused
    /// SETCONF changed.
    fn undo(
        &mut self,
        config: config::Section,
        backend: Option<Option<Box<dyn PlcBackend>>>,
        pending_fetch: bool,
    ) {
        self.set_config(config);
        if let Some(tables) = self.tables.as_mut() {
            tables.pending_fetch = pending_fetch;
        }
        if let Some(backend) = backend {
            self.backend = backend;
            self.relinked();
            if self.backend.is_none() {
                self.publisher.publish_offline();
            }
        }
    }

    /// Serves a batch of jobs in arrival order; consecutive reads share one
    /// plan, consecutive SETs one write request and one read-back per round.
    /// A SET that waited in the queue longer than EPSTOUT before its batch
    /// was taken up is refused: the link was stuck, and a command sent that
    /// late is not what its sender meant any more. (Within a batch, a PLC
    /// that stops answering is declared lost, which refuses the rest.)
    async fn serve(&mut self, batch: Vec<Job>) {
        let taken = Instant::now();
        if self.health.state() == LinkState::Connecting && self.health.probe_due(Instant::now()) {
            // A request is a reason to try the link now rather than at the
            // next tick.
            self.probe().await;
        }
        let mut batch = batch.into_iter().peekable();
        while let Some(job) = batch.next() {
            if self.health.state() != LinkState::Online {
                if let Some(Job::Reconfigure { change, reply }) = job.refuse(LinkError::Offline) {
                    let _ = reply.send(self.reconfigure(change).await);
                }
                continue;
            }
            match job {
                Job::Read { requests, reply } => {
                    let mut group = vec![(requests, reply)];
                    while let Some(Job::Read { .. }) = batch.peek() {
                        if let Some(Job::Read { requests, reply }) = batch.next() {
                            group.push((requests, reply));
                        }
                    }
                    let backend = self.backend.as_deref_mut().expect("online");
                    if let Err(err) = jobs::serve_reads(backend, group).await {
                        self.judge(&err);
                    }
                }
                Job::Reconfigure { change, reply } => {
                    let _ = reply.send(self.reconfigure(change).await);
                }
                Job::Set {
                    item,
                    arrived,
                    reply,
                } => {
                    let mut group = vec![(item, arrived, reply)];
                    while let Some(Job::Set { .. }) = batch.peek() {
                        if let Some(Job::Set {
                            item,
                            arrived,
                            reply,
                        }) = batch.next()
                        {
                            group.push((item, arrived, reply));
                        }
                    }
                    self.serve_sets(group, taken).await;
                }
                Job::File { job, reply } => {
                    let answer = self.serve_file(job).await;
                    let _ = reply.send(answer);
                }
            }
        }
    }

    async fn serve_sets(
        &mut self,
        group: Vec<(SetItem, Instant, oneshot::Sender<SetReply>)>,
        taken: Instant,
    ) {
        let backend = self.backend.as_deref_mut().expect("online");
        let limit = backend.answer_timeout();
        let mut timely = Vec::with_capacity(group.len());
        let mut oldest = taken;
        for (item, arrived, reply) in group {
            if taken.saturating_duration_since(arrived) > limit {
                let _ = reply.send(Err(LinkError::Late));
            } else {
                oldest = oldest.min(arrived);
                timely.push((item, reply));
            }
        }
        if timely.is_empty() {
            return;
        }
        if let Err(err) = jobs::serve_sets(backend, &mut self.publisher, timely, oldest).await {
            self.judge(&err);
        }
    }

    async fn serve_file(&mut self, job: FileJob) -> FileReply {
        let result = {
            let Link {
                backend,
                files,
                cycle,
                publisher,
                ..
            } = self;
            let backend = backend.as_deref_mut().expect("online");
            files.run(job, backend, cycle, publisher).await
        };
        match result {
            Ok(answer) => Ok(answer),
            Err(err) => {
                self.judge(&err);
                Err(LinkError::from_failure(&err))
            }
        }
    }
}

fn describe(backend: Option<&dyn PlcBackend>) -> String {
    backend.map_or_else(|| "no PLC configured".to_string(), |b| b.describe())
}

/// Where a section's link runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// A thread of its own, at real-time priority `priority` (COMM_SCHED_PRI,
    /// 0 = normal) when the process may have it: for a real-time priority
    /// and for serial lines, whose silences are timed below the timer's
    /// millisecond step.
    OwnThread { priority: u8 },
    /// A task on the links' shared pool of threads (see [`pool`]).
    Pool,
}

impl Placement {
    /// The placement a section's configuration asks for. A section moved
    /// onto a serial line later by SETCONF keeps its place; a Modbus RTU
    /// line's waits below a millisecond then block a pool thread that long.
    pub fn of(config: &config::Section, priority: u8) -> Placement {
        if priority > 0 || config.serial_device.is_some() {
            Placement::OwnThread { priority }
        } else {
            Placement::Pool
        }
    }
}

/// A running link: its thread or its task on the pool.
pub enum Running {
    Thread(std::thread::JoinHandle<()>),
    Task(tokio::task::JoinHandle<()>),
}

impl Running {
    /// The link's loop has ended.
    pub fn is_finished(&self) -> bool {
        match self {
            Running::Thread(thread) => thread.is_finished(),
            Running::Task(task) => task.is_finished(),
        }
    }
}

/// Starts the link where `placement` says.
pub fn spawn(mut link: Link, placement: Placement) -> std::io::Result<Running> {
    match placement {
        Placement::OwnThread { priority } => {
            link.own_thread = true;
            spawn_thread(link, priority).map(Running::Thread)
        }
        Placement::Pool => {
            use tracing::instrument::WithSubscriber;
            // The task logs where its creator logs (a scoped subscriber
            // included), as a link thread does.
            let dispatch = tracing::dispatcher::get_default(|d| d.clone());
            Ok(Running::Task(
                pool()?.spawn(link.run().with_subscriber(dispatch)),
            ))
        }
    }
}

/// The runtime every pooled link runs on: a few threads for all sections
/// (one per core, at most 8) instead of a thread and a runtime per
/// section, which at a thousand sections cost 50 KB of stack each and a
/// context switch per wake-up. It is apart from the clients' runtime, so
/// that client load never queues a poll cycle behind client work.
pub fn pool() -> std::io::Result<&'static tokio::runtime::Runtime> {
    static POOL: Pool = Pool::new("links", links_threads);
    POOL.get()
}

fn links_threads() -> usize {
    std::thread::available_parallelism().map_or(2, |n| n.get().clamp(1, 8))
}

/// A runtime of threads named `name` apart from the others, started at its
/// first use; where the process may start no more threads, that use gets
/// the error and the next one tries again.
pub struct Pool {
    runtime: std::sync::OnceLock<tokio::runtime::Runtime>,
    start: std::sync::Mutex<()>,
    name: &'static str,
    threads: fn() -> usize,
}

impl Pool {
    pub const fn new(name: &'static str, threads: fn() -> usize) -> Pool {
        Pool {
            runtime: std::sync::OnceLock::new(),
            start: std::sync::Mutex::new(()),
            name,
            threads,
        }
    }

    pub fn get(&self) -> std::io::Result<&tokio::runtime::Runtime> {
        if let Some(runtime) = self.runtime.get() {
            return Ok(runtime);
        }
        let _once = self.start.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(runtime) = self.runtime.get() {
            return Ok(runtime);
        }
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads((self.threads)())
            .thread_name(self.name)
            .enable_all()
            .build()?;
        Ok(self.runtime.get_or_init(|| runtime))
    }
}

/// Runs the link on a thread of its own, so that client load never delays a
/// poll cycle, with real-time priority `priority` (COMM_SCHED_PRI, 0 = off)
/// when the process may have it.
fn spawn_thread(link: Link, priority: u8) -> std::io::Result<std::thread::JoinHandle<()>> {
    let section = link.name.clone();
    // The thread logs where its creator logs (a scoped subscriber included).
    let dispatch = tracing::dispatcher::get_default(|d| d.clone());
    std::thread::Builder::new()
        .name(format!("link {section}"))
        .spawn(move || {
            let _log = tracing::dispatcher::set_default(&dispatch);
            if priority > 0 {
                if let Err(err) = set_realtime_priority(priority) {
                    warn!(section = %section, "COMM_SCHED_PRI = {priority}: cannot use real-time priority ({err}); polling at normal priority");
                } else {
                    info!(section = %section, "poll loop at real-time priority {priority}");
                }
            }
            match tokio::runtime::Builder::new_current_thread().enable_all().build() {
                Ok(runtime) => runtime.block_on(link.run()),
                Err(err) => warn!(section = %section, "cannot start the poll loop: {err}"),
            }
        })
}

/// SCHED_FIFO at `priority` for the calling thread.
fn set_realtime_priority(priority: u8) -> std::io::Result<()> {
    let param = libc::sched_param {
        sched_priority: i32::from(priority),
    };
    // SAFETY: plain syscall on the current thread with a valid parameter.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        Ok(())
    } else {
        Err(std::io::Error::from_raw_os_error(rc))
    }
}

/// What the backend pushes; never, without one.
async fn wait_pushed(backend: Option<&mut (dyn PlcBackend + 'static)>) -> Result<(), PlcError> {
    match backend {
        Some(backend) => backend.wait_pushed().await,
        None => std::future::pending().await,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A listed pushed value finds its variable by the name the backend
    /// gives once per table and list: a reloaded table, or a new list whose
    /// places mean other variables, is looked up anew.
    #[test]
    fn pushed_keys_are_looked_up_once_per_table_and_list() {
        use crate::vars::table_of;
        let a_b = Arc::new(table_of(&[("A", "INT"), ("B", "INT")]));
        let mut ids = PushedIds::default();
        let asked = std::cell::Cell::new(0);
        // The backend's names: its list `names_of` numbered `list`.
        let names = |list: u32, names: &'static [&'static str]| {
            let asked = &asked;
            move |l: u32, i: u32| {
                asked.set(asked.get() + 1);
                assert_eq!(l, list, "asked for the list of the value");
                names.get(i as usize).map(|n| Arc::from(n.as_bytes()))
            }
        };
        let listed = |list, index| PushedVar::Listed { list, index };
        let list = crate::driver::next_list_version();
        let a = a_b.lookup(b"A").unwrap();
        let b = a_b.lookup(b"B").unwrap();
        assert_eq!(
            ids.id(&a_b, &listed(list, 0), names(list, &["A", "B"])),
            Some(a)
        );
        // Kept by place: the name is not asked again.
        assert_eq!(ids.id(&a_b, &listed(list, 0), names(list, &[])), Some(a));
        assert_eq!(asked.get(), 1);
        assert_eq!(
            ids.id(&a_b, &listed(list, 1), names(list, &["A", "B"])),
            Some(b)
        );
        // A new list: place 0 is B now.
        let next = crate::driver::next_list_version();
        assert_eq!(ids.id(&a_b, &listed(next, 0), names(next, &["B"])), Some(b));
        // A new table (B first), the same list number.
        let b_a = Arc::new(table_of(&[("B", "INT"), ("C", "INT"), ("A", "INT")]));
        assert_eq!(
            ids.id(&b_a, &listed(next, 0), names(next, &["A"])),
            b_a.lookup(b"A")
        );
        assert_ne!(b_a.lookup(b"A"), Some(a));
        // Named, or listed far beyond the table: by name each time.
        let c = PushedVar::Named(Arc::from(&b"C"[..]));
        assert_eq!(ids.id(&b_a, &c, names(next, &[])), b_a.lookup(b"C"));
        let far = listed(next, u32::MAX);
        let asked_before = asked.get();
        for _ in 0..2 {
            let name = |_, _| Some(Arc::from(&b"B"[..]));
            assert_eq!(ids.id(&b_a, &far, name), b_a.lookup(b"B"));
        }
        assert_eq!(asked.get(), asked_before);
        assert!(ids.ids.len() <= 2 * b_a.len());
        // A name the table lacks, or a list the backend no longer serves.
        assert_eq!(
            ids.id(&b_a, &listed(next, 7), |_, _| Some(Arc::from(
                &b"NOT_THERE"[..]
            ))),
            None
        );
        assert_eq!(ids.id(&b_a, &listed(next, 6), |_, _| None), None);
    }

    #[test]
    fn deadlines_stay_on_the_schedule_and_skip_missed_cycles() {
        let start = Instant::now();
        let period = Duration::from_millis(100);
        // On time: the next slot.
        let now = start + Duration::from_millis(30);
        assert_eq!(next_deadline(start, period, now), (start + period, 0));
        // 250 ms late: slots 100 and 200 are gone, 300 is next.
        let now = start + Duration::from_millis(250);
        assert_eq!(next_deadline(start, period, now), (start + period * 3, 2));
        // Exactly on a slot counts as missed: no zero-length cycle.
        let now = start + period * 2;
        assert_eq!(next_deadline(start, period, now), (start + period * 3, 2));
    }

    #[test]
    fn freshness_bound_at_vendor_defaults() {
        assert_eq!(
            fresh_for(Duration::from_millis(100), Duration::from_millis(1000)),
            Duration::from_millis(1200)
        );
    }
}
