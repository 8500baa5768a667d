//! bench-mqtt: what reaches an MQTT subscriber, for `bench/run`.
//!
//! - `subscribe`: subscribes (QoS 1) to a filter and counts the value
//!   messages that arrive in a window after a warm-up: messages per second,
//!   and with `--latency` the delay of each json value after the poll that
//!   read it (arrival time minus the payload's `ts`, both UTC on this
//!   machine; `ts` has millisecond resolution and is the poll's start).
//! - `baseline`: the same subscriber, with a minimal publisher beside it
//!   (one connection, QoS 1, retained, as fast as the broker takes them, on
//!   as many topics with payloads of the same size): what the broker alone
//!   delivers, the reference for plccoms' figure.
//!
//! Both count changes and the bytes (topic and payload) that carry them: a
//! json value message is one change, a Sparkplug DDATA as many as its
//! metrics (other Sparkplug messages carry none).
//!
//! Results are `label.metric value` lines appended to `--out`.

use std::io::Write as _;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use clap::{Parser, Subcommand};
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};

#[derive(Debug, Parser)]
#[command(name = "bench-mqtt")]
struct Args {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Debug, clap::Args)]
struct Common {
    /// Broker port on 127.0.0.1.
    #[arg(long)]
    port: u16,
    /// Seconds before counting starts.
    #[arg(long, default_value_t = 2)]
    warmup: u64,
    /// Seconds counted.
    #[arg(long, default_value_t = 10)]
    duration: u64,
    #[arg(long)]
    label: String,
    /// Results file (appended).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Counts (and times) the messages on a topic filter.
    Subscribe {
        #[command(flatten)]
        common: Common,
        #[arg(long)]
        filter: String,
        /// Latency from the json payload's `ts`.
        #[arg(long)]
        latency: bool,
    },
    /// A minimal publisher and the same subscriber.
    Baseline {
        #[command(flatten)]
        common: Common,
        #[arg(long, default_value_t = 10_000)]
        topics: usize,
        #[arg(long, default_value_t = 75)]
        payload: usize,
    },
}

fn now_ms() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs_f64()
        * 1000.0
}

/// `ts` of a json value payload, in UTC milliseconds.
fn ts_ms(payload: &[u8]) -> Option<f64> {
    let v: serde_json::Value = serde_json::from_slice(payload).ok()?;
    let ts = chrono::DateTime::parse_from_rfc3339(v["ts"].as_str()?).ok()?;
    Some(ts.timestamp_millis() as f64)
}

fn options(role: &str, port: u16) -> MqttOptions {
    let id = format!("bench-{role}-{}", std::process::id());
    let mut options = MqttOptions::new(id, "127.0.0.1", port);
    options
        .set_max_packet_size(1 << 20, 1 << 20)
        .set_keep_alive(Duration::from_secs(30));
    options
}

struct Counts {
    counting: AtomicBool,
    messages: AtomicU64,
    changes: AtomicU64,
    bytes: AtomicU64,
}

/// The changes a message carries.
fn changes_in(topic: &[u8], payload: &[u8]) -> u64 {
    use prost::Message as _;
    if !topic.starts_with(b"spBv1.0/") {
        return 1;
    }
    if !topic.windows(7).any(|w| w == b"/DDATA/") {
        return 0;
    }
    plccoms_mqtt::sparkplug::proto::Payload::decode(payload).map_or(0, |p| p.metrics.len() as u64)
}

