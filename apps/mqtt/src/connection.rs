//! One section's MQTT task: takes the section's changes, queues them on
//! disk (`spool.rs`), keeps a connection to the broker and sends the queue
//! in order, handles `/set` writes (`writes.rs`), the `status` and `plc`
//! topics and Home Assistant discovery.
//!
//! rumqttc is the transport (MQTT 5: codec, TLS, keep-alive). MQTT 5
//! because only its Retain As Published tells a retained `/set` from a live
//! one while subscribed, so that every retained write is refused. Delivery is this
//! task's: every QoS 1 message is in the spool before it is handed to
//! rumqttc and leaves it when the broker acknowledges it (matched through
//! rumqttc's `Outgoing::Publish(pkid)` events, which come in the order the
//! messages were handed over). Each connection attempt gets a fresh client
//! and event loop with a clean session, and sending starts again at the
//! oldest unacknowledged message: no message is lost to a dropped
//! connection, none is reordered, and a broker never holds writes for us
//! while we are away. The event loop runs in a task of its own and forwards
//! its events, so this task only ever waits on channels.
//!
//! State messages (`status`, `plc`, discovery configs) are not queued: they
//! are sent again on every connection.
//!
//! Each attempt goes to the current broker of MQTT_URL (`client.rs`); a
//! lost or failed one moves to the next, so a new node of a cluster gets the
//! queue from its oldest unacknowledged message, the state messages and
//! discovery, and the will. With MQTT_VERSION = 3.1.1 the link speaks
//! 3.1.1 and hands its events over in the MQTT 5 types used here.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use plccoms_protocol::cp1250;
use plccoms_protocol::value::Value;
use rumqttc::v5::mqttbytes::v5::{ConnectReturnCode, Filter, Packet, SubscribeReasonCode};
use rumqttc::v5::mqttbytes::{self, QoS};
use rumqttc::v5::{ConnectionError, Event, StateError};
use rumqttc::Outgoing;
use tokio::sync::mpsc;
use tokio::time::{Instant, MissedTickBehavior};
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};

use super::client::{Brokers, Connect, Link, NEXT_BROKER};
use super::discovery::{self, Device, Maker};
use super::settings::{SectionRules, Settings};
use super::spool::{Message, Spool};
use super::topics::Topics;
use super::writes::{self, Refused};
use super::Metrics;
use plccoms_core::changes::{ChangeBatch, Quality, Subscription};
use plccoms_core::config::MqttFormat;
use plccoms_core::present::Presented;
use plccoms_core::ratelimit::{self, RateLimited};
use plccoms_core::section::Section;
use plccoms_core::vars::{VarId, VarTable};

/// Publishes handed to rumqttc and not yet acknowledged (or, QoS 0,
/// written), at most.
const WINDOW: usize = 256;
/// The largest message taken from the broker, announced to it as MQTT 5's
/// maximum packet size: the broker drops a bigger one for this client
/// rather than send it (before MQTT 5 a retained one, too big for the
/// client, broke every connection at its subscription). Generous, far above
/// any write (`/set` values of more than [`writes::MAX_VALUE`] bytes are
/// refused), and still a bound on what one message can make this process
/// hold.
pub(super) const MAX_INCOMING: usize = 16 << 20;
pub(super) const RETRY_FIRST: Duration = Duration::from_millis(250);
pub(super) const RETRY_MAX: Duration = Duration::from_secs(5);
/// A connection up this long is a healthy one: the retry delay starts
/// again from [`RETRY_FIRST`] and the next problem is logged. One that
/// fails sooner (at its subscriptions, say) keeps backing off quietly.
const STABLE: Duration = Duration::from_secs(30);
/// Refused writes of one error code are logged at most this often.
pub(super) const REFUSAL_LOG_INTERVAL: Duration = Duration::from_secs(1);
/// How long a clean stop waits for `offline` and DISCONNECT to go out.
pub(super) const STOP_WAIT: Duration = Duration::from_secs(2);

/// An announcement under way: the next of `wanted` to announce, and the
/// config topics left to clear.
struct Announcement {
    next: usize,
    gone: Vec<String>,
}

