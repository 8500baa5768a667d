//! The poller: one task per PLC section that owns the backend. It polls the
//! enabled variables on a fixed-deadline schedule, serves the sessions' direct
//! reads and writes between polls (batching whatever is queued into shared
//! requests), and keeps the link alive across outages.

pub mod files;
pub mod interest;
pub mod plan;
pub mod reload;

use std::time::Duration;

use tokio::sync::{mpsc, oneshot, watch};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::backend::{Answer, Exception, PlcBackend, PlcError, ReadRequest, WriteRequest};
use crate::fanout::Publisher;
use crate::vars::VarId;
use files::{FileCache, FileJob, FileOutput, FileReply};
use plan::{Range, ReadPlan};

/// Why the poller could not serve a request.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// No link to the PLC right now (never connected, or lost).
    #[error("no connection to the PLC")]
    Offline,
    #[error(transparent)]
    Plc(#[from] PlcError),
}

pub type ReadReply = Result<Vec<Answer<Vec<u8>>>, LinkError>;

/// A SET: write, then read the variable back.
#[derive(Debug, Clone)]
pub struct SetItem {
    pub write: WriteRequest,
    pub readback: ReadRequest,
    /// The table variable, so other clients get the DIFF too; ignored when
    /// the table changed meanwhile.
    pub var: Option<(std::sync::Arc<crate::vars::VarTable>, VarId)>,
}

#[derive(Debug)]
pub struct SetOutcome {
    /// The bytes read back after the write, or the PLC's refusal.
    pub answer: Answer<Vec<u8>>,
    /// Snapshot sequence that carries the read-back value.
    pub seq: u64,
}

pub type SetReply = Result<SetOutcome, LinkError>;

/// Work the sessions hand to the poller.
pub enum Job {
    Read {
        requests: Vec<ReadRequest>,
        reply: oneshot::Sender<ReadReply>,
    },
    Set {
        item: SetItem,
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

/// A section setting changed at run time (SETCONF).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConfChange {
    IpAddr(std::net::Ipv4Addr),
    EpsAddr(u8),
    EpsPort(u16),
    SerialDevice(String),
    SerialSpeed(u32),
    PubFile(String),
}

/// A public-file load that SETCONF caused: the notice every client gets.
#[derive(Debug, Clone)]
pub struct ReconfOutcome {
    pub notice: std::sync::Arc<crate::fanout::Notice>,
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

/// File transfer settings (FFILE_MAXRECS, FFILE_TIMEOUT, SYNC_VAR_ENABLED).
#[derive(Debug, Clone, Copy)]
pub struct FileSettings {
    pub cache_recs: usize,
    pub cache_timeout: Duration,
    /// Whether polling goes on while a file transfer is in progress.
    pub sync_var_enabled: bool,
}

impl Default for FileSettings {
    fn default() -> Self {
        FileSettings {
            cache_recs: 0,
            cache_timeout: Duration::ZERO,
            sync_var_enabled: true,
        }
    }
}

/// How long after its last file request a transfer counts as in progress
/// (for SYNC_VAR_ENABLED = No): a client reading a file asks for the next
/// block well within this.
const TRANSFER_IDLE: Duration = Duration::from_millis(500);

/// What GETINFO shows about the link.
#[derive(Debug, Clone, Default)]
pub struct LinkInfo {
    pub describe: String,
    pub ident: Option<String>,
    pub source_address: Option<u8>,
    pub online: bool,
    /// The section's settings as changed by SETCONF (`None`: as configured).
    pub section: Option<crate::config::Section>,
}

/// The sessions' handle to their section's poller.
#[derive(Clone)]
pub struct PollerHandle {
    jobs: mpsc::Sender<Job>,
    info: watch::Receiver<LinkInfo>,
}

impl PollerHandle {
    /// Queues direct reads; answers in request order.
    pub async fn read(&self, requests: Vec<ReadRequest>) -> oneshot::Receiver<ReadReply> {
        let (reply, rx) = oneshot::channel();
        // A closed channel drops `reply`, which the receiver sees as offline.
        let _ = self.jobs.send(Job::Read { requests, reply }).await;
        rx
    }

