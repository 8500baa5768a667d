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
}

const FAMILIES: [(&str, &str, &str); 10] = [
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
            _ => self.write_refusals.get(),
        }
    }
}

/// Every section's MQTT counters, for `/metrics`.
pub struct Source {
    sections: Vec<(String, Arc<Metrics>)>,
}

impl metrics::Source for Source {
    fn render(&self, out: &mut String) {
        use std::fmt::Write as _;
        for (index, (name, kind, help)) in FAMILIES.iter().enumerate() {
            metrics::header(out, name, kind, help);
            for (section, m) in &self.sections {
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

/// The running MQTT tasks.
pub struct Mqtt {
    tasks: Vec<JoinHandle<()>>,
    writers: Vec<JoinHandle<()>>,
    stop: CancellationToken,
    pub source: Arc<Source>,
}

impl Mqtt {
    /// Stops every section's task cleanly (`offline`, DISCONNECT, the queue
    /// saved), waiting at most `grace`.
    pub async fn shutdown(self, grace: Duration) {
        self.stop.cancel();
        let all = futures::future::join_all(self.tasks);
        if tokio::time::timeout(grace, all).await.is_err() {
            warn!("MQTT: not every section stopped within {grace:?}");
        }
        for writer in self.writers {
            writer.abort();
        }
    }
}

/// Starts a task per section. Fails when a section's rules or queue folder
/// cannot be used (the folder held by another process, say).
pub fn start(settings: Settings, sections: &[Arc<Section>]) -> Result<Mqtt, String> {
    let settings = Arc::new(settings);
    let stop = CancellationToken::new();
    let mut prepared = Vec::new();
    let mut devices = Vec::new();
    for section in sections {
        let section = section.clone();
        let config = section.state().config.clone();
        let rules =
            SectionRules::new(&config.mqtt).map_err(|e| format!("[{}] {e}", section.name()))?;
        if config.mqtt.sparkplug {
            devices.push((section, rules));
            continue;
        }
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
        prepared.push((section, rules, topics, client_id, spool, spool_dir));
    }
    let mut tasks = Vec::new();
    let mut writers = Vec::new();
    let mut source = Source {
        sections: Vec::new(),
    };
    for (section, rules, topics, client_id, spool, spool_dir) in prepared {
        let metrics = Arc::new(Metrics::default());
        source
            .sections
            .push((section.name().to_string(), metrics.clone()));
        metrics.queued.set(spool.len());
        metrics.queued_bytes.set(spool.bytes());
        // Every change, in order, while the connection lags within the
        // follow bounds: QoS 1 promises them to the broker.
        let changes = section.subscribe_names(&rules.publish).every_change();
        let (write_tx, write_rx) = mpsc::channel(writes::QUEUE);
        let (outcome_tx, outcome_rx) = mpsc::channel(writes::QUEUE);
        writers.push(tokio::spawn(writes::worker(
            section.clone(),
            write_rx,
            outcome_tx,
        )));
        let task = Task {
            section,
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
            state: Default::default(),
        };
        tasks.push(tokio::spawn(task.run(changes)));
    }
    if !devices.is_empty() {
        let devices = devices
            .into_iter()
            .map(|(section, rules)| {
                let metrics = Arc::new(Metrics::default());
                source
                    .sections
                    .push((section.name().to_string(), metrics.clone()));
                (section, rules, metrics)
            })
            .collect();
        let (node, helpers) = sparkplug::start(settings.clone(), devices, stop.clone())?;
        tasks.push(node);
        writers.extend(helpers);
    }
    Ok(Mqtt {
        tasks,
        writers,
        stop,
        source: Arc::new(source),
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
        let source = Source {
            sections: vec![("Hala \"1\"".into(), metrics)],
        };
        let mut out = String::new();
        source.render(&mut out);
        assert!(out.contains("# TYPE plccoms_mqtt_connected gauge\n"));
        assert!(out.contains("plccoms_mqtt_connected{section=\"Hala \\\"1\\\"\"} 1\n"));
        assert!(out.contains("plccoms_mqtt_dropped_total{section=\"Hala \\\"1\\\"\"} 3\n"));
        assert_eq!(out.matches("# HELP").count(), FAMILIES.len());
    }
}
