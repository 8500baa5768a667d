//! The edge node: one MQTT connection for every Sparkplug section (a
//! section is a device), its NDEATH as the connection's will.
//!
//! - At each connection: bdSeq is the one after the previous connection's,
//!   kept on disk before CONNECT so that a crash cannot reuse it; NCMD and
//!   DCMD are subscribed before NBIRTH; with SPARKPLUG_HOST nothing is
//!   born until the host's STATE says online.
//! - NBIRTH (seq 0), then a DBIRTH per device whose PLC is online, with
//!   every published metric (name, alias, datatype, value, poll time,
//!   properties); DDATA carries the changes by alias; DDEATH when the
//!   link is lost, DBIRTH when it returns. seq counts every message but
//!   NDEATH, 0-255.
//! - NCMD `Node Control/Rebirth` = true: NBIRTH and DBIRTHs again.
//! - DCMD: each metric (by alias or name) written through the section's
//!   one write path (`writes::worker`); the value read back comes as
//!   DDATA; a refusal is logged, counted (`plccoms_mqtt_write_refusals_total`
//!   and the node metric `Node Info/Write Refusals`) and changes nothing.
//! - Sparkplug messages are QoS 0 and not retained (spec 3.0). Without
//!   SPARKPLUG_HOST nothing is kept while the broker is away: a rebirth on
//!   the next connection brings every current value. With it, the changes
//!   made while the node is not born (host offline, broker away) are kept
//!   in the on-disk queue (`spool.rs`, in `<MQTT_SPOOL>/sparkplug-<node>/held`,
//!   bounded by MQTT_BUFFER) and sent after the next births as historical
//!   DDATA, oldest first, with their poll times.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use plccoms_core::changes::{unix_ms, ChangeBatch, Quality, Snapshot};
use plccoms_core::present::Presented;
use plccoms_core::ratelimit::{self, RateLimited};
use plccoms_core::section::Section;
use plccoms_core::vars::{VarId, VarTable};
use plccoms_protocol::value::Value;
use plccoms_protocol::{cp1250, IecType, Mask};
use prost::Message as _;
use rumqttc::v5::mqttbytes::v5::Packet;
use rumqttc::v5::mqttbytes::QoS;
use rumqttc::v5::{ConnectionError, Event};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::command::{self, Target, REBIRTH};
use super::metric::{self, datatype};
use super::proto::{Metric, MetricValue, Payload};
use super::topic::{Incoming, Topics};
use crate::client::{Brokers, Connect, Link, NEXT_BROKER};
use crate::connection::{
    describe, next_event, sleep_until, MAX_INCOMING, REFUSAL_LOG_INTERVAL, RETRY_FIRST, RETRY_MAX,
    STOP_WAIT,
};
use crate::settings::{SectionRules, Settings};
use crate::spool::{Message, Spool};
use crate::writes::{self, Refused, Request};
use crate::Metrics;

const BDSEQ: &str = "bdSeq";
const VERSION: &str = "Node Info/Version";
const REFUSALS: &str = "Node Info/Write Refusals";
/// Aliases of the node's metrics; a device's start past them.
const BDSEQ_ALIAS: u64 = 1;
pub const REBIRTH_ALIAS: u64 = 2;
const VERSION_ALIAS: u64 = 3;
const REFUSALS_ALIAS: u64 = 4;
const FIRST_DEVICE_ALIAS: u64 = 16;
/// How long a device's birth waits for the first read of every metric.
const BIRTH_WAIT: Duration = Duration::from_secs(2);
/// Requests rumqttc may hold: a burst of DDATA while the socket is slow.
const REQUESTS: usize = 4096;

/// The edge node's settings.
#[derive(Debug, Clone)]
pub struct NodeSettings {
    pub group: String,
    pub node: String,
    pub host: Option<String>,
    /// The file holding the next bdSeq.
    pub bdseq_file: PathBuf,
}

/// A section as a Sparkplug device.
pub struct Device {
    pub section: Arc<Section>,
    pub rules: SectionRules,
    pub id: String,
    pub metrics: Arc<Metrics>,
    pub writes: mpsc::Sender<Request>,
    table: Arc<VarTable>,
    wanted: Vec<VarId>,
    /// Variable id -> its place in `wanted` (its alias is `alias_base` + it).
    place: Vec<Option<u32>>,
    alias_base: u64,
    /// Aliases were given for `table` in this NBIRTH.
    aliased: bool,
    born: bool,
    online: bool,
    /// When the PLC was first seen online (not yet up).
    online_at: Option<Instant>,
    /// Per variable, the variable holding the PLC's time of its value
    /// (HISTORY_STAMP), and the pairs as (stamp, value).
    stamp_of: Vec<Option<VarId>>,
    stamps: Vec<(VarId, VarId)>,
    /// The change stream's sequence of the value last sent per variable: a
    /// confirmed write it already carried is not sent again.
    sent_seq: Vec<u64>,
    /// MQTT_DELTA: the value last sent per variable.
    last: Vec<Option<Value>>,
    /// The quality last sent per place.
    quality: Vec<Quality>,
}

