//! The `web` scenario: browsers' worth of live-value streams on the web page
//! (`/api/sections/{S}/live`, server-sent events) while telnet clients GET
//! at a steady pace. Run once with `--streams 0` and once with the streams:
//! the difference in server CPU is what the page costs, and the GET
//! latencies of the two runs tell whether the telnet clients noticed.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Args;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::scenarios::list_names;
use crate::util::{Histogram, LineConn, ProcWindow, Report};
use crate::{check_loopback, Common};

#[derive(Debug, Args)]
pub struct WebArgs {
    #[command(flatten)]
    pub common: Common,
    /// The web page's address (HTTP_PORT).
    #[arg(long, default_value = "127.0.0.1:5080")]
    pub http: SocketAddr,
    #[arg(long, default_value = "Bench")]
    pub section: String,
    /// Live-value streams, one per browser (0: the baseline run).
    #[arg(long, default_value_t = 50)]
    pub streams: usize,
    /// Masks each stream shows.
    #[arg(long, default_value = "ANIM_000*,ANIM_001*")]
    pub stream_vars: String,
    /// Telnet clients sending GETs, each at `--get-rate` per second.
    #[arg(long, default_value_t = 10)]
    pub get_clients: usize,
    #[arg(long, default_value_t = 100.0)]
    pub get_rate: f64,
    /// Variables the GET clients enable and read.
    #[arg(long, default_value = "VAR_000*")]
    pub get_mask: String,
    #[arg(long, default_value_t = 5.0)]
    pub duration: f64,
    /// Not measured, at the start (streams connect, polls settle).
    #[arg(long, default_value_t = 2.0)]
    pub warmup: f64,
}

/// What the streams received: events and bytes, in the measured window.
#[derive(Default)]
struct Received {
    events: AtomicU64,
    bytes: AtomicU64,
    /// `"good"` values in the events (one per variable and event).
    values: AtomicU64,
    failed: AtomicU64,
}

pub async fn run(args: WebArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    check_loopback(args.http)?;
    let names: Vec<String> = list_names(addr, &args.get_mask)
        .await?
        .into_iter()
        .map(|(n, _)| n)
        .collect();
    if names.is_empty() {
        return Err(format!("no variables match {}", args.get_mask));
    }
    let names = Arc::new(names);
    let t0 = Instant::now();
    let measure_from = t0 + Duration::from_secs_f64(args.warmup.clamp(0.0, 600.0));
    let deadline = measure_from + Duration::from_secs_f64(args.duration.clamp(0.1, 3600.0));

    let received = Arc::new(Received::default());
    let path = format!(
        "/api/sections/{}/live?vars={}",
        args.section,
        args.stream_vars.replace('*', "%2A")
    );
    let mut streams = Vec::new();
    for _ in 0..args.streams.min(10_000) {
        let received = received.clone();
        let (http, path) = (args.http, path.clone());
        streams.push(tokio::spawn(async move {
            if let Err(e) = stream(http, &path, measure_from, deadline, &received).await {
                received.failed.fetch_add(1, Ordering::Relaxed);
                eprintln!("loadgen: stream failed: {e}");
            }
        }));
    }

    let mut getters = Vec::new();
    for c in 0..args.get_clients.clamp(1, 1000) {
        let names = names.clone();
        let (mask, rate) = (args.get_mask.clone(), args.get_rate.clamp(0.1, 100_000.0));
        getters.push(tokio::spawn(async move {
            let mut conn = LineConn::connect(addr).await?;
            conn.command("SETCONF:diff,no", b"SETCONF:").await?;
            conn.command(&format!("EN:{mask}"), b"WARNING:").await?;
            let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / rate));
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            let mut hist = Histogram::default();
            let mut i = c * 7919 % names.len();
            while Instant::now() < deadline {
                tick.tick().await;
                let request = format!("GET:{}\n", names[i]);
                i = (i + 1) % names.len();
                let sent = Instant::now();
                conn.send(request.as_bytes()).await?;
                let ok = conn.expect_line().await?.starts_with(b"GET:");
                if sent >= measure_from && ok {
                    hist.record(sent.elapsed());
                }
            }
            Ok::<_, std::io::Error>(hist)
        }));
    }

    tokio::time::sleep_until(measure_from.into()).await;
    let server = ProcWindow::start(args.common.server_pid);
    let me = ProcWindow::start(Some(std::process::id()));
    let mut hist = Histogram::default();
    let mut get_failed = 0;
    for getter in getters {
        match getter.await {
            Ok(Ok(h)) => hist.merge(&h),
            Ok(Err(e)) => {
                get_failed += 1;
                eprintln!("loadgen: GET client failed: {e}");
            }
            Err(e) => return Err(e.to_string()),
        }
    }
    let wall = measure_from.elapsed().as_secs_f64();
    let mut report = Report::new(
        args.common.label.as_deref().unwrap_or("web"),
        args.common.out.clone(),
    );
    server.finish(&mut report, "server");
    me.finish(&mut report, "loadgen");
    for stream in streams {
        let _ = stream.await;
    }
    let events = received.events.load(Ordering::Relaxed) as f64;
    report.metric("streams", args.streams as f64);
    report.metric(
        "failed_streams",
        received.failed.load(Ordering::Relaxed) as f64,
    );
    report.metric("events_per_s", events / wall);
    report.metric(
        "events_per_stream_per_s",
        events / wall / args.streams.max(1) as f64,
    );
    report.metric(
        "values_per_event",
        received.values.load(Ordering::Relaxed) as f64 / events.max(1.0),
    );
    report.metric(
        "event_kib_per_s",
        received.bytes.load(Ordering::Relaxed) as f64 / 1024.0 / wall,
    );
    report.metric("get_clients", args.get_clients as f64);
    report.metric("get_failed_clients", get_failed as f64);
    report.metric("get_rps", hist.count() as f64 / wall);
    report.latency("get", &hist);
    report.finish().map_err(|e| e.to_string())
}