pub(super) struct Task {
    pub section: Arc<Section>,
    pub settings: Arc<Settings>,
    pub rules: SectionRules,
    pub topics: Topics,
    pub client_id: String,
    pub spool: Spool,
    pub spool_dir: PathBuf,
    pub metrics: Arc<Metrics>,
    pub shutdown: CancellationToken,
    pub writes: mpsc::Sender<writes::Request>,
    pub outcomes: mpsc::Receiver<writes::Outcome>,
    /// Any client of the broker can have writes refused at will: logged at
    /// most once a second per error code (each one counted and published
    /// on its `error` topic). The codes are SET's few, so the map is small.
    pub refusal_logs: BTreeMap<u16, RateLimited>,
    /// MQTT_URL's brokers, the one in use.
    pub brokers: Brokers,
    pub state: State,
}

/// What the task keeps between events.
#[derive(Default)]
pub(super) struct State {
    link: Option<Link>,
    connected: bool,
    retry_at: Option<Instant>,
    backoff: Duration,
    /// The last connection problem logged (each logged once per outage;
    /// an outage ends when a connection stayed up [`STABLE`]).
    logged: Option<String>,
    /// "Connected again" was logged in this outage.
    reconnect_logged: bool,
    /// The place in MQTT_URL of the broker last connected to.
    last_broker: Option<usize>,
    /// When the current connection was made.
    connected_at: Option<Instant>,
    /// State messages for this connection, sent before the queue.
    direct: VecDeque<Message>,
    /// Per publish handed to rumqttc, in order: its spool sequence number,
    /// or `None` for a state message.
    submitted: VecDeque<Option<u64>>,
    /// Packet id -> spool sequence number of QoS 1 messages on the wire.
    inflight: HashMap<u16, u64>,
    outstanding: usize,
    table: Option<Arc<VarTable>>,
    wanted: Vec<VarId>,
    /// Value topic per variable of `table`, made once.
    value_topics: Vec<Option<String>>,
    /// Deadband: the value last published per variable (MQTT_DELTA only).
    last: Vec<Option<Value>>,
    /// The change stream's sequence of the value last published per
    /// variable: a confirmed write it already carried is not published again.
    published_seq: Vec<u64>,
    plc_online: Option<bool>,
    announced: BTreeSet<String>,
    /// The device's maker as last announced: announced again when the
    /// PLC's identification becomes known or changes.
    maker: Option<Maker>,
    /// The discovery announcement under way: one at a time, however many
    /// `online`s come while it is pending or running.
    announcing: Option<Announcement>,
    /// Messages dropped over MQTT_BUFFER since the queue was last empty.
    dropping: u64,
    spool_failing: bool,
    /// When falling behind the change stream was last logged.
    missed_logged: Option<Instant>,
}

impl Task {
    pub async fn run(mut self, mut changes: Subscription) {
        self.state.announced = discovery::load_announced(&self.spool_dir);
        self.adopt_table(&changes);
        self.connect();
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        tick.set_missed_tick_behavior(MissedTickBehavior::Skip);
        let mut stream_open = true;
        // The PLC's identification comes after the first values (the
        // public file is fetched first): discovery names it once known.
        let mut section_state = self.section.watch_state();
        loop {
            self.pump();
            tokio::select! {
                biased;
                _ = self.shutdown.cancelled() => break,
                event = next_event(&mut self.state.link) => self.on_event(event),
                // Changes before outcomes: the link publishes a write's
                // value before it answers, so a write's outcome finds the
                // batch that carried its value handled (`published_seq`).
                batch = changes.next(), if stream_open => match batch {
                    Some(batch) => {
                        if batch.table_changed {
                            self.adopt_table(&changes);
                        }
                        self.on_batch(&batch);
                    }
                    None => stream_open = false,
                },
                Some(outcome) = self.outcomes.recv() => self.on_outcome(outcome),
                _ = sleep_until(self.state.retry_at) => {
                    self.state.retry_at = None;
                    self.connect();
                }
                _ = tick.tick() => self.checkpoint(),
                Ok(()) = section_state.changed() => self.on_state(),
            }
        }
        self.stop().await;
    }

    // ------------------------------------------------------------ connection

