//! The request/response scenarios: get, set, poll, list, connect, memory,
//! startup.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Args;
use plccoms_protocol::Area;
use tokio::sync::Barrier;

use crate::proxy::{self, Observer};
use crate::util::{proc_sample, Histogram, LineConn, ProcWindow, Report};
use crate::{check_loopback, Common};

fn secs(s: f64) -> Duration {
    Duration::from_secs_f64(s.clamp(0.0, 3600.0))
}

fn report_for(common: &Common, default: &str) -> Report {
    Report::new(
        common.label.as_deref().unwrap_or(default),
        common.out.clone(),
    )
}

/// `LIST:mask`: the names (upper case, markers stripped) and types.
pub async fn list_names(addr: SocketAddr, mask: &str) -> Result<Vec<(String, String)>, String> {
    let mut conn = LineConn::connect(addr)
        .await
        .map_err(|e| format!("{addr}: {e}"))?;
    conn.send(format!("LIST:{mask}\n").as_bytes())
        .await
        .map_err(|e| e.to_string())?;
    let mut names = Vec::new();
    loop {
        let line = conn.expect_line().await.map_err(|e| e.to_string())?;
        if line == b"LIST:" {
            break;
        }
        if let Some(rest) = line.strip_prefix(b"LIST:") {
            let text = String::from_utf8_lossy(rest);
            let (name, ty) = text.split_once(',').unwrap_or((&text, ""));
            names.push((
                name.to_string(),
                ty.trim_end_matches(['*', '~']).to_string(),
            ));
        }
    }
    Ok(names)
}

