//! OPC UA client: the backend for PLCs reached through their own OPC UA
//! servers (Siemens S7-1500, Beckhoff TwinCAT TF6100, B&R, Phoenix
//! PLCnext, Codesys), behind the same line protocol as a Tecomat PLC.
//!
//! Its variables are the nodes it browses from `OPCUA_BROWSE` or lists in
//! `OPCUA_TAGS` ([`browse`]), typed from their DataType and laid out in R
//! one after another (`plccoms_plc::opcua::tags::vars`); the link reads and
//! writes those bytes like any PLC's memory, and this backend turns them
//! into Read, Write and subscriptions. The list is served to the link as a
//! tag file through the file services (`plccoms_plc::opcua::VARS_FILE`),
//! and `__PF_CRC` (S70) is its CRC: when the server's nodes change (looked
//! at again every `OPCUA_REBROWSE`), the section reloads its table as for a
//! new public file.
//!
//! - `OPCUA_MODE = read`: the enabled variables' nodes are read in as few
//!   Read calls as the server's MaxNodesPerRead allows.
//! - `OPCUA_MODE = subscribe` (default): a subscription with a monitored
//!   item per enabled variable, created when the link first reads it, at
//!   the sampling interval the link polls at (the time between its reads,
//!   no faster than the server's MinSupportedSampleRate). Notifications
//!   reach the link as pushed values ([`PlcBackend::take_pushed`]) stamped
//!   with their SourceTimestamp (else ServerTimestamp), so DIFFs and the
//!   history carry the PLC's time; the link's reads are answered from the
//!   last values taken, without a round trip. A variable just written is
//!   read from the server once, so the value confirmed is the server's.
//! - SETs (the Write and that read) go on a second session where the
//!   server grants one (`OPCUA_WRITE_SESSION`): on the subscription's,
//!   a Write's answer queues behind its publishes.
//! - Quality: Good is a value; Uncertain is a value marked uncertain
//!   ([`Pushed::uncertain`], [`PlcBackend::take_uncertain`]), which the
//!   faces that show quality show as stale (the line protocol has no
//!   quality: GET and DIFF serve it as a value); Bad is the refusal of that
//!   variable, with the StatusCode's name.
//! - Arrays: each element is a variable (`NAME[i]`, `NAME[i][j]`); the
//!   array node is read or monitored once for all ([`List::sources`]), and
//!   a write of an element writes the whole array read just before.
//! - Structures without child variables: each scalar field is a variable
//!   (`NAME.FIELD`), decoded by the DataType's definition ([`structure`]);
//!   read, monitored and written as the whole node, as arrays are.
//! - `__PLC_RUN` (S2.2) is the server's ServerStatus.State = Running.
//! - Session loss (the server closes, a request times out): the link
//!   probes (a new session, a GetEndpoints and the session's own requests)
//!   about every second until the server answers; subscriptions are made
//!   anew on the new session.

pub mod browse;
pub mod convert;
pub mod nodelay;
mod rebrowse;
pub mod structure;

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use opcua::client::{
    ClientBuilder, IdentityToken, MonitoredItemMap, OnSubscriptionNotificationCore, Session,
};
use opcua::crypto::SecurityPolicy;
use opcua::types::{
    DataChangeNotification, DataValue, EndpointDescription, MessageSecurityMode,
    MonitoredItemCreateRequest, MonitoringMode, MonitoringParameters, NodeId, NotificationMessage,
    ReadValueId, StatusCode, TimestampsToReturn, UserTokenPolicy, Variant, WriteValue,
};
use tokio::task::JoinHandle;
use tracing::{info, warn};

use convert::Builtin;
use plccoms_core::config::Protocol;
use plccoms_core::driver::{
    Answer, Driver, FileInfo, Opened, PlcBackend, PlcError, PlcStatus, Pushed, PushedBytes,
    PushedVar, ReadRequest, Refusal, WriteData, WriteRequest,
};
use plccoms_core::link::Pool;
use plccoms_core::metrics::BackendCounters;
use plccoms_plc::memory::{PF_CRC_OFFSET, PLC_RUN_BIT, PLC_RUN_BYTE};
use plccoms_plc::opcua::nodeid::{self, NodeRef};
use plccoms_plc::opcua::tags::{self, Tag};
use plccoms_plc::opcua::VARS_FILE;
use plccoms_protocol::{Area, IecType};

/// Settings of one OPC UA link (the section's keys).
#[derive(Debug, Clone)]
pub struct OpcuaConfig {
    /// OPCUA_URL.
    pub url: String,
    /// OPCUA_SECURITY.
    pub mode: MessageSecurityMode,
    pub policy: SecurityPolicy,
    /// OPCUA_USER, OPCUA_PASSWORD.
    pub user: Option<(String, String)>,
    /// OPCUA_PKI: own certificate, trusted/ and rejected/ server certificates.
    pub pki: PathBuf,
    /// OPCUA_BROWSE.
    pub browse: Vec<NodeRef>,
    /// OPCUA_TAGS.
    pub tags: Option<PathBuf>,
    /// OPCUA_MODE = subscribe.
    pub subscribe: bool,
    /// OPCUA_TIMEOUT.
    pub timeout: Duration,
    /// OPCUA_REBROWSE; `None`: never.
    pub rebrowse: Option<Duration>,
    /// OPCUA_WRITE_SESSION: SETs on a second session.
    pub write_session: bool,
    /// OPCUA_SESSION_ITEMS: monitored items a session holds, more on
    /// further sessions; `usize::MAX`: all on the link's.
    pub session_items: usize,
    /// The section, for the log.
    pub section: String,
}

/// `OPCUA_SECURITY`: `None`, or `mode:policy`.
pub fn parse_security(text: &str) -> Result<(MessageSecurityMode, SecurityPolicy), String> {
    let text = text.trim();
    if text.eq_ignore_ascii_case("none") {
        return Ok((MessageSecurityMode::None, SecurityPolicy::None));
    }
    let (mode, policy) = text.split_once(':').ok_or_else(|| {
        format!("OPCUA_SECURITY = {text}: expected None or mode:policy (e.g. SignAndEncrypt:Basic256Sha256)")
    })?;
    let mode = match mode.trim().to_ascii_lowercase().as_str() {
        "sign" => MessageSecurityMode::Sign,
        "signandencrypt" => MessageSecurityMode::SignAndEncrypt,
        other => {
            return Err(format!(
                "OPCUA_SECURITY = {text}: mode '{other}' is not Sign or SignAndEncrypt"
            ))
        }
    };
    let policy = policy.trim();
    let known = [
        SecurityPolicy::Basic256Sha256,
        SecurityPolicy::Aes128Sha256RsaOaep,
        SecurityPolicy::Aes256Sha256RsaPss,
        SecurityPolicy::Basic256,
        SecurityPolicy::Basic128Rsa15,
    ];
    let policy = known
        .into_iter()
        .find(|p| p.to_str().eq_ignore_ascii_case(policy) || p.to_uri() == policy)
        .ok_or_else(|| {
            format!("OPCUA_SECURITY = {text}: unknown policy '{policy}' (Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss)")
        })?;
    Ok((mode, policy))
}

/// The server's limits (its ServerCapabilities), or ours where it gives
/// none.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub per_read: usize,
    pub per_write: usize,
    pub per_browse: usize,
    pub per_call: usize,
    /// MaxMonitoredItemsPerSubscription (else learnt from the server's
    /// BadTooManyMonitoredItems).
    pub per_subscription: usize,
    /// MinSupportedSampleRate, ms.
    pub min_sampling: f64,
    /// How long one request of a browse may take: a server answers a
    /// Browse or a Read of thousands of attributes slower than a poll.
    pub browse_timeout: Duration,
}

/// Most nodes one of our requests carries when the server sets no limit,
/// so that a message stays well inside the default message size.
const OWN_LIMIT: usize = 5000;

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            per_read: OWN_LIMIT,
            per_write: OWN_LIMIT,
            per_browse: 1000,
            per_call: OWN_LIMIT,
            per_subscription: usize::MAX,
            min_sampling: 0.0,
            browse_timeout: Duration::from_secs(10),
        }
    }
}

/// A variable the link reads and writes: its place in R and its node.
#[derive(Debug, Clone)]
struct Entry {
    /// As the list names it (the link's table looks pushed values up by it).
    name: Arc<[u8]>,
    offset: u32,
    ty: IecType,
    builtin: Builtin,
    /// The element of an array node.
    index: Option<u32>,
    /// Its node in [`List::sources`] (each node id held once): an array's
    /// elements share one.
    source: usize,
    /// A structure's field (of the element `index` for an array of
    /// structures): its layout and leaf.
    leaf: Option<(Arc<structure::Layout>, usize)>,
}

/// The variable list the link's table was built from.
#[derive(Default)]
struct List {
    bytes: Vec<u8>,
    entries: Vec<Entry>,
    /// The nodes read or monitored, each once: a whole array for all its
    /// elements (servers differ in honouring index ranges).
    sources: Vec<NodeId>,
    /// The entries of each source: those of source `s` are
    /// `members[starts[s]..starts[s + 1]]` (one allocation, not one per
    /// node).
    starts: Vec<u32>,
    members: Vec<u32>,
    /// How its nodes are written and read.
    types: browse::Types,
}

/// The list as built, shared by `newest` and the fetch in progress:
/// its bytes, and how its nodes are written and read.
type Listing = Arc<(Vec<u8>, browse::Types)>;

impl List {
    /// The node of entry `i`.
    fn node(&self, i: usize) -> &NodeId {
        &self.sources[self.entries[i].source]
    }

    /// The entries of source `s`, by index.
    fn of_source(&self, s: usize) -> Option<&[u32]> {
        let from = *self.starts.get(s)? as usize;
        let to = *self.starts.get(s + 1)? as usize;
        self.members.get(from..to)
    }
}

struct Connection {
    session: Arc<Session>,
    event_loop: JoinHandle<StatusCode>,
    /// SETs' Writes and read-backs, on a session of their own where the
    /// server grants a second: servers answer one session's requests in
    /// turn (asyncua's, many PLCs') and one connection's answers in order,
    /// so on the link's session a Write's answer waits behind publishes of
    /// up to 10,000 notifications each.
    writer: Option<(Arc<Session>, JoinHandle<StatusCode>)>,
    /// Sessions holding subscriptions beyond the link's own
    /// (OPCUA_SESSION_ITEMS): a server builds a session's notifications
    /// under one lock (async-opcua's), and a Write of one of its items
    /// waits for that; on more sessions, for a part of them.
    readers: Vec<(Arc<Session>, JoinHandle<StatusCode>)>,
    /// The server granted no further one: the rest on those there are.
    readers_refused: bool,
    /// Looking for the variables again (OPCUA_REBROWSE), on this session.
    rebrowse: Option<JoinHandle<()>>,
    /// The list it built last, for the link's next read.
    rebuilt: rebrowse::Slot,
}

impl Drop for Connection {
    fn drop(&mut self) {
        self.event_loop.abort();
        if let Some((_, event_loop)) = &self.writer {
            event_loop.abort();
        }
        for (_, event_loop) in &self.readers {
            event_loop.abort();
        }
        if let Some(task) = &self.rebrowse {
            task.abort();
        }
    }
}