    /// Starts a connection attempt to the current broker: a fresh client
    /// and event loop.
    fn connect(&mut self) {
        self.metrics.broker_index.set(self.brokers.index() as u64);
        let connect = Connect {
            settings: &self.settings,
            broker: self.brokers.current(),
            client_id: &self.client_id,
            inflight: Some((WINDOW + 8) as u16),
            will_topic: self.topics.status(),
            will_payload: b"offline".to_vec(),
            will_retain: true,
            max_incoming: MAX_INCOMING,
        };
        self.state.link = Some(Link::spawn(connect, WINDOW + 16, WINDOW * 2));
    }

    fn on_event(&mut self, event: Result<Event, ConnectionError>) {
        match event {
            Ok(Event::Incoming(Packet::ConnAck(_))) => self.on_connected(),
            Ok(Event::Incoming(Packet::PubAck(ack))) => {
                self.state.outstanding = self.state.outstanding.saturating_sub(1);
                if let Some(seq) = self.state.inflight.remove(&ack.pkid) {
                    self.spool.ack(seq);
                    self.metrics.published.inc();
                }
            }
            Ok(Event::Outgoing(Outgoing::Publish(pkid))) => {
                let submitted = self.state.submitted.pop_front().flatten();
                match (pkid, submitted) {
                    // QoS 0: done once written.
                    (0, seq) => {
                        self.state.outstanding = self.state.outstanding.saturating_sub(1);
                        if let Some(seq) = seq {
                            self.spool.ack(seq);
                            self.metrics.published.inc();
                        }
                    }
                    (pkid, Some(seq)) => {
                        self.state.inflight.insert(pkid, seq);
                    }
                    (_, None) => {}
                }
            }
            Ok(Event::Incoming(Packet::Publish(publish))) => {
                let topic = String::from_utf8_lossy(&publish.topic);
                self.on_message(&topic, &publish.payload, publish.retain)
            }
            Ok(Event::Incoming(Packet::SubAck(ack))) => {
                let failed =
                    |code: &SubscribeReasonCode| !matches!(code, SubscribeReasonCode::Success(_));
                if ack.return_codes.iter().any(failed) {
                    error!(section = %self.section.name(), "MQTT: the broker refused a subscription (to {} or {}): writes or discovery refreshes will not arrive; check the broker's ACL", self.topics.set_filter(), discovery::HA_STATUS);
                }
            }
            Ok(_) => {}
            Err(e) => self.on_disconnected(e),
        }
    }

    fn on_connected(&mut self) {
        let broker = &self.brokers;
        let queued = self.spool.len();
        // A move to another broker of MQTT_URL is always told.
        let moved = self.state.last_broker.replace(broker.index()) != Some(broker.index());
        if moved {
            self.state.reconnect_logged = false;
        }
        match (&self.state.logged, self.state.reconnect_logged) {
            (None, _) => {
                info!(section = %self.section.name(), "MQTT: connected to {broker} as {} ({queued} queued messages)", self.client_id)
            }
            (Some(_), false) => {
                info!(section = %self.section.name(), "MQTT: connected to {broker} again as {}; sending {queued} queued messages", self.client_id);
                self.state.reconnect_logged = true;
            }
            // Connections that fail at once, again and again: quiet.
            (Some(_), true) => {
                debug!(section = %self.section.name(), "MQTT: connected again ({queued} queued messages)")
            }
        }
        self.brokers.connected();
        let state = &mut self.state;
        state.connected = true;
        state.connected_at = Some(Instant::now());
        state.submitted.clear();
        state.inflight.clear();
        state.outstanding = 0;
        self.metrics.connected.set(1);
        self.metrics.connects.inc();
        if let Some(link) = &self.state.link {
            if !self.rules.write.is_empty() {
                // Retain As Published: a retained `/set` comes marked
                // retained also while subscribed, so it is refused
                // whenever it comes (MQTT 3.1.1 marks only those sent at
                // subscription).
                let mut filter = Filter::new(self.topics.set_filter(), QoS::AtLeastOnce);
                filter.preserve_retain = true;
                let _ = link.client.try_subscribe_filter(filter);
            }
            if self.rules.ha_discovery {
                let _ = link
                    .client
                    .try_subscribe(discovery::HA_STATUS.into(), QoS::AtLeastOnce);
            }
        }
        self.state.direct.clear();
        self.state
            .direct
            .push_back(state_message(self.topics.status(), "online"));
        // Before its first batch (a section publishing nothing has batches
        // only when the link changes), the link as the stream has it now.
        let plc = self
            .state
            .plc_online
            .unwrap_or_else(|| self.section.latest().online);
        self.state.direct.push_back(plc_message(&self.topics, plc));
        self.announce();
        self.spool.rewind();
        if self.rules.qos == 0 {
            // QoS 0 changes were not kept while the broker was away: the
            // latest values instead.
            self.publish_all(None);
        }
    }