/// Waits until the server answers `GET:__PLC_RUN` with a value (its PLC link
/// is up), at most `limit`.
pub async fn wait_online(addr: SocketAddr, limit: Duration) -> Result<(), String> {
    let deadline = Instant::now() + limit;
    loop {
        if let Ok(mut conn) = LineConn::connect(addr).await {
            if let Ok(line) = conn.command("GET:__PLC_RUN", b"").await {
                if line.starts_with(b"GET:") {
                    return Ok(());
                }
            }
        }
        if Instant::now() > deadline {
            return Err(format!(
                "{addr}: the server did not reach its PLC within {limit:?}"
            ));
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Starts the EPSNET relay of `spec` (LISTEN,PLC) and waits until the server
/// polls through it.
async fn start_proxy(
    spec: &str,
    addr: SocketAddr,
    watched: Vec<proxy::Watched>,
) -> Result<Arc<Observer>, String> {
    let (listen, upstream) = proxy::parse_spec(spec)?;
    let obs = Observer::new(Instant::now(), watched);
    proxy::spawn(listen, upstream, obs.clone())
        .await
        .map_err(|e| format!("relay on {listen}: {e}"))?;
    wait_online(addr, Duration::from_secs(15)).await?;
    Ok(obs)
}

// ---------------------------------------------------------------- get

#[derive(Debug, Args)]
pub struct GetArgs {
    #[command(flatten)]
    pub common: Common,
    #[arg(long, default_value_t = 50)]
    pub clients: usize,
    /// Requests written at once per client; the next batch goes when all are
    /// answered (redis-benchmark -P semantics). Latency is per batch.
    #[arg(long, default_value_t = 1)]
    pub pipeline: usize,
    /// Variables to read: names matching this mask (from LIST).
    #[arg(long, default_value = "VAR_*")]
    pub mask: String,
    /// Or: a file with one name a line.
    #[arg(long)]
    pub names: Option<PathBuf>,
    /// Enable the variables first (served from the poll); else they are
    /// disabled and every GET reads the PLC.
    #[arg(long)]
    pub enabled: bool,
    #[arg(long, default_value_t = 5.0)]
    pub duration: f64,
    /// Not measured, at the start.
    #[arg(long, default_value_t = 1.0)]
    pub warmup: f64,
    /// EPSNET relay `LISTEN,PLC` (the server's section points at LISTEN):
    /// counts EPSNET datagrams and read requests during the measurement.
    #[arg(long)]
    pub proxy: Option<String>,
    /// The server is Redis: the same loop sends RESP `GET <key>` (keys
    /// `VAR_00000`.. set first, to values the size of plccoms' answers) and
    /// reads bulk replies, so both servers are driven by one generator.
    #[arg(long)]
    pub redis: bool,
    /// Keys set and read in Redis mode.
    #[arg(long, default_value_t = 10_000)]
    pub keys: usize,
}

/// Sets `VAR_00000`.. in Redis, pipelined; returns the names.
async fn redis_keys(addr: SocketAddr, keys: usize) -> Result<Vec<String>, String> {
    let mut conn = LineConn::connect(addr).await.map_err(|e| e.to_string())?;
    let names: Vec<String> = (0..keys.max(1)).map(|i| format!("VAR_{i:05}")).collect();
    for chunk in names.chunks(1000) {
        let mut batch = Vec::new();
        for name in chunk {
            // A value the length of a plccoms answer's value.
            resp(&mut batch, &["SET", name, "12345"]);
        }
        conn.send(&batch).await.map_err(|e| e.to_string())?;
        for _ in chunk {
            let line = conn.expect_line().await.map_err(|e| e.to_string())?;
            if line != b"+OK" {
                return Err(format!("SET: {}", String::from_utf8_lossy(line)));
            }
        }
    }
    Ok(names)
}

/// A RESP command: an array of bulk strings.
fn resp(out: &mut Vec<u8>, words: &[&str]) {
    out.extend_from_slice(format!("*{}\r\n", words.len()).as_bytes());
    for word in words {
        out.extend_from_slice(format!("${}\r\n{word}\r\n", word.len()).as_bytes());
    }
}

/// Reads one RESP reply to GET: `$<len>` and the value line, or `$-1`.
async fn redis_reply(conn: &mut LineConn) -> std::io::Result<bool> {
    let line = conn.expect_line().await?;
    if !line.starts_with(b"$") {
        return Ok(false);
    }
    if line == b"$-1" {
        return Ok(false);
    }
    conn.expect_line().await?;
    Ok(true)
}

pub async fn get(args: GetArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let obs = match &args.proxy {
        Some(spec) => Some(start_proxy(spec, addr, Vec::new()).await?),
        None => None,
    };
    let names: Vec<String> = match &args.names {
        None if args.redis => redis_keys(addr, args.keys).await?,
        Some(path) => std::fs::read_to_string(path)
            .map_err(|e| format!("{}: {e}", path.display()))?
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(str::to_string)
            .collect(),
        None => list_names(addr, &args.mask)
            .await?
            .into_iter()
            .map(|(n, _)| n)
            .collect(),
    };
    if names.is_empty() {
        return Err("no variables to GET".into());
    }
    let names = Arc::new(names);
    let clients = args.clients.clamp(1, 10_000);
    let pipeline = args.pipeline.clamp(1, 1024);
    let barrier = Arc::new(Barrier::new(clients + 1));
    let start_at = Arc::new(std::sync::OnceLock::<(Instant, Instant)>::new());
    let mut tasks = Vec::new();
    for c in 0..clients {
        let names = names.clone();
        let barrier = barrier.clone();
        let start_at = start_at.clone();
        let enabled = args.enabled;
        let mask = args.mask.clone();
        let by_name = args.names.is_some();
        let redis = args.redis;
        tasks.push(tokio::spawn(async move {
            let setup = async {
                let mut conn = LineConn::connect(addr).await?;
                if redis {
                    return Ok::<_, std::io::Error>(conn);
                }
                conn.command("SETCONF:diff,no", b"SETCONF:").await?;
                if !enabled {
                    conn.command("DI:*", b"WARNING:").await?;
                } else if by_name {
                    for name in names.iter() {
                        conn.command(&format!("EN:{name}"), b"WARNING:").await?;
                    }
                } else {
                    conn.command(&format!("EN:{mask}"), b"WARNING:").await?;
                }
                Ok::<_, std::io::Error>(conn)
            };
            let conn = setup.await;
            barrier.wait().await;
            let mut conn = conn?;
            let (measure_from, deadline) = *start_at.get().expect("set before the barrier");
            let mut hist = Histogram::default();
            let (mut ok, mut errors) = (0u64, 0u64);
            let mut i = c * 7919 % names.len();
            let mut batch = Vec::with_capacity(pipeline * 32);
            while Instant::now() < deadline {
                batch.clear();
                for _ in 0..pipeline {
                    if redis {
                        resp(&mut batch, &["GET", &names[i]]);
                    } else {
                        batch.extend_from_slice(b"GET:");
                        batch.extend_from_slice(names[i].as_bytes());
                        batch.push(b'\n');
                    }
                    i = (i + 1) % names.len();
                }
                let sent = Instant::now();
                conn.send(&batch).await?;
                let (mut good, mut bad) = (0, 0);
                for _ in 0..pipeline {
                    let answered = if redis {
                        redis_reply(&mut conn).await?
                    } else {
                        conn.expect_line().await?.starts_with(b"GET:")
                    };
                    if answered {
                        good += 1;
                    } else {
                        bad += 1;
                    }
                }
                if sent >= measure_from {
                    let took = sent.elapsed();
                    for _ in 0..pipeline {
                        hist.record(took);
                    }
                    ok += good;
                    errors += bad;
                }
            }
            Ok::<_, std::io::Error>((hist, ok, errors))
        }));
    }
    // Settle: enabled variables become current with the next poll.
    let settle = args.enabled && !args.redis;
    tokio::time::sleep(Duration::from_millis(if settle { 500 } else { 0 })).await;
    let t0 = Instant::now();
    let measure_from = t0 + secs(args.warmup);
    let deadline = measure_from + secs(args.duration);
    let _ = start_at.set((measure_from, deadline));
    barrier.wait().await;
    tokio::time::sleep_until(measure_from.into()).await;
    let server = ProcWindow::start(args.common.server_pid);
    let me = ProcWindow::start(Some(std::process::id()));
    let before = obs.as_ref().map(|o| o.snapshot());
    let mut hist = Histogram::default();
    let (mut ok, mut errors, mut failed) = (0u64, 0u64, 0u64);
    for task in tasks {
        match task.await {
            Ok(Ok((h, o, e))) => {
                hist.merge(&h);
                ok += o;
                errors += e;
            }
            Ok(Err(e)) => {
                failed += 1;
                eprintln!("loadgen: client failed: {e}");
            }
            Err(e) => return Err(e.to_string()),
        }
    }
    let wall = measure_from.elapsed().as_secs_f64();
    let mut report = report_for(&args.common, "get");
    report.metric("clients", clients as f64);
    report.metric("pipeline", pipeline as f64);
    report.metric("variables", names.len() as f64);
    report.metric("requests", ok as f64);
    report.metric("rps", ok as f64 / wall);
    report.metric("errors", errors as f64);
    report.metric("failed_clients", failed as f64);
    report.latency("latency", &hist);
    if let (Some(obs), Some((d0, r0, _, _))) = (&obs, before) {
        let (d1, r1, _, _) = obs.snapshot();
        let datagrams = d1 - d0;
        let reads = r1 - r0;
        report.metric("epsnet_datagrams", datagrams as f64);
        report.metric("epsnet_read_requests", reads as f64);
        report.metric(
            "gets_per_epsnet_datagram",
            (ok + errors) as f64 / datagrams.max(1) as f64,
        );
        report.metric(
            "gets_per_epsnet_read",
            (ok + errors) as f64 / reads.max(1) as f64,
        );
    }
    server.finish(&mut report, "server");
    me.finish(&mut report, "loadgen");
    report.finish().map_err(|e| e.to_string())
}

// ---------------------------------------------------------------- set

#[derive(Debug, Args)]
pub struct SetArgs {
    #[command(flatten)]
    pub common: Common,
    /// Clients doing SET -> DIFF round trips, one variable each.
    #[arg(long, default_value_t = 1)]
    pub clients: usize,
    /// Variables to SET (DINT), from LIST.
    #[arg(long, default_value = "SETV_*")]
    pub mask: String,
    /// Do not add the client that enables every variable (EN:*).
    #[arg(long)]
    pub no_poll_all: bool,
    #[arg(long, default_value_t = 5.0)]
    pub duration: f64,
    #[arg(long, default_value_t = 1.0)]
    pub warmup: f64,
    /// Pause between one client's round trips.
    #[arg(long, default_value_t = 0)]
    pub pause_ms: u64,
}

pub async fn set(args: SetArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let names = list_names(addr, &args.mask).await?;
    if names.is_empty() {
        return Err(format!("no variables match {}", args.mask));
    }
    let stop = Arc::new(AtomicBool::new(false));
    let drained = Arc::new(AtomicU64::new(0));
    let mut poll_all = None;
    if !args.no_poll_all {
        let mut conn = LineConn::connect(addr).await.map_err(|e| e.to_string())?;
        conn.command("EN:*", b"WARNING:")
            .await
            .map_err(|e| e.to_string())?;
        let stop = stop.clone();
        let drained = drained.clone();
        poll_all = Some(tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                match tokio::time::timeout(Duration::from_millis(200), conn.next_line()).await {
                    Ok(Ok(true)) => {
                        drained.fetch_add(1, Ordering::Relaxed);
                    }
                    Ok(_) => break,
                    Err(_) => {}
                }
            }
        }));
        // Let the initial DIFF burst of EN:* pass.
        tokio::time::sleep(Duration::from_secs(2)).await;
    }
    let clients = args.clients.clamp(1, 1000);
    let t0 = Instant::now();
    let measure_from = t0 + secs(args.warmup);
    let deadline = measure_from + secs(args.duration);
    let mut tasks = Vec::new();
    for c in 0..clients {
        let name = names[c % names.len()].0.clone();
        let pause = Duration::from_millis(args.pause_ms);
        tasks.push(tokio::spawn(async move {
            let mut conn = LineConn::connect(addr).await?;
            let mut hist = Histogram::default();
            let (mut errors, mut value) = (0u64, (c as i64 + 1) * 1_000_000);
            while Instant::now() < deadline {
                value += 1;
                let expect = format!("DIFF:{name},{value}");
                let sent = Instant::now();
                conn.send(format!("SET:{name},{value}\n").as_bytes())
                    .await?;
                loop {
                    let line = conn.expect_line().await?;
                    if line == expect.as_bytes() {
                        break;
                    }
                    if line.starts_with(b"ERROR:") {
                        errors += 1;
                        break;
                    }
                }
                if sent >= measure_from {
                    hist.record(sent.elapsed());
                }
                if !pause.is_zero() {
                    tokio::time::sleep(pause).await;
                }
            }
            Ok::<_, std::io::Error>((hist, errors))
        }));
    }
    tokio::time::sleep_until(measure_from.into()).await;
    let server = ProcWindow::start(args.common.server_pid);
    let mut hist = Histogram::default();
    let mut errors = 0;
    for task in tasks {
        match task.await.map_err(|e| e.to_string())? {
            Ok((h, e)) => {
                hist.merge(&h);
                errors += e;
            }
            Err(e) => return Err(format!("setter failed: {e}")),
        }
    }
    let wall = measure_from.elapsed().as_secs_f64();
    stop.store(true, Ordering::Relaxed);
    if let Some(task) = poll_all {
        let _ = task.await;
    }
    let mut report = report_for(&args.common, "set");
    report.metric("clients", clients as f64);
    report.metric("poll_all", if args.no_poll_all { 0.0 } else { 1.0 });
    report.metric("round_trips_per_s", hist.count() as f64 / wall);
    report.metric("errors", errors as f64);
    report.latency("set_diff", &hist);
    server.finish(&mut report, "server");
    report.finish().map_err(|e| e.to_string())
}