/// The client handle of ServerStatus.State's monitored item (the others
/// are source index + 1).
const STATE_HANDLE: u32 = u32::MAX;

/// Values notified and taken by the link, by client handle (source index
/// + 1): what reads answer.
type Notified = Arc<Mutex<Values>>;

/// A value per source, by client handle: in a vector, not a map (100,000
/// in a map were 10.6 MB and a hash each).
#[derive(Default)]
struct Values {
    sources: Vec<Option<DataValue>>,
    state: Option<DataValue>,
}

impl Values {
    fn slot(&self, handle: u32) -> Option<&Option<DataValue>> {
        match handle {
            STATE_HANDLE => Some(&self.state),
            _ => self.sources.get((handle as usize).checked_sub(1)?),
        }
    }

    fn get(&self, handle: &u32) -> Option<&DataValue> {
        self.slot(*handle)?.as_ref()
    }

    fn contains_key(&self, handle: &u32) -> bool {
        self.get(handle).is_some()
    }

    /// The value of `handle`, the state's or one of `of` sources' (the
    /// list's: made that long at once, exactly; others are ignored).
    fn insert(&mut self, handle: u32, value: DataValue, of: usize) {
        if handle == STATE_HANDLE {
            self.state = Some(value);
            return;
        }
        let Some(at) = (handle as usize).checked_sub(1).filter(|&at| at < of) else {
            return;
        };
        if self.sources.len() < of {
            self.sources.reserve_exact(of - self.sources.len());
            self.sources.resize_with(of, || None);
        }
        self.sources[at] = Some(value);
    }

    /// Released: a new list or session starts anew.
    fn clear(&mut self) {
        *self = Values::default();
    }
}

/// Notifications not yet taken by the link, oldest first: (subscription
/// generation, client handle, value).
type Inbox = Arc<Mutex<Vec<(u64, u32, DataValue)>>>;

/// The subscriptions of the enabled variables: more than one where the
/// server limits the monitored items of one, or OPCUA_SESSION_ITEMS those
/// of a session.
struct Subscription {
    /// Each subscription; the last one is filled next.
    parts: Vec<Part>,
    monitored: Monitored,
}

/// One subscription of [`Subscription`].
#[derive(Debug, Clone, Copy)]
struct Part {
    /// Its session: 0 the link's, n the n-th of [`Connection::readers`].
    session: usize,
    id: u32,
    /// Its monitored items.
    items: usize,
}

impl Subscription {
    /// The monitored items on session `session`.
    fn on_session(&self, session: usize) -> usize {
        self.parts
            .iter()
            .filter(|p| p.session == session)
            .map(|p| p.items)
            .sum()
    }
}

/// The sources monitored, by index: a bit each (each poll asks for all
/// of them; 100,000 hashed lookups a poll were 3 % of the CPU).
#[derive(Default)]
struct Monitored {
    bits: Vec<u64>,
}

impl Monitored {
    fn contains(&self, source: usize) -> bool {
        self.bits
            .get(source / 64)
            .is_some_and(|word| word & (1 << (source % 64)) != 0)
    }

    fn insert(&mut self, source: usize) {
        let word = source / 64;
        if word >= self.bits.len() {
            self.bits.resize(word + 1, 0);
        }
        self.bits[word] |= 1 << (source % 64);
    }

    /// Counted when asked (twice a poll: 1,563 words at 100,000).
    fn len(&self) -> usize {
        self.bits
            .iter()
            .map(|word| word.count_ones() as usize)
            .sum()
    }
}

pub struct OpcuaBackend {
    config: OpcuaConfig,
    client: Option<opcua::client::Client>,
    connection: Option<Connection>,
    counters: Arc<BackendCounters>,
    limits: Limits,
    /// ServerStatus.State = Running.
    run: bool,
    /// The list the link's table was built from.
    served: List,
    /// Its number (`PushedVar::Listed`): a new one with each list served.
    served_version: u32,
    /// The list as last built (served once the link fetches it).
    newest: Option<Listing>,
    /// The CRC of the newest list, once made.
    crc: Option<u32>,
    /// The list being fetched by the link (file_info .. last read_file).
    fetching: Option<Listing>,
    subscription: Option<Subscription>,
    notified: Notified,
    inbox: Inbox,
    /// Rung by each notification (the link's `wait_pushed`).
    wake: Arc<tokio::sync::Notify>,
    /// The inbox's other buffer: taking swaps them, so that 100,000
    /// notifications a second do not allocate a new one each time.
    spare: Vec<(u64, u32, DataValue)>,
    /// A take's (handle, place in the inbox), sorted: kept for the next.
    order: Vec<(u32, u32)>,
    /// Of the current subscription: notifications of an older one (its
    /// handles meant another list) are dropped.
    generation: u64,
    /// SourceTimestamp of each SET's read-back, by client handle, and
    /// when it was read: notifications of its item sampled before it are
    /// dropped until one at or after it comes (or [`READ_BACK_FLOOR`]
    /// passes).
    read_back: HashMap<u32, (opcua::types::DateTime, Instant)>,
    /// Sources written since their last notification: read from the server.
    written: HashSet<usize>,
    /// When the link's last read started, and the gap before it.
    last_read: Option<Instant>,
    /// The last three periods between poll cycles.
    poll_gaps: [Option<Duration>; 3],
    /// Variables whose values reads answered with an Uncertain status since
    /// the link last took them (bounded by the variables' names).
    uncertain: HashSet<Box<[u8]>>,
}

/// How often reads give freed heap back, in the whole process (every
/// OPC UA section's reads together: a thousand sections must not trim a
/// thousand times as often): 100,000 notifications a second leave freed
/// pages resident, 15-30 MB in 10 s (measured), with no OPCUA_REBROWSE
/// to trim after.
const TRIM_EVERY: Duration = Duration::from_secs(5);
/// Values read directly, or items monitored, by one read that trims after.
const BIG_READ: usize = 10_000;

fn not_connected() -> PlcError {
    PlcError::Io(std::io::Error::new(
        std::io::ErrorKind::NotConnected,
        "no session with the OPC UA server",
    ))
}

/// A service call that failed as a whole: the link's failure where the
/// session or its connection is gone, else the server's answer.
pub(crate) fn service_error(service: &str, e: opcua::types::Error) -> PlcError {
    let status = e.status();
    if is_link_status(status) {
        PlcError::Timeout(format!("{service}: {status}"))
    } else {
        PlcError::Protocol(format!("{service} refused: {status} ({e})"))
    }
}

fn is_link_status(status: StatusCode) -> bool {
    matches!(
        status,
        StatusCode::BadTimeout
            | StatusCode::BadRequestTimeout
            | StatusCode::BadConnectionClosed
            | StatusCode::BadNotConnected
            | StatusCode::BadServerNotConnected
            | StatusCode::BadCommunicationError
            | StatusCode::BadSecureChannelClosed
            | StatusCode::BadSecureChannelIdInvalid
            | StatusCode::BadSessionIdInvalid
            | StatusCode::BadSessionClosed
            | StatusCode::BadSessionNotActivated
            | StatusCode::BadShutdown
            | StatusCode::BadServerHalted
            | StatusCode::BadTcpInternalError
            | StatusCode::BadNoCommunication
    )
}

fn refusal(status: StatusCode) -> Refusal {
    Refusal::Opcua(status.bits())
}

impl OpcuaBackend {
    pub fn new(config: OpcuaConfig) -> OpcuaBackend {
        OpcuaBackend {
            config,
            client: None,
            connection: None,
            counters: Arc::default(),
            limits: Limits::default(),
            run: false,
            served: List::default(),
            served_version: plccoms_core::driver::next_list_version(),
            newest: None,
            crc: None,
            fetching: None,
            subscription: None,
            notified: Arc::default(),
            inbox: Arc::default(),
            wake: Arc::default(),
            spare: Vec::new(),
            order: Vec::new(),
            generation: 0,
            written: HashSet::new(),
            read_back: HashMap::new(),
            last_read: None,
            poll_gaps: [None; 3],
            uncertain: HashSet::new(),
        }
    }

    /// The link's session, while it and every session holding a
    /// subscription last: one lost, the link makes them all anew.
    fn session(&self) -> Result<Arc<Session>, PlcError> {
        match &self.connection {
            Some(c)
                if !c.event_loop.is_finished()
                    && c.readers.iter().all(|(_, r)| !r.is_finished()) =>
            {
                Ok(c.session.clone())
            }
            _ => Err(not_connected()),
        }
    }

    /// Session `n` of a [`Part`].
    fn subscription_session(&self, n: usize) -> Result<Arc<Session>, PlcError> {
        let link = self.session()?;
        match n {
            0 => Ok(link),
            n => self
                .connection
                .as_ref()
                .and_then(|c| c.readers.get(n - 1))
                .map(|(session, _)| session.clone())
                .ok_or_else(not_connected),
        }
    }

    /// A further session for subscriptions: its number, or `None` where
    /// the server grants no more while the link's session goes on (one
    /// log line; the items go on the sessions there are, until the next
    /// connection).
    async fn open_reader(&mut self) -> Result<Option<usize>, PlcError> {
        let Some(client) = self.client.as_mut() else {
            return Err(not_connected());
        };
        self.counters.requests.inc();
        let opened = connect_session(client, &self.config, Carries::Values).await;
        self.session()?;
        let connection = self.connection.as_mut().ok_or_else(not_connected)?;
        match opened {
            Ok(reader) => {
                connection.readers.push(reader);
                Ok(Some(connection.readers.len()))
            }
            Err(e) => {
                connection.readers_refused = true;
                info!(section = %self.config.section, "no further session for monitored items ({e}): the rest on the sessions there are");
                Ok(None)
            }
        }
    }

    /// The monitored items one session takes now.
    fn session_items(&self) -> usize {
        match &self.connection {
            Some(c) if !c.readers_refused => self.config.session_items.max(1),
            _ => usize::MAX,
        }
    }

    /// The monitored items a session holding `on_session` takes more, of
    /// `pending`: up to [`Self::session_items`], and a rest of no more than
    /// a tenth of them besides. A further session for a handful of items
    /// (a list of 10,000 and the link's state) would cost the server a
    /// session, of the few an S7-1200 shares with its HMIs, for nothing.
    fn session_room(&self, on_session: usize, pending: usize) -> usize {
        let most = self.session_items();
        match most.saturating_sub(on_session) {
            0 if on_session.saturating_add(pending) <= most.saturating_add(most / 10) => pending,
            room => room,
        }
    }

    /// The session for SETs: the writer's while it lasts, else the link's.
    fn write_session(&self) -> Result<Arc<Session>, PlcError> {
        match &self.connection {
            Some(Connection {
                writer: Some((session, event_loop)),
                ..
            }) if !event_loop.is_finished() => Ok(session.clone()),
            _ => self.session(),
        }
    }