    fn on_disconnected(&mut self, e: ConnectionError) {
        let was_connected = self.state.connected;
        self.settle();
        let state = &mut self.state;
        state.link = None;
        state.connected = false;
        state.connected_at = None;
        state.direct.clear();
        state.announcing = None;
        state.submitted.clear();
        state.inflight.clear();
        state.outstanding = 0;
        self.spool.rewind();
        self.metrics.connected.set(0);
        let broker = self.brokers.to_string();
        let problem = describe(&e);
        let section = self.section.name();
        let round = self.brokers.advance();
        let several = self.brokers.len() > 1;
        let next = if several {
            format!(", moving to {}", self.brokers)
        } else {
            String::new()
        };
        // Each move off a lost broker is logged; failed attempts once per
        // outage and problem.
        if (several && was_connected) || self.state.logged.as_deref() != Some(problem.as_str()) {
            if was_connected {
                warn!(section = %section, "MQTT: connection to {broker} lost: {problem}; changes are queued on disk{next}");
            } else if matches!(e, ConnectionError::ConnectionRefused(_)) {
                error!(section = %section, "MQTT: {broker} refused the connection as {}: {problem}; retrying{next}", self.client_id);
            } else {
                warn!(section = %section, "MQTT: cannot connect to {broker}: {problem}; changes are queued on disk{next}");
            }
            self.state.logged = Some(problem);
        }
        self.metrics.broker_index.set(self.brokers.index() as u64);
        let delay = if !round {
            NEXT_BROKER
        } else if self.state.backoff.is_zero() {
            RETRY_FIRST
        } else {
            (self.state.backoff * 2).min(RETRY_MAX)
        };
        if round {
            self.state.backoff = delay;
        }
        self.state.retry_at = Some(Instant::now() + delay);
    }

    /// Hands messages to rumqttc while the window has room: state messages
    /// first, then the queue in order.
    fn pump(&mut self) {
        if !self.state.connected {
            return;
        }
        while self.state.outstanding < WINDOW {
            let state_message = match self.state.direct.pop_front() {
                Some(message) => Some(message),
                None => self.next_announcement(),
            };
            let (message, seq) = match state_message {
                Some(message) => (message, None),
                None => match self.spool.next_unsent() {
                    Ok(Some((seq, message))) => (message, Some(seq)),
                    Ok(None) => break,
                    Err(e) => {
                        error!(section = %self.section.name(), "MQTT: cannot read the queue: {e}");
                        break;
                    }
                },
            };
            let Some(link) = &self.state.link else {
                return;
            };
            let qos = if message.qos == 0 {
                QoS::AtMostOnce
            } else {
                QoS::AtLeastOnce
            };
            match link
                .client
                .try_publish(message.topic, qos, message.retain, message.payload)
            {
                Ok(()) => {
                    self.state.outstanding += 1;
                    self.state.submitted.push_back(seq);
                }
                Err(e) => {
                    // Only a topic rumqttc refuses gets here (the channel
                    // has room for the whole window): skip it, once.
                    error!(section = %self.section.name(), "MQTT: message not sent: {e}");
                    if let Some(seq) = seq {
                        self.spool.ack(seq);
                    }
                }
            }
        }
    }

    // ------------------------------------------------------------- changes

