//! bench-opcua-server: one OPC UA client (async-opcua's) that drives any OPC UA
//! server the same way, for `bench/run`'s plccoms vs node-opcua rows.
//!
//! Against the folder `--folder` (a STRING NodeId in namespace `--ns`):
//! - browse: every Variable below it (1,000 references a call, then
//!   BrowseNext), timed until `--browse` references have arrived;
//! - read: one Read of the Value of the first `--read` of them, three times,
//!   once every value is Good (`values_ready_s`: how long that took);
//! - subscribe: `--subscriptions` subscriptions of `--per-subscription`
//!   monitored items (no filter, sampling 0: the server's fastest, queue
//!   `--queue`, publishing every `--publish-ms`), in one session.
//!
//! The changing variables (browse name starting with `--changing`) all hold
//! the same rising counter (plcsim `--animate`, or the node script's tick),
//! so each counter value measured must reach every one of them: loss is
//! the number of (item, value) notifications missing over the window.
//! Latency is arrival minus SourceTimestamp (the poll's time at plccoms,
//! the time the value was set at node-opcua; both on this machine's clock),
//! split at the ServerTimestamp (`to_server`: until the server made the
//! notification's value; `from_server`: its queue, publish and delivery),
//! and that again at the message's PublishTime (`queued`: the stack's
//! queue and publishing interval; `wire`: encoding, socket, decoding).
//! With `--server-pid`, the server's RSS is sampled every second.
//!
//! Results are `label.metric value` lines on stdout, appended to `--out`.

#[path = "../procfs.rs"]
#[allow(dead_code)]
mod procfs;

use std::collections::HashMap;
use std::io::Write as _;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use clap::Parser;
use opcua::client::{
    ClientBuilder, IdentityToken, MonitoredItemMap, OnSubscriptionNotificationCore, Session,
};
use opcua::types::{
    AttributeId, BrowseDescription, BrowseDirection, BrowseResultMask, DataChangeNotification,
    DataValue, EndpointDescription, MessageSecurityMode, MonitoredItemCreateRequest,
    MonitoringMode, MonitoringParameters, NodeClassMask, NodeId, NotificationMessage, ReadValueId,
    ReferenceTypeId, TimestampsToReturn, UserTokenPolicy, VariableId, Variant,
};

#[derive(Debug, Parser)]
#[command(name = "bench-opcua-server")]
struct Args {
    /// Endpoint (security None, anonymous).
    #[arg(long)]
    url: String,
    /// Namespace URI of the folder's NodeId (plccoms: urn:plccoms).
    #[arg(long, default_value = "urn:plccoms")]
    ns: String,
    /// STRING NodeId of the folder holding the variables (plccoms: the section).
    #[arg(long, default_value = "Bench")]
    folder: String,
    /// Browse-name prefix of the changing variables.
    #[arg(long, default_value = "ANIM_")]
    changing: String,
    #[arg(long, default_value_t = 10)]
    subscriptions: usize,
    #[arg(long, default_value_t = 10_000)]
    per_subscription: usize,
    #[arg(long, default_value_t = 100)]
    publish_ms: u64,
    /// Queue size of each monitored item.
    #[arg(long, default_value_t = 10)]
    queue: u32,
    /// References browsed before the browse time is taken.
    #[arg(long, default_value_t = 50_000)]
    browse: usize,
    /// Nodes in the one Read.
    #[arg(long, default_value_t = 10_000)]
    read: usize,
    /// Seconds after the subscriptions are made before counting.
    #[arg(long, default_value_t = 5)]
    warmup: u64,
    /// Seconds counted.
    #[arg(long, default_value_t = 20)]
    duration: u64,
    /// Seconds to wait for the folder to hold every variable wanted.
    #[arg(long, default_value_t = 120)]
    wait: u64,
    /// Minutes counted instead of --duration (the RSS soak).
    #[arg(long)]
    soak: Option<u64>,
    /// The server's pid: its RSS sampled every second.
    #[arg(long)]
    server_pid: Option<u32>,
    #[arg(long)]
    label: String,
    /// Results file (appended).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
}

