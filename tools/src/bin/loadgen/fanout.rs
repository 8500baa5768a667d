//! DIFF fan-out: N clients send `EN:*` over the project while the simulated
//! PLC animates M variables every cycle (plcsim `--animate 'ANIM_*'`: each
//! animated UDINT holds the PLC cycle counter, so every value is new).
//!
//! Ground truth comes from the EPSNET relay (see `proxy`): it decodes the
//! poll's read answers, so it knows, per animated variable, which value the
//! server read in which poll cycle and when that cycle's last answer went to
//! the server. A client's `DIFF:ANIM_x,v` is matched to the cycle that first
//! read `v`, and its latency is receipt time minus that cycle's completion
//! (one clock: relay and clients live in this process).
//!
//! Counted in the measurement window (cycles starting within it): every
//! change the relay saw must reach every client exactly once. Missing DIFFs
//! (including values a slow client skipped), duplicates and values no cycle
//! read are reported separately.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Args;

use crate::proxy::{self, Observer, Watched};
use crate::util::{now_ns, Histogram, LineConn, ProcWindow, Report};
use crate::{check_loopback, Common};

#[derive(Debug, Args)]
pub struct FanoutArgs {
    #[command(flatten)]
    pub common: Common,
    #[arg(long, default_value_t = 1000)]
    pub clients: usize,
    /// EPSNET relay `LISTEN,PLC`; the server's section points at LISTEN.
    #[arg(long)]
    pub proxy: String,
    /// The project's user public file (names, addresses).
    #[arg(long = "pub")]
    pub pubfile: PathBuf,
    /// The variables the PLC animates (integers holding the cycle counter).
    #[arg(long, default_value = "ANIM_*")]
    pub animated: String,
    /// Measurement window.
    #[arg(long, default_value_t = 10.0)]
    pub duration: f64,
    /// Longest wait for every client to receive its initial values.
    #[arg(long, default_value_t = 90.0)]
    pub settle_max: f64,
    /// Mark the measurement window for a server built with the
    /// fanout-trace feature: SIGUSR1 to --server-pid at its start, SIGUSR2
    /// at its end.
    #[arg(long)]
    pub trace_window: bool,
    /// Wait after the window for late DIFFs.
    #[arg(long, default_value_t = 2.0)]
    pub grace: f64,
    /// The server's COMM_LOOP_DELAY (for the cycle start jitter).
    #[arg(long, default_value_t = 100)]
    pub period_ms: u64,
    /// Clients connecting at once.
    #[arg(long, default_value_t = 50)]
    pub connect_batch: usize,
}

/// FNV-1a: names are short; SipHash would dominate the client's per-line cost.
#[derive(Default)]
struct Fnv(u64);

impl Hasher for Fnv {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        let mut h = if self.0 == 0 {
            0xcbf2_9ce4_8422_2325
        } else {
            self.0
        };
        for &b in bytes {
            h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
        self.0 = h;
    }
}

type Names = HashMap<Box<[u8]>, (u32, u32), BuildHasherDefault<Fnv>>;

struct Shared {
    obs: Arc<Observer>,
    /// Upper-case name -> (variable index, animated index or u32::MAX).
    names: Names,
    user_vars: usize,
    animated: usize,
    t0: AtomicU64,
    t1: AtomicU64,
    stop: AtomicBool,
    settled: AtomicUsize,
}

#[derive(Default)]
struct ClientResult {
    hist: Histogram,
    received: u64,
    duplicates: u64,
    unknown: u64,
    lines: u64,
    settled: bool,
}