    pub async fn set(&self, item: SetItem) -> oneshot::Receiver<SetReply> {
        let (reply, rx) = oneshot::channel();
        let _ = self.jobs.send(Job::Set { item, reply }).await;
        rx
    }

    pub async fn reconfigure(&self, change: ConfChange) -> oneshot::Receiver<ReconfReply> {
        let (reply, rx) = oneshot::channel();
        let _ = self.jobs.send(Job::Reconfigure { change, reply }).await;
        rx
    }

    pub async fn file(&self, job: FileJob) -> oneshot::Receiver<FileReply> {
        let (reply, rx) = oneshot::channel();
        let _ = self.jobs.send(Job::File { job, reply }).await;
        rx
    }

    pub fn info(&self) -> LinkInfo {
        self.info.borrow().clone()
    }
}

/// How early the tokio timer wakes the poller before a cycle's deadline.
const TIMER_SLACK: Duration = Duration::from_micros(1500);

/// The first deadline of the schedule `previous + k * period` after `now`
/// (cycles that are already late are skipped, not bunched).
fn next_deadline(previous: Instant, period: Duration, now: Instant) -> Instant {
    let next = previous + period;
    if next > now {
        return next;
    }
    let period_ns = period.as_nanos().max(1);
    let missed = (now - next).as_nanos() / period_ns + 1;
    next + period * u32::try_from(missed).unwrap_or(u32::MAX)
}

/// Retry delays while the PLC is unreachable: short, so polling resumes
/// within a second of the PLC coming back.
const RECONNECT_MIN: Duration = Duration::from_millis(100);
const RECONNECT_MAX: Duration = Duration::from_secs(1);
/// Jobs taken into one batch at most.
const MAX_BATCH: usize = 1024;

pub struct Poller {
    section: String,
    backend: Option<Box<dyn PlcBackend>>,
    publisher: Publisher,
    jobs: mpsc::Receiver<Job>,
    info: watch::Sender<LinkInfo>,
    loop_delay: Duration,
    online: bool,
    /// Outage already logged.
    outage_logged: bool,
    reconnect_delay: Duration,
    next_connect: Instant,
    poll_vars: Vec<VarId>,
    plan: ReadPlan,
    last_run: Option<bool>,
    last_crc: Option<u64>,
    /// Blocks the PLC refused, logged once per plan.
    refused_logged: bool,
    stop: CancellationToken,
    /// How to reload the public files; `None` when the section was built
    /// from a fixed table (tests).
    source: Option<reload::PubSource>,
    user: Option<reload::UserFile>,
    /// The user file's CRC was compared with `__PF_CRC`.
    crc_checked: bool,
    files: FileSettings,
    cache: FileCache,
    /// A file transfer counts as in progress until then.
    transfer_until: Instant,
    last_poll: Instant,
}

impl Poller {
    /// Creates the poller and the handle sessions use. `backend` is `None`
    /// when the section has no PLC yet (`IPADDR = 0.0.0.0`).
    pub fn new(
        section: String,
        backend: Option<Box<dyn PlcBackend>>,
        publisher: Publisher,
        loop_delay: Duration,
    ) -> (Poller, PollerHandle) {
        let (jobs_tx, jobs) = mpsc::channel(4096);
        let describe = backend
            .as_ref()
            .map_or_else(|| "no PLC configured".to_string(), |b| b.describe());
        let (info, info_rx) = watch::channel(LinkInfo {
            describe,
            ident: None,
            source_address: backend.as_ref().and_then(|b| b.source_address()),
            online: false,
            section: None,
        });
        let poller = Poller {
            section,
            backend,
            publisher,
            jobs,
            info,
            loop_delay,
            online: false,
            outage_logged: false,
            reconnect_delay: RECONNECT_MIN,
            next_connect: Instant::now(),
            poll_vars: Vec::new(),
            plan: ReadPlan::default(),
            last_run: None,
            last_crc: None,
            refused_logged: false,
            stop: CancellationToken::new(),
            source: None,
            user: None,
            crc_checked: false,
            files: FileSettings::default(),
            cache: FileCache::new(0, Duration::ZERO),
            transfer_until: Instant::now(),
            last_poll: Instant::now(),
        };
        (
            poller,
            PollerHandle {
                jobs: jobs_tx,
                info: info_rx,
            },
        )
    }