/// One browser's stream: reads events until `deadline`, counting those that
/// end inside the measured window.
async fn stream(
    http: SocketAddr,
    path: &str,
    measure_from: Instant,
    deadline: Instant,
    received: &Received,
) -> std::io::Result<()> {
    let mut socket = TcpStream::connect(http).await?;
    socket.set_nodelay(true)?;
    let request =
        format!("GET {path} HTTP/1.1\r\nHost: {http}\r\nAccept: text/event-stream\r\n\r\n");
    socket.write_all(request.as_bytes()).await?;
    let mut buf = vec![0u8; 64 * 1024];
    let mut head_seen = false;
    // The tail of the previous read, so a marker split across reads counts
    // (once).
    let mut carry: Vec<u8> = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Ok(());
        }
        let n = match tokio::time::timeout(left, socket.read(&mut buf)).await {
            Ok(read) => read?,
            Err(_) => return Ok(()),
        };
        if n == 0 {
            return Err(std::io::Error::other("the server closed the stream"));
        }
        let chunk = &buf[..n];
        if !head_seen {
            if !chunk.starts_with(b"HTTP/1.1 200") {
                return Err(std::io::Error::other(format!(
                    "refused: {}",
                    String::from_utf8_lossy(&chunk[..chunk.len().min(200)])
                )));
            }
            head_seen = true;
        }
        let old = carry.len();
        carry.extend_from_slice(chunk);
        let events = count_new(&carry, old, b"event: values");
        let values = count_new(&carry, old, b"\"good\"");
        carry.drain(..carry.len().saturating_sub(CARRY));
        if Instant::now() >= measure_from {
            received.events.fetch_add(events, Ordering::Relaxed);
            received.values.fetch_add(values, Ordering::Relaxed);
            received.bytes.fetch_add(n as u64, Ordering::Relaxed);
        }
    }
}

/// Bytes kept from one read to the next: one less than the longest marker.
const CARRY: usize = 12;

/// Occurrences of `needle` in `data` that end after `old` (the bytes
/// before `old` were counted with the previous read).
fn count_new(data: &[u8], old: usize, needle: &[u8]) -> u64 {
    let first = (old + 1).saturating_sub(needle.len());
    data.get(first..)
        .unwrap_or_default()
        .windows(needle.len())
        .filter(|w| w == &needle)
        .count() as u64
}
