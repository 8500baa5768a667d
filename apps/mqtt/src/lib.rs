//! The MQTT north side: each section's changes published to a broker, writes
//! taken back, nothing lost while the broker is away. On when `[*]` has an
//! MQTT_URL.
//!
//! - `settings.rs`: the keys resolved (broker URL, credentials, TLS, client
//!   ids, each section's rules);
//! - `topics.rs`: topic names and the escape of names;
//! - `payload.rs`: plain and json payloads;
//! - `spool.rs`: the on-disk queue (store-and-forward), crash-safe, bounded;
//! - `connection.rs`: one task per section, with a connection of its own
//!   (its own client id and last will): changes -> queue -> broker;
//! - `writes.rs`: `/set` through SET's validation, one write at a time;
//! - `discovery.rs`: Home Assistant discovery;
//! - `sparkplug/`: Sparkplug B, the sections with SPARKPLUG = Yes as the
//!   devices of one edge node.
//!
//! Counters are `plccoms_mqtt_*` in `/metrics` ([`Source`]).

mod client;
mod connection;
pub mod discovery;
pub mod payload;
pub mod settings;
pub mod sparkplug;
pub mod spool;
pub mod topics;
pub mod writes;

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use connection::Task;
use plccoms_core::metrics::{self, escape_label, Counter, Gauge};
use plccoms_core::section::Section;
use settings::{id_safe, SectionRules, Settings};
use spool::Spool;
use topics::Topics;

/// One section's MQTT counters.
#[derive(Debug, Default)]
pub struct Metrics {
    /// 1 while connected to the broker.
    pub connected: Gauge,
    pub connects: Counter,
    /// Messages the broker acknowledged (QoS 1) or that were written to it
    /// (QoS 0), from the queue.
    pub published: Counter,
    /// Messages queued and not yet acknowledged.
    pub queued: Gauge,
    pub queued_bytes: Gauge,
    /// Queued messages dropped, oldest first, over MQTT_BUFFER (or when the
    /// queue could not be written).
    pub dropped: Counter,
    /// QoS 0 changes not sent because the broker was away.
    pub not_sent: Counter,
    /// Change-stream publishes whose intermediate values this task did not
    /// see (it fell behind; the latest values were published).
    pub missed: Counter,
    pub writes: Counter,
    pub write_refusals: Counter,
    /// The place in MQTT_URL (from 0) of the broker connected to, or
    /// being tried.
    pub broker_index: Gauge,
}

const FAMILIES: [(&str, &str, &str); 11] = [
    (
        "plccoms_mqtt_connected",
        "gauge",
        "1 while connected to the MQTT broker.",
    ),
    (
        "plccoms_mqtt_connects_total",
        "counter",
        "Connections made to the MQTT broker.",
    ),
    (
        "plccoms_mqtt_published_total",
        "counter",
        "Queued messages the broker took (acknowledged at QoS 1).",
    ),
    (
        "plccoms_mqtt_queued_messages",
        "gauge",
        "Messages queued on disk and not yet acknowledged.",
    ),
    (
        "plccoms_mqtt_queued_bytes",
        "gauge",
        "Bytes of the on-disk queue.",
    ),
    (
        "plccoms_mqtt_dropped_total",
        "counter",
        "Queued messages dropped, oldest first, over MQTT_BUFFER.",
    ),
    (
        "plccoms_mqtt_not_sent_total",
        "counter",
        "QoS 0 changes not sent while the broker was away.",
    ),
    (
        "plccoms_mqtt_missed_total",
        "counter",
        "Change publishes coalesced because the MQTT task fell behind.",
    ),
    (
        "plccoms_mqtt_writes_total",
        "counter",
        "Writes from /set topics confirmed by the PLC.",
    ),
    (
        "plccoms_mqtt_write_refusals_total",
        "counter",
        "Writes from /set topics refused.",
    ),
    (
        "plccoms_mqtt_broker_index",
        "gauge",
        "Place in MQTT_URL (from 0) of the broker connected to or being tried.",
    ),
];