    /// Lets the poller reload public files from `source` (`user` is the
    /// file loaded at start-up).
    pub fn with_source(
        mut self,
        source: reload::PubSource,
        user: Option<reload::UserFile>,
    ) -> Self {
        self.info
            .send_modify(|info| info.section = Some(source.section.clone()));
        self.source = Some(source);
        self.user = user;
        self
    }

    /// Cancelling this token stops the poller.
    pub fn stop_token(&self) -> CancellationToken {
        self.stop.clone()
    }

    pub fn with_file_settings(mut self, files: FileSettings) -> Poller {
        self.cache = FileCache::new(files.cache_recs, files.cache_timeout);
        self.files = files;
        self
    }

    /// Runs until stopped or every handle is dropped.
    pub async fn run(mut self) {
        // Fixed deadlines: a late cycle does not shift the ones after it.
        let mut deadline = Instant::now();
        loop {
            tokio::select! {
                biased;
                _ = self.stop.cancelled() => break,
                // A due cycle goes before queued requests, so a flood of
                // them cannot delay polling.
                _ = tokio::time::sleep_until(deadline.checked_sub(TIMER_SLACK).unwrap_or(deadline)) => {
                    // tokio's timer has millisecond granularity; the last
                    // stretch is slept precisely on this dedicated thread.
                    let now = Instant::now();
                    if deadline > now {
                        std::thread::sleep(deadline - now);
                    }
                    self.cycle().await;
                    deadline = next_deadline(deadline, self.loop_delay, Instant::now());
                }
                job = self.jobs.recv() => {
                    let Some(job) = job else { break };
                    let mut batch = vec![job];
                    while batch.len() < MAX_BATCH {
                        match self.jobs.try_recv() {
                            Ok(job) => batch.push(job),
                            Err(_) => break,
                        }
                    }
                    self.serve(batch).await;
                }
            }
        }
        debug!(section = %self.section, "poller stopped");
    }

    async fn cycle(&mut self) {
        if !self.online {
            if Instant::now() >= self.next_connect {
                self.connect().await;
            }
            if !self.online {
                return;
            }
        }
        if !self.files.sync_var_enabled && Instant::now() < self.transfer_until {
            return;
        }
        self.poll().await;
    }

    async fn connect(&mut self) {
        let Some(backend) = self.backend.as_mut() else {
            return;
        };
        match backend.connect().await {
            Ok(ident) => {
                info!(section = %self.section, plc = %backend.describe(), ident = %ident, "PLC connected");
                self.online = true;
                self.outage_logged = false;
                self.reconnect_delay = RECONNECT_MIN;
                let source_address = backend.source_address();
                self.info.send_modify(|info| {
                    info.ident = Some(ident);
                    info.source_address = source_address;
                    info.online = true;
                });
            }
            Err(err) => {
                if !self.outage_logged {
                    warn!(section = %self.section, plc = %backend.describe(), "cannot reach PLC: {err}; retrying");
                    self.outage_logged = true;
                }
                self.next_connect = Instant::now() + self.reconnect_delay;
                self.reconnect_delay = (self.reconnect_delay * 2).min(RECONNECT_MAX);
            }
        }
    }