    /// Runs `f` on the session within the timeout; a link failure gives
    /// the session up.
    async fn call<T, F>(&mut self, what: &str, f: F) -> Result<T, PlcError>
    where
        F: std::future::Future<Output = Result<T, opcua::types::Error>>,
    {
        self.counters.requests.inc();
        let started = Instant::now();
        let result = match tokio::time::timeout(self.config.timeout, f).await {
            Ok(Ok(value)) => Ok(value),
            Ok(Err(e)) => Err(service_error(what, e)),
            Err(_) => {
                self.counters.timeouts.inc();
                Err(PlcError::Timeout(format!(
                    "{what}: no answer within {} ms",
                    self.config.timeout.as_millis()
                )))
            }
        };
        self.counters.round_trip.observe(started.elapsed());
        if let Err(e) = &result {
            self.counters.errors.inc();
            if e.is_link_failure() {
                self.lose();
            }
        }
        result
    }

    /// As [`Self::call`], but the server's answer that a request asked
    /// too much (BadTooManyOperations, BadTooManyMonitoredItems) is
    /// returned to be asked again in smaller parts.
    async fn call_within_limits<T, F>(
        &mut self,
        what: &str,
        f: F,
    ) -> Result<Result<T, StatusCode>, PlcError>
    where
        F: std::future::Future<Output = Result<T, opcua::types::Error>>,
    {
        let limited = |e: &opcua::types::Error| {
            matches!(
                e.status(),
                StatusCode::BadTooManyOperations | StatusCode::BadTooManyMonitoredItems
            )
        };
        let answer = self
            .call(what, async {
                match f.await {
                    Ok(value) => Ok(Ok(value)),
                    Err(e) if limited(&e) => Ok(Err(e.status())),
                    Err(e) => Err(e),
                }
            })
            .await?;
        Ok(answer)
    }

    /// Gives the session up: the link probes for a new one.
    fn lose(&mut self) {
        self.connection = None;
        self.subscription = None;
        // Released, not kept at its largest while the server is away.
        *self.inbox.lock().unwrap_or_else(|e| e.into_inner()) = Vec::new();
        self.spare = Vec::new();
        self.notified
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
        self.written.clear();
        self.read_back.clear();
    }

    /// A new session: endpoint, security and identity as configured, the
    /// server's limits and state read, and the variable list built.
    async fn open_session(&mut self) -> Result<String, PlcError> {
        self.lose();
        if self.client.is_none() {
            self.client = Some(new_client(&self.config, self.config.timeout)?);
        }
        let client = self.client.as_mut().expect("made above");
        self.counters.requests.inc();
        let (session, event_loop) = connect_session(client, &self.config, Carries::Values).await?;
        self.connection = Some(Connection {
            session: session.clone(),
            event_loop,
            writer: None,
            readers: Vec::new(),
            readers_refused: false,
            rebrowse: None,
            rebuilt: rebrowse::Slot::default(),
        });
        let ident = self.read_capabilities().await?;
        // The first list before the link serves; the later ones beside it.
        let lister = self.lister();
        let limits = self.limits;
        let listed = tokio::time::timeout(
            self.config.timeout * 60,
            rebrowse::list(&session, &lister, &limits, None, true),
        )
        .await
        .map_err(|_| PlcError::Timeout("browsing the server's variables took too long".into()))
        .and_then(|listed| listed);
        let (found, built) = match listed {
            Ok(listed) => listed,
            Err(e) => {
                if e.is_link_failure() {
                    self.lose();
                }
                return Err(e);
            }
        };
        if let Some(built) = built {
            self.take_list(built);
        }
        trim_heap();
        if self.config.write_session {
            let client = self.client.as_mut().expect("made above");
            match connect_session(client, &self.config, Carries::Sets).await {
                Ok(writer) => {
                    if let Some(connection) = &mut self.connection {
                        connection.writer = Some(writer);
                    }
                }
                Err(e) => {
                    info!(section = %self.config.section, "no session of its own for SETs ({e}): on the link's session")
                }
            }
        }
        if let (Some(every), Some(connection)) = (self.config.rebrowse, &mut self.connection) {
            connection.rebrowse = Some(rebrowse::spawn(
                session,
                self.config.clone(),
                lister,
                limits,
                every,
                found,
                connection.rebuilt.clone(),
            ));
        }
        Ok(ident)
    }

    /// ServerCapabilities, ServerStatus.State and BuildInfo, in one Read.
    async fn read_capabilities(&mut self) -> Result<String, PlcError> {
        use opcua::types::VariableId as V;
        let ids = [
            V::Server_ServerCapabilities_OperationLimits_MaxNodesPerRead,
            V::Server_ServerCapabilities_OperationLimits_MaxNodesPerWrite,
            V::Server_ServerCapabilities_OperationLimits_MaxNodesPerBrowse,
            V::Server_ServerCapabilities_OperationLimits_MaxMonitoredItemsPerCall,
            V::Server_ServerCapabilities_MinSupportedSampleRate,
            V::Server_ServerStatus_State,
            V::Server_ServerStatus_BuildInfo_ProductName,
            V::Server_ServerStatus_BuildInfo_SoftwareVersion,
            V::Server_ServerCapabilities_MaxMonitoredItemsPerSubscription,
        ];
        let reads: Vec<ReadValueId> = ids.iter().map(|&id| NodeId::from(id).into()).collect();
        let session = self.session()?;
        let values = self
            .call(
                "Read",
                session.read(&reads, TimestampsToReturn::Neither, 0.0),
            )
            .await?;
        let number = |i: usize| -> Option<f64> {
            match values.get(i).and_then(|v| v.value.as_ref())? {
                Variant::UInt32(n) => Some(f64::from(*n)),
                Variant::Double(n) => Some(*n),
                Variant::Int32(n) => Some(f64::from(*n)),
                _ => None,
            }
        };
        let limit = |i: usize, own: usize| {
            number(i)
                .filter(|&n| n >= 1.0)
                .map_or(own, |n| (n as usize).min(own))
        };
        let own = Limits::default();
        self.limits = Limits {
            per_read: limit(0, own.per_read),
            per_write: limit(1, own.per_write),
            per_browse: limit(2, own.per_browse),
            per_call: limit(3, own.per_call),
            per_subscription: limit(8, own.per_subscription),
            min_sampling: number(4).unwrap_or(0.0).max(0.0),
            browse_timeout: (self.config.timeout * 10).max(own.browse_timeout),
        };
        self.run = number(5) == Some(0.0);
        let text = |i: usize| match values.get(i).and_then(|v| v.value.as_ref()) {
            Some(Variant::String(s)) => s.value().clone().unwrap_or_default(),
            _ => String::new(),
        };
        let ident = format!("OPC UA {} {}", text(6), text(7));
        Ok(ident.trim().to_string())
    }

    /// What the section's variables are looked for by.
    fn lister(&self) -> rebrowse::Lister {
        rebrowse::Lister {
            section: self.config.section.clone(),
            tags: self.config.tags.clone(),
            starts: if self.config.browse.is_empty() {
                vec![NodeRef::standard(85)]
            } else {
                self.config.browse.clone()
            },
        }
    }

    /// A list built: one that differs from the one served becomes the
    /// newest, whose CRC `__PF_CRC` shows.
    fn take_list(&mut self, built: browse::Built) {
        let section = &self.config.section;
        let bytes = tags::write(&built.tags);
        if bytes == self.served.bytes && !self.served.bytes.is_empty() {
            // Same list: the link keeps its table; node ids are the same.
            self.served = list_of(bytes, built.types);
            self.newest = None;
            self.crc = None;
        } else {
            if self.newest.as_ref().is_none_or(|n| n.0 != bytes) {
                if !self.served.bytes.is_empty() {
                    info!(section = %section, "the server's variables changed: {} now", built.tags.len());
                }
                for line in &built.skipped {
                    info!(section = %section, "{line}");
                }
            }
            self.newest = Some(Arc::new((bytes, built.types)));
            self.crc = None;
        }
    }

    /// The list whose CRC `__PF_CRC` shows: the newest built.
    fn current_bytes(&self) -> &[u8] {
        self.newest.as_ref().map_or(&self.served.bytes, |n| &n.0)
    }

    /// The CRC of [`Self::current_bytes`], made once a list (3.7 MB at
    /// 100,000 variables, each poll cycle).
    fn list_crc(&mut self) -> u32 {
        if let Some(crc) = self.crc {
            return crc;
        }
        let crc = plccoms_plc::pubfile::crc_of(self.current_bytes());
        self.crc = Some(crc);
        crc
    }

    fn system(&self, offset: u32, len: u32, crc: u32) -> Answer<Vec<u8>> {
        let mut image = [0u8; 4096];
        if self.run {
            image[PLC_RUN_BYTE as usize] |= 1 << PLC_RUN_BIT;
        }
        let at = PF_CRC_OFFSET as usize;
        image[at..at + 4].copy_from_slice(&crc.to_le_bytes());
        let end = offset as usize + len as usize;
        image
            .get(offset as usize..end)
            .map(<[u8]>::to_vec)
            .ok_or(Refusal::BAD_PARAMETERS)
    }

    /// The entries a read of R covers, by index.
    fn covered(&self, offset: u32, len: u32) -> std::ops::Range<usize> {
        let entries = &self.served.entries;
        let end = offset.saturating_add(len);
        let first = entries.partition_point(|e| e.offset + e.ty.size() as u32 <= offset);
        let last = entries.partition_point(|e| e.offset < end);
        first..last.max(first)
    }

    /// Reads the values of `indexes` from the server, in as few Read calls
    /// as MaxNodesPerRead allows; also ServerStatus.State when `state`.
    async fn read_values(
        &mut self,
        session: Arc<Session>,
        indexes: &[usize],
        state: bool,
    ) -> Result<HashMap<usize, DataValue>, PlcError> {
        let mut reads: Vec<ReadValueId> = indexes
            .iter()
            .map(|&s| self.served.sources[s].clone().into())
            .collect();
        if state {
            reads.push(NodeId::from(opcua::types::VariableId::Server_ServerStatus_State).into());
        }
        let mut values = Vec::with_capacity(reads.len());
        for chunk in reads.chunks(self.limits.per_read.max(1)) {
            let answer = self
                .call("Read", session.read(chunk, TimestampsToReturn::Source, 0.0))
                .await?;
            if answer.len() != chunk.len() {
                return Err(PlcError::Protocol(format!(
                    "Read of {} nodes answered {}",
                    chunk.len(),
                    answer.len()
                )));
            }
            values.extend(answer);
        }
        if state {
            if let Some(state) = values.pop() {
                self.run = matches!(state.value, Some(Variant::Int32(0)));
            }
        }
        Ok(indexes.iter().copied().zip(values).collect())
    }