impl Device {
    pub fn new(
        section: Arc<Section>,
        rules: SectionRules,
        id: String,
        metrics: Arc<Metrics>,
        writes: mpsc::Sender<Request>,
        table: Arc<VarTable>,
        wanted: Vec<VarId>,
    ) -> Device {
        let mut device = Device {
            section,
            rules,
            id,
            metrics,
            writes,
            table: table.clone(),
            wanted: Vec::new(),
            place: Vec::new(),
            alias_base: 0,
            aliased: false,
            born: false,
            online: false,
            online_at: None,
            stamp_of: Vec::new(),
            stamps: Vec::new(),
            sent_seq: Vec::new(),
            last: Vec::new(),
            quality: Vec::new(),
        };
        device.adopt(table, wanted);
        device
    }

    /// A new table: its metrics are the subscribed variables MQTT_PUBLISH
    /// names (the subscription also holds HISTORY_STAMP's), each paired
    /// with the variable that holds the PLC's time of its value, if any.
    fn adopt(&mut self, table: Arc<VarTable>, subscribed: Vec<VarId>) {
        let publish: Vec<Mask> = self.rules.publish.iter().map(|m| Mask::new(m)).collect();
        let wanted: Vec<VarId> = subscribed
            .into_iter()
            .filter(|&id| publish.iter().any(|m| m.matches_name(&table.var(id).name)))
            .collect();
        self.place = vec![None; table.len()];
        for (i, &id) in wanted.iter().enumerate() {
            self.place[id as usize] = Some(i as u32);
        }
        self.stamp_of = vec![None; table.len()];
        self.stamps.clear();
        for pair in &self.section.state().config.history.stamps {
            let (Some(value), Some(stamp)) = (
                table.lookup(&cp1250::encode(&pair.value)),
                table.lookup(&cp1250::encode(&pair.stamp)),
            ) else {
                continue;
            };
            let is_time = matches!(
                table.var(stamp).ty,
                IecType::Dt | IecType::Date | IecType::Lint | IecType::Ulint | IecType::Lword
            );
            if is_time && self.place[value as usize].is_some() {
                self.stamp_of[value as usize] = Some(stamp);
                self.stamps.push((stamp, value));
            }
        }
        self.sent_seq = vec![0; table.len()];
        self.last = vec![None; table.len()];
        self.quality = vec![Quality::Good; wanted.len()];
        self.table = table;
        self.wanted = wanted;
        self.aliased = false;
    }

    /// Whether the device is up: its PLC online and its metrics read, so
    /// that it is born with values, not before them. A metric the PLC
    /// will not read (its read refused) is waited for [`BIRTH_WAIT`] at
    /// most, then born `is_null`; so is a table with none of the metrics
    /// (the fixed variables, polled while the PLC's public file is still
    /// being made the section's table), then born without them.
    fn up(&mut self, snapshot: &Snapshot) -> bool {
        if !snapshot.online || snapshot.polled.is_none() {
            self.online_at = None;
            return false;
        }
        if self.online {
            return true;
        }
        let since = *self.online_at.get_or_insert_with(Instant::now);
        since.elapsed() >= BIRTH_WAIT
            || (!self.wanted.is_empty()
                && self
                    .wanted
                    .iter()
                    .all(|&id| snapshot.slot(id).text().is_some()))
    }

    /// The time of `id`'s value: the PLC's own where HISTORY_STAMP pairs
    /// one and it holds a time, else the poll's.
    fn timestamp(&self, snapshot: &Snapshot, id: VarId) -> u64 {
        let plc = self.stamp_of[id as usize].and_then(|stamp| {
            match snapshot.slot(stamp).value(self.table.var(stamp))? {
                Value::Date(seconds) => Some((seconds * 1000.0).round() as i64),
                Value::Signed(ms) => Some(ms),
                Value::Unsigned(ms) => i64::try_from(ms).ok(),
                _ => None,
            }
        });
        plc.unwrap_or(snapshot.slot(id).changed_ms).max(0) as u64
    }