    fn go_offline(&mut self, err: &PlcError) {
        if self.online {
            warn!(section = %self.section, "PLC lost: {err}; retrying");
            self.outage_logged = true;
        }
        self.online = false;
        self.last_run = None;
        self.next_connect = Instant::now();
        self.info.send_modify(|info| info.online = false);
        self.publisher.publish(false, false);
    }

    fn rebuild_plan(&mut self, max_block: u32) {
        let table = self.publisher.table().clone();
        let interest = self.publisher.interest().clone();
        self.poll_vars = (0..table.len() as VarId)
            .filter(|&id| table.is_fixed(id) || interest.is_wanted(id))
            .collect();
        let ranges: Vec<Range> = self
            .poll_vars
            .iter()
            .map(|&id| {
                let var = table.var(id);
                Range {
                    area: var.area,
                    offset: var.offset,
                    len: var.byte_len(),
                }
            })
            .collect();
        self.plan = ReadPlan::new(&ranges, max_block);
        self.refused_logged = false;
        debug!(
            section = %self.section,
            variables = self.poll_vars.len(),
            requests = self.plan.blocks().len(),
            bytes = self.plan.bytes(),
            "poll plan rebuilt"
        );
    }

    async fn poll(&mut self) {
        let Some(backend) = self.backend.as_mut() else {
            return;
        };
        let max_block = backend.max_read_block();
        if self.publisher.interest().take_dirty() {
            self.rebuild_plan(max_block);
        }
        let backend = self.backend.as_mut().expect("checked above");
        self.last_poll = Instant::now();
        let answers = match backend.read(self.plan.blocks()).await {
            Ok(answers) => answers,
            // A datagram lost to all its retries is no outage yet (at 20 %
            // loss that happens every few minutes): the PLC is lost only when
            // the cycle fails twice in a row.
            Err(first) => match backend.read(self.plan.blocks()).await {
                Ok(answers) => {
                    debug!(section = %self.section, "poll read failed once ({first}), the retry succeeded");
                    answers
                }
                Err(_) => return self.go_offline(&first),
            },
        };
        let (data, refused) = self.plan.assemble_answers(answers);
        if !refused.is_empty() && !self.refused_logged {
            warn!(section = %self.section, blocks = ?refused, "PLC refused some poll reads; those variables are not updated");
            self.refused_logged = true;
        }
        for (index, &id) in self.poll_vars.iter().enumerate() {
            if let Ok(bytes) = self.plan.range_answer(&data, index) {
                self.publisher.update(id, bytes);
            }
        }
        self.publisher.publish(true, true);
        self.watch_system_variables().await;
    }

    /// HALT -> RUN re-initialises the link; a changed `__PF_CRC` means the
    /// PLC's program changed.
    async fn watch_system_variables(&mut self) {
        let table = self.publisher.table().clone();
        let run = self
            .publisher
            .slot(table.plc_run())
            .value(table.var(table.plc_run()))
            .map(|v| matches!(v, plccoms_protocol::value::Value::Bool(true)));
        if let Some(run) = run {
            if self.last_run != Some(run) {
                if self.last_run.is_some() {
                    info!(section = %self.section, "PLC is in {}", if run { "RUN" } else { "HALT" });
                }
                if self.last_run == Some(false) && run {
                    if let Some(backend) = self.backend.as_mut() {
                        if let Err(err) = backend.connect().await {
                            self.go_offline(&err);
                            return;
                        }
                        info!(section = %self.section, "HALT -> RUN: PLC link re-initialised");
                    }
                }
                self.last_run = Some(run);
            }
        }
        let crc_var = table.var(table.pf_crc());
        let crc = match self.publisher.slot(table.pf_crc()).value(crc_var) {
            Some(plccoms_protocol::value::Value::Unsigned(crc)) => Some(crc),
            _ => None,
        };
        if let (Some(last), Some(now)) = (self.last_crc, crc) {
            if last != now {
                info!(section = %self.section, "__PF_CRC changed ({last:08X} -> {now:08X}): the PLC's program changed, reloading the public file");
                self.last_crc = crc;
                self.crc_checked = false;
                if let Err(err) = self.reload().await {
                    warn!(section = %self.section, "public file not reloaded: {err}");
                }
                return;
            }
        }
        self.last_crc = crc;
        if let Some(crc) = crc {
            self.check_crc(crc);
        }
    }