    /// Subscribe mode: monitored items for `indexes` not yet monitored.
    async fn monitor(&mut self, indexes: &[usize]) -> Result<(), PlcError> {
        // Until the poll's period is known (the median of three cycles: a
        // client's EN polls at once, the first after a connection is
        // late), values are read directly.
        let gaps: Option<Vec<Duration>> = self.poll_gaps.iter().copied().collect();
        let Some(gap) = gaps.map(|mut g| {
            g.sort_unstable();
            g[1]
        }) else {
            return Ok(());
        };
        let session = self.session()?;
        let gap = gap.clamp(Duration::from_millis(10), Duration::from_secs(10));
        let interval = (gap.as_secs_f64() * 1000.0).max(self.limits.min_sampling);
        if self.subscription.is_none() {
            self.generation += 1;
            let id = self.new_subscription(&session, interval).await?;
            self.subscription = Some(Subscription {
                parts: vec![Part {
                    session: 0,
                    id,
                    items: 0,
                }],
                monitored: Monitored::default(),
            });
            // ServerStatus.State too: `__PLC_RUN` without a round trip.
            let state = MonitoredItemCreateRequest {
                item_to_monitor: NodeId::from(opcua::types::VariableId::Server_ServerStatus_State)
                    .into(),
                monitoring_mode: MonitoringMode::Reporting,
                requested_parameters: MonitoringParameters {
                    client_handle: STATE_HANDLE,
                    sampling_interval: interval,
                    queue_size: 1,
                    discard_oldest: true,
                    ..Default::default()
                },
            };
            self.call(
                "CreateMonitoredItems",
                create_monitored_items(&session, id, TimestampsToReturn::Neither, vec![state]),
            )
            .await?;
            if let Some(subscription) = &mut self.subscription {
                subscription.parts[0].items = 1;
            }
        }
        let Some(subscription) = &self.subscription else {
            return Ok(());
        };
        let mut pending: std::collections::VecDeque<usize> = indexes
            .iter()
            .copied()
            .filter(|i| !subscription.monitored.contains(*i))
            .collect();
        // Within the server's limits: MaxMonitoredItemsPerCall (halved
        // while it answers BadTooManyOperations) and the items one
        // subscription takes (its capability, else learnt from its
        // BadTooManyMonitoredItems): more subscriptions, not a failure;
        // and within OPCUA_SESSION_ITEMS: more sessions.
        let mut most = self.limits.per_call.max(1);
        while !pending.is_empty() {
            let Some((last, on_session)) = self
                .subscription
                .as_ref()
                .and_then(|s| Some((*s.parts.last()?, s.on_session(s.parts.last()?.session))))
            else {
                return Ok(());
            };
            let (id, count) = (last.id, last.items);
            let session_room = self.session_room(on_session, pending.len());
            let room = self
                .limits
                .per_subscription
                .saturating_sub(count)
                .min(session_room);
            if room == 0 {
                let at = match session_room {
                    0 => match self.open_reader().await? {
                        Some(n) => n,
                        // Refused: room again on this one.
                        None => continue,
                    },
                    _ => last.session,
                };
                let on = self.subscription_session(at)?;
                let id = self.new_subscription(&on, interval).await?;
                if let Some(subscription) = &mut self.subscription {
                    subscription.parts.push(Part {
                        session: at,
                        id,
                        items: 0,
                    });
                }
                continue;
            }
            let session = self.subscription_session(last.session)?;
            let n = pending.len().min(most).min(room);
            let chunk: Vec<usize> = pending.drain(..n).collect();
            let items: Vec<MonitoredItemCreateRequest> = chunk
                .iter()
                .map(|&i| MonitoredItemCreateRequest {
                    item_to_monitor: self.served.sources[i].clone().into(),
                    monitoring_mode: MonitoringMode::Reporting,
                    requested_parameters: MonitoringParameters {
                        client_handle: i as u32 + 1,
                        sampling_interval: interval,
                        queue_size: 1,
                        discard_oldest: true,
                        ..Default::default()
                    },
                })
                .collect();
            let created = self
                .call_within_limits(
                    "CreateMonitoredItems",
                    // Both: ServerTimestamp stands in for a missing
                    // SourceTimestamp in the history.
                    create_monitored_items(&session, id, TimestampsToReturn::Both, items),
                )
                .await?;
            let created = match created {
                Ok(created) => created,
                Err(status) => {
                    for &i in chunk.iter().rev() {
                        pending.push_front(i);
                    }
                    if n > 1 {
                        // Too many at once (for the call or for the room
                        // left in this subscription): half as many.
                        most = n / 2;
                        if status == StatusCode::BadTooManyOperations {
                            self.limits.per_call = most;
                        }
                    } else if status == StatusCode::BadTooManyMonitoredItems && count > 0 {
                        // Not one more: this subscription is full.
                        self.limits.per_subscription = count;
                        most = self.limits.per_call.max(1);
                        info!(section = %self.config.section, "the server takes {count} monitored items a subscription: more subscriptions");
                    } else {
                        return Err(PlcError::Protocol(format!(
                            "CreateMonitoredItems refused: {status}"
                        )));
                    }
                    continue;
                }
            };
            let mut notified = self.notified.lock().unwrap_or_else(|e| e.into_inner());
            let mut full = Vec::new();
            let mut monitored = Vec::with_capacity(chunk.len());
            for (&i, status) in chunk.iter().zip(created) {
                if status == StatusCode::BadTooManyMonitoredItems {
                    // Refused one by one: in the next subscription.
                    full.push(i);
                    continue;
                }
                monitored.push(i);
                if status.is_bad() {
                    // Its refusal stands until the next table.
                    notified.insert(
                        i as u32 + 1,
                        DataValue {
                            status: Some(status),
                            ..Default::default()
                        },
                        self.served.sources.len(),
                    );
                }
            }
            drop(notified);
            let taken = monitored.len();
            if let Some(subscription) = &mut self.subscription {
                for i in monitored {
                    subscription.monitored.insert(i);
                }
                if let Some(last) = subscription.parts.last_mut() {
                    last.items += taken;
                }
            }
            if !full.is_empty() {
                if count + taken == 0 {
                    return Err(PlcError::Protocol(
                        "CreateMonitoredItems refused: BadTooManyMonitoredItems".into(),
                    ));
                }
                self.limits.per_subscription = count + taken;
                info!(section = %self.config.section, "the server takes {} monitored items a subscription: more subscriptions", count + taken);
                for &i in full.iter().rev() {
                    pending.push_front(i);
                }
            }
        }
        Ok(())
    }

    /// A subscription publishing every `interval` ms into the inbox.
    async fn new_subscription(
        &mut self,
        session: &Arc<Session>,
        interval: f64,
    ) -> Result<u32, PlcError> {
        let sink = Sink {
            inbox: self.inbox.clone(),
            wake: self.wake.clone(),
            generation: self.generation,
            // One value per item and a quarter more: dropping the older
            // ones when full keeps every item of a link a cycle behind
            // (4 times as many were 46 MB at 100,000 variables).
            most: (self.served.sources.len() + self.served.sources.len() / 4).max(4096),
            counters: self.counters.clone(),
        };
        let id = self
            .call(
                "CreateSubscription",
                session.create_subscription(
                    Duration::from_secs_f64(interval / 1000.0),
                    // Lifetime and keep-alive counts: the server ends a
                    // forgotten subscription within a minute or so.
                    60,
                    10,
                    NOTIFICATIONS_PER_PUBLISH,
                    0,
                    true,
                    sink,
                ),
            )
            .await?;
        tracing::debug!(section = %self.config.section, "subscription {id} made, publishing and sampling every {interval:.0} ms");
        Ok(id)
    }

    /// The answer to a read of `read` (R) from the values of its sources;
    /// the entries whose value is Uncertain added to `uncertain`.
    fn answer<'v>(
        &self,
        read: &ReadRequest,
        value_of: impl Fn(usize) -> Option<&'v DataValue>,
        uncertain: &mut Vec<usize>,
    ) -> Answer<Vec<u8>> {
        let mut bytes = vec![0u8; read.len as usize];
        let mut fields = structure::Fields::default();
        for i in self.covered(read.offset, read.len) {
            let entry = &self.served.entries[i];
            let Some(value) = value_of(entry.source) else {
                return Err(Refusal::Opcua(StatusCode::BadWaitingForInitialData.bits()));
            };
            let own = entry_bytes(entry, value, &mut fields)?;
            if is_uncertain(value) {
                uncertain.push(i);
            }
            // The overlap of the entry's bytes and the read.
            let (start, end) = (entry.offset, entry.offset + own.len() as u32);
            let (from, to) = (start.max(read.offset), end.min(read.offset + read.len));
            if from < to {
                bytes[(from - read.offset) as usize..(to - read.offset) as usize]
                    .copy_from_slice(&own[(from - start) as usize..(to - start) as usize]);
            }
        }
        Ok(bytes)
    }

    /// Writes in one Write call per MaxNodesPerWrite. An array element or
    /// a structure's field is written as its whole node, read just before
    /// with the element or field changed (servers differ in honouring an
    /// index range on Write: asyncua's replaces the whole array by the one
    /// element; a structure has none): a change the PLC makes to the
    /// node's other elements or fields in between is lost.
    async fn write_all(&mut self, writes: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let mut answers: Vec<Answer<()>> = Vec::with_capacity(writes.len());
        // (write, entry, value) of scalars and of array elements.
        let mut scalars = Vec::new();
        let mut elements = Vec::new();
        for (n, write) in writes.iter().enumerate() {
            match self.write_value(write) {
                Ok((i, value)) => {
                    answers.push(Ok(()));
                    let entry = &self.served.entries[i];
                    if entry.index.is_some() || entry.leaf.is_some() {
                        elements.push((n, i, value));
                    } else {
                        scalars.push((n, i, value));
                    }
                }
                Err(e) => answers.push(Err(e)),
            }
        }
        // Each WriteValue, and the writes it answers.
        let mut values: Vec<WriteValue> = Vec::new();
        let mut serves: Vec<Vec<(usize, usize)>> = Vec::new();
        for (n, i, value) in scalars {
            values.push(WriteValue {
                node_id: self.served.node(i).clone(),
                attribute_id: 13,
                // The value alone: a server that cannot take the
                // timestamps a client gives must refuse the whole write
                // (BadWriteNotSupported, Part 4 5.10.4.2), as S7-1200/1500,
                // Kepware and servers on the OPC Foundation's .NET stack
                // do. The server stamps it with the clock its
                // notifications carry, which a SET's read-back is
                // compared with.
                value: DataValue::value_only(value),
                ..Default::default()
            });
            serves.push(vec![(n, i)]);
        }
        if !elements.is_empty() {
            let mut nodes: Vec<NodeId> = Vec::new();
            for (_, i, _) in &elements {
                let node = self.served.node(*i);
                if !nodes.contains(node) {
                    nodes.push(node.clone());
                }
            }
            let session = self.write_session()?;
            let reads: Vec<ReadValueId> = nodes.iter().map(|n| n.clone().into()).collect();
            let mut current = Vec::with_capacity(reads.len());
            for chunk in reads.chunks(self.limits.per_read.max(1)) {
                current.extend(
                    self.call(
                        "Read",
                        session.read(chunk, TimestampsToReturn::Neither, 0.0),
                    )
                    .await?,
                );
            }
            for (node, now) in nodes.into_iter().zip(current) {
                let mine: Vec<&(usize, usize, Variant)> = elements
                    .iter()
                    .filter(|(_, i, _)| *self.served.node(*i) == node)
                    .collect();
                let status = now.status.unwrap_or(StatusCode::Good);
                let Some(mut whole) = now.value.filter(|_| !status.is_bad()) else {
                    let why = if status.is_bad() {
                        status
                    } else {
                        StatusCode::BadTypeMismatch
                    };
                    for (n, _, _) in mine {
                        answers[*n] = Err(refusal(why));
                    }
                    continue;
                };
                let mut served = Vec::new();
                for (n, i, value) in mine {
                    match put(&mut whole, &self.served.entries[*i], value) {
                        Ok(()) => served.push((*n, *i)),
                        Err(status) => answers[*n] = Err(refusal(status)),
                    }
                }
                if !served.is_empty() {
                    values.push(WriteValue {
                        node_id: node,
                        attribute_id: 13,
                        value: DataValue::value_only(whole),
                        ..Default::default()
                    });
                    serves.push(served);
                }
            }
        }
        if values.is_empty() {
            return Ok(answers);
        }
        let session = self.write_session()?;
        let mut results = Vec::with_capacity(values.len());
        for chunk in values.chunks(self.limits.per_write.max(1)) {
            let answer = self.call("Write", session.write(chunk)).await?;
            if answer.len() != chunk.len() {
                return Err(PlcError::Protocol(format!(
                    "Write of {} nodes answered {}",
                    chunk.len(),
                    answer.len()
                )));
            }
            results.extend(answer);
        }
        for (served, status) in serves.into_iter().zip(results) {
            for (n, i) in served {
                if status.is_bad() {
                    warn!(section = %self.config.section, "write of {} refused: {}", self.served.node(i), refusal(status));
                    answers[n] = Err(refusal(status));
                } else {
                    let source = self.served.entries[i].source;
                    self.written.insert(source);
                }
            }
        }
        Ok(answers)
    }

    /// The entry and value of one write; a write that matches no variable
    /// (a `%R` address across two) is refused here.
    fn write_value(&self, write: &WriteRequest) -> Result<(usize, Variant), Refusal> {
        if write.area != Area::R {
            return Err(Refusal::BAD_PARAMETERS);
        }
        let entries = &self.served.entries;
        let i = entries
            .binary_search_by_key(&write.offset, |e| e.offset)
            .map_err(|_| Refusal::BAD_PARAMETERS)?;
        let entry = &entries[i];
        let bytes = match &write.data {
            WriteData::Bytes(bytes) if bytes.len() == entry.ty.size() => bytes.clone(),
            WriteData::Bit { bit: 0, value } if entry.ty == IecType::Bool => vec![u8::from(*value)],
            _ => return Err(Refusal::BAD_PARAMETERS),
        };
        let variant = convert::variant_of(&bytes, entry.ty, entry.builtin)
            .ok_or(Refusal::Opcua(StatusCode::BadNotWritable.bits()))?;
        Ok((i, variant))
    }
}