async fn subscriber(
    port: u16,
    filter: String,
    latency: bool,
    counts: Arc<Counts>,
    latencies: Arc<std::sync::Mutex<Vec<f64>>>,
) {
    let (client, mut eventloop) = AsyncClient::new(options("sub", port), 64);
    client
        .subscribe(filter, QoS::AtLeastOnce)
        .await
        .expect("subscribe");
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::Publish(p))) => {
                if p.retain || (latency && !p.payload.starts_with(b"{")) {
                    continue;
                }
                if !counts.counting.load(Ordering::Relaxed) {
                    continue;
                }
                counts.messages.fetch_add(1, Ordering::Relaxed);
                counts.changes.fetch_add(
                    changes_in(p.topic.as_bytes(), &p.payload),
                    Ordering::Relaxed,
                );
                counts
                    .bytes
                    .fetch_add((p.topic.len() + p.payload.len()) as u64, Ordering::Relaxed);
                if latency {
                    if let Some(ts) = ts_ms(&p.payload) {
                        latencies.lock().unwrap().push(now_ms() - ts);
                    }
                }
            }
            Ok(_) => {}
            Err(e) => {
                eprintln!("subscriber: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

async fn publisher(port: u16, topics: usize, payload: usize) {
    let mut options = options("pub", port);
    // plccoms' window.
    options.set_inflight(264);
    let (client, mut eventloop) = AsyncClient::new(options, 272);
    tokio::spawn(async move {
        loop {
            if let Err(e) = eventloop.poll().await {
                eprintln!("publisher: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    });
    let topics: Vec<String> = (0..topics)
        .map(|i| format!("baseline/Bench/ANIM_{i:05}"))
        .collect();
    let body = vec![b'x'; payload];
    let mut i = 0usize;
    loop {
        let topic = topics[i % topics.len()].clone();
        if client
            .publish(topic, QoS::AtLeastOnce, true, body.clone())
            .await
            .is_err()
        {
            return;
        }
        i += 1;
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = ((p / 100.0) * (sorted.len() - 1) as f64).round() as usize;
    sorted[rank.min(sorted.len() - 1)]
}

#[tokio::main]
async fn main() {
    let args = Args::parse();
    let (common, filter, latency) = match &args.command {
        Cmd::Subscribe {
            common,
            filter,
            latency,
        } => (common, filter.clone(), *latency),
        Cmd::Baseline { common, .. } => (common, "baseline/Bench/#".to_string(), false),
    };
    let counts = Arc::new(Counts {
        counting: AtomicBool::new(false),
        messages: AtomicU64::new(0),
        changes: AtomicU64::new(0),
        bytes: AtomicU64::new(0),
    });
    let latencies = Arc::new(std::sync::Mutex::new(Vec::new()));
    tokio::spawn(subscriber(
        common.port,
        filter,
        latency,
        counts.clone(),
        latencies.clone(),
    ));
    if let Cmd::Baseline {
        topics, payload, ..
    } = &args.command
    {
        tokio::time::sleep(Duration::from_millis(300)).await;
        tokio::spawn(publisher(common.port, *topics, *payload));
    }
    tokio::time::sleep(Duration::from_secs(common.warmup)).await;
    counts.counting.store(true, Ordering::Relaxed);
    let start = Instant::now();
    tokio::time::sleep(Duration::from_secs(common.duration)).await;
    counts.counting.store(false, Ordering::Relaxed);
    let elapsed = start.elapsed().as_secs_f64();
    let messages = counts.messages.load(Ordering::Relaxed);
    let changes = counts.changes.load(Ordering::Relaxed);
    let bytes = counts.bytes.load(Ordering::Relaxed);
    let mut lines = vec![
        format!("{}.changes {changes}", common.label),
        format!(
            "{}.changes_per_s {:.0}",
            common.label,
            changes as f64 / elapsed
        ),
        format!(
            "{}.bytes_per_change {:.1}",
            common.label,
            bytes as f64 / changes.max(1) as f64
        ),
        format!("{}.messages {messages}", common.label),
        format!(
            "{}.msgs_per_s {:.0}",
            common.label,
            messages as f64 / elapsed
        ),
    ];
    if latency {
        let mut l = latencies.lock().unwrap().clone();
        l.sort_by(|a, b| a.total_cmp(b));
        lines.push(format!(
            "{}.latency_p50_ms {:.2}",
            common.label,
            percentile(&l, 50.0)
        ));
        lines.push(format!(
            "{}.latency_p99_ms {:.2}",
            common.label,
            percentile(&l, 99.0)
        ));
        lines.push(format!(
            "{}.latency_max_ms {:.2}",
            common.label,
            l.last().copied().unwrap_or(f64::NAN)
        ));
        lines.push(format!("{}.latency_samples {}", common.label, l.len()));
    }
    let text = lines.join("\n") + "\n";
    print!("{text}");
    if let Some(out) = &common.out {
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(out)
            .expect("open --out");
        file.write_all(text.as_bytes()).expect("write --out");
    }
    std::process::exit(0);
}