impl Metrics {
    fn value(&self, family: usize) -> u64 {
        match family {
            0 => self.connected.get(),
            1 => self.connects.get(),
            2 => self.published.get(),
            3 => self.queued.get(),
            4 => self.queued_bytes.get(),
            5 => self.dropped.get(),
            6 => self.not_sent.get(),
            7 => self.missed.get(),
            8 => self.writes.get(),
            9 => self.write_refusals.get(),
            _ => self.broker_index.get(),
        }
    }
}

/// Every section's MQTT counters, for `/metrics`.
#[derive(Default)]
pub struct Source {
    sections: std::sync::Mutex<Vec<(String, Arc<Metrics>)>>,
}

impl Source {
    fn sections(&self) -> std::sync::MutexGuard<'_, Vec<(String, Arc<Metrics>)>> {
        self.sections.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl metrics::Source for Source {
    fn render(&self, out: &mut String) {
        use std::fmt::Write as _;
        let sections = self.sections().clone();
        for (index, (name, kind, help)) in FAMILIES.iter().enumerate() {
            metrics::header(out, name, kind, help);
            for (section, m) in &sections {
                let _ = writeln!(
                    out,
                    "{name}{{section=\"{}\"}} {}",
                    escape_label(section),
                    m.value(index)
                );
            }
        }
    }
}

/// The running MQTT side: a task per section, started and stopped as the
/// running sections change (a reload), the others left alone.
pub struct Mqtt {
    supervisor: JoinHandle<()>,
    stop: CancellationToken,
    pub source: Arc<Source>,
}

impl Mqtt {
    /// Stops every section's task cleanly (`offline`, DISCONNECT, the queue
    /// saved), waiting at most `grace`.
    pub async fn shutdown(self, grace: Duration) {
        self.stop.cancel();
        if tokio::time::timeout(grace, self.supervisor).await.is_err() {
            warn!("MQTT: not every section stopped within {grace:?}");
        }
    }
}

/// One section's MQTT work.
struct Running {
    section: Arc<Section>,
    stop: CancellationToken,
    task: JoinHandle<()>,
    writer: JoinHandle<()>,
}

impl Running {
    /// Ends the section's session cleanly, at most `grace`.
    async fn stop(self, grace: Duration) {
        self.stop.cancel();
        if tokio::time::timeout(grace, self.task).await.is_err() {
            warn!(section = %self.section.name(), "MQTT: the section's task did not stop within {grace:?}");
        }
        self.writer.abort();
    }
}

/// What a section needs before its task can run (checked at start, so a
/// folder that cannot be used stops the start).
struct Prepared {
    section: Arc<Section>,
    rules: SectionRules,
    topics: Topics,
    client_id: String,
    spool: Spool,
    spool_dir: std::path::PathBuf,
}

fn prepare(settings: &Settings, section: &Arc<Section>) -> Result<Prepared, String> {
    let section = section.clone();
    let config = section.state().config.clone();
    let rules = SectionRules::new(&config.mqtt).map_err(|e| format!("[{}] {e}", section.name()))?;
    let client_id = settings.section_client_id(section.name());
    let spool_dir = settings.spool.join(id_safe(&client_id));
    let (spool, recovered) = Spool::open(&spool_dir, settings.buffer).map_err(|e| {
        format!(
            "[{}] MQTT_SPOOL {}: {e}; make the folder writable by the server's user, or set MQTT_SPOOL to one that is (a relative path starts in $STATE_DIRECTORY under systemd, else beside the configuration)",
            section.name(),
            spool_dir.display()
        )
    })?;
    for cut in &recovered.cut {
        warn!(section = %section.name(), "MQTT queue: {cut}");
    }
    if recovered.messages > 0 {
        info!(section = %section.name(), "MQTT: {} messages ({} bytes) queued from before are sent first", recovered.messages, recovered.bytes);
    }
    if !rules.write.is_empty() && config.read_only {
        warn!(section = %section.name(), "MQTT_WRITE is set but the section is READ_ONLY: every write is refused");
    }
    let topics = Topics::new(&settings.prefix, section.name());
    info!(
        section = %section.name(),
        "MQTT: publishing [{}] under {}/, writable [{}], QoS {}, {:?}, as {}",
        config.mqtt.publish.join(", "),
        topics.base(),
        config.mqtt.write.join(", "),
        rules.qos,
        rules.format,
        client_id
    );
    Ok(Prepared {
        section,
        rules,
        topics,
        client_id,
        spool,
        spool_dir,
    })
}

fn run(
    prepared: Prepared,
    settings: &Arc<Settings>,
    stop: &CancellationToken,
    source: &Source,
) -> Running {
    let Prepared {
        section,
        rules,
        topics,
        client_id,
        spool,
        spool_dir,
    } = prepared;
    let metrics = Arc::new(Metrics::default());
    {
        let mut sections = source.sections();
        sections.retain(|(name, _)| name != section.name());
        sections.push((section.name().to_string(), metrics.clone()));
    }
    metrics.queued.set(spool.len());
    metrics.queued_bytes.set(spool.bytes());
    // Every change, in order, while the connection lags within the follow
    // bounds: QoS 1 promises them to the broker.
    let changes = section.subscribe_names(&rules.publish).every_change();
    let (write_tx, write_rx) = mpsc::channel(writes::QUEUE);
    let (outcome_tx, outcome_rx) = mpsc::channel(writes::QUEUE);
    let writer = tokio::spawn(writes::worker(section.clone(), write_rx, outcome_tx));
    let stop = stop.child_token();
    let task = Task {
        section: section.clone(),
        settings: settings.clone(),
        rules,
        topics,
        client_id,
        spool,
        spool_dir,
        metrics,
        shutdown: stop.clone(),
        writes: write_tx,
        outcomes: outcome_rx,
        refusal_logs: Default::default(),
        brokers: client::Brokers::new(settings.brokers.clone()),
        state: Default::default(),
    };
    Running {
        section,
        stop,
        task: tokio::spawn(task.run(changes)),
        writer,
    }
}

/// Whether the section publishes as a Sparkplug device.
fn is_sparkplug(section: &Arc<Section>) -> bool {
    section.state().config.mqtt.sparkplug
}

/// The Sparkplug edge node, when some sections are its devices: its task
/// and helpers (change forwarders, write workers).
type Node = Option<(JoinHandle<()>, Vec<JoinHandle<()>>)>;

fn start_sparkplug(
    settings: &Arc<Settings>,
    sections: &[Arc<Section>],
    stop: &CancellationToken,
    source: &Source,
) -> Result<Node, String> {
    if sections.is_empty() {
        return Ok(None);
    }
    let mut devices = Vec::new();
    for section in sections {
        let rules = SectionRules::new(&section.state().config.mqtt)
            .map_err(|e| format!("[{}] {e}", section.name()))?;
        let metrics = Arc::new(Metrics::default());
        source
            .sections()
            .push((section.name().to_string(), metrics.clone()));
        devices.push((section.clone(), rules, metrics));
    }
    sparkplug::start(settings.clone(), devices, stop.child_token()).map(Some)
}

/// Waits for a stopped node's clean end (NDEATH, DISCONNECT), then ends
/// its helpers.
async fn stop_node(node: Node) {
    if let Some((task, helpers)) = node {
        let _ = task.await;
        helpers.iter().for_each(JoinHandle::abort);
    }
}

/// How long a section removed or restarted by a reload has to say
/// `offline` and save its queue before its replacement opens the queue.
const RELOAD_GRACE: Duration = Duration::from_secs(2);

/// Starts a task per running section and follows `sections`: a section
/// added by a reload gets a task, a removed one's ends cleanly, the others
/// keep their sessions. Fails when a section's rules or queue folder cannot
/// be used at start (the folder held by another process, say).
pub fn start(
    settings: Settings,
    sections: &plccoms_core::sections::Sections,
) -> Result<Mqtt, String> {
    let settings = Arc::new(settings);
    let stop = CancellationToken::new();
    let mut watch = sections.watch();
    let (devices, first): (Vec<_>, Vec<_>) = watch
        .borrow_and_update()
        .iter()
        .cloned()
        .partition(is_sparkplug);
    let prepared = first
        .iter()
        .map(|section| prepare(&settings, section))
        .collect::<Result<Vec<_>, _>>()?;
    let source = Arc::new(Source::default());
    let mut devices = devices;
    let mut node_stop = stop.child_token();
    let mut node = start_sparkplug(&settings, &devices, &node_stop, &source)?;
    let mut running: Vec<Running> = prepared
        .into_iter()
        .map(|p| run(p, &settings, &stop, &source))
        .collect();
    let supervisor = {
        let (stop, source) = (stop.clone(), source.clone());
        tokio::spawn(async move {
            loop {
                tokio::select! {
                    _ = stop.cancelled() => break,
                    changed = watch.changed() => if changed.is_err() { break },
                }
                let (now_devices, now): (Vec<_>, Vec<_>) = watch
                    .borrow_and_update()
                    .iter()
                    .cloned()
                    .partition(is_sparkplug);
                let (added, removed) = plccoms_core::sections::diff(&devices, &now_devices);
                if !added.is_empty() || !removed.is_empty() {
                    // The node's devices are its births: a new session
                    // (NDEATH, then NBIRTH and DBIRTHs of the new set).
                    info!(
                        "Sparkplug: the reload changed the node's devices: starting a new session"
                    );
                    node_stop.cancel();
                    stop_node(node.take()).await;
                    source
                        .sections()
                        .retain(|(n, _)| !devices.iter().any(|d| d.name() == n));
                    devices = now_devices;
                    node_stop = stop.child_token();
                    node = start_sparkplug(&settings, &devices, &node_stop, &source)
                        .unwrap_or_else(|message| {
                            tracing::error!("Sparkplug: the node not started again: {message}");
                            None
                        });
                }
                let current: Vec<_> = running.iter().map(|r| r.section.clone()).collect();
                let (added, removed) = plccoms_core::sections::diff(&current, &now);
                let (gone, kept): (Vec<_>, Vec<_>) = running
                    .into_iter()
                    .partition(|r| removed.iter().any(|s| Arc::ptr_eq(s, &r.section)));
                running = kept;
                // Before the replacements start: a restarted section's queue
                // folder is free again once its old task has saved it.
                futures::future::join_all(gone.into_iter().map(|r| {
                    let name = r.section.name().to_string();
                    let source = source.clone();
                    async move {
                        r.stop(RELOAD_GRACE).await;
                        source.sections().retain(|(n, _)| *n != name);
                    }
                }))
                .await;
                for section in &added {
                    match prepare(&settings, section) {
                        Ok(p) => running.push(run(p, &settings, &stop, &source)),
                        Err(message) => {
                            tracing::error!(section = %section.name(), "MQTT not started for this section: {message}")
                        }
                    }
                }
            }
            let sections = running.into_iter().map(|r| r.stop(Duration::MAX));
            futures::future::join(futures::future::join_all(sections), stop_node(node)).await;
        })
    };
    Ok(Mqtt {
        supervisor,
        stop,
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::metrics::Source as _;

    #[test]
    fn counters_in_prometheus_text() {
        let metrics = Arc::new(Metrics::default());
        metrics.connected.set(1);
        metrics.dropped.add(3);
        let source = Source::default();
        source.sections().push(("Hala \"1\"".into(), metrics));
        let mut out = String::new();
        source.render(&mut out);
        assert!(out.contains("# TYPE plccoms_mqtt_connected gauge\n"));
        assert!(out.contains("plccoms_mqtt_connected{section=\"Hala \\\"1\\\"\"} 1\n"));
        assert!(out.contains("plccoms_mqtt_dropped_total{section=\"Hala \\\"1\\\"\"} 3\n"));
        assert_eq!(out.matches("# HELP").count(), FAMILIES.len());
    }
}