/// `whole` (an entry's node's value) with the entry's element or field
/// set to `value`.
fn put(whole: &mut Variant, entry: &Entry, value: &Variant) -> Result<(), StatusCode> {
    let slot = match (entry.index, whole) {
        (Some(at), Variant::Array(array)) => array
            .values
            .get_mut(at as usize)
            .ok_or(StatusCode::BadIndexRangeNoData)?,
        (Some(_), _) => return Err(StatusCode::BadTypeMismatch),
        (None, whole) => whole,
    };
    match &entry.leaf {
        Some((layout, leaf)) => {
            *slot = layout
                .write(slot, *leaf, value)
                .map_err(|_| StatusCode::BadDecodingError)?;
        }
        None => *slot = value.clone(),
    }
    Ok(())
}

/// An entry's bytes in `value` (of its source), or the refusal its status
/// or type makes; a structure's body decoded once in `fields` for all the
/// entries of one value.
fn entry_bytes(
    entry: &Entry,
    value: &DataValue,
    fields: &mut structure::Fields,
) -> Answer<PushedBytes> {
    let status = value.status.unwrap_or(StatusCode::Good);
    if status.is_bad() {
        return Err(refusal(status));
    }
    let element = match (&value.value, entry.index) {
        (Some(Variant::Array(array)), Some(at)) => array.values.get(at as usize),
        (value, None) => value.as_ref(),
        (_, Some(_)) => None,
    };
    let field;
    let element = match (&entry.leaf, element) {
        (Some((layout, leaf)), Some(object)) => {
            // An array of structures: each element its own body.
            let key = (entry.source, entry.index);
            field = fields
                .read(key, layout, object, *leaf)
                .map_err(|_| refusal(StatusCode::BadDecodingError))?;
            Some(&field)
        }
        (_, element) => element,
    };
    element
        .and_then(|v| convert::bytes_of(v, entry.ty))
        .ok_or(Refusal::Opcua(StatusCode::BadTypeMismatch.bits()))
}

/// Whether the server marked `value` Uncertain (served, as stale).
fn is_uncertain(value: &DataValue) -> bool {
    value.status.is_some_and(|s| s.is_uncertain())
}

/// The device's time of a notified value: its SourceTimestamp, else its
/// ServerTimestamp, else now (UTC ms).
fn stamp_of(value: &DataValue) -> i64 {
    value
        .source_timestamp
        .or(value.server_timestamp)
        .map(|t| t.as_chrono().timestamp_millis())
        .filter(|&ms| ms > 0)
        .unwrap_or_else(|| plccoms_core::changes::unix_ms(std::time::SystemTime::now()))
}

/// CreateMonitoredItems by the raw service: `Session::create_monitored_items`
/// keeps its own copy of every item (node id, parameters, filter: 24 MB at
/// 100,000, the largest part of the heap at rest), which only its own
/// reconnection (disabled: subscriptions are made anew here) and callbacks
/// that look items up (not [`Sink`]) use. Each item's StatusCode.
async fn create_monitored_items(
    session: &Session,
    id: u32,
    timestamps: TimestampsToReturn,
    items: Vec<MonitoredItemCreateRequest>,
) -> Result<Vec<StatusCode>, opcua::types::Error> {
    use opcua::client::UARequest;
    opcua::client::services::CreateMonitoredItems::new(id, session)
        .items_to_create(items)
        .timestamps_to_return(timestamps)
        .send(session.channel())
        .await
        .map(|created| {
            created
                .results
                .into_iter()
                .map(|c| c.result.status_code)
                .collect()
        })
}

/// MaxNotificationsPerPublish asked of the server. Without it a server
/// answers one Publish with every change (two of 50,000 a second at
/// 100,000 variables from plccoms's own): one message of megabytes,
/// decoded at once, with a Write's answer waiting behind it on the one
/// secure channel. The client asks for the rest at once (MoreNotifications),
/// so the throughput stays; 10 messages a cycle at 100,000 changes stay
/// well inside the 20 a server queues by default (async-opcua's).
const NOTIFICATIONS_PER_PUBLISH: u32 = 10_000;

/// Most bytes of R one read answers in subscribe mode.
const SUBSCRIBED_READ_BLOCK: u32 = 4096;

/// Most notifications the link takes at once ([`PlcBackend::take_pushed`]):
/// between two such slices a SET queued meanwhile is served. A slice is
/// one publish of the link's state, which costs the state's chunks it
/// touches: servers notify in no order of the variables (a slice of 2,000
/// touched nearly all of them), so one publish a message, not more.
const TAKE_SLICE: usize = NOTIFICATIONS_PER_PUBLISH as usize;

/// How long after a SET's read-back notifications sampled before it are
/// dropped, at most: one whose server stamps reads and notifications from
/// different clocks is taken again after this.
const READ_BACK_FLOOR: Duration = Duration::from_secs(5);

/// Where a subscription's notifications go: the inbox, the link woken.
struct Sink {
    inbox: Inbox,
    wake: Arc<tokio::sync::Notify>,
    generation: u64,
    /// Bounded: a link that does not take them keeps the newest of each
    /// item only.
    most: usize,
    counters: Arc<BackendCounters>,
}

impl OnSubscriptionNotificationCore for Sink {
    fn on_subscription_notification(
        &mut self,
        notification: NotificationMessage,
        _items: MonitoredItemMap<'_>,
    ) {
        // Each message answers one Publish request: counted with the
        // others, so requests per cycle include them.
        self.counters.requests.inc();
        let Some(data) = notification.notification_data else {
            return;
        };
        let mut inbox = self.inbox.lock().unwrap_or_else(|e| e.into_inner());
        for object in data {
            let Some(changes) = object.into_inner_as::<DataChangeNotification>() else {
                continue;
            };
            for change in changes.monitored_items.into_iter().flatten() {
                if inbox.len() >= self.most {
                    keep_newest(&mut inbox);
                }
                inbox.push((self.generation, change.client_handle, change.value));
            }
        }
        drop(inbox);
        self.wake.notify_one();
    }
}

/// Keeps the newest notification of each item only, in their order (in
/// place: no second inbox at the peak).
fn keep_newest(inbox: &mut Vec<(u64, u32, DataValue)>) {
    let mut seen = HashSet::with_capacity(inbox.len());
    let keep: Vec<bool> = inbox
        .iter()
        .rev()
        .map(|(g, h, _)| seen.insert((*g, *h)))
        .collect();
    drop(seen);
    let mut at = keep.len();
    inbox.retain(|_| {
        at -= 1;
        keep[at]
    });
}

/// What a session carries, which decides where its event loop runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Carries {
    /// Values in bulk: subscriptions' publishes, the poll's reads, browses.
    /// On [`bulk_threads`].
    Values,
    /// SETs and their read-backs: beside the link, on its runtime.
    Sets,
}

/// The threads that run the event loops of the sessions carrying values in
/// bulk, shared by every OPC UA section. Decoding a publish of 10,000
/// notifications takes milliseconds in one poll of a session's task, and
/// tokio does not preempt a task: beside the link, a SET's Write, its
/// answer and the DIFF would wait for it. The kernel preempts a thread, so
/// here they wait for a time slice at most. Half the cores, at least one;
/// started with the first such session (an error where the process may
/// start no more threads: the session is not opened, and tried again).
fn bulk_threads() -> std::io::Result<&'static tokio::runtime::Handle> {
    static BULK: Pool = Pool::new("opcua-values", half_the_cores);
    BULK.get().map(|runtime| runtime.handle())
}

fn half_the_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| (n.get() / 2).max(1))
}

/// A session with the server: endpoint, security and identity as
/// configured; its event loop spawned where what it carries runs.
pub(crate) async fn connect_session(
    client: &mut opcua::client::Client,
    config: &OpcuaConfig,
    carries: Carries,
) -> Result<(Arc<Session>, JoinHandle<StatusCode>), PlcError> {
    let token_policy = match &config.user {
        Some(_) => UserTokenPolicy {
            token_type: opcua::types::UserTokenType::UserName,
            ..UserTokenPolicy::anonymous()
        },
        None => UserTokenPolicy::anonymous(),
    };
    let endpoint: EndpointDescription = (
        config.url.as_str(),
        config.policy.to_str(),
        config.mode,
        token_policy,
    )
        .into();
    let identity = match &config.user {
        Some((user, password)) => IdentityToken::new_user_name(user.clone(), password.clone()),
        None => IdentityToken::Anonymous,
    };
    let timeout = config.timeout;
    let url = config.url.clone();
    let pki = config.pki.clone();
    let (session, event_loop) = match tokio::time::timeout(
        timeout,
        nodelay::connect_to_matching_endpoint(client, endpoint, identity),
    )
    .await
    {
        Ok(Ok(pair)) => pair,
        Ok(Err(e)) => return Err(connect_error(&url, &pki, e.status(), &e.to_string())),
        Err(_) => {
            return Err(PlcError::Timeout(format!(
                "{url}: no endpoints within {} ms",
                timeout.as_millis()
            )))
        }
    };
    session.disable_reconnects();
    let mut event_loop = match carries {
        Carries::Values => bulk_threads()?.spawn(event_loop.run()),
        Carries::Sets => event_loop.spawn(),
    };
    // Secure channel, CreateSession, ActivateSession: a few round trips.
    let connected = tokio::select! {
        connected = session.wait_for_connection() => Ok(connected),
        ended = &mut event_loop => Err(ended.unwrap_or(StatusCode::BadUnexpectedError)),
        _ = tokio::time::sleep(timeout * 3) => Err(StatusCode::BadTimeout),
    };
    match connected {
        Ok(true) => {}
        Ok(false) => {
            event_loop.abort();
            return Err(PlcError::Timeout(format!("{url}: session not established")));
        }
        Err(status) => {
            event_loop.abort();
            return Err(connect_error(&url, &pki, status, ""));
        }
    }
    Ok((session, event_loop))
}