    /// The variable an alias or a name of a command names.
    fn resolve(&self, target: &Target<'_>) -> Option<VarId> {
        match target {
            Target::Alias(alias) => {
                let place = alias.checked_sub(self.alias_base)?;
                self.wanted.get(usize::try_from(place).ok()?).copied()
            }
            Target::Name(name) => {
                let id = self.table.lookup(&cp1250::try_encode(name)?)?;
                self.place[id as usize].map(|_| id)
            }
            Target::None => None,
        }
    }
}

/// A change batch of device `.0`, with its subscription's wanted variables
/// when the table changed.
pub type DeviceBatch = (usize, ChangeBatch, Option<Vec<VarId>>);

pub struct Node {
    pub settings: Arc<Settings>,
    pub node: NodeSettings,
    pub topics: Topics,
    pub client_id: String,
    pub devices: Vec<Device>,
    pub shutdown: CancellationToken,
    pub batches: mpsc::Receiver<DeviceBatch>,
    pub outcomes: mpsc::Receiver<(usize, writes::Outcome)>,
    link: Option<Link>,
    /// MQTT_URL's brokers, the one in use.
    brokers: Brokers,
    connected: bool,
    retry_at: Option<Instant>,
    backoff: Duration,
    logged: Option<String>,
    bdseq: u64,
    seq: u8,
    /// NBIRTH sent on this connection.
    born: bool,
    next_alias: u64,
    /// The primary host's latest STATE timestamp seen.
    host_seen: Option<u64>,
    refusals: u64,
    /// Per device (`None`: commands to devices this node does not have,
    /// whose ids any client can make up), so the map stays small.
    refusal_logs: BTreeMap<Option<usize>, RateLimited>,
    /// With SPARKPLUG_HOST, the changes made while the node is not born
    /// (the host offline, the broker away), each batch a message whose
    /// topic is the device id and whose payload a Sparkplug payload of
    /// named metrics; sent as historical DDATA after the next births.
    held: Spool,
    /// Held messages dropped over MQTT_BUFFER since the queue was last
    /// drained.
    dropping: u64,
}