// ---------------------------------------------------------------- poll

#[derive(Debug, Args)]
pub struct PollArgs {
    #[command(flatten)]
    pub common: Common,
    /// EPSNET relay `LISTEN,PLC`; the server's section points at LISTEN.
    #[arg(long)]
    pub proxy: String,
    /// The project's user public file (for the minimum request count).
    #[arg(long = "pub")]
    pub pubfile: PathBuf,
    /// The server's COMM_LOOP_DELAY.
    #[arg(long, default_value_t = 100)]
    pub period_ms: u64,
    #[arg(long, default_value_t = 10.0)]
    pub duration: f64,
}

/// Fewest block reads of at most `max` bytes that cover every range: greedy
/// from the lowest uncovered byte, exact at byte granularity.
pub fn min_reads(mut ranges: Vec<(Area, u32, u32)>, max: u32) -> u64 {
    ranges.sort_unstable();
    let mut count = 0;
    let mut covered: Option<(Area, u64)> = None;
    for (area, offset, len) in ranges {
        let end = u64::from(offset) + u64::from(len);
        let mut at = u64::from(offset);
        if let Some((a, c)) = covered {
            if a == area {
                if end <= c {
                    continue;
                }
                at = at.max(c);
            }
        }
        while at < end {
            count += 1;
            at += u64::from(max);
        }
        covered = Some((area, at));
    }
    count
}