/// Largest message accepted from a server.
const MAX_MESSAGE: usize = 64 * 1024 * 1024;

/// The client (its certificate store loaded once): a key pair is made in
/// the PKI folder only where security needs one. Its requests and
/// keep-alives wait up to `timeout`.
pub(crate) fn new_client(
    config: &OpcuaConfig,
    timeout: Duration,
) -> Result<opcua::client::Client, PlcError> {
    ClientBuilder::new()
        .application_name("plccoms")
        .application_uri("urn:plccoms:client")
        .product_uri("urn:plccoms")
        .pki_dir(&config.pki)
        .create_sample_keypair(config.mode != MessageSecurityMode::None)
        // First contact: an unknown server certificate is refused and
        // stored in pki/rejected; moving it to pki/trusted trusts it.
        .trust_server_certs(false)
        .session_retry_limit(0)
        .request_timeout(timeout)
        .keep_alive_interval(timeout.max(Duration::from_millis(500)))
        .max_failed_keep_alive_count(1)
        // async-opcua accepts 5 chunks (about 320 KB) by default: too
        // little for a Browse of a folder of thousands of variables from a
        // server that ignores the references-per-node limit (asyncua's), or
        // for a Read of MaxNodesPerRead strings. Bounded all the same.
        .max_chunk_count(MAX_MESSAGE / 65_536)
        .max_message_size(MAX_MESSAGE)
        // And 1000 array elements: a Read of 5000 nodes, a Browse of a
        // folder of 10,000 answer longer arrays.
        .max_array_length(4 * plccoms_plc::pubfile::MAX_VARS)
        .client()
        .map_err(|e| PlcError::Protocol(format!("OPC UA client settings: {}", e.join("; "))))
}

/// The certificate last stored in `dir` and its SHA-1 thumbprint, as the
/// server's configuration tools show it.
fn newest_certificate(dir: &std::path::Path) -> Option<(PathBuf, String)> {
    let newest = std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .filter_map(|e| Some((e.metadata().ok()?.modified().ok()?, e.path())))
        .max()?
        .1;
    let der = std::fs::read(&newest).ok()?;
    let cert = opcua::crypto::X509::from_der(&der).ok()?;
    Some((newest, cert.thumbprint().as_hex_string()))
}

fn connect_error(url: &str, pki: &std::path::Path, status: StatusCode, detail: &str) -> PlcError {
    if matches!(
        status,
        StatusCode::BadCertificateUntrusted
            | StatusCode::BadSecurityChecksFailed
            | StatusCode::BadCertificateInvalid
    ) {
        let rejected = pki.join("rejected");
        let stored = newest_certificate(&rejected).map_or_else(
            || format!("in {}", rejected.display()),
            |(path, thumbprint)| format!("as {}, thumbprint {thumbprint}", path.display()),
        );
        return PlcError::Protocol(format!(
            "{url}: {status}: the server's certificate is not trusted; it was stored {stored}: check the thumbprint against the server's own (its configuration shows it) and move the file to {}/trusted to trust it",
            pki.display()
        ));
    }
    let detail = if detail.is_empty() {
        String::new()
    } else {
        format!(" ({detail})")
    };
    if matches!(
        status,
        StatusCode::BadIdentityTokenInvalid
            | StatusCode::BadIdentityTokenRejected
            | StatusCode::BadUserAccessDenied
            | StatusCode::BadSecurityPolicyRejected
            | StatusCode::BadSecurityModeRejected
            | StatusCode::BadTcpEndpointUrlInvalid
    ) {
        return PlcError::Protocol(format!("{url}: {status}{detail}"));
    }
    PlcError::Timeout(format!("{url}: {status}{detail}"))
}

/// The tag file's tags, its problems logged (a few lines at most).
pub(crate) fn read_tag_file(section: &str, path: &std::path::Path) -> Vec<Tag> {
    match std::fs::read(path) {
        Ok(bytes) => {
            let file = tags::parse(&bytes);
            for warning in file.warnings.iter().take(5) {
                warn!(section, "tag file {}: {warning}", path.display());
            }
            let more = file.warnings.len().saturating_sub(5) + file.more_warnings;
            if more > 0 {
                warn!(
                    section,
                    "tag file {}: {more} more problems not shown",
                    path.display()
                );
            }
            file.tags
        }
        Err(e) => {
            warn!(section, "tag file {}: {e}", path.display());
            Vec::new()
        }
    }
}

/// Gives freed heap back to the system after a big transient (a list
/// built, a rebrowse): glibc keeps the top of each arena a peak grew, and
/// the RSS stayed at the peak's.
pub(crate) fn trim_heap() {
    use plccoms_core::link::jobs::{micros, SET_TIMING};
    LAST_TRIM_MS.store(process_ms(), std::sync::atomic::Ordering::Relaxed);
    let started = Instant::now();
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks the allocator's own free lists.
    unsafe {
        libc::malloc_trim(0);
    }
    tracing::debug!(target: SET_TIMING, trim_us = micros(started.elapsed()), "heap trim");
}

/// When the process last gave freed heap back ([`process_ms`]).
static LAST_TRIM_MS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Milliseconds since the first call (a monotonic clock for atomics).
fn process_ms() -> u64 {
    static START: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    u64::try_from(START.get_or_init(Instant::now).elapsed().as_millis()).unwrap_or(u64::MAX)
}

/// [`trim_heap`], if no section of the process did for [`TRIM_EVERY`].
fn trim_heap_when_due() {
    use std::sync::atomic::Ordering::Relaxed;
    let now = process_ms();
    let last = LAST_TRIM_MS.load(Relaxed);
    let every = TRIM_EVERY.as_millis() as u64;
    // One reader wins the turn; the others see it taken.
    if now.saturating_sub(last) >= every
        && LAST_TRIM_MS
            .compare_exchange(last, now, Relaxed, Relaxed)
            .is_ok()
    {
        trim_heap();
    }
}

/// The entries of a list's bytes, placed as the link's table places them.
fn list_of(bytes: Vec<u8>, types: browse::Types) -> List {
    let file = tags::parse(&bytes);
    let placed = tags::vars(&file.tags);
    let mut sources: Vec<NodeId> = Vec::new();
    // By a 128-bit hash of the node id: 100,000 node ids cloned as keys
    // were 6 MB more of this peak.
    let mut source_of: HashMap<u128, usize> = HashMap::new();
    let mut entries: Vec<Entry> = Vec::with_capacity(placed.len());
    for (tag, var) in file.tags.iter().filter(|t| t.ty.is_some()).zip(placed) {
        let text = tag.node.to_string();
        let node = node_of(&tag.node);
        let key = browse::visit_key(&node);
        let source = match source_of.get(&key) {
            Some(&s) => s,
            None => {
                source_of.insert(key, sources.len());
                sources.push(node);
                sources.len() - 1
            }
        };
        let leaf = tag.field.as_deref().and_then(|path| {
            let layout = types.layouts.get(&text)?;
            Some((layout.clone(), layout.leaf(path)?))
        });
        let builtin = match &leaf {
            Some((layout, i)) => layout.builtin(*i),
            None => types.builtins.get(&text).copied(),
        };
        entries.push(Entry {
            name: var.name.into(),
            offset: var.offset,
            ty: var.ty,
            builtin: builtin.unwrap_or_else(|| Builtin::of_iec(var.ty)),
            index: tag.index,
            source,
            leaf,
        });
    }
    drop(source_of);
    drop(file);
    sources.shrink_to_fit();
    // The entries of each source, counted then placed (a counting sort).
    let mut starts = vec![0u32; sources.len() + 1];
    for entry in &entries {
        starts[entry.source + 1] += 1;
    }
    for s in 1..starts.len() {
        starts[s] += starts[s - 1];
    }
    let mut next = starts.clone();
    let mut members = vec![0u32; entries.len()];
    for (i, entry) in entries.iter().enumerate() {
        members[next[entry.source] as usize] = i as u32;
        next[entry.source] += 1;
    }
    List {
        bytes,
        entries,
        sources,
        starts,
        members,
        types,
    }
}

/// The node id of a list's node (namespace indexes only: the list is
/// written with the server's indexes).
fn node_of(node: &NodeRef) -> NodeId {
    use plccoms_plc::opcua::nodeid::{Identifier, Namespace};
    let ns = match node.namespace {
        Namespace::Index(i) => i,
        Namespace::Uri(_) => 0,
    };
    match &node.identifier {
        Identifier::Numeric(n) => NodeId::new(ns, *n),
        Identifier::String(s) => NodeId::new(ns, s.clone()),
        Identifier::Guid(g) => g
            .parse::<opcua::types::Guid>()
            .map_or_else(|_| NodeId::null(), |g| NodeId::new(ns, g)),
        Identifier::Opaque(b) => opcua::types::ByteString::from_base64(b)
            .map_or_else(NodeId::null, |b| NodeId::new(ns, b)),
    }
}

#[async_trait]
impl PlcBackend for OpcuaBackend {
    fn describe(&self) -> String {
        format!("OPC UA {}", self.config.url)
    }

    /// Read mode: as many nodes a Read as the server takes. Subscribe
    /// mode: reads are answered from the values notified, without a round
    /// trip, in blocks of about 1,000 variables, so that the link serves a
    /// SET between two (one block of 100,000 held a SET up for all).
    fn max_read_block(&self, _area: Area) -> u32 {
        if self.config.subscribe {
            SUBSCRIBED_READ_BLOCK
        } else {
            1024 * 1024
        }
    }

    /// Only adjacent variables are read together: a gap is other nodes.
    fn read_gap(&self, _area: Area) -> Option<u32> {
        Some(0)
    }

    fn max_file_block(&self) -> u32 {
        1024 * 1024
    }