/// An OPC UA time in ms since the epoch, as [`now_ms`].
fn epoch_ms(t: &opcua::types::DateTime) -> f64 {
    t.as_chrono().timestamp_micros() as f64 / 1000.0
}

fn now_ms() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs_f64()
        * 1000.0
}

/// Where a run is: values first seen while measuring are the ones counted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Warmup,
    Measuring,
    Draining,
}

struct Stats {
    phase: Phase,
    /// Per client handle - 1: a changing variable?
    changing: Vec<bool>,
    changing_count: u32,
    /// Per client handle - 1: the last counter value.
    last: Vec<Option<u64>>,
    /// Counter value first seen while measuring -> items that reported it.
    seen: HashMap<u64, u32>,
    /// The newest counter value seen before measuring: its notifications
    /// straddle the window's start (those of some subscriptions before,
    /// of others after), so it is not counted.
    before: Option<u64>,
    notifications: u64,
    duplicates: u64,
    unexpected: u64,
    not_good: u64,
    overflow: u64,
    not_counter: u64,
    latencies_ms: Vec<f64>,
    /// The same split at the DataValue's ServerTimestamp (when the server
    /// made the notification's value): source -> server, server -> arrival.
    to_server_ms: Vec<f64>,
    from_server_ms: Vec<f64>,
    /// ServerTimestamp -> the message's PublishTime (the stack's queue and
    /// publishing interval), and PublishTime -> the message's arrival
    /// (encoding, the socket, decoding).
    queued_ms: Vec<f64>,
    wire_ms: Vec<f64>,
}

impl Stats {
    /// `message`: the notification message's PublishTime and when it
    /// arrived (ms since the epoch).
    fn on_value(&mut self, handle: u32, value: &DataValue, message: Option<(f64, f64)>) {
        let Some(i) = (handle as usize)
            .checked_sub(1)
            .filter(|&i| i < self.changing.len())
        else {
            return;
        };
        let measuring = self.phase == Phase::Measuring;
        if measuring {
            self.notifications += 1;
            let status = value.status();
            if status.overflow() {
                self.overflow += 1;
            }
            if !status.is_good() {
                self.not_good += 1;
            }
        }
        if !self.changing[i] {
            self.unexpected += u64::from(measuring);
            return;
        }
        let Some(v) = counter(value.value.as_ref()) else {
            self.not_counter += u64::from(measuring);
            return;
        };
        if self.last[i] == Some(v) {
            self.duplicates += u64::from(measuring);
            return;
        }
        self.last[i] = Some(v);
        if measuring {
            let arrival = now_ms();
            if let Some(source) = value.source_timestamp {
                self.latencies_ms.push(arrival - epoch_ms(&source));
                if let Some(server) = value.server_timestamp {
                    self.to_server_ms
                        .push(epoch_ms(&server) - epoch_ms(&source));
                    self.from_server_ms.push(arrival - epoch_ms(&server));
                    if let Some((published, received)) = message {
                        self.queued_ms.push(published - epoch_ms(&server));
                        self.wire_ms.push(received - published);
                    }
                }
            }
            if self.before.is_none_or(|b| v > b) {
                *self.seen.entry(v).or_insert(0) += 1;
            }
        } else if self.phase == Phase::Warmup {
            self.before = self.before.max(Some(v));
        } else if let Some(n) = self.seen.get_mut(&v) {
            // Late arrivals of a value first seen while measuring.
            *n += 1;
        }
    }
}

/// The subscriptions' callback: each data change with its message's
/// PublishTime and arrival.
struct Notified(Arc<Mutex<Stats>>);

impl OnSubscriptionNotificationCore for Notified {
    fn on_subscription_notification(
        &mut self,
        notification: NotificationMessage,
        items: MonitoredItemMap<'_>,
    ) {
        let received = now_ms();
        // node-opcua's messages carry no PublishTime: no split there.
        let message = (!notification.publish_time.is_null())
            .then(|| (epoch_ms(&notification.publish_time), received));
        let mut stats = self.0.lock().unwrap_or_else(|e| e.into_inner());
        for object in notification.notification_data.into_iter().flatten() {
            let Some(change) = object.into_inner_as::<DataChangeNotification>() else {
                continue;
            };
            for n in change.monitored_items.into_iter().flatten() {
                if items.get(n.client_handle).is_some() {
                    stats.on_value(n.client_handle, &n.value, message);
                }
            }
        }
    }
}