async fn client(shared: Arc<Shared>, mut conn: LineConn) -> std::io::Result<ClientResult> {
    let mut r = ClientResult::default();
    let mut seen = vec![0u64; shared.user_vars.div_ceil(64) + 1];
    let mut seen_count = 0usize;
    let mut last = vec![u64::MAX; shared.animated];
    conn.read_timeout = Some(Duration::from_millis(200));
    let epoch = shared.obs.epoch;
    while !shared.stop.load(Ordering::Relaxed) {
        let more = match conn.next_line().await {
            Ok(more) => more,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => continue,
            Err(e) => return Err(e),
        };
        if !more {
            break;
        }
        let line = conn.line();
        r.lines += 1;
        let Some(rest) = line.strip_prefix(b"DIFF:") else {
            continue;
        };
        let Some(comma) = rest.iter().position(|&b| b == b',') else {
            continue;
        };
        let Some(&(id, anim)) = shared.names.get(&rest[..comma]) else {
            continue;
        };
        if !r.settled && (id as usize) < shared.user_vars {
            let (w, bit) = (id as usize / 64, 1u64 << (id % 64));
            if seen[w] & bit == 0 {
                seen[w] |= bit;
                seen_count += 1;
                if seen_count == shared.user_vars {
                    r.settled = true;
                    shared.settled.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
        if anim == u32::MAX {
            continue;
        }
        let value = rest[comma + 1..].iter().try_fold(0u64, |acc, &b| {
            b.is_ascii_digit()
                .then(|| acc.wrapping_mul(10).wrapping_add(u64::from(b - b'0')))
        });
        let Some(value) = value else {
            r.unknown += 1;
            continue;
        };
        // Receipt: when the read that brought this line returned.
        let now = conn.read_at.saturating_duration_since(epoch).as_nanos() as u64;
        let t0 = shared.t0.load(Ordering::Relaxed);
        let a = anim as usize;
        if last[a] == value && now >= t0 {
            r.duplicates += 1;
        }
        last[a] = value;
        match shared.obs.lookup(a, value) {
            Some((_, start, end)) if start >= t0 && start <= shared.t1.load(Ordering::Relaxed) => {
                r.received += 1;
                r.hist.record_us(now.saturating_sub(end) / 1000);
            }
            Some(_) => {}
            None if now >= t0 => r.unknown += 1,
            None => {}
        }
    }
    Ok(r)
}

pub async fn run(args: FanoutArgs) -> Result<(), String> {
    let addr = args.common.addr;
    check_loopback(addr)?;
    let file = plccoms_plc::pubfile::load(&args.pubfile)
        .map_err(|e| format!("{}: {e}", args.pubfile.display()))?;
    let mut names = Names::default();
    let mut watched = Vec::new();
    for (i, v) in file.vars.iter().map(|def| &def.var).enumerate() {
        let upper = plccoms_protocol::cp1250::to_upper(&v.name);
        let anim = if plcsim::program::mask_matches(args.animated.as_bytes(), &v.name)
            && !v.ty.is_string()
            && v.ty.size() >= 2
        {
            watched.push(Watched {
                area: v.area,
                offset: v.offset,
                size: v.ty.size() as u32,
            });
            (watched.len() - 1) as u32
        } else {
            u32::MAX
        };
        names.insert(upper.into_boxed_slice(), (i as u32, anim));
    }
    if watched.is_empty() {
        return Err(format!("no integer variable matches {}", args.animated));
    }
    let animated = watched.len();
    let obs = {
        let (listen, upstream) = proxy::parse_spec(&args.proxy)?;
        let obs = Observer::new(Instant::now(), watched);
        proxy::spawn(listen, upstream, obs.clone())
            .await
            .map_err(|e| format!("relay on {listen}: {e}"))?;
        crate::scenarios::wait_online(addr, Duration::from_secs(15)).await?;
        obs
    };
    let shared = Arc::new(Shared {
        obs: obs.clone(),
        names,
        user_vars: file.vars.len(),
        animated,
        t0: AtomicU64::new(u64::MAX),
        t1: AtomicU64::new(u64::MAX),
        stop: AtomicBool::new(false),
        settled: AtomicUsize::new(0),
    });
    let clients = args.clients.clamp(1, 5000);
    let started = Instant::now();
    let mut tasks = Vec::with_capacity(clients);
    let mut connect_failures = 0;
    let mut pending = Vec::new();
    for c in 0..clients {
        pending.push(tokio::spawn(async move {
            let mut conn = LineConn::connect(addr).await?;
            conn.send(b"EN:*\n").await?;
            Ok::<_, std::io::Error>(conn)
        }));
        if pending.len() >= args.connect_batch.max(1) || c + 1 == clients {
            for p in pending.drain(..) {
                match p.await {
                    Ok(Ok(conn)) => tasks.push(tokio::spawn(client(shared.clone(), conn))),
                    _ => connect_failures += 1,
                }
            }
        }
    }
    let connected = tasks.len();
    let settle_deadline = started + Duration::from_secs_f64(args.settle_max.clamp(1.0, 600.0));
    while shared.settled.load(Ordering::Relaxed) < connected && Instant::now() < settle_deadline {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let settled = shared.settled.load(Ordering::Relaxed);
    let settle_s = started.elapsed().as_secs_f64();
    // One more cycle, so the window starts with every client caught up.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let server = ProcWindow::start(args.common.server_pid);
    let me = ProcWindow::start(Some(std::process::id()));
    let signal_server = |signal| {
        if let (true, Some(pid)) = (args.trace_window, args.common.server_pid) {
            // SAFETY: kill(2) with a pid and a signal number; no memory shared.
            unsafe { libc::kill(pid as libc::pid_t, signal) };
        }
    };
    let t0 = now_ns(obs.epoch);
    shared.t0.store(t0, Ordering::Relaxed);
    signal_server(libc::SIGUSR1);
    tokio::time::sleep(Duration::from_secs_f64(args.duration.clamp(0.5, 600.0))).await;
    let t1 = now_ns(obs.epoch);
    shared.t1.store(t1, Ordering::Relaxed);
    signal_server(libc::SIGUSR2);
    let mut report = Report::new(
        args.common.label.as_deref().unwrap_or("fanout"),
        args.common.out.clone(),
    );
    // CPU over the window only (the grace period is mostly idle).
    server.finish(&mut report, "server");
    me.finish(&mut report, "loadgen");
    tokio::time::sleep(Duration::from_secs_f64(args.grace.clamp(0.0, 60.0))).await;
    shared.stop.store(true, Ordering::Relaxed);
    let bursts = obs.snapshot().3;
    let window: Vec<_> = bursts
        .iter()
        .filter(|b| b.start_ns >= t0 && b.start_ns <= t1)
        .collect();
    let expected_per_client: u64 = window.iter().map(|b| u64::from(b.changes)).sum();
    let mut hist = Histogram::default();
    let (mut received, mut duplicates, mut unknown, mut lines) = (0u64, 0u64, 0u64, 0u64);
    let (mut min_received, mut failed) = (u64::MAX, 0);
    for task in tasks {
        match task.await {
            Ok(Ok(r)) => {
                hist.merge(&r.hist);
                received += r.received;
                duplicates += r.duplicates;
                unknown += r.unknown;
                lines += r.lines;
                min_received = min_received.min(r.received);
            }
            _ => failed += 1,
        }
    }
    let expected = expected_per_client * (connected - failed) as u64;
    let window_s = (t1 - t0) as f64 / 1e9;
    report.metric("clients", connected as f64);
    report.metric("connect_failures", connect_failures as f64);
    report.metric("client_failures", failed as f64);
    report.metric("settled_clients", settled as f64);
    report.metric("settle_s", settle_s);
    report.metric("variables", file.vars.len() as f64);
    report.metric("animated", animated as f64);
    report.metric("cycles", window.len() as f64);
    report.metric(
        "changes_per_cycle",
        expected_per_client as f64 / window.len().max(1) as f64,
    );
    report.metric("expected_diffs", expected as f64);
    report.metric("received_diffs", received as f64);
    report.metric("missing_diffs", expected.saturating_sub(received) as f64);
    report.metric(
        "min_received_per_client",
        if min_received == u64::MAX {
            0.0
        } else {
            min_received as f64
        },
    );
    report.metric("duplicate_diffs", duplicates as f64);
    report.metric("unmatched_diffs", unknown as f64);
    report.metric("diffs_per_s", received as f64 / window_s);
    report.metric("lines_total", lines as f64);
    report.latency("diff_after_read", &hist);
    let mut jitter = Histogram::default();
    for pair in window.windows(2) {
        let gap_us = (pair[1].start_ns - pair[0].start_ns) / 1000;
        jitter.record_us(gap_us.abs_diff(args.period_ms * 1000));
    }
    report.latency("poll_start_jitter", &jitter);
    report.finish().map_err(|e| e.to_string())
}