    fn answer_timeout(&self) -> Duration {
        self.config.timeout
    }

    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters;
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        self.open_session().await
    }

    async fn read(&mut self, reads: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        self.session()?;
        // A list the rebrowse built since.
        let rebuilt = self
            .connection
            .as_ref()
            .and_then(|c| c.rebuilt.lock().unwrap_or_else(|e| e.into_inner()).take());
        if let Some(built) = rebuilt {
            self.take_list(built);
        }
        trim_heap_when_due();
        let mut wanted: Vec<usize> = Vec::new();
        let mut state = false;
        for read in reads {
            match read.area {
                Area::R => wanted.extend(self.covered(read.offset, read.len)),
                _ => state = true,
            }
        }
        // The poll reads the system variables each cycle: its period is
        // the sampling interval (a GET or a SET's read-back in between is
        // no cycle).
        tracing::trace!(section = %self.config.section, blocks = reads.len(), system = state, "read");
        if state {
            let now = Instant::now();
            if let Some(last) = self.last_read.replace(now) {
                self.poll_gaps.rotate_right(1);
                self.poll_gaps[0] = Some(now - last);
            }
        }
        // The sources the entries read: an array once for its elements.
        let mut wanted: Vec<usize> = wanted
            .into_iter()
            .map(|i| self.served.entries[i].source)
            .collect();
        wanted.sort_unstable();
        wanted.dedup();
        // Subscribe mode answers from the values notified, in place: a
        // copy of 100,000 of them each cycle was 10 MB a second.
        let monitored = |b: &Self| b.subscription.as_ref().map_or(0, |s| s.monitored.len());
        let before = monitored(self);
        let read = if self.config.subscribe {
            self.monitor(&wanted).await?;
            // Not notified yet, or just written: from the server, once.
            let direct: Vec<usize> = {
                let notified = self.notified.lock().unwrap_or_else(|e| e.into_inner());
                if let Some(run) = notified.get(&STATE_HANDLE) {
                    self.run = matches!(run.value, Some(Variant::Int32(0)));
                    state = false;
                }
                wanted
                    .iter()
                    .copied()
                    .filter(|i| {
                        !notified.contains_key(&(*i as u32 + 1)) || self.written.contains(i)
                    })
                    .collect()
            };
            if !direct.is_empty() || state {
                // A SET's read-back on the session of its Write; the
                // poll's own reads on the link's.
                let read_back =
                    !direct.is_empty() && direct.iter().all(|i| self.written.contains(i));
                let session = match read_back {
                    true => self.write_session()?,
                    false => self.session()?,
                };
                let read = self.read_values(session, &direct, state).await?;
                let mut notified = self.notified.lock().unwrap_or_else(|e| e.into_inner());
                for (i, value) in read {
                    if let (true, Some(at)) = (self.written.contains(&i), value.source_timestamp) {
                        self.read_back.insert(i as u32 + 1, (at, Instant::now()));
                    }
                    notified.insert(i as u32 + 1, value, self.served.sources.len());
                }
                drop(notified);
                for i in &direct {
                    self.written.remove(i);
                }
            }
            // The first cycles of a big list read every value directly,
            // then monitor them all: what those took is given back at
            // once (the start-up's RSS peak: 126-141 MiB at 100,000
            // variables with the 10 s trim only).
            if direct.len() + monitored(self).saturating_sub(before) >= BIG_READ {
                trim_heap();
            }
            None
        } else {
            let session = self.session()?;
            Some(self.read_values(session, &wanted, state).await?)
        };
        let mut uncertain = Vec::new();
        let crc = self.list_crc();
        let notified = self.notified.clone();
        let notified = notified.lock().unwrap_or_else(|e| e.into_inner());
        let value_of = |s: usize| match &read {
            Some(read) => read.get(&s),
            None => notified.get(&(s as u32 + 1)),
        };
        let answers = reads
            .iter()
            .map(|read| match read.area {
                Area::R => self.answer(read, value_of, &mut uncertain),
                Area::S => self.system(read.offset, read.len, crc),
                _ => Err(Refusal::BAD_PARAMETERS),
            })
            .collect();
        drop(notified);
        for i in uncertain {
            self.uncertain
                .insert(self.served.entries[i].name[..].into());
        }
        Ok(answers)
    }

    async fn write(&mut self, writes: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        self.session()?;
        self.write_all(writes).await
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        self.session()?;
        Ok(PlcStatus { run: self.run })
    }

    /// Subscribe mode: the values notified since the last call, each with
    /// its SourceTimestamp; the last of each item is what reads answer
    /// from now on. A Bad one is no value: reads answer its refusal.
    /// At most [`TAKE_SLICE`] a call: the rest at the next, after the
    /// link's queued requests.
    fn take_pushed(&mut self) -> Vec<Pushed> {
        let mut inbox = std::mem::take(&mut self.spare);
        let behind = {
            let mut shared = self.inbox.lock().unwrap_or_else(|e| e.into_inner());
            if shared.len() <= TAKE_SLICE {
                std::mem::swap(&mut *shared, &mut inbox);
                false
            } else {
                inbox.extend(shared.drain(..TAKE_SLICE));
                true
            }
        };
        if behind {
            // The rest: the link comes back for it.
            self.wake.notify_one();
        }
        if inbox.is_empty() || self.subscription.is_none() {
            inbox.clear();
            self.spare = inbox;
            return Vec::new();
        }
        let mut pushed = Vec::with_capacity(inbox.len());
        // In the order of the handles, which is the list's and the table's:
        // servers notify in any order (async-opcua's in its hashes'), and
        // the values kept here, the link's slots and the chunks a publish
        // copies are then walked in order, not at random. The same item's
        // values stay in the order they came.
        let mut order = std::mem::take(&mut self.order);
        order.clear();
        order.extend(
            inbox
                .iter()
                .enumerate()
                .map(|(at, (_, handle, _))| (*handle, at as u32)),
        );
        order.sort_unstable();
        let mut notified = self.notified.lock().unwrap_or_else(|e| e.into_inner());
        for &(_, at) in &order {
            let (generation, handle, value) = std::mem::take(&mut inbox[at as usize]);
            if generation != self.generation {
                continue;
            }
            // The server has no value yet (a plccoms serving a variable it
            // starts polling now): the one it notifies next is what counts,
            // and the value shown stays meanwhile.
            if value.status == Some(StatusCode::BadWaitingForInitialData) {
                continue;
            }
            // A notification sampled before a SET's read-back (older)
            // would undo the SET. More than one can be on the way: a
            // plccoms serving the PLC notifies a change a SET made twice
            // (the value it left, Uncertain, then polled, Good), each in
            // its own publish, and both of an earlier SET's can still come.
            // The first at or after the read-back ends it.
            if let Some(&(shown, read_at)) = self.read_back.get(&handle) {
                match value.source_timestamp {
                    Some(new) if new < shown && read_at.elapsed() < READ_BACK_FLOOR => continue,
                    _ => {
                        self.read_back.remove(&handle);
                    }
                }
            }
            if handle != STATE_HANDLE {
                let Some(entries) = (handle as usize)
                    .checked_sub(1)
                    .and_then(|source| self.served.of_source(source))
                else {
                    continue;
                };
                let unix_ms = stamp_of(&value);
                let mut fields = structure::Fields::default();
                for &i in entries {
                    let entry = &self.served.entries[i as usize];
                    if let Ok(bytes) = entry_bytes(entry, &value, &mut fields) {
                        pushed.push(Pushed {
                            var: PushedVar::Listed {
                                list: self.served_version,
                                index: i,
                            },
                            bytes,
                            unix_ms,
                            uncertain: is_uncertain(&value),
                        });
                    }
                }
            }
            notified.insert(handle, value, self.served.sources.len());
        }
        drop(notified);
        // Kept for the next take, at the size of a slice or two at most.
        inbox.clear();
        inbox.shrink_to(2 * TAKE_SLICE);
        self.spare = inbox;
        order.shrink_to(2 * TAKE_SLICE);
        self.order = order;
        pushed
    }

    fn pushed_name(&self, list: u32, index: u32) -> Option<Arc<[u8]>> {
        let entry = self.served.entries.get(index as usize);
        Some(entry.filter(|_| list == self.served_version)?.name.clone())
    }

    /// The variables reads answered with an Uncertain status.
    fn take_uncertain(&mut self) -> Option<Vec<Box<[u8]>>> {
        Some(self.uncertain.drain().collect())
    }

    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        if self.subscription.is_none() {
            return std::future::pending().await;
        }
        self.wake.notified().await;
        Ok(())
    }

    /// The variable list ([`VARS_FILE`]), the newest built.
    async fn file_info(&mut self, path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        if path != VARS_FILE.as_bytes() {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        let fetching = match &self.newest {
            Some(newest) => newest.clone(),
            None => Arc::new((self.served.bytes.clone(), self.served.types.clone())),
        };
        let size = fetching.0.len() as u64;
        self.fetching = Some(fetching);
        Ok(Ok(FileInfo {
            size,
            attributes: plccoms_core::driver::FILE_ATTRIBUTE_READONLY,
            created: 0,
            modified: 0,
        }))
    }

    /// A part of the list being fetched; its last part makes it the list
    /// the link's reads and writes are laid out by.
    async fn read_file(
        &mut self,
        path: &[u8],
        offset: u64,
        len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        let Some(fetching) = &self.fetching else {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        };
        let bytes = &fetching.0;
        if path != VARS_FILE.as_bytes() || offset > bytes.len() as u64 {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        let end = (offset + u64::from(len)).min(bytes.len() as u64);
        let part = bytes[offset as usize..end as usize].to_vec();
        if end == bytes.len() as u64 {
            if let Some(fetched) = self.fetching.take() {
                if self.newest.as_ref().is_some_and(|n| n.0 == fetched.0) {
                    self.newest = None;
                }
                // Its only holder now, unless a newer list came meanwhile.
                let (bytes, types) = Arc::unwrap_or_clone(fetched);
                self.served = list_of(bytes, types);
                self.served_version = plccoms_core::driver::next_list_version();
                self.crc = None;
                // The old list and this one's making gone: 30 MB at
                // 100,000 variables, kept resident otherwise.
                trim_heap();
                // The handles of the old list mean other variables now.
                if let Some(subscription) = self.subscription.take() {
                    let mut sessions: Vec<usize> =
                        subscription.parts.iter().map(|p| p.session).collect();
                    sessions.dedup();
                    for n in sessions {
                        let Ok(session) = self.subscription_session(n) else {
                            break;
                        };
                        let ids: Vec<u32> = subscription
                            .parts
                            .iter()
                            .filter(|p| p.session == n)
                            .map(|p| p.id)
                            .collect();
                        let _ = self
                            .call("DeleteSubscriptions", session.delete_subscriptions(&ids))
                            .await;
                    }
                }
                self.notified
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .clear();
                self.written.clear();
                self.read_back.clear();
            }
        }
        Ok(Ok(part))
    }
}

/// This driver, for the binary's list: sections with `PROTOCOL = OPCUA`.
pub const DRIVER: Driver = Driver {
    name: "opcua",
    open,
};

fn open(section: &plccoms_core::config::Section, dir: &std::path::Path) -> Option<Opened> {
    if section.protocol != Protocol::Opcua {
        return None;
    }
    Some(config_of(section, dir).map(|config| {
        config.map(|config| Box::new(OpcuaBackend::new(config)) as Box<dyn PlcBackend>)
    }))
}

/// OPC UA settings from a section's keys; `None` when it names no server
/// yet (no OPCUA_URL).
pub fn config_of(
    section: &plccoms_core::config::Section,
    dir: &std::path::Path,
) -> Result<Option<OpcuaConfig>, String> {
    let keys = &section.opcua_client;
    let Some(url) = keys.url.clone().filter(|u| !u.trim().is_empty()) else {
        return Ok(None);
    };
    if !url.starts_with("opc.tcp://") {
        return Err(format!(
            "OPCUA_URL = {url}: expected opc.tcp://host:port/path"
        ));
    }
    let (mode, policy) = parse_security(&keys.security)?;
    let user = match (&keys.user, &keys.password) {
        (Some(user), password) => Some((user.clone(), password.clone().unwrap_or_default())),
        (None, Some(_)) => return Err("OPCUA_PASSWORD without OPCUA_USER".to_string()),
        (None, None) => None,
    };
    let browse = match &keys.browse {
        Some(list) => list
            .split(',')
            .filter(|n| !n.trim().is_empty())
            .map(|n| nodeid::parse(n).map_err(|e| format!("OPCUA_BROWSE: {e}")))
            .collect::<Result<Vec<_>, _>>()?,
        None => Vec::new(),
    };
    let state = plccoms_core::config::systemd_state_dir().unwrap_or_else(|| dir.to_path_buf());
    let pki = match &keys.pki {
        Some(path) => state.join(path),
        None => state.join("opcua-client-pki"),
    };
    Ok(Some(OpcuaConfig {
        url,
        mode,
        policy,
        user,
        pki,
        browse,
        tags: keys.tags.as_deref().map(|name| section.path_of(dir, name)),
        subscribe: keys.subscribe,
        timeout: keys.timeout,
        rebrowse: (!keys.rebrowse.is_zero()).then_some(keys.rebrowse),
        write_session: keys.write_session,
        session_items: match keys.session_items {
            0 => usize::MAX,
            n => n,
        },
        section: section.name.clone(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn security_settings() {
        assert_eq!(
            parse_security("None").unwrap(),
            (MessageSecurityMode::None, SecurityPolicy::None)
        );
        assert_eq!(
            parse_security("SignAndEncrypt:Basic256Sha256").unwrap(),
            (
                MessageSecurityMode::SignAndEncrypt,
                SecurityPolicy::Basic256Sha256
            )
        );
        assert!(parse_security("Encrypt:Basic256Sha256")
            .unwrap_err()
            .contains("mode 'encrypt'"));
        assert!(parse_security("Sign:Foo")
            .unwrap_err()
            .contains("unknown policy"));
        assert!(parse_security("Sign").unwrap_err().contains("mode:policy"));
    }

    fn backend_of(served: List) -> OpcuaBackend {
        OpcuaBackend {
            served,
            ..OpcuaBackend::new(OpcuaConfig {
                url: String::new(),
                mode: MessageSecurityMode::None,
                policy: SecurityPolicy::None,
                user: None,
                pki: PathBuf::new(),
                browse: Vec::new(),
                tags: None,
                subscribe: false,
                timeout: Duration::from_secs(1),
                rebrowse: None,
                write_session: true,
                session_items: usize::MAX,
                section: String::new(),
            })
        }
    }

    /// A backend of the INT variables `A` (handle 1) and `B` (2), with a
    /// subscription.
    fn subscribed_to_a_and_b() -> OpcuaBackend {
        let list = list_of(
            b"name,node,type\nA,i=1,INT\nB,i=2,INT\n".to_vec(),
            browse::Types::default(),
        );
        let mut backend = backend_of(list);
        backend.subscription = Some(Subscription {
            parts: Vec::new(),
            monitored: Monitored::default(),
        });
        backend
    }

    fn int(n: i16) -> DataValue {
        DataValue::new_now(Variant::Int16(n))
    }

    /// The name of a pushed value's variable, as the link asks it.
    fn name_of(backend: &OpcuaBackend, pushed: &Pushed) -> Vec<u8> {
        let PushedVar::Listed { list, index } = pushed.var else {
            panic!("pushed by name: {:?}", pushed.var);
        };
        backend.pushed_name(list, index).expect("a name").to_vec()
    }

    #[test]
    fn monitored_sources_are_counted_once() {
        let mut monitored = Monitored::default();
        assert!(!monitored.contains(0) && !monitored.contains(1_000_000));
        for source in [0, 63, 64, 100_000, 63] {
            monitored.insert(source);
        }
        assert_eq!(monitored.len(), 4);
        assert!(monitored.contains(63) && monitored.contains(64) && monitored.contains(100_000));
        assert!(!monitored.contains(1) && !monitored.contains(99_999) && !monitored.contains(128));
    }

    #[test]
    fn values_are_kept_for_the_lists_sources_only() {
        let mut values = Values::default();
        values.insert(3, int(3), 5);
        values.insert(STATE_HANDLE, int(0), 5);
        // Not a source of the list: a server's stray handle.
        values.insert(6, int(6), 5);
        values.insert(0, int(-1), 5);
        assert_eq!(values.get(&3).unwrap().value, Some(Variant::Int16(3)));
        assert_eq!(
            values.get(&STATE_HANDLE).unwrap().value,
            Some(Variant::Int16(0))
        );
        assert!(!values.contains_key(&1));
        assert!(!values.contains_key(&6));
        assert!(!values.contains_key(&0));
        assert_eq!(values.sources.capacity(), 5);
        values.clear();
        assert!(!values.contains_key(&3));
    }

    #[test]
    fn a_full_inbox_keeps_the_newest_of_each_item_in_order() {
        let mut inbox: Vec<(u64, u32, DataValue)> =
            [(1, 1), (1, 2), (1, 1), (2, 1), (1, 3), (1, 2)]
                .iter()
                .enumerate()
                .map(|(n, &(g, h))| (g, h, int(n as i16)))
                .collect();
        keep_newest(&mut inbox);
        let kept: Vec<(u64, u32, Option<Variant>)> =
            inbox.into_iter().map(|(g, h, v)| (g, h, v.value)).collect();
        assert_eq!(
            kept,
            [
                (1, 1, Some(Variant::Int16(2))),
                (2, 1, Some(Variant::Int16(3))),
                (1, 3, Some(Variant::Int16(4))),
                (1, 2, Some(Variant::Int16(5))),
            ]
        );
    }

    /// Notifications are taken a slice at a time, oldest first, and the
    /// link is woken for the rest.
    #[tokio::test]
    async fn notifications_are_taken_in_slices() {
        let mut backend = subscribed_to_a_and_b();
        let all = TAKE_SLICE + 7;
        backend
            .inbox
            .lock()
            .unwrap()
            .extend((0..all).map(|n| (backend.generation, (n % 2) as u32 + 1, int(n as i16))));
        let first = backend.take_pushed();
        assert_eq!(first.len(), TAKE_SLICE);
        assert_eq!(first[0].bytes[..], 0i16.to_le_bytes());
        // Woken for the rest.
        tokio::time::timeout(Duration::from_secs(5), backend.wait_pushed())
            .await
            .expect("woken for the rest")
            .unwrap();
        // In the order of the items, each one's values as they came.
        let rest = backend.take_pushed();
        let names: Vec<Vec<u8>> = rest.iter().map(|p| name_of(&backend, p)).collect();
        assert_eq!(names, [&b"A"[..], b"A", b"A", b"A", b"B", b"B", b"B"]);
        let values: Vec<i16> = rest
            .iter()
            .map(|p| i16::from_le_bytes([p.bytes[0], p.bytes[1]]))
            .collect();
        let slice = TAKE_SLICE as i16;
        assert_eq!(values, [0, 2, 4, 6, 1, 3, 5].map(|n| slice + n));
        // A list no longer served names nothing.
        let other = backend.served_version.wrapping_add(1);
        assert_eq!(backend.pushed_name(other, 0), None);
        assert_eq!(rest[3].bytes[..], ((all - 1) as i16).to_le_bytes());
        assert!(backend.take_pushed().is_empty());
        // The value reads answer is the last taken.
        let notified = backend.notified.lock().unwrap();
        assert_eq!(
            notified.get(&1).unwrap().value,
            Some(Variant::Int16((all - 1) as i16))
        );
        assert!(!notified.contains_key(&3));
    }

    /// Every notification sampled before a SET's read-back is dropped,
    /// not only the first (a plccoms serving the PLC sends the value the
    /// SET left Uncertain, then polled Good); the first at or after it ends
    /// that, and other items are untouched.
    #[test]
    fn notifications_older_than_a_sets_read_back_are_dropped() {
        let mut backend = subscribed_to_a_and_b();
        let read_at = opcua::types::DateTime::now();
        let at = |ms: i64, n: i16, uncertain: bool| DataValue {
            source_timestamp: Some(read_at + chrono::Duration::milliseconds(ms)),
            status: uncertain.then_some(StatusCode::UncertainLastUsableValue),
            ..int(n)
        };
        backend.read_back.insert(1, (read_at, Instant::now()));
        let generation = backend.generation;
        backend.inbox.lock().unwrap().extend([
            (generation, 1, at(-20, 1, true)),
            (generation, 2, at(-10, 7, false)),
            (generation, 1, at(-5, 1, false)),
            (generation, 1, at(0, 2, false)),
            (generation, 1, at(-30, 3, false)),
        ]);
        let taken: Vec<(Vec<u8>, i16)> = backend
            .take_pushed()
            .into_iter()
            .map(|p| {
                (
                    name_of(&backend, &p),
                    i16::from_le_bytes([p.bytes[0], p.bytes[1]]),
                )
            })
            .collect();
        assert_eq!(
            taken,
            [(b"A".to_vec(), 2), (b"A".to_vec(), 3), (b"B".to_vec(), 7)]
        );
        assert!(backend.read_back.is_empty());
    }

    #[test]
    fn reads_cover_the_variables_they_touch() {
        let list = list_of(
            b"name,node,type\nA,i=1,BOOL\nB,i=2,INT\nC,i=3,LREAL\n".to_vec(),
            browse::Types::default(),
        );
        let backend = backend_of(list);
        assert_eq!(backend.covered(0, 1), 0..1);
        assert_eq!(backend.covered(1, 2), 1..2);
        assert_eq!(backend.covered(0, 11), 0..3);
        assert_eq!(backend.covered(2, 1), 1..2);
        assert_eq!(backend.covered(11, 4), 3..3);
        let mut values = HashMap::new();
        values.insert(0, DataValue::new_now(Variant::Boolean(true)));
        values.insert(1, DataValue::new_now(Variant::Int16(-2)));
        let read = ReadRequest {
            area: Area::R,
            offset: 0,
            len: 3,
        };
        let mut uncertain = Vec::new();
        assert_eq!(
            backend.answer(&read, |s| values.get(&s), &mut uncertain),
            Ok(vec![1, 0xFE, 0xFF])
        );
        assert!(uncertain.is_empty());
        // Uncertain: the value, and the entry marked.
        values.insert(
            1,
            DataValue {
                value: Some(Variant::Int16(-3)),
                status: Some(StatusCode::UncertainLastUsableValue),
                ..Default::default()
            },
        );
        assert_eq!(
            backend.answer(&read, |s| values.get(&s), &mut uncertain),
            Ok(vec![1, 0xFD, 0xFF])
        );
        assert_eq!(uncertain, [1]);
        values.insert(
            1,
            DataValue {
                status: Some(StatusCode::BadNotReadable),
                ..Default::default()
            },
        );
        assert_eq!(
            backend.answer(&read, |s| values.get(&s), &mut uncertain),
            Err(Refusal::Opcua(StatusCode::BadNotReadable.bits()))
        );
    }
}