    fn adopt_table(&mut self, changes: &Subscription) {
        let table = changes.table().clone();
        let state = &mut self.state;
        state.value_topics = vec![None; table.len()];
        state.last = vec![None; table.len()];
        state.published_seq = vec![0; table.len()];
        state.wanted = changes.wanted().to_vec();
        let replaced = state.table.replace(table).is_some();
        if replaced {
            self.announce();
        }
    }

    fn value_topic(&mut self, id: VarId) -> String {
        let slot = &mut self.state.value_topics[id as usize];
        if let Some(topic) = slot {
            return topic.clone();
        }
        let table = self.state.table.as_ref().expect("a table");
        let topic = self.topics.value(&table.var(id).name);
        *slot = Some(topic.clone());
        topic
    }

    fn on_batch(&mut self, batch: &ChangeBatch) {
        if batch.missed > 0 {
            self.metrics.missed.add(batch.missed);
            let quiet = self
                .state
                .missed_logged
                .is_some_and(|at| at.elapsed() < Duration::from_secs(60));
            if !quiet {
                warn!(section = %self.section.name(), "MQTT: fell behind the polls past {} publishes or {} MiB of them ({} not seen); the latest values are published, intermediate ones are not (plccoms_mqtt_missed_total)", plccoms_core::changes::FOLLOW_BOUND, plccoms_core::changes::FOLLOW_BYTES >> 20, batch.missed);
                self.state.missed_logged = Some(Instant::now());
            }
        }
        let online = batch.snapshot.online;
        let link_changed = self.state.plc_online.replace(online) != Some(online);
        if link_changed && self.state.connected {
            self.state
                .direct
                .push_back(plc_message(&self.topics, online));
            if online {
                self.on_state();
            }
        }
        if link_changed && self.rules.format == MqttFormat::Json && !batch.table_changed {
            // Every value's quality changed with the link.
            self.publish_all(Some(batch));
        } else {
            self.publish(batch, &batch.changes, false);
        }
    }

    /// Publishes the latest value of every published variable (`batch`'s
    /// snapshot, else the latest one), deadband aside.
    fn publish_all(&mut self, batch: Option<&ChangeBatch>) {
        let snapshot = match batch {
            Some(batch) => batch.snapshot.clone(),
            None => self.section.latest(),
        };
        let same_table = self
            .state
            .table
            .as_ref()
            .is_some_and(|t| Arc::ptr_eq(t, &snapshot.table));
        if !same_table {
            return;
        }
        let wanted = std::mem::take(&mut self.state.wanted);
        let batch = ChangeBatch {
            snapshot,
            missed: 0,
            table_changed: false,
            link: None,
            changes: Vec::new(),
        };
        self.publish(&batch, &wanted, true);
        self.state.wanted = wanted;
    }

    fn publish(&mut self, batch: &ChangeBatch, ids: &[VarId], force: bool) {
        let snapshot = &batch.snapshot;
        let table = &snapshot.table;
        let section = self.section.clone();
        let format = section.format();
        let mut out = Vec::with_capacity(ids.len());
        for &id in ids {
            let slot = snapshot.slot(id);
            let Some(text) = slot.text() else {
                continue;
            };
            if let Some(delta) = &self.rules.delta {
                let var = table.var(id);
                let value = slot.value(var);
                let last = &mut self.state.last[id as usize];
                if let (Some(value), Some(previous), false) = (&value, last.as_ref(), force) {
                    if !value.exceeds(previous, delta, var.ty, format) {
                        continue;
                    }
                }
                *last = value;
            }
            self.state.published_seq[id as usize] = snapshot.seq;
            let shown = Presented::of(table.var(id).ty, text, format);
            let payload = super::payload::value(
                self.rules.format,
                &shown,
                slot.changed_ms,
                snapshot.quality(id),
            );
            out.push(Message {
                topic: self.value_topic(id),
                payload,
                qos: self.rules.qos,
                retain: self.rules.retain,
            });
        }
        self.queue(out);
    }