pub async fn poll(args: PollArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let user = plccoms_plc::pubfile::load(&args.pubfile)
        .map_err(|e| format!("{}: {e}", args.pubfile.display()))?;
    let fixed = plccoms_plc::pubfile::parse(plcsim::FIXED_PUB);
    let ranges: Vec<(Area, u32, u32)> = user
        .vars
        .iter()
        .chain(&fixed.vars)
        .map(|def| (def.var.area, def.var.offset, def.var.ty.size() as u32))
        .collect();
    let minimum = min_reads(ranges, plccoms_plc::epsnet::service::MAX_READ);
    let obs = start_proxy(&args.proxy, addr, Vec::new()).await?;
    let mut conn = LineConn::connect(addr).await.map_err(|e| e.to_string())?;
    conn.command("SETCONF:diff,no", b"SETCONF:")
        .await
        .map_err(|e| e.to_string())?;
    let enabled = conn
        .command("EN:*", b"WARNING:")
        .await
        .map_err(|e| e.to_string())?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let server = ProcWindow::start(args.common.server_pid);
    let from = obs.snapshot().3.len();
    tokio::time::sleep(secs(args.duration)).await;
    let bursts = obs.snapshot().3;
    // The last burst may be in progress.
    let bursts = &bursts[from..bursts.len().saturating_sub(1)];
    if bursts.len() < 3 {
        return Err("fewer than 3 poll cycles seen".into());
    }
    let period_us = args.period_ms * 1000;
    let mut jitter = Histogram::default();
    for pair in bursts.windows(2) {
        let gap_us = (pair[1].start_ns - pair[0].start_ns) / 1000;
        jitter.record_us(gap_us.abs_diff(period_us));
    }
    let mut duration = Histogram::default();
    let mut reads = Histogram::default();
    let mut datagrams = 0u64;
    let mut total_reads = 0u64;
    for b in bursts {
        duration.record_us((b.end_ns - b.start_ns) / 1000);
        reads.record_us(u64::from(b.reads));
        total_reads += u64::from(b.reads);
        datagrams += u64::from(b.datagrams);
    }
    let mean_reads = total_reads as f64 / bursts.len() as f64;
    let mut report = report_for(&args.common, "poll");
    report.text("enabled", &String::from_utf8_lossy(&enabled));
    report.metric("variables", (user.vars.len() + fixed.vars.len()) as f64);
    report.metric("cycles", bursts.len() as f64);
    report.metric("min_reads_per_cycle", minimum as f64);
    report.metric("reads_per_cycle_mean", mean_reads);
    report.metric("reads_per_cycle_max", reads.max_us() as f64);
    report.metric("reads_ratio_to_min", mean_reads / minimum.max(1) as f64);
    report.metric(
        "datagrams_per_cycle_mean",
        datagrams as f64 / bursts.len() as f64,
    );
    report.latency("start_jitter", &jitter);
    report.latency("poll_duration", &duration);
    server.finish(&mut report, "server");
    report.finish().map_err(|e| e.to_string())
}