    /// PUBFILE_CRC: the user file's CRC trailer must match `__PF_CRC`. A
    /// mismatch is logged once per file; the variables stay served.
    fn check_crc(&mut self, pf_crc: u64) {
        if self.crc_checked {
            return;
        }
        self.crc_checked = true;
        let (Some(source), Some(user)) = (&self.source, &self.user) else {
            return;
        };
        if !source.section.pubfile_crc {
            return;
        }
        match reload::trailer_crc(user) {
            Some(crc) if u64::from(crc) == pf_crc => {
                debug!(section = %self.section, "public file {} matches __PF_CRC {crc:08X}", user.name)
            }
            Some(crc) => warn!(
                section = %self.section,
                "public file {} has CRC {crc:08X} but the PLC's __PF_CRC is {pf_crc:08X}: the file does not describe the program in the PLC",
                user.name
            ),
            None => warn!(
                section = %self.section,
                "PUBFILE_CRC = Yes but public file {} has no CRC line",
                user.name
            ),
        }
    }

    /// Loads the public file again; when its content changed, switches every
    /// client to the new table. Announces the outcome (250 or 251).
    async fn reload(&mut self) -> Result<std::sync::Arc<crate::fanout::Notice>, String> {
        let Some(source) = self.source.clone() else {
            return Err("this section has no public-file source".to_string());
        };
        let user = source.load_user(self.backend.as_deref_mut()).await?;
        let name = user
            .as_ref()
            .map_or_else(|| source.fixed_name.clone(), |u| u.name.clone());
        let changed = user != self.user;
        if changed {
            let table = source.build(user.as_ref())?;
            info!(section = %self.section, variables = table.len(), "public file {name} loaded: new variable table");
            self.publisher.replace_table(std::sync::Arc::new(table));
            self.poll_vars.clear();
            self.plan = ReadPlan::default();
            self.user = user;
        } else {
            info!(section = %self.section, "public file {name} reloaded: content unchanged");
        }
        let notice = self.publisher.announce(changed, name);
        let online = self.online;
        self.publisher.publish(false, online);
        Ok(notice)
    }

    /// SETCONF of a section key: apply it, reconnect when the link changed,
    /// reload the public file, and tell every client.
    async fn reconfigure(&mut self, change: ConfChange) -> ReconfReply {
        let Some(source) = self.source.as_ref() else {
            return Err(ReconfError::PubFile(
                "this section cannot be reconfigured".to_string(),
            ));
        };
        let mut section = source.section.clone();
        let relink = match &change {
            ConfChange::IpAddr(ip) => {
                section.ipaddr = Some(*ip);
                // A real address replaces the simulated PLC.
                section.simulator = None;
                true
            }
            ConfChange::EpsAddr(addr) => {
                section.epsaddr = Some(*addr);
                true
            }
            ConfChange::EpsPort(port) => {
                section.epsport = *port;
                true
            }
            ConfChange::SerialDevice(device) => {
                section.serial_device = Some(device.clone());
                true
            }
            ConfChange::SerialSpeed(speed) => {
                section.serial_speed = Some(*speed);
                true
            }
            ConfChange::PubFile(name) => {
                section.pubfile = Some(name.clone());
                false
            }
        };
        // A link this server cannot make (a serial line) is refused before
        // anything changes, so the section keeps its working link.
        let backend = if relink {
            Some(crate::backend::for_section(&section).map_err(ReconfError::Unreachable)?)
        } else {
            None
        };
        if let Some(source) = self.source.as_mut() {
            source.section = section.clone();
        }
        info!(section = %self.section, "SETCONF: {change:?}");
        self.info
            .send_modify(|info| info.section = Some(section.clone()));
        if let Some(backend) = backend {
            self.backend = backend;
            self.online = false;
            self.last_run = None;
            self.last_crc = None;
            self.crc_checked = false;
            let describe = self
                .backend
                .as_ref()
                .map_or_else(|| "no PLC configured".to_string(), |b| b.describe());
            self.info.send_modify(|info| {
                info.describe = describe.clone();
                info.ident = None;
                info.online = false;
            });
            self.next_connect = Instant::now();
            self.connect().await;
            if !self.online {
                self.publisher.publish(false, false);
                return Err(ReconfError::Unreachable(describe));
            }
        }
        let notice = self.reload().await.map_err(ReconfError::PubFile)?;
        Ok(ReconfOutcome { notice })
    }