    /// Queues messages on disk: QoS 1 always, QoS 0 only while connected.
    fn queue(&mut self, mut messages: Vec<Message>) {
        if !self.state.connected {
            let before = messages.len();
            messages.retain(|m| m.qos > 0);
            self.metrics.not_sent.add((before - messages.len()) as u64);
        }
        if messages.is_empty() {
            return;
        }
        match self.spool.push(&messages) {
            Ok(dropped) => {
                self.state.spool_failing = false;
                if dropped > 0 {
                    self.metrics.dropped.add(dropped);
                    if self.state.dropping == 0 {
                        warn!(section = %self.section.name(), "MQTT: MQTT_BUFFER ({} bytes) is full: dropping the oldest queued messages (counted in plccoms_mqtt_dropped_total)", self.settings.buffer);
                    }
                    self.state.dropping += dropped;
                }
            }
            Err(e) => {
                self.metrics.dropped.add(messages.len() as u64);
                if !self.state.spool_failing {
                    error!(section = %self.section.name(), "MQTT: cannot write the queue in {}: {e}; changes are dropped until it works again", self.spool_dir.display());
                    self.state.spool_failing = true;
                }
            }
        }
        self.metrics.queued.set(self.spool.len());
    }

    // -------------------------------------------------------------- writes

    fn on_message(&mut self, topic: &str, payload: &[u8], retained: bool) {
        if topic == discovery::HA_STATUS {
            // Coalesced: an announcement pending or running already
            // sends every config.
            let pending = self.state.announcing.is_some();
            if payload == b"online" && self.rules.ha_discovery && !retained && !pending {
                self.announce();
            }
            return;
        }
        let Some(level) = self.topics.set_level(topic) else {
            return;
        };
        if retained && payload.is_empty() {
            // Someone clearing a retained `/set`, as its refusal asks:
            // nothing to write, nothing to say.
            return;
        }
        let checked = writes::check(&self.rules, level, payload, retained);
        let request = match checked {
            Ok(request) => request,
            Err(refused) => return self.refuse(level.to_string(), refused),
        };
        if let Err(e) = self.writes.try_send(request) {
            let request = match e {
                mpsc::error::TrySendError::Full(r) | mpsc::error::TrySendError::Closed(r) => r,
            };
            let refused = writes::busy(&request);
            self.refuse(request.level, refused);
        }
    }

    fn on_outcome(&mut self, outcome: writes::Outcome) {
        match outcome.result {
            Ok(confirmed) => {
                self.metrics.writes.inc();
                debug!(section = %self.section.name(), "MQTT: wrote {} = {}", cp1250::decode(&confirmed.name), cp1250::decode(&confirmed.text));
                let table = self.state.table.clone();
                if let Some(id) = table.and_then(|t| t.lookup(&confirmed.name)) {
                    let id = id as usize;
                    // The change stream published this value or a later
                    // one: confirmed already. It does not when the value
                    // is unchanged, not in MQTT_PUBLISH, or in the deadband.
                    if self.state.published_seq[id] >= confirmed.seq {
                        return;
                    }
                    self.state.published_seq[id] = confirmed.seq;
                    if self.rules.delta.is_some() {
                        self.state.last[id] = Some(confirmed.value.clone());
                    }
                }
                let now = plccoms_core::changes::unix_ms(std::time::SystemTime::now());
                let shown = match &confirmed.var {
                    Some((table, id)) => Presented::of_value(table.var(*id).ty, &confirmed.value),
                    // A `%` address has no type: its text as printed.
                    None => Presented::Text(cp1250::decode(&confirmed.text).into_owned()),
                };
                let payload = super::payload::value(self.rules.format, &shown, now, Quality::Good);
                self.queue(vec![Message {
                    topic: self.topics.value(&confirmed.name),
                    payload,
                    qos: self.rules.qos,
                    retain: self.rules.retain,
                }]);
            }
            Err(refused) => self.refuse(outcome.level, refused),
        }
    }

    fn refuse(&mut self, level: String, refused: Refused) {
        self.metrics.write_refusals.inc();
        let log = self
            .refusal_logs
            .entry(refused.code)
            .or_insert_with(|| RateLimited::new(REFUSAL_LOG_INTERVAL));
        if let Some(quiet) = log.admit() {
            warn!(section = %self.section.name(), "MQTT: write refused: {}{}", refused.line, ratelimit::more(quiet));
        }
        let now = plccoms_core::changes::unix_ms(std::time::SystemTime::now());
        self.queue(vec![Message {
            topic: self.topics.error_of_level(&level),
            payload: super::payload::error(self.rules.format, refused.code, &refused.line, now),
            qos: 1,
            retain: false,
        }]);
    }