// ---------------------------------------------------------------- list

#[derive(Debug, Args)]
pub struct ListArgs {
    #[command(flatten)]
    pub common: Common,
    #[arg(long, default_value_t = 10)]
    pub runs: usize,
    #[arg(long, default_value = "")]
    pub mask: String,
}

pub async fn list(args: ListArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let mut conn = LineConn::connect(addr).await.map_err(|e| e.to_string())?;
    let server = ProcWindow::start(args.common.server_pid);
    let mut hist = Histogram::default();
    let (mut lines, mut bytes) = (0u64, 0u64);
    let mut first = 0.0;
    for run in 0..args.runs.clamp(1, 1000) {
        let before = conn.bytes_read;
        let sent = Instant::now();
        conn.send(format!("LIST:{}\n", args.mask).as_bytes())
            .await
            .map_err(|e| e.to_string())?;
        let mut n = 0u64;
        loop {
            let line = tokio::time::timeout(Duration::from_secs(30), conn.expect_line())
                .await
                .map_err(|_| "LIST took over 30 s".to_string())?
                .map_err(|e| e.to_string())?;
            if line == b"LIST:" {
                break;
            }
            n += 1;
        }
        let took = sent.elapsed();
        if run == 0 {
            first = took.as_secs_f64() * 1000.0;
        }
        hist.record(took);
        lines = n;
        bytes = conn.bytes_read - before;
    }
    let mut report = report_for(&args.common, "list");
    report.metric("lines", lines as f64);
    report.metric("bytes", bytes as f64);
    report.metric("first_ms", first);
    report.latency("list", &hist);
    server.finish(&mut report, "server");
    report.finish().map_err(|e| e.to_string())
}