    /// Serves a batch of jobs in arrival order; consecutive reads share one
    /// plan, consecutive SETs one write request and one read-back.
    async fn serve(&mut self, batch: Vec<Job>) {
        if !self.online && Instant::now() >= self.next_connect {
            // A request is a reason to try the link now rather than at the
            // next tick.
            self.connect().await;
        }
        let mut batch = batch.into_iter().peekable();
        while let Some(job) = batch.next() {
            match job {
                Job::Read { requests, reply } => {
                    let mut group = vec![(requests, reply)];
                    while let Some(Job::Read { .. }) = batch.peek() {
                        if let Some(Job::Read { requests, reply }) = batch.next() {
                            group.push((requests, reply));
                        }
                    }
                    self.serve_reads(group).await;
                }
                Job::Reconfigure { change, reply } => {
                    let outcome = self.reconfigure(change).await;
                    let _ = reply.send(outcome);
                }
                Job::Set { item, reply } => {
                    let mut group = vec![(item, reply)];
                    while let Some(Job::Set { .. }) = batch.peek() {
                        if let Some(Job::Set { item, reply }) = batch.next() {
                            group.push((item, reply));
                        }
                    }
                    self.serve_sets(group).await;
                }
                Job::File { job, reply } => {
                    let answer = self.serve_file(job).await;
                    let _ = reply.send(answer);
                }
            }
        }
    }

    async fn serve_reads(&mut self, group: Vec<(Vec<ReadRequest>, oneshot::Sender<ReadReply>)>) {
        if !self.online || self.backend.is_none() {
            for (_, reply) in group {
                let _ = reply.send(Err(LinkError::Offline));
            }
            return;
        }
        let requests: Vec<ReadRequest> =
            group.iter().flat_map(|(r, _)| r.iter().copied()).collect();
        match self.read_ranges(&requests).await {
            Ok(mut answers) => {
                for (requests, reply) in group.into_iter().rev() {
                    let mine = answers.split_off(answers.len() - requests.len());
                    let _ = reply.send(Ok(mine));
                }
            }
            Err(err) => {
                // The client hears of it; whether the PLC is gone is the
                // poll's to decide.
                let message = err.to_string();
                for (_, reply) in group {
                    let _ = reply.send(Err(LinkError::Plc(PlcError::Timeout(message.clone()))));
                }
            }
        }
    }