    // ------------------------------------------------------------ discovery

    /// Starts (or starts over) sending the discovery configs of the
    /// published variables and clearing those announced before and gone now
    /// (all of them with discovery off). The configs are made one at a time
    /// as the window has room ([`Task::next_announcement`]), so an
    /// announcement holds a cursor and the topics to clear, never the
    /// messages.
    /// Announces discovery again when what it says of the device (the PLC's
    /// identification) changed, while connected and the PLC online.
    fn on_state(&mut self) {
        if !self.rules.ha_discovery || !self.state.connected || self.state.plc_online != Some(true)
        {
            return;
        }
        let state = self.section.state();
        let maker = Maker::of(&state.config, state.link.ident.as_deref());
        if self.state.maker.as_ref() != Some(&maker) {
            self.announce();
        }
    }

    fn announce(&mut self) {
        if !self.state.connected {
            return;
        }
        let state = self.section.state();
        self.state.maker = Some(Maker::of(&state.config, state.link.ident.as_deref()));
        let mut current = BTreeSet::new();
        for index in 0..self.state.wanted.len() {
            if let Some(topic) = self.discovery_config(index, true) {
                current.insert(topic.0);
            }
        }
        let gone = self.state.announced.difference(&current).cloned().collect();
        if current != self.state.announced {
            if let Err(e) = discovery::save_announced(&self.spool_dir, &current) {
                warn!(section = %self.section.name(), "MQTT: cannot save the discovery topics in {}: {e}", self.spool_dir.display());
            }
            self.state.announced = current;
        }
        self.state.announcing = Some(Announcement { next: 0, gone });
    }

    /// The discovery config topic and, unless `topic_only`, payload of the
    /// `index`th published variable (discovery on, a table).
    fn discovery_config(&self, index: usize, topic_only: bool) -> Option<(String, Vec<u8>)> {
        let table = self
            .state
            .table
            .as_ref()
            .filter(|_| self.rules.ha_discovery)?;
        let var = table.var(*self.state.wanted.get(index)?);
        let device = Device {
            prefix: &self.settings.prefix,
            section: self.section.name(),
            topics: &self.topics,
            format: self.rules.format,
            qos: self.rules.qos,
            maker: self.state.maker.as_ref()?,
        };
        let writable = discovery::writable(
            var,
            self.section.read_only(),
            self.rules.writable(&var.name),
        );
        Some(if topic_only {
            (discovery::config_topic(&device, var, writable), Vec::new())
        } else {
            discovery::config(&device, var, writable)
        })
    }

    /// The next message of the announcement under way, if any: the clears,
    /// then a config per published variable.
    fn next_announcement(&mut self) -> Option<Message> {
        let mut announcement = self.state.announcing.take()?;
        if let Some(topic) = announcement.gone.pop() {
            self.state.announcing = Some(announcement);
            return Some(Message {
                topic,
                payload: Vec::new(),
                qos: 1,
                retain: true,
            });
        }
        let (topic, payload) = self.discovery_config(announcement.next, false)?;
        announcement.next += 1;
        self.state.announcing = Some(announcement);
        Some(Message {
            topic,
            payload,
            qos: 1,
            retain: true,
        })
    }

    // -------------------------------------------------------------- upkeep

    /// Once a connection has stayed up [`STABLE`]: the outage is over (the
    /// next problem is logged) and retries start quick again.
    fn settle(&mut self) {
        let state = &mut self.state;
        if state.connected_at.is_some_and(|at| at.elapsed() >= STABLE) {
            state.logged = None;
            state.reconnect_logged = false;
            state.backoff = Duration::ZERO;
        }
    }