// ---------------------------------------------------------------- connect

#[derive(Debug, Args)]
pub struct ConnectArgs {
    #[command(flatten)]
    pub common: Common,
    /// Connect/disconnect cycles in total.
    #[arg(long, default_value_t = 10_000)]
    pub cycles: u64,
    /// Cycles in progress at once.
    #[arg(long, default_value_t = 50)]
    pub concurrency: usize,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 60.0)]
    pub max_seconds: f64,
}

pub async fn connect(args: ConnectArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let next = Arc::new(AtomicU64::new(0));
    let start = Instant::now();
    let deadline = start + secs(args.max_seconds);
    let server = ProcWindow::start(args.common.server_pid);
    let mut tasks = Vec::new();
    for _ in 0..args.concurrency.clamp(1, 1000) {
        let next = next.clone();
        let cycles = args.cycles;
        tasks.push(tokio::spawn(async move {
            let mut hist = Histogram::default();
            let (mut done, mut failed) = (0u64, 0u64);
            while next.fetch_add(1, Ordering::Relaxed) < cycles && Instant::now() < deadline {
                let t = Instant::now();
                let attempt = async {
                    let mut conn = LineConn::connect(addr).await?;
                    let line = conn.command("GET:__PLC_RUN", b"").await?;
                    Ok::<bool, std::io::Error>(line.starts_with(b"GET:"))
                };
                match tokio::time::timeout(Duration::from_secs(5), attempt).await {
                    Ok(Ok(true)) => {
                        hist.record(t.elapsed());
                        done += 1;
                    }
                    _ => failed += 1,
                }
            }
            (hist, done, failed)
        }));
    }
    let mut hist = Histogram::default();
    let (mut done, mut failed) = (0, 0);
    for task in tasks {
        let (h, d, f) = task.await.map_err(|e| e.to_string())?;
        hist.merge(&h);
        done += d;
        failed += f;
    }
    let wall = start.elapsed().as_secs_f64();
    let mut report = report_for(&args.common, "connect");
    report.metric("cycles", done as f64);
    report.metric("failures", failed as f64);
    report.metric("cycles_per_s", done as f64 / wall);
    report.latency("cycle", &hist);
    server.finish(&mut report, "server");
    report.finish().map_err(|e| e.to_string())
}

// ---------------------------------------------------------------- memory

#[derive(Debug, Args)]
pub struct MemoryArgs {
    #[command(flatten)]
    pub common: Common,
    /// Clients that enable every variable (EN:*) and read their DIFFs.
    #[arg(long, default_value_t = 100)]
    pub active: usize,
    /// Total clients after adding idle ones (connected, silent).
    #[arg(long, default_value_t = 1000)]
    pub total: usize,
    /// Wait after each step.
    #[arg(long, default_value_t = 3.0)]
    pub settle: f64,
}