    /// Reads arbitrary ranges through one shared plan. A block the PLC
    /// refuses is retried range by range, so one bad address does not fail
    /// its neighbours.
    async fn read_ranges(
        &mut self,
        requests: &[ReadRequest],
    ) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let backend = self.backend.as_mut().ok_or(PlcError::NotConfigured)?;
        let ranges: Vec<Range> = requests
            .iter()
            .map(|r| Range {
                area: r.area,
                offset: r.offset,
                len: r.len,
            })
            .collect();
        let plan = ReadPlan::new(&ranges, backend.max_read_block());
        let (data, refused) = plan.assemble_answers(backend.read(plan.blocks()).await?);
        let mut answers: Vec<Answer<Vec<u8>>> = (0..requests.len())
            .map(|i| plan.range_answer(&data, i).map(<[u8]>::to_vec))
            .collect();
        if !refused.is_empty() {
            let retry: Vec<usize> = (0..requests.len())
                .filter(|&i| answers[i].is_err())
                .collect();
            let single: Vec<ReadRequest> = retry
                .iter()
                .flat_map(|&i| split(requests[i], backend.max_read_block()))
                .collect();
            let mut results = backend.read(&single).await?.into_iter();
            for &i in &retry {
                let parts = split(requests[i], backend.max_read_block()).count();
                let mut bytes = Vec::with_capacity(requests[i].len as usize);
                let mut failure: Option<Exception> = None;
                for answer in results.by_ref().take(parts) {
                    match answer {
                        Ok(b) => bytes.extend_from_slice(&b),
                        Err(e) => failure = failure.or(Some(e)),
                    }
                }
                answers[i] = match failure {
                    Some(e) => Err(e),
                    None if bytes.len() == requests[i].len as usize => Ok(bytes),
                    None => Err(Exception::BadParameters),
                };
            }
        }
        Ok(answers)
    }

    async fn serve_sets(&mut self, group: Vec<(SetItem, oneshot::Sender<SetReply>)>) {
        if !self.online || self.backend.is_none() {
            for (_, reply) in group {
                let _ = reply.send(Err(LinkError::Offline));
            }
            return;
        }
        let backend = self.backend.as_mut().expect("checked above");
        let writes: Vec<WriteRequest> = group.iter().map(|(item, _)| item.write.clone()).collect();
        let written = match backend.write(&writes).await {
            Ok(written) if written.len() == writes.len() => written,
            Ok(_) => {
                let err = PlcError::Protocol("write answer count mismatch".to_string());
                return self.fail_sets(group, err);
            }
            Err(err) => return self.fail_sets(group, err),
        };
        let readbacks: Vec<ReadRequest> = group.iter().map(|(item, _)| item.readback).collect();
        let read = match self.read_ranges(&readbacks).await {
            Ok(read) => read,
            Err(err) => return self.fail_sets(group, err),
        };
        let seq = self.publisher.next_seq();
        let mut outcomes = Vec::with_capacity(group.len());
        for (((item, reply), write), read) in group.into_iter().zip(written).zip(read) {
            let answer = write.and(read);
            let var = item
                .var
                .filter(|(table, _)| std::sync::Arc::ptr_eq(table, self.publisher.table()))
                .map(|(_, id)| id);
            if let (Some(var), Ok(bytes)) = (var, &answer) {
                self.publisher.update(var, bytes);
            }
            outcomes.push((reply, SetOutcome { answer, seq }));
        }
        // Publish before answering: a client that reads its answer and asks
        // again at once must find the new value in the snapshot. The writer
        // holds back DIFF lines while its SET is unanswered, so it does not
        // get the change twice.
        self.publisher.publish(false, true);
        for (reply, outcome) in outcomes {
            let _ = reply.send(Ok(outcome));
        }
    }

    async fn serve_file(&mut self, job: FileJob) -> FileReply {
        if !self.online || self.backend.is_none() {
            return Err(LinkError::Offline);
        }
        self.transfer_until = Instant::now() + TRANSFER_IDLE;
        let result = self.run_file_job(job).await;
        self.transfer_until = Instant::now() + TRANSFER_IDLE;
        result.map_err(|err| LinkError::Plc(PlcError::Timeout(err.to_string())))
    }