fn counter(v: Option<&Variant>) -> Option<u64> {
    match v? {
        Variant::UInt32(v) => Some(u64::from(*v)),
        Variant::UInt64(v) => Some(*v),
        Variant::UInt16(v) => Some(u64::from(*v)),
        Variant::Int32(v) => u64::try_from(*v).ok(),
        Variant::Int64(v) => u64::try_from(*v).ok(),
        _ => None,
    }
}

struct Report {
    label: String,
    lines: Vec<String>,
}

impl Report {
    fn metric(&mut self, name: &str, value: f64) {
        let line = format!(
            "{}.{name} {}",
            self.label,
            (value * 1000.0).round() / 1000.0
        );
        println!("{line}");
        self.lines.push(line);
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

type Fail = Box<dyn std::error::Error>;

async fn connect(args: &Args, pki: &std::path::Path) -> Result<Arc<Session>, Fail> {
    // Big enough for a Browse or Read of 100,000 nodes and a publish of
    // 10,000 notifications; bounded all the same.
    const MAX_MESSAGE: usize = 256 * 1024 * 1024;
    let mut client = ClientBuilder::new()
        .application_name("bench-opcua-server")
        .application_uri("urn:plccoms:bench-opcua-server")
        .product_uri("urn:plccoms")
        .pki_dir(pki)
        .create_sample_keypair(false)
        .trust_server_certs(true)
        .session_retry_limit(0)
        .request_timeout(Duration::from_secs(120))
        .publish_timeout(Duration::from_secs(60))
        .max_chunk_count(MAX_MESSAGE / 65_536)
        .max_message_size(MAX_MESSAGE)
        .max_array_length(1_000_000)
        .client()
        .map_err(|e| format!("client settings: {}", e.join("; ")))?;
    let endpoint: EndpointDescription = (
        args.url.as_str(),
        "None",
        MessageSecurityMode::None,
        UserTokenPolicy::anonymous(),
    )
        .into();
    // Nagle off, as plccoms's own client: the generator's Publish
    // requests are not held for the server's delayed ACK.
    let (session, event_loop) = plccoms_driver_opcua::nodelay::connect_to_matching_endpoint(
        &mut client,
        endpoint,
        IdentityToken::Anonymous,
    )
    .await?;
    session.disable_reconnects();
    tokio::spawn(async move {
        let ended = event_loop.run().await;
        eprintln!("bench-opcua-server: session ended: {ended}");
    });
    if !tokio::time::timeout(Duration::from_secs(30), session.wait_for_connection())
        .await
        .unwrap_or(false)
    {
        return Err(format!("{}: no session within 30 s", args.url).into());
    }
    Ok(session)
}

async fn namespace_index(session: &Session, uri: &str) -> Result<u16, Fail> {
    let read = session
        .read(
            &[ReadValueId::new_value(NodeId::from(
                VariableId::Server_NamespaceArray,
            ))],
            TimestampsToReturn::Neither,
            0.0,
        )
        .await?;
    if let Some(Variant::Array(array)) = read.first().and_then(|v| v.value.as_ref()) {
        for (i, v) in array.values.iter().enumerate() {
            if matches!(v, Variant::String(s) if s.as_ref() == uri) {
                return Ok(u16::try_from(i)?);
            }
        }
    }
    Err(format!("the server has no namespace {uri}").into())
}

/// Every Variable below `folder` (name, node): the time to the first
/// `target` references, and to all.
async fn browse(
    session: &Session,
    folder: NodeId,
    target: usize,
) -> Result<(Vec<(String, NodeId)>, Duration, Duration), Fail> {
    let start = Instant::now();
    let description = BrowseDescription {
        node_id: folder,
        browse_direction: BrowseDirection::Forward,
        reference_type_id: ReferenceTypeId::HierarchicalReferences.into(),
        include_subtypes: true,
        node_class_mask: NodeClassMask::VARIABLE.bits(),
        result_mask: BrowseResultMask::All as u32,
    };
    let mut result = session
        .browse(&[description], 1000, None)
        .await?
        .into_iter()
        .next()
        .ok_or("Browse: no result")?;
    let mut nodes = Vec::new();
    let mut at_target = None;
    let property: NodeId = ReferenceTypeId::HasProperty.into();
    loop {
        if !result.status_code.is_good() {
            return Err(format!("Browse: {}", result.status_code).into());
        }
        for r in result.references.take().unwrap_or_default() {
            if r.reference_type_id != property {
                nodes.push((r.browse_name.name.to_string(), r.node_id.node_id));
            }
        }
        if at_target.is_none() && nodes.len() >= target {
            at_target = Some(start.elapsed());
        }
        if result.continuation_point.is_null() {
            break;
        }
        result = session
            .browse_next(false, &[result.continuation_point.clone()])
            .await?
            .into_iter()
            .next()
            .ok_or("BrowseNext: no result")?;
    }
    let all = start.elapsed();
    Ok((nodes, at_target.unwrap_or(all), all))
}

async fn run(args: Args) -> Result<(), Fail> {
    let pki = tempfile::tempdir()?;
    let mut report = Report {
        label: args.label.clone(),
        lines: Vec::new(),
    };
    let session = connect(&args, pki.path()).await?;
    // A server just started may not have its namespace and variables yet
    // (plccoms: the PLC's table): ask again until they are all there.
    let deadline = Instant::now() + Duration::from_secs(args.wait);
    let ns = loop {
        match namespace_index(&session, &args.ns).await {
            Err(e) if Instant::now() < deadline => {
                eprintln!("bench-opcua-server: {e}; asking again");
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
            other => break other?,
        }
    };
    let folder = NodeId::new(ns, args.folder.clone());

    let items = args.subscriptions * args.per_subscription;
    let (mut nodes, browse_time, browse_all) = loop {
        let found = browse(&session, folder.clone(), args.browse).await?;
        if found.0.len() >= items.max(args.read) || Instant::now() > deadline {
            break found;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    };
    report.metric("browsed", nodes.len() as f64);
    report.metric("browse_nodes", args.browse.min(nodes.len()) as f64);
    report.metric("browse_s", browse_time.as_secs_f64());
    report.metric("browse_all_s", browse_all.as_secs_f64());

    // The same items from every server, whatever its browse order: the
    // changing variables first, then the others, each by name.
    nodes.sort_by(|(a, _), (b, _)| {
        (!a.starts_with(&args.changing), a).cmp(&(!b.starts_with(&args.changing), b))
    });
    let to_read: Vec<ReadValueId> = nodes
        .iter()
        .take(args.read)
        .map(|(_, n)| ReadValueId::new_value(n.clone()))
        .collect();
    if to_read.len() < args.read {
        return Err(format!("{} variables browsed, {} to read", nodes.len(), args.read).into());
    }
    // A server up is not yet a server with values: plccoms answers
    // BadNoCommunication until its link's first poll of the PLC (seconds
    // for 100,000 variables on a busy machine). Timed reads start once
    // every value is Good, within 60 s.
    let ready = Instant::now();
    loop {
        let values = session
            .read(&to_read, TimestampsToReturn::Both, 0.0)
            .await?;
        if values.len() == to_read.len() && values.iter().all(|v| v.status().is_good()) {
            break;
        }
        if ready.elapsed() > Duration::from_secs(60) {
            break; // the timed reads below say what is not Good
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    report.metric("values_ready_s", ready.elapsed().as_secs_f64());
    let mut reads = Vec::new();
    for _ in 0..3 {
        let start = Instant::now();
        let values = session
            .read(&to_read, TimestampsToReturn::Both, 0.0)
            .await?;
        reads.push(start.elapsed().as_secs_f64() * 1000.0);
        let bad = values.iter().filter(|v| !v.status().is_good()).count();
        if values.len() != to_read.len() || bad > 0 {
            let statuses: std::collections::BTreeSet<String> = values
                .iter()
                .filter(|v| !v.status().is_good())
                .map(|v| format!("{}", v.status()))
                .collect();
            return Err(format!(
                "Read of {}: {} values, {bad} not Good ({})",
                to_read.len(),
                values.len(),
                statuses.into_iter().collect::<Vec<_>>().join(", ")
            )
            .into());
        }
    }
    reads.sort_by(f64::total_cmp);
    report.metric("read_nodes", to_read.len() as f64);
    report.metric("read_ms", reads[1]);

    if nodes.len() < items {
        return Err(format!("{} variables browsed, {items} wanted", nodes.len()).into());
    }
    let changing: Vec<bool> = nodes[..items]
        .iter()
        .map(|(name, _)| name.starts_with(&args.changing))
        .collect();
    let changing_count = changing.iter().filter(|&&c| c).count() as u32;
    if changing_count == 0 {
        return Err(format!("no variable's name starts with {}", args.changing).into());
    }
    let stats = Arc::new(Mutex::new(Stats {
        phase: Phase::Warmup,
        changing,
        changing_count,
        last: vec![None; items],
        seen: HashMap::new(),
        before: None,
        notifications: 0,
        duplicates: 0,
        unexpected: 0,
        not_good: 0,
        overflow: 0,
        not_counter: 0,
        latencies_ms: Vec::new(),
        to_server_ms: Vec::new(),
        from_server_ms: Vec::new(),
        queued_ms: Vec::new(),
        wire_ms: Vec::new(),
    }));
    let start = Instant::now();
    let mut revised = f64::NAN;
    for s in 0..args.subscriptions {
        let stats = stats.clone();
        let id = session
            .create_subscription(
                Duration::from_millis(args.publish_ms),
                600,
                10,
                0,
                0,
                true,
                Notified(stats),
            )
            .await?;
        let first = s * args.per_subscription;
        for chunk_start in (first..first + args.per_subscription).step_by(1000) {
            let end = (chunk_start + 1000).min(first + args.per_subscription);
            let requests: Vec<MonitoredItemCreateRequest> = (chunk_start..end)
                .map(|i| MonitoredItemCreateRequest {
                    item_to_monitor: ReadValueId {
                        node_id: nodes[i].1.clone(),
                        attribute_id: AttributeId::Value as u32,
                        ..Default::default()
                    },
                    monitoring_mode: MonitoringMode::Reporting,
                    requested_parameters: MonitoringParameters {
                        client_handle: i as u32 + 1,
                        sampling_interval: 0.0,
                        queue_size: args.queue,
                        discard_oldest: true,
                        ..Default::default()
                    },
                })
                .collect();
            let created = session
                .create_monitored_items(id, TimestampsToReturn::Both, requests)
                .await?;
            if let Some(bad) = created.iter().find(|c| !c.result.status_code.is_good()) {
                return Err(format!("CreateMonitoredItems: {}", bad.result.status_code).into());
            }
            if let Some(c) = created.first() {
                revised = c.result.revised_sampling_interval;
            }
        }
    }
    report.metric("subscriptions", args.subscriptions as f64);
    report.metric("items", items as f64);
    report.metric("changing", f64::from(changing_count));
    report.metric("subscribe_s", start.elapsed().as_secs_f64());
    report.metric("revised_sampling_ms", revised);

    tokio::time::sleep(Duration::from_secs(args.warmup)).await;
    let window = Duration::from_secs(args.soak.map_or(args.duration, |m| m * 60));
    let rss = Arc::new(Mutex::new(Vec::new()));
    let sampler = args.server_pid.map(|pid| {
        let rss = rss.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tick.tick().await;
                if let Some(kib) = procfs::status_field(pid, "VmRSS") {
                    rss.lock().unwrap_or_else(|e| e.into_inner()).push(kib);
                }
            }
        })
    });
    let begun = Instant::now();
    stats.lock().unwrap_or_else(|e| e.into_inner()).phase = Phase::Measuring;
    tokio::time::sleep(window).await;
    let measured = begun.elapsed().as_secs_f64();
    stats.lock().unwrap_or_else(|e| e.into_inner()).phase = Phase::Draining;
    if let Some(s) = sampler {
        s.abort();
    }
    // Values first seen in the window may still be on their way: wait until
    // every changing item has passed the last of them (each item's values
    // arrive in order), or 60 s.
    let drain = Instant::now();
    while drain.elapsed() < Duration::from_secs(60) {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let st = stats.lock().unwrap_or_else(|e| e.into_inner());
        let Some(&top) = st.seen.keys().max() else {
            break;
        };
        let passed = st
            .changing
            .iter()
            .zip(&st.last)
            .all(|(&c, &last)| !c || last.is_some_and(|v| v > top));
        if passed {
            break;
        }
    }

    {
        let mut guard = stats.lock().unwrap_or_else(|e| e.into_inner());
        let st = &mut *guard;
        let expected = st.seen.len() as u64 * u64::from(st.changing_count);
        let received: u64 = st.seen.values().map(|&n| u64::from(n)).sum();
        let mut values: Vec<u64> = st.seen.keys().copied().collect();
        values.sort_unstable();
        let skipped: u64 = values
            .windows(2)
            .map(|w| w[1].saturating_sub(w[0]).saturating_sub(1))
            .sum();
        report.metric("notifications_per_s", st.notifications as f64 / measured);
        report.metric("drain_s", drain.elapsed().as_secs_f64());
        report.metric("counter_values", values.len() as f64);
        report.metric("lost", expected.saturating_sub(received) as f64);
        report.metric("source_skipped", skipped as f64);
        report.metric("duplicates", st.duplicates as f64);
        report.metric("unexpected", st.unexpected as f64);
        report.metric("not_good", st.not_good as f64);
        report.metric("overflow", st.overflow as f64);
        report.metric("not_counter", st.not_counter as f64);
        st.latencies_ms.sort_by(f64::total_cmp);
        report.metric("latency_min_ms", percentile(&st.latencies_ms, 0.0));
        report.metric("latency_p50_ms", percentile(&st.latencies_ms, 0.5));
        report.metric("latency_p99_ms", percentile(&st.latencies_ms, 0.99));
        report.metric("latency_max_ms", percentile(&st.latencies_ms, 1.0));
        for (name, list) in [
            ("to_server", &mut st.to_server_ms),
            ("from_server", &mut st.from_server_ms),
            ("queued", &mut st.queued_ms),
            ("wire", &mut st.wire_ms),
        ] {
            list.sort_by(f64::total_cmp);
            report.metric(&format!("{name}_p50_ms"), percentile(list, 0.5));
            report.metric(&format!("{name}_p99_ms"), percentile(list, 0.99));
        }
    }
    let rss = rss.lock().unwrap_or_else(|e| e.into_inner()).clone();
    if !rss.is_empty() {
        let mib = |k: u64| k as f64 / 1024.0;
        // Flat: the mean of the last fifth against the first fifth.
        let fifth = (rss.len() / 5).max(1);
        let mean = |s: &[u64]| s.iter().sum::<u64>() as f64 / s.len() as f64 / 1024.0;
        report.metric("rss_first_mib", mib(rss[0]));
        report.metric("rss_last_mib", mib(rss[rss.len() - 1]));
        report.metric("rss_max_mib", mib(rss.iter().copied().max().unwrap_or(0)));
        report.metric(
            "rss_growth_mib",
            mean(&rss[rss.len() - fifth..]) - mean(&rss[..fifth]),
        );
    }
    if let Some(out) = &args.out {
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(out)?;
        for line in &report.lines {
            writeln!(f, "{line}")?;
        }
    }
    // A server that does not answer CloseSession must not hold the run.
    let _ = tokio::time::timeout(Duration::from_secs(5), session.disconnect()).await;
    Ok(())
}

#[tokio::main]
async fn main() {
    let args = Args::parse();
    if let Err(e) = run(args).await {
        eprintln!("bench-opcua-server: {e}");
        std::process::exit(1);
    }
}