pub async fn memory(args: MemoryArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let pid = args.common.server_pid.ok_or("memory needs --server-pid")?;
    let base = proc_sample(pid).ok_or("cannot read /proc of the server")?;
    let stop = Arc::new(AtomicBool::new(false));
    let mut keep = Vec::new();
    for _ in 0..args.active.min(2000) {
        let mut conn = LineConn::connect(addr).await.map_err(|e| e.to_string())?;
        conn.command("EN:*", b"WARNING:")
            .await
            .map_err(|e| e.to_string())?;
        let stop = stop.clone();
        keep.push(tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                match tokio::time::timeout(Duration::from_millis(200), conn.next_line()).await {
                    Ok(Ok(true)) | Err(_) => {}
                    Ok(_) => break,
                }
            }
        }));
    }
    tokio::time::sleep(secs(args.settle)).await;
    let active = proc_sample(pid).ok_or("server gone")?;
    let mut idle = Vec::new();
    for _ in args.active..args.total.min(2000) {
        idle.push(
            LineConn::connect(addr)
                .await
                .map_err(|e| format!("idle client: {e}"))?,
        );
    }
    // Make sure every idle session is set up: the last one answers.
    if let Some(conn) = idle.last_mut() {
        conn.command("GET:__PLC_RUN", b"GET:")
            .await
            .map_err(|e| e.to_string())?;
    }
    tokio::time::sleep(secs(args.settle)).await;
    let full = proc_sample(pid).ok_or("server gone")?;
    stop.store(true, Ordering::Relaxed);
    let extra = idle.len().max(1) as f64;
    let mut report = report_for(&args.common, "memory");
    report.metric("rss_start_mib", base.rss_kib as f64 / 1024.0);
    report.metric("active_clients", args.active as f64);
    report.metric("rss_active_mib", active.rss_kib as f64 / 1024.0);
    report.metric("total_clients", (args.active + idle.len()) as f64);
    report.metric("rss_total_mib", full.rss_kib as f64 / 1024.0);
    report.metric("peak_rss_mib", full.hwm_kib as f64 / 1024.0);
    report.metric(
        "kib_per_idle_client",
        (full.rss_kib as f64 - active.rss_kib as f64) / extra,
    );
    drop(idle);
    for task in keep {
        let _ = task.await;
    }
    report.finish().map_err(|e| e.to_string())
}

// ---------------------------------------------------------------- startup

#[derive(Debug, Args)]
pub struct StartupArgs {
    #[command(flatten)]
    pub common: Common,
    #[arg(long, default_value_t = 10)]
    pub runs: usize,
    /// The server command line, after `--`.
    #[arg(last = true, required = true)]
    pub command: Vec<String>,
}

pub async fn startup(args: StartupArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let mut hist = Histogram::default();
    let mut rss = 0.0f64;
    for _ in 0..args.runs.clamp(1, 100) {
        if tokio::net::TcpStream::connect(addr).await.is_ok() {
            return Err(format!("{addr} already accepts: stop the other server"));
        }
        let t0 = Instant::now();
        let mut child = std::process::Command::new(&args.command[0])
            .args(&args.command[1..])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .map_err(|e| format!("{}: {e}", args.command[0]))?;
        let mut up = None;
        while t0.elapsed() < Duration::from_secs(10) {
            if tokio::net::TcpStream::connect(addr).await.is_ok() {
                up = Some(t0.elapsed());
                break;
            }
            if let Ok(Some(status)) = child.try_wait() {
                return Err(format!("the server exited: {status}"));
            }
            tokio::time::sleep(Duration::from_micros(500)).await;
        }
        if let Some(sample) = proc_sample(child.id()) {
            rss = rss.max(sample.hwm_kib as f64 / 1024.0);
        }
        let _ = child.kill();
        let _ = child.wait();
        hist.record(up.ok_or("the server did not listen within 10 s")?);
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let mut report = report_for(&args.common, "startup");
    report.latency("listening", &hist);
    report.metric("peak_rss_at_listen_mib", rss);
    report.finish().map_err(|e| e.to_string())
}