    async fn run_file_job(&mut self, job: FileJob) -> Result<Answer<FileOutput>, PlcError> {
        let backend = self.backend.as_mut().ok_or(PlcError::NotConfigured)?;
        let block = backend.max_file_block().max(1);
        Ok(match job {
            FileJob::Info { path } => backend.file_info(&path).await?.map(FileOutput::Info),
            FileJob::List { path } => backend.list_dir(&path).await?.map(FileOutput::List),
            FileJob::Read { path, offset, len } => {
                if let Some(data) = self.cache.get(&path, offset, len) {
                    return Ok(Ok(FileOutput::Data(data)));
                }
                let mut data = Vec::with_capacity(len as usize);
                while data.len() < len as usize {
                    let want = (len - data.len() as u32).min(block);
                    let at = offset + data.len() as u64;
                    match backend.read_file(&path, at, want).await? {
                        Ok(piece) => {
                            let short = piece.len() < want as usize;
                            data.extend_from_slice(&piece);
                            if short {
                                break;
                            }
                        }
                        Err(e) => return Ok(Err(e)),
                    }
                }
                self.cache.note_read(&path, offset, len, &data);
                Ok(FileOutput::Data(data))
            }
            FileJob::Write { path, data } => {
                self.cache.invalidate(&path);
                let pieces = data.len().div_ceil(block as usize).max(1);
                for index in 0..pieces {
                    let start = index * block as usize;
                    let end = (start + block as usize).min(data.len());
                    let last = index + 1 == pieces;
                    let backend = self.backend.as_mut().ok_or(PlcError::NotConfigured)?;
                    if let Err(e) = backend
                        .write_file(&path, start as u64, &data[start..end], last)
                        .await?
                    {
                        return Ok(Err(e));
                    }
                    self.transfer_until = Instant::now() + TRANSFER_IDLE;
                    if self.files.sync_var_enabled && self.last_poll.elapsed() >= self.loop_delay {
                        // A long upload does not stop polling.
                        self.poll().await;
                        if !self.online {
                            return Err(PlcError::Timeout("PLC lost during upload".into()));
                        }
                    }
                }
                Ok(FileOutput::Done)
            }
            FileJob::WriteInfo { path, info } => {
                self.cache.invalidate(&path);
                backend
                    .write_file_info(&path, &info)
                    .await?
                    .map(|()| FileOutput::Done)
            }
        })
    }

    fn fail_sets(&mut self, group: Vec<(SetItem, oneshot::Sender<SetReply>)>, err: PlcError) {
        let message = err.to_string();
        for (_, reply) in group {
            let _ = reply.send(Err(LinkError::Plc(PlcError::Timeout(message.clone()))));
        }
    }
}

/// `request` cut into blocks of at most `max` bytes.
fn split(request: ReadRequest, max: u32) -> impl Iterator<Item = ReadRequest> {
    let max = max.max(1);
    let end = request.offset + request.len;
    (request.offset..end)
        .step_by(max as usize)
        .map(move |offset| ReadRequest {
            area: request.area,
            offset,
            len: (end - offset).min(max),
        })
}

/// Runs the poller on a thread of its own, so that client load never delays
/// a poll cycle, with real-time priority `priority` (COMM_SCHED_PRI, 0 = off)
/// when the process may have it.
pub fn spawn_thread(poller: Poller, priority: u8) -> std::io::Result<std::thread::JoinHandle<()>> {
    let section = poller.section.clone();
    // The thread logs where its creator logs (a scoped subscriber included).
    let dispatch = tracing::dispatcher::get_default(|d| d.clone());
    std::thread::Builder::new()
        .name(format!("poll {section}"))
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
                Ok(runtime) => runtime.block_on(poller.run()),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadlines_stay_on_the_schedule_and_skip_missed_cycles() {
        let start = Instant::now();
        let period = Duration::from_millis(100);
        // On time: the next slot.
        let now = start + Duration::from_millis(30);
        assert_eq!(next_deadline(start, period, now), start + period);
        // 250 ms late: slots 100 and 200 are gone, 300 is next.
        let now = start + Duration::from_millis(250);
        assert_eq!(next_deadline(start, period, now), start + period * 3);
        // Exactly on a slot counts as missed: no zero-length cycle.
        let now = start + period * 2;
        assert_eq!(next_deadline(start, period, now), start + period * 3);
    }
}