    /// Once a second: `head` saved, the queue synced while it is not being
    /// emptied at once, gauges, and the end of an episode of drops.
    fn checkpoint(&mut self) {
        self.settle();
        let durable = !self.state.connected || self.spool.len() > WINDOW as u64;
        if let Err(e) = self.spool.checkpoint(durable) {
            if !self.state.spool_failing {
                error!(section = %self.section.name(), "MQTT: cannot sync the queue in {}: {e}", self.spool_dir.display());
                self.state.spool_failing = true;
            }
        }
        self.metrics.queued.set(self.spool.len());
        self.metrics.queued_bytes.set(self.spool.bytes());
        if self.state.dropping > 0 && self.state.connected && !self.spool.has_unsent() {
            warn!(section = %self.section.name(), "MQTT: {} queued messages were dropped (MQTT_BUFFER full) while the broker was away or behind", self.state.dropping);
            self.state.dropping = 0;
        }
    }

    /// A clean stop: `offline` on the status topic, DISCONNECT (so the will
    /// is not sent), and the queue saved.
    async fn stop(&mut self) {
        if self.state.connected {
            if let Some(link) = &self.state.link {
                let status = state_message(self.topics.status(), "offline");
                let sent = link
                    .client
                    .try_publish(status.topic, QoS::AtLeastOnce, true, status.payload)
                    .is_ok()
                    && link.client.try_disconnect().is_ok();
                if sent {
                    let deadline = Instant::now() + STOP_WAIT;
                    self.state.submitted.push_back(None);
                    while let Ok(event) =
                        tokio::time::timeout_at(deadline, next_event(&mut self.state.link)).await
                    {
                        match event {
                            Ok(Event::Outgoing(Outgoing::Disconnect)) | Err(_) => break,
                            other => self.on_event(other),
                        }
                    }
                }
            }
        }
        self.state.link = None;
        self.metrics.connected.set(0);
        if let Err(e) = self.spool.checkpoint(true) {
            error!(section = %self.section.name(), "MQTT: cannot save the queue in {}: {e}", self.spool_dir.display());
        }
        let queued = self.spool.len();
        if queued > 0 {
            info!(section = %self.section.name(), "MQTT: {queued} messages stay queued in {} for the next start", self.spool_dir.display());
        }
    }
}

fn state_message(topic: String, payload: &str) -> Message {
    Message {
        topic,
        payload: payload.as_bytes().to_vec(),
        qos: 1,
        retain: true,
    }
}

fn plc_message(topics: &Topics, online: bool) -> Message {
    state_message(topics.plc(), if online { "online" } else { "offline" })
}

/// A connection problem in words, with what to check for a refusal.
pub(super) fn describe(e: &ConnectionError) -> String {
    match e {
        ConnectionError::ConnectionRefused(code) => match code {
            ConnectReturnCode::BadUserNamePassword => {
                "bad user name or password (check MQTT_USER and MQTT_PASSWORD)".into()
            }
            ConnectReturnCode::NotAuthorized => {
                "not authorized (check MQTT_USER, MQTT_PASSWORD and the broker's ACL)".into()
            }
            ConnectReturnCode::BadClientId | ConnectReturnCode::ClientIdentifierNotValid => {
                "client id refused (check MQTT_CLIENT_ID)".into()
            }
            ConnectReturnCode::RefusedProtocolVersion
            | ConnectReturnCode::UnsupportedProtocolVersion => {
                "the broker does not speak MQTT 5 (Mosquitto 1.6 or later, EMQX, HiveMQ, ... do); for one that speaks only 3.1.1 (NATS) set MQTT_VERSION = 3.1.1".into()
            }
            other => format!("{other:?}"),
        },
        ConnectionError::Tls(e) => format!("TLS: {e} (check MQTT_CA, MQTT_CERT, MQTT_KEY)"),
        ConnectionError::MqttState(StateError::Deserialization(
            mqttbytes::Error::PayloadSizeLimitExceeded { pkt_size: size, .. },
        )) => format!(
            "the broker sent a message of {size} bytes, over the limit of {MAX_INCOMING} bytes (a retained one on a /set topic or on {}? clear it; the broker's max_packet_size keeps such messages out)",
            discovery::HA_STATUS
        ),
        other => other.to_string(),
    }
}

pub(super) async fn next_event(link: &mut Option<Link>) -> Result<Event, ConnectionError> {
    match link {
        Some(link) => link.next_event().await,
        None => std::future::pending().await,
    }
}

pub(super) async fn sleep_until(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}