impl Node {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        settings: Arc<Settings>,
        node: NodeSettings,
        client_id: String,
        devices: Vec<Device>,
        shutdown: CancellationToken,
        batches: mpsc::Receiver<DeviceBatch>,
        outcomes: mpsc::Receiver<(usize, writes::Outcome)>,
        held: Spool,
    ) -> Node {
        Node {
            topics: Topics::new(&node.group, &node.node),
            brokers: Brokers::new(settings.brokers.clone()),
            settings,
            node,
            client_id,
            devices,
            shutdown,
            batches,
            outcomes,
            link: None,
            connected: false,
            retry_at: None,
            backoff: Duration::ZERO,
            logged: None,
            bdseq: 0,
            seq: 0,
            born: false,
            next_alias: FIRST_DEVICE_ALIAS,
            host_seen: None,
            refusals: 0,
            refusal_logs: BTreeMap::new(),
            held,
            dropping: 0,
        }
    }

    pub async fn run(mut self) {
        self.connect();
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            self.drain_held();
            tokio::select! {
                biased;
                _ = self.shutdown.cancelled() => break,
                event = next_event(&mut self.link) => self.on_event(event),
                Some((index, batch, wanted)) = self.batches.recv() => self.on_batch(index, batch, wanted),
                Some((index, outcome)) = self.outcomes.recv() => self.on_outcome(index, outcome),
                _ = sleep_until(self.retry_at) => {
                    self.retry_at = None;
                    self.connect();
                }
                _ = tick.tick() => {
                    self.births_waited();
                    let durable = !self.born;
                    if let Err(e) = self.held.checkpoint(durable) {
                        warn!("Sparkplug: cannot save the held changes: {e}");
                    }
                }
            }
        }
        self.stop().await;
    }

    // ------------------------------------------------------------ connection

    /// The bdSeq of this connection ([tck-id-payloads-ndeath-bdseq]): the
    /// one after the previous connection's, saved before CONNECT.
    fn next_bdseq(&mut self) -> u64 {
        let path = &self.node.bdseq_file;
        let stored = std::fs::read_to_string(path)
            .ok()
            .and_then(|t| t.trim().parse::<u64>().ok())
            .map_or(0, |n| n % 256);
        let next = (stored + 1) % 256;
        if let Err(e) = write_durably(path, &next.to_string()) {
            warn!(
                "Sparkplug: cannot save bdSeq in {}: {e}; a restart may reuse {stored}",
                path.display()
            );
        }
        stored
    }

    fn connect(&mut self) {
        self.bdseq = self.next_bdseq();
        // [tck-id-payloads-ndeath-will-message] QoS 1, not retained; set
        // on whichever broker of MQTT_URL this connection is made to.
        let connect = Connect {
            settings: &self.settings,
            broker: self.brokers.current(),
            client_id: &self.client_id,
            inflight: None,
            will_topic: self.topics.node("NDEATH"),
            will_payload: self.death(),
            will_retain: false,
            max_incoming: MAX_INCOMING,
        };
        self.link = Some(Link::spawn(connect, REQUESTS, REQUESTS));
    }

    fn on_event(&mut self, event: Result<Event, ConnectionError>) {
        match event {
            Ok(Event::Incoming(Packet::ConnAck(_))) => self.on_connected(),
            Ok(Event::Incoming(Packet::Publish(publish))) => {
                let topic = String::from_utf8_lossy(&publish.topic).into_owned();
                self.on_message(&topic, &publish.payload);
            }
            Ok(_) => {}
            Err(e) => self.on_disconnected(e),
        }
    }

    fn on_connected(&mut self) {
        info!(
            "Sparkplug: edge node {}/{} connected to {} (bdSeq {})",
            self.node.group, self.node.node, self.brokers, self.bdseq
        );
        self.brokers.connected();
        self.connected = true;
        self.logged = None;
        self.backoff = Duration::ZERO;
        self.host_seen = None;
        for device in &self.devices {
            device.metrics.connected.set(1);
            device.metrics.connects.inc();
        }
        if let Some(link) = &self.link {
            // [tck-id-message-flow-edge-node-ncmd-subscribe]
            // commands subscribed before NBIRTH.
            let _ = link
                .client
                .try_subscribe(self.topics.node("NCMD"), QoS::AtLeastOnce);
            let _ = link
                .client
                .try_subscribe(self.topics.device_commands(), QoS::AtLeastOnce);
            if let Some(host) = &self.node.host {
                let _ = link
                    .client
                    .try_subscribe(Topics::state(host), QoS::AtLeastOnce);
            }
        }
        if self.node.host.is_none() {
            self.birth();
        }
    }

    fn on_disconnected(&mut self, e: ConnectionError) {
        let problem = describe(&e);
        let broker = self.brokers.to_string();
        let round = self.brokers.advance();
        let moved = self.connected && self.brokers.len() > 1;
        if moved || self.logged.as_deref() != Some(problem.as_str()) {
            warn!(
                "Sparkplug: edge node {}/{}: connection to {broker}: {problem}; reconnecting to {}",
                self.node.group, self.node.node, self.brokers
            );
            self.logged = Some(problem);
        }
        self.link = None;
        self.connected = false;
        self.born = false;
        for device in &mut self.devices {
            device.born = false;
            device.metrics.connected.set(0);
        }
        if !round {
            self.retry_at = Some(Instant::now() + NEXT_BROKER);
            return;
        }
        self.backoff = if self.backoff.is_zero() {
            RETRY_FIRST
        } else {
            (self.backoff * 2).min(RETRY_MAX)
        };
        self.retry_at = Some(Instant::now() + self.backoff);
    }

    /// Publishes a Sparkplug message (QoS 0, not retained); `false` when it
    /// could not be handed over.
    fn send(&mut self, topic: String, mut payload: Payload) -> bool {
        let Some(link) = &self.link else {
            return false;
        };
        if !self.connected {
            return false;
        }
        payload.seq = Some(u64::from(self.seq));
        payload.timestamp.get_or_insert_with(now_ms);
        match link
            .client
            .try_publish(topic, QoS::AtMostOnce, false, payload.encode_to_vec())
        {
            Ok(()) => {
                self.seq = self.seq.wrapping_add(1);
                true
            }
            Err(e) => {
                debug!("Sparkplug: message not sent: {e}");
                false
            }
        }
    }

    // ------------------------------------------------------------- births

    /// NBIRTH and every online device's DBIRTH, seq from 0
    /// ([tck-id-payloads-nbirth-seq]).
    fn birth(&mut self) {
        self.seq = 0;
        self.next_alias = FIRST_DEVICE_ALIAS;
        for device in &mut self.devices {
            device.aliased = false;
            device.born = false;
        }
        let metrics = vec![
            metric::node_metric(
                BDSEQ,
                BDSEQ_ALIAS,
                MetricValue::LongValue(self.bdseq),
                datatype::UINT64,
            ),
            metric::node_metric(
                REBIRTH,
                REBIRTH_ALIAS,
                MetricValue::BooleanValue(false),
                datatype::BOOLEAN,
            ),
            metric::node_metric(
                VERSION,
                VERSION_ALIAS,
                MetricValue::StringValue(format!("plccoms {}", env!("CARGO_PKG_VERSION"))),
                datatype::STRING,
            ),
            metric::node_metric(
                REFUSALS,
                REFUSALS_ALIAS,
                MetricValue::LongValue(self.refusals),
                datatype::UINT64,
            ),
        ];
        let payload = Payload {
            metrics,
            ..Payload::default()
        };
        if !self.send(self.topics.node("NBIRTH"), payload) {
            return;
        }
        self.born = true;
        for index in 0..self.devices.len() {
            let snapshot = self.devices[index].section.latest();
            self.birth_when_up(index, &snapshot);
        }
    }

    /// Device `index` online where it is up, with its DBIRTH.
    fn birth_when_up(&mut self, index: usize, snapshot: &Snapshot) {
        let up = self.devices[index].up(snapshot);
        self.devices[index].online = up;
        if up {
            self.device_birth(index, snapshot);
        }
    }

    /// The DBIRTH of a device whose wait ([`BIRTH_WAIT`]) ended with no
    /// change to bring it: a section with none of its metrics sends none.
    fn births_waited(&mut self) {
        if !self.born {
            return;
        }
        for index in 0..self.devices.len() {
            if self.devices[index].online {
                continue;
            }
            let snapshot = self.devices[index].section.latest();
            // A newer table comes as a batch, and is born from there.
            if Arc::ptr_eq(&self.devices[index].table, &snapshot.table) {
                self.birth_when_up(index, &snapshot);
            }
        }
    }

    /// A DBIRTH of every published metric of device `index`.
    fn device_birth(&mut self, index: usize, snapshot: &Snapshot) {
        let device = &mut self.devices[index];
        if !Arc::ptr_eq(&device.table, &snapshot.table) {
            // The subscription's batch of the new table comes next.
            return;
        }
        if !device.aliased {
            // [tck-id-payloads-alias-uniqueness]: unique across the node
            // until its next NBIRTH.
            device.alias_base = self.next_alias;
            self.next_alias += device.wanted.len() as u64;
            device.aliased = true;
        }
        let format = *device.section.format();
        let mut metrics = Vec::with_capacity(device.wanted.len());
        for (place, &id) in device.wanted.iter().enumerate() {
            let var = device.table.var(id);
            let slot = snapshot.slot(id);
            let ty = datatype_of(var.ty);
            let quality = snapshot.quality(id);
            device.quality[place] = quality;
            device.sent_seq[id as usize] = snapshot.seq;
            device.last[id as usize] = slot.value(var);
            let value = slot
                .text()
                .and_then(|text| metric::value(ty, &Presented::of(var.ty, text, &format)));
            metrics.push(Metric {
                name: Some(cp1250::decode(&var.name).into_owned()),
                alias: Some(device.alias_base + place as u64),
                timestamp: Some(device.timestamp(snapshot, id)),
                datatype: Some(ty),
                is_null: value.is_none().then_some(true),
                properties: Some(metric::properties(Some(var), quality)),
                value,
                ..Metric::default()
            });
        }
        let topic = self.topics.device("DBIRTH", &self.devices[index].id);
        let sent = self.send(
            topic,
            Payload {
                metrics,
                ..Payload::default()
            },
        );
        self.devices[index].born = sent;
    }

    fn device_death(&mut self, index: usize) {
        if !self.devices[index].born {
            return;
        }
        self.devices[index].born = false;
        let topic = self.topics.device("DDEATH", &self.devices[index].id);
        self.send(topic, Payload::default());
    }

    // ------------------------------------------------------------- changes

    fn on_batch(&mut self, index: usize, batch: ChangeBatch, wanted: Option<Vec<VarId>>) {
        let device = &mut self.devices[index];
        if batch.missed > 0 {
            device.metrics.missed.add(batch.missed);
        }
        if let Some(wanted) = wanted {
            device.adopt(batch.snapshot.table.clone(), wanted);
            // A new table is a new set of metrics: born again.
            let up = self.devices[index].up(&batch.snapshot);
            if self.born && up {
                self.device_birth(index, &batch.snapshot);
            }
            self.devices[index].online = up;
            return;
        }
        let online = device.up(&batch.snapshot);
        let was = std::mem::replace(&mut device.online, online);
        if !self.born {
            if self.node.host.is_some() && online {
                self.hold(index, &batch.snapshot, &batch.changes);
            }
            return;
        }
        match (was, online) {
            (true, false) => return self.device_death(index),
            (false, true) => return self.device_birth(index, &batch.snapshot),
            _ => {}
        }
        if !device.born {
            return;
        }
        // A new PLC time is a new event of the values it stamps, even with
        // the same value.
        let mut ids: Vec<VarId> = batch.changes.clone();
        for &(stamp, value) in &device.stamps {
            if batch.changes.contains(&stamp) && !ids.contains(&value) {
                ids.push(value);
            }
        }
        self.device_data(index, &batch.snapshot, &ids, true);
    }

    /// Keeps the values of `ids` for the host, by name (aliases are given
    /// anew at the next birth), with their poll times.
    fn hold(&mut self, index: usize, snapshot: &Snapshot, ids: &[VarId]) {
        let device = &self.devices[index];
        if !Arc::ptr_eq(&device.table, &snapshot.table) {
            return;
        }
        let format = *device.section.format();
        let mut metrics = Vec::new();
        for &id in ids {
            if device.place.get(id as usize).copied().flatten().is_none() {
                continue;
            }
            let var = device.table.var(id);
            let slot = snapshot.slot(id);
            let Some(text) = slot.text() else {
                continue;
            };
            let value = metric::value(datatype_of(var.ty), &Presented::of(var.ty, text, &format));
            metrics.push(Metric {
                name: Some(cp1250::decode(&var.name).into_owned()),
                timestamp: Some(device.timestamp(snapshot, id)),
                is_null: value.is_none().then_some(true),
                value,
                ..Metric::default()
            });
        }
        if metrics.is_empty() {
            return;
        }
        let message = Message {
            topic: device.id.clone(),
            payload: Payload {
                metrics,
                ..Payload::default()
            }
            .encode_to_vec(),
            qos: 1,
            retain: false,
        };
        match self.held.push(&[message]) {
            Ok(0) => {}
            Ok(dropped) => {
                if self.dropping == 0 {
                    warn!("Sparkplug: MQTT_BUFFER ({} bytes) is full: dropping the oldest held changes", self.settings.buffer);
                }
                self.dropping += dropped;
                self.devices[index].metrics.dropped.add(dropped);
            }
            Err(e) => warn!("Sparkplug: cannot hold a change for the host: {e}"),
        }
        self.devices[index].metrics.queued.set(self.held.len());
    }

    /// Sends the held changes as historical DDATA
    /// ((spec 3.0, Payloads: the metric's is_historical)), oldest first, while born and
    /// while rumqttc takes them.
    fn drain_held(&mut self) {
        while self.born && self.held.has_unsent() {
            let (seq, message) = match self.held.next_unsent() {
                Ok(Some(next)) => next,
                Ok(None) => break,
                Err(e) => {
                    warn!("Sparkplug: cannot read the held changes: {e}");
                    break;
                }
            };
            let Some(index) = self.devices.iter().position(|d| d.id == message.topic) else {
                self.held.ack(seq);
                continue;
            };
            let Ok(mut payload) = Payload::decode(&message.payload[..]) else {
                self.held.ack(seq);
                continue;
            };
            let device = &self.devices[index];
            if !device.born {
                // Its PLC is down now: kept until it is born again.
                self.held.rewind();
                break;
            }
            payload.metrics.retain_mut(|m| {
                let name = m.name.take().unwrap_or_default();
                let Some(id) = device.resolve(&Target::Name(&name)) else {
                    return false;
                };
                let place = device.place[id as usize].unwrap_or_default();
                m.alias = Some(device.alias_base + u64::from(place));
                m.is_historical = Some(true);
                true
            });
            let topic = self.topics.device("DDATA", &device.id);
            if !payload.metrics.is_empty() && !self.send(topic, payload) {
                self.held.rewind();
                break;
            }
            self.held.ack(seq);
        }
        if self.born && !self.held.has_unsent() && self.dropping > 0 {
            warn!("Sparkplug: {} held changes were dropped (MQTT_BUFFER full) while the host was away", self.dropping);
            self.dropping = 0;
        }
    }

    /// A DDATA of the values of `ids` in `snapshot`, by alias; with
    /// `deadband`, those MQTT_DELTA lets through.
    fn device_data(&mut self, index: usize, snapshot: &Snapshot, ids: &[VarId], deadband: bool) {
        let device = &mut self.devices[index];
        if !Arc::ptr_eq(&device.table, &snapshot.table) {
            return;
        }
        let format = *device.section.format();
        let mut metrics = Vec::with_capacity(ids.len());
        for &id in ids {
            let Some(place) = device.place.get(id as usize).copied().flatten() else {
                continue;
            };
            let var = device.table.var(id);
            let slot = snapshot.slot(id);
            let Some(text) = slot.text() else {
                continue;
            };
            let value = slot.value(var);
            if let (true, Some(delta), Some(new), Some(last)) = (
                deadband,
                &device.rules.delta,
                &value,
                &device.last[id as usize],
            ) {
                if !new.exceeds(last, delta, var.ty, &format) {
                    continue;
                }
            }
            device.last[id as usize] = value;
            device.sent_seq[id as usize] = snapshot.seq;
            let quality = snapshot.quality(id);
            let properties = (std::mem::replace(&mut device.quality[place as usize], quality)
                != quality)
                .then(|| metric::properties(None, quality));
            let value = metric::value(datatype_of(var.ty), &Presented::of(var.ty, text, &format));
            metrics.push(Metric {
                alias: Some(device.alias_base + u64::from(place)),
                timestamp: Some(device.timestamp(snapshot, id)),
                is_null: value.is_none().then_some(true),
                properties,
                value,
                ..Metric::default()
            });
        }
        if metrics.is_empty() {
            return;
        }
        let topic = self.topics.device("DDATA", &device.id);
        if !self.send(
            topic,
            Payload {
                metrics,
                ..Payload::default()
            },
        ) {
            // Lost in a full request queue: the host gets every value
            // again with a DBIRTH.
            let snapshot = self.devices[index].section.latest();
            self.device_birth(index, &snapshot);
        }
    }

    // ------------------------------------------------------------ commands

    fn on_message(&mut self, topic: &str, payload: &[u8]) {
        match self.topics.parse(topic, self.node.host.as_deref()) {
            Some(Incoming::State) => self.on_state(payload),
            Some(Incoming::NodeCommand) => match command::decode(payload) {
                Ok(p) if command::asks_rebirth(&p, REBIRTH_ALIAS) => {
                    info!("Sparkplug: rebirth asked by NCMD");
                    if self.node.host.is_none() || self.born {
                        self.birth();
                    }
                }
                Ok(_) => {}
                Err(e) => warn!("Sparkplug: NCMD refused: {e}"),
            },
            Some(Incoming::DeviceCommand(device)) => {
                let Some(index) = self.devices.iter().position(|d| d.id == device) else {
                    return self.refuse(None, device, "no such device".into());
                };
                match command::decode(payload) {
                    Ok(p) => self.on_device_command(index, p),
                    Err(e) => self.refuse(Some(index), device, e.to_string()),
                }
            }
            None => {}
        }
    }

    /// The primary host's STATE (spec 3.0: JSON `{"online": .., "timestamp": ..}`).
    fn on_state(&mut self, payload: &[u8]) {
        let Ok(state) = serde_json::from_slice::<serde_json::Value>(payload) else {
            return warn!("Sparkplug: a STATE message that is not JSON ignored");
        };
        let (Some(online), timestamp) = (state["online"].as_bool(), state["timestamp"].as_u64())
        else {
            return warn!("Sparkplug: a STATE message without \"online\" ignored");
        };
        let timestamp = timestamp.unwrap_or(0);
        // [tck-id-operational-behavior-edge-node-birth-sequence-wait]: an
        // older STATE than one seen is stale.
        if self.host_seen.is_some_and(|seen| timestamp < seen) {
            return;
        }
        self.host_seen = Some(timestamp);
        match (online, self.born) {
            (true, false) => {
                info!("Sparkplug: primary host online: birth");
                self.birth();
            }
            (false, true) => {
                // [tck-id-message-flow-edge-node-birth-publish-phid-offline]:
                // NDEATH, disconnect, connect again and wait for the host.
                info!("Sparkplug: primary host offline: NDEATH, disconnecting; waiting for it");
                self.say_death();
                self.born = false;
                for device in &mut self.devices {
                    device.born = false;
                }
            }
            _ => {}
        }
    }

    fn on_device_command(&mut self, index: usize, payload: Payload) {
        let device_id = self.devices[index].id.clone();
        for m in &payload.metrics {
            let device = &self.devices[index];
            let target = command::target(m);
            let label = match &target {
                Target::Alias(a) => format!("alias {a}"),
                Target::Name(n) => n.to_string(),
                Target::None => "a metric without name or alias".into(),
            };
            let Some(id) = device.resolve(&target) else {
                self.refuse(Some(index), &device_id, format!("{label}: no such metric"));
                continue;
            };
            let var = device.table.var(id);
            let name = cp1250::decode(&var.name).into_owned();
            if !device.rules.writable(&var.name) {
                self.refuse(
                    Some(index),
                    &device_id,
                    format!("{name}: not writable (see MQTT_WRITE)"),
                );
                continue;
            }
            let text = match metric::command_text(var.ty, command::value(m)) {
                Ok(text) => text,
                Err(e) => {
                    self.refuse(Some(index), &device_id, format!("{name}: {e}"));
                    continue;
                }
            };
            let Some(value) = cp1250::try_encode(&text) else {
                self.refuse(
                    Some(index),
                    &device_id,
                    format!("{name}: the value has no cp1250 form"),
                );
                continue;
            };
            let request = Request {
                level: name.clone(),
                name: var.name.to_vec(),
                value,
            };
            if device.writes.try_send(request).is_err() {
                self.refuse(
                    Some(index),
                    &device_id,
                    format!("{name}: too many writes waiting for the PLC"),
                );
            }
        }
    }

    fn on_outcome(&mut self, index: usize, outcome: writes::Outcome) {
        match outcome.result {
            Ok(confirmed) => {
                let device = &self.devices[index];
                device.metrics.writes.inc();
                let Some(id) = device.table.lookup(&confirmed.name) else {
                    return;
                };
                // The change stream carried this value already.
                if device.sent_seq[id as usize] >= confirmed.seq || !device.born {
                    return;
                }
                let snapshot = device.section.latest();
                if snapshot.seq >= confirmed.seq {
                    self.device_data(index, &snapshot, &[id], false);
                }
            }
            Err(Refused { line, .. }) => {
                let id = self.devices[index].id.clone();
                self.refuse(Some(index), &id, line);
            }
        }
    }

    /// A refused command: logged (at most once a second per device),
    /// counted, and the node's refusal metric sent.
    fn refuse(&mut self, index: Option<usize>, device: &str, why: String) {
        self.refusals += 1;
        if let Some(index) = index {
            self.devices[index].metrics.write_refusals.inc();
        }
        let log = self
            .refusal_logs
            .entry(index)
            .or_insert_with(|| RateLimited::new(REFUSAL_LOG_INTERVAL));
        if let Some(quiet) = log.admit() {
            warn!(
                "Sparkplug: DCMD to {device} refused: {why}{}",
                ratelimit::more(quiet)
            );
        }
        if self.born {
            let metrics = vec![Metric {
                alias: Some(REFUSALS_ALIAS),
                timestamp: Some(now_ms()),
                value: Some(MetricValue::LongValue(self.refusals)),
                ..Metric::default()
            }];
            self.send(
                self.topics.node("NDATA"),
                Payload {
                    metrics,
                    ..Payload::default()
                },
            );
        }
    }

    // ---------------------------------------------------------------- stop

    /// The NDEATH payload of this connection: its bdSeq.
    fn death(&self) -> Vec<u8> {
        Payload {
            timestamp: Some(now_ms()),
            metrics: vec![metric::node_metric(
                BDSEQ,
                BDSEQ_ALIAS,
                MetricValue::LongValue(self.bdseq),
                datatype::UINT64,
            )],
            ..Payload::default()
        }
        .encode_to_vec()
    }

    /// NDEATH and DISCONNECT (the will is not sent on a clean one): whether
    /// both were handed to rumqttc.
    fn say_death(&self) -> bool {
        let Some(link) = &self.link else {
            return false;
        };
        link.client
            .try_publish(
                self.topics.node("NDEATH"),
                QoS::AtLeastOnce,
                false,
                self.death(),
            )
            .is_ok()
            && link.client.try_disconnect().is_ok()
    }

    /// A clean stop: NDEATH (the will is not sent on a clean DISCONNECT,
    /// [tck-id-operational-behavior-edge-node-intentional-disconnect-ndeath]),
    /// then DISCONNECT.
    async fn stop(&mut self) {
        if self.connected && self.say_death() {
            let deadline = Instant::now() + STOP_WAIT;
            while let Ok(event) =
                tokio::time::timeout_at(deadline, next_event(&mut self.link)).await
            {
                if matches!(
                    event,
                    Ok(Event::Outgoing(rumqttc::Outgoing::Disconnect)) | Err(_)
                ) {
                    break;
                }
            }
        }
        self.link = None;
        for device in &self.devices {
            device.metrics.connected.set(0);
        }
    }
}

fn datatype_of(ty: plccoms_protocol::IecType) -> u32 {
    metric::datatype(ty)
}

fn now_ms() -> u64 {
    unix_ms(SystemTime::now()).max(0) as u64
}

/// `text` in `path`, through a temporary file renamed over it and synced.
fn write_durably(path: &std::path::Path, text: &str) -> std::io::Result<()> {
    use std::io::Write as _;
    let dir = path.parent().unwrap_or(std::path::Path::new("."));
    std::fs::create_dir_all(dir)?;
    let mut file = tempfile::NamedTempFile::new_in(dir)?;
    file.write_all(text.as_bytes())?;
    file.as_file().sync_all()?;
    file.persist(path).map_err(|e| e.error)?;
    std::fs::File::open(dir)?.sync_all()
}
