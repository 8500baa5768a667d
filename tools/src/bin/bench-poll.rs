//! bench-poll: what one poll cycle of a large project costs on the wire and
//! in time, through the real server (poller, read plan, EPSNET backend)
//! against the simulated PLC on 127.0.0.1.
//!
//! It generates a public file laid out like a real project, starts the
//! simulated PLC on it and a server section on an EPSNET backend pointed at
//! it, connects one client that enables every variable (`EN:*`), and then
//! watches the poll cycles:
//!
//! - requests and bytes: the backend is wrapped in a counting `PlcBackend`
//!   decorator (every poll cycle is one `read` call: its blocks are the
//!   EPSNET READ requests, at most 1230 bytes each), and in the counting
//!   phase the datagrams pass a UDP relay that counts them, their frames
//!   and their bytes in each direction;
//! - time: the decorator stamps the start and end of each cycle's `read`;
//!   jitter is each start's distance from the ideal schedule (first start +
//!   k * COMM_LOOP_DELAY).
//!
//! Run: `cargo run --release --bin bench-poll` (see `--help`).

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use clap::Parser;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpStream, UdpSocket};

use plccoms::startup::start_section;
use plccoms_core::config;
use plccoms_core::driver::{
    Answer, DirEntry, FileInfo, PlcBackend, PlcError, PlcStatus, ReadRequest, WriteRequest,
};
use plccoms_core::vars::VarTable;
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_plc::epsnet::codec;
use plccoms_plc::epsnet::frame::MAX_PACKET;
use plccoms_plc::pubfile;
use plccoms_plc::MemoryMap;
use plcsim::program::ProgramKind;
use plcsim::{PubSource, SimConfig};

/// Measures poll cycles of a generated large project against the simulated
/// PLC over EPSNET/UDP on 127.0.0.1 and prints a markdown report.
#[derive(Debug, Parser)]
#[command(name = "bench-poll")]
struct Args {
    /// Variables in the generated public file (all enabled).
    #[arg(long, default_value_t = 10_000)]
    vars: usize,
    /// Cycles timed at each COMM_LOOP_DELAY.
    #[arg(long, default_value_t = 300)]
    cycles: usize,
    /// Cycles counted through the UDP relay.
    #[arg(long, default_value_t = 20)]
    count_cycles: usize,
    /// COMM_LOOP_DELAY of the jitter run (ms).
    #[arg(long, default_value_t = 100)]
    delay: u64,
    /// COMM_LOOP_DELAY of the pure cycle cost run (ms, 1 = back to back).
    #[arg(long, default_value_t = 1)]
    fast_delay: u64,
    /// Animate every variable in the simulated PLC (each PLC cycle), so
    /// every poll also publishes and sends DIFFs.
    #[arg(long)]
    animate: bool,
    /// Write the generated public file here, too.
    #[arg(long, value_name = "FILE")]
    save_pub: Option<std::path::PathBuf>,
    /// Seed of the layout generator.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

// ---------------------------------------------------------------------------
// The project: a generated public file.

struct Layout {
    text: Vec<u8>,
    vars: usize,
    /// Distinct bytes the variables occupy (BOOLs sharing a byte count once).
    bytes: u64,
    per_area: [(char, usize, u64); 4],
}

struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 33
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// Types of a typical project and their weights: mostly REAL, INT, BOOL,
/// with every other type sprinkled in.
const TYPES: [(&str, u32, u64); 17] = [
    ("BOOL", 0, 22),
    ("REAL", 4, 18),
    ("INT", 2, 12),
    ("UINT", 2, 6),
    ("DINT", 4, 6),
    ("UDINT", 4, 4),
    ("BYTE", 1, 4),
    ("USINT", 1, 3),
    ("SINT", 1, 2),
    ("WORD", 2, 4),
    ("DWORD", 4, 3),
    ("LREAL", 8, 5),
    ("LINT", 8, 1),
    ("TIME", 4, 3),
    ("TOD", 4, 1),
    ("DT", 8, 2),
    ("STRING", 0, 4),
];

fn generate(total: usize, seed: u64) -> Layout {
    let mut rng = Lcg(seed);
    let weight_sum: u64 = TYPES.iter().map(|t| t.2).sum();
    let mut text = b"; bench-poll: generated project\r\n".to_vec();
    let mut covered: std::collections::BTreeSet<(char, u32)> = Default::default();
    let mut per_area = [('X', 0, 0), ('Y', 0, 0), ('S', 0, 0), ('R', 0, 0)];
    let mut line = |text: &mut Vec<u8>,
                    name: String,
                    area: char,
                    off: u32,
                    bit: Option<u8>,
                    ty: &str,
                    len: u32| {
        let kind = if ty == "REAL" || ty == "LREAL" {
            'F'
        } else {
            'B'
        };
        let bit = bit.map(|b| format!(" .{b}")).unwrap_or_default();
        text.extend_from_slice(
            format!(" {name} {area} {kind} {off}{bit} {ty} PUB_INOUT\r\n").as_bytes(),
        );
        for o in off..off + len.max(1) {
            covered.insert((area, o));
        }
        let slot = per_area.iter_mut().find(|a| a.0 == area).unwrap();
        slot.1 += 1;
    };
    let mut n = 0usize;
    // About 1 % of the variables are I/O and system registers: X and Y bits
    // and bytes, a few S words.
    let io = (total / 100).max(3);
    let (mut x, mut y) = (0u32, 0u32);
    while n < io && n < total {
        let (area, at) = if n % 3 == 2 {
            ('Y', &mut y)
        } else {
            ('X', &mut x)
        };
        if rng.below(3) == 0 {
            line(
                &mut text,
                format!("IO_{area}{}_W", *at),
                area,
                *at,
                None,
                "WORD",
                2,
            );
            *at += 2;
        } else {
            let bits = 1 + rng.below(8) as u8;
            for b in 0..bits {
                line(
                    &mut text,
                    format!("IO_{area}{}_{b}", *at),
                    area,
                    *at,
                    Some(b),
                    "BOOL",
                    1,
                );
                n += 1;
            }
            *at += 1;
            continue;
        }
        n += 1;
    }
    for i in 0..3u32.min((total - n) as u32) {
        line(
            &mut text,
            format!("SYS_S{}", 200 + 4 * i),
            'S',
            200 + 4 * i,
            None,
            "UDINT",
            4,
        );
        n += 1;
    }
    // The program's data in R: runs of mixed types one after the other, a
    // gap now and then (unused or unpublished data; some small enough to be
    // read through, some not).
    let mut off = 0u32;
    let mut block = 0;
    while n < total {
        if rng.below(400) == 0 {
            off += [4, 12, 40, 300, 2000][rng.below(5) as usize];
            block += 1;
        }
        let mut pick = rng.below(weight_sum);
        let (ty, size, _) = *TYPES
            .iter()
            .find(|t| {
                if pick < t.2 {
                    true
                } else {
                    pick -= t.2;
                    false
                }
            })
            .unwrap();
        match ty {
            "BOOL" => {
                let bits = (1 + rng.below(8) as u8).min((total - n) as u8);
                for b in 0..bits {
                    line(
                        &mut text,
                        format!("B{block}.F{n}"),
                        'R',
                        off,
                        Some(b),
                        "BOOL",
                        1,
                    );
                    n += 1;
                }
                off += 1;
            }
            "STRING" => {
                let len = [10u32, 20, 40, 80][rng.below(4) as usize];
                line(
                    &mut text,
                    format!("B{block}.S{n}"),
                    'R',
                    off,
                    None,
                    &format!("STRING[{len}]"),
                    len + 1,
                );
                off += len + 1;
                n += 1;
            }
            _ => {
                // Natural alignment up to 4 bytes, as a compiler lays it out.
                let align = size.min(4);
                off = off.div_ceil(align) * align;
                line(
                    &mut text,
                    format!("B{block}.V{n}"),
                    'R',
                    off,
                    None,
                    ty,
                    size,
                );
                off += size;
                n += 1;
            }
        }
    }
    for a in per_area.iter_mut() {
        a.2 = covered.iter().filter(|c| c.0 == a.0).count() as u64;
    }
    // The fixed variables: S2 (__PLC_RUN) and S70..73 (__PF_CRC).
    for o in [2, 70, 71, 72, 73] {
        covered.insert(('S', o));
    }
    Layout {
        text,
        vars: n,
        bytes: covered.len() as u64 - 5,
        per_area,
    }
}

// ---------------------------------------------------------------------------
// Counting: a backend decorator and a UDP relay.

#[derive(Debug, Clone, Copy)]
struct Cycle {
    start: Instant,
    end: Instant,
    requests: usize,
    bytes: u64,
    /// Relay counters at the end of the cycle.
    relay: [u64; 6],
    /// Its first block.
    first: ReadRequest,
}

struct Counting {
    inner: EpsnetBackend,
    relay: Option<Arc<Relay>>,
    cycles: Arc<Mutex<Vec<Cycle>>>,
}

#[async_trait]
impl PlcBackend for Counting {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn source_address(&self) -> Option<u8> {
        self.inner.source_address()
    }
    fn max_read_block(&self, area: plccoms_protocol::Area) -> u32 {
        self.inner.max_read_block(area)
    }
    fn max_file_block(&self) -> u32 {
        self.inner.max_file_block()
    }
    async fn connect(&mut self) -> Result<String, PlcError> {
        self.inner.connect().await
    }
    /// The link reads a poll in slices: a read whose first block comes
    /// after the current cycle's first continues that cycle; one that starts
    /// again from the front begins the next.
    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let start = Instant::now();
        let answer = self.inner.read(requests).await;
        let end = Instant::now();
        let relay = self.relay.as_ref().map_or([0; 6], |r| r.snapshot());
        let Some(&first) = requests.first() else {
            return answer;
        };
        let bytes: u64 = requests.iter().map(|r| u64::from(r.len)).sum();
        let mut cycles = self.cycles.lock().unwrap();
        match cycles.last_mut() {
            Some(last) if (first.area, first.offset) > (last.first.area, last.first.offset) => {
                last.end = end;
                last.requests += requests.len();
                last.bytes += bytes;
                last.relay = relay;
            }
            _ => cycles.push(Cycle {
                start,
                end,
                requests: requests.len(),
                bytes,
                relay,
                first,
            }),
        }
        answer
    }
    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        self.inner.write(requests).await
    }
    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        self.inner.status().await
    }
    async fn file_info(&mut self, path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        self.inner.file_info(path).await
    }
    async fn read_file(
        &mut self,
        path: &[u8],
        offset: u64,
        len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        self.inner.read_file(path, offset, len).await
    }
    async fn write_file(
        &mut self,
        path: &[u8],
        offset: u64,
        data: &[u8],
        last: bool,
    ) -> Result<Answer<()>, PlcError> {
        self.inner.write_file(path, offset, data, last).await
    }
    async fn write_file_info(
        &mut self,
        path: &[u8],
        info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        self.inner.write_file_info(path, info).await
    }
    async fn list_dir(&mut self, path: &[u8]) -> Result<Answer<Vec<DirEntry>>, PlcError> {
        self.inner.list_dir(path).await
    }
}

/// Relays datagrams between the backend and the PLC, counting datagrams,
/// EPSNET frames and UDP payload bytes each way:
/// [to PLC datagrams, frames, bytes, from PLC datagrams, frames, bytes].
#[derive(Default)]
struct Relay {
    counts: [AtomicU64; 6],
}

impl Relay {
    fn snapshot(&self) -> [u64; 6] {
        std::array::from_fn(|i| self.counts[i].load(Ordering::Relaxed))
    }

    fn count(&self, base: usize, datagram: &[u8]) {
        let frames = codec::decode_packet(datagram).map_or(0, |p| p.frames.len() as u64);
        self.counts[base].fetch_add(1, Ordering::Relaxed);
        self.counts[base + 1].fetch_add(frames, Ordering::Relaxed);
        self.counts[base + 2].fetch_add(datagram.len() as u64, Ordering::Relaxed);
    }

    /// Starts relaying to `plc`; returns the address to point the backend at.
    async fn start(self: &Arc<Self>, plc: SocketAddr) -> std::io::Result<SocketAddr> {
        let socket = Arc::new(UdpSocket::bind("127.0.0.1:0").await?);
        let addr = socket.local_addr()?;
        let relay = self.clone();
        tokio::spawn(async move {
            let mut buf = vec![0u8; MAX_PACKET + 64];
            let mut client: Option<SocketAddr> = None;
            loop {
                let Ok((len, from)) = socket.recv_from(&mut buf).await else {
                    continue;
                };
                if from == plc {
                    relay.count(3, &buf[..len]);
                    if let Some(client) = client {
                        let _ = socket.send_to(&buf[..len], client).await;
                    }
                } else {
                    client = Some(from);
                    relay.count(0, &buf[..len]);
                    let _ = socket.send_to(&buf[..len], plc).await;
                }
            }
        });
        Ok(addr)
    }
}

// ---------------------------------------------------------------------------
// A run: simulator + section + one client with everything enabled.

struct Run {
    cycles: Vec<Cycle>,
    /// Bytes the client received (DIFF lines) per measured cycle.
    client_bytes: f64,
    plan_requests: usize,
    plan_bytes: u64,
}

async fn run(
    args: &Args,
    layout: &Layout,
    delay_ms: u64,
    window: usize,
    count: bool,
    cycles_wanted: usize,
) -> Run {
    let sim = plcsim::spawn(SimConfig {
        bind: "127.0.0.1:0".parse().unwrap(),
        pubfile: PubSource::Bytes(layout.text.clone()),
        program: ProgramKind::Idle,
        animate: if args.animate {
            vec!["*".to_string()]
        } else {
            Vec::new()
        },
        cycle: Duration::from_millis(10),
        ..SimConfig::default()
    })
    .await
    .expect("simulator");
    let relay = Arc::new(Relay::default());
    let plc = if count {
        relay.start(sim.local_addr()).await.expect("relay")
    } else {
        sim.local_addr()
    };
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = {delay_ms}\nNET_CONNECT_MAX = 4\n[Bench]\nSERVER_PORT = 5010\n"
    );
    let loaded = config::parse(Path::new("bench.ini"), &ini).expect("ini");
    let global = Arc::new(loaded.config.global);
    let section = loaded.config.sections.into_iter().next().unwrap();
    let mut warnings = Vec::new();
    let table = VarTable::build(
        "FIXED.pub",
        &pubfile::parse(plcsim::FIXED_PUB),
        Some(("bench.pub", &pubfile::parse(&layout.text))),
        &MemoryMap::FOXTROT,
        &mut warnings,
    )
    .expect("table");
    assert!(warnings.is_empty(), "public file: {warnings:?}");
    let mut eps = EpsnetConfig::new(plc);
    eps.local_ip = "127.0.0.1".parse().unwrap();
    eps.window = window;
    let cycles = Arc::new(Mutex::new(Vec::new()));
    let backend = Counting {
        inner: EpsnetBackend::new(eps),
        relay: count.then(|| relay.clone()),
        cycles: cycles.clone(),
    };
    let server = start_section(
        global,
        section,
        table,
        Some(Box::new(backend)),
        "127.0.0.1:0".parse().unwrap(),
        std::env::temp_dir(),
        None,
    )
    .await
    .expect("section");

    // One client enables everything and reads whatever it is sent.
    let mut client = TcpStream::connect(server.local_addr).await.unwrap();
    client.write_all(b"EN:*\r\n").await.unwrap();
    let (mut rd, _wr) = client.into_split();
    let received = Arc::new(AtomicU64::new(0));
    let counter = received.clone();
    let drain = tokio::spawn(async move {
        let mut buf = vec![0u8; 1 << 16];
        while let Ok(n @ 1..) = rd.read(&mut buf).await {
            counter.fetch_add(n as u64, Ordering::Relaxed);
        }
    });

    // Warm up: the plan covers every variable, and a few cycles after that.
    let everything = layout.bytes;
    // No poll cycle for this long: report instead of hanging.
    let mut progress = (0, Instant::now());
    let mut stalled = |len: usize| {
        if len != progress.0 {
            progress = (len, Instant::now());
        } else if progress.1.elapsed() > Duration::from_secs(30) {
            eprintln!(
                "bench-poll: no poll cycle for 30 s after {len} cycles (link: {:?})",
                server.section.state().link
            );
            std::process::exit(2);
        }
    };
    let first = loop {
        tokio::time::sleep(Duration::from_millis(20)).await;
        let c = cycles.lock().unwrap();
        stalled(c.len());
        if let Some(i) = c.iter().position(|c| c.bytes >= everything) {
            break i + 5;
        }
    };
    let mut at_first = None;
    loop {
        tokio::time::sleep(Duration::from_millis(50)).await;
        let len = cycles.lock().unwrap().len();
        stalled(len);
        if at_first.is_none() && len > first {
            at_first = Some((len, received.load(Ordering::Relaxed)));
        }
        if len > first + cycles_wanted {
            break;
        }
    }
    server.abort();
    drain.abort();
    sim.stop().await;
    let all = cycles.lock().unwrap().clone();
    let cycles = all[first..first + cycles_wanted + 1].to_vec();
    let (from, bytes0) = at_first.expect("measured");
    let client_bytes =
        (received.load(Ordering::Relaxed) - bytes0) as f64 / (all.len() - from).max(1) as f64;
    Run {
        client_bytes,
        plan_requests: cycles[1].requests,
        plan_bytes: cycles[1].bytes,
        cycles,
    }
}

fn pct(sorted: &[f64], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn stats(mut v: Vec<f64>) -> String {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    format!(
        "{:.2} / {:.2} / {:.2}",
        pct(&v, 0.5),
        pct(&v, 0.99),
        v[v.len() - 1]
    )
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

/// Cycle time (the EPSNET exchange), start-to-start interval, and start
/// lateness against the ideal schedule.
fn timing(run: &Run, delay_ms: u64) -> (String, String, String) {
    let c = &run.cycles;
    let exchange: Vec<f64> = c[1..].iter().map(|c| ms(c.end - c.start)).collect();
    let interval: Vec<f64> = c.windows(2).map(|w| ms(w[1].start - w[0].start)).collect();
    let period = delay_ms as f64;
    let t0 = c[0].start;
    // Distance of each start from the nearest point of the schedule
    // t0 + k * period (t0: the first start measured).
    let late: Vec<f64> = c[1..]
        .iter()
        .map(|c| {
            let t = ms(c.start - t0);
            (t - (t / period).round() * period).abs()
        })
        .collect();
    (stats(exchange), stats(interval), stats(late))
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let args = Args::parse();
    let layout = generate(args.vars, args.seed);
    if let Some(path) = &args.save_pub {
        std::fs::write(path, &layout.text).expect("--save-pub");
    }
    let mut out = String::new();
    let given: Vec<String> = std::env::args().skip(1).collect();
    let _ = writeln!(out, "## bench-poll\n");
    let _ = writeln!(
        out,
        "Command: `cargo run --release --bin bench-poll{}{}`\n",
        if given.is_empty() { "" } else { " -- " },
        given.join(" ")
    );
    let fixed = 2; // __PLC_RUN, __PF_CRC: always polled
    let _ = writeln!(
        out,
        "Project: {} variables + {fixed} fixed, {} distinct bytes ({}), all enabled (`EN:*`); \
         animation {}; host: {} CPUs.\n",
        layout.vars,
        layout.bytes,
        layout
            .per_area
            .iter()
            .map(|(a, n, b)| format!("{a}: {n} vars / {b} B"))
            .collect::<Vec<_>>()
            .join(", "),
        if args.animate {
            "on (every variable, every 10 ms PLC cycle)"
        } else {
            "off"
        },
        std::thread::available_parallelism().map_or(0, |n| n.get()),
    );

    // Requests, datagrams and bytes per cycle (through the relay).
    let counted = run(&args, &layout, args.delay, 4, true, args.count_cycles).await;
    let c = &counted.cycles;
    let n = (c.len() - 1) as f64;
    let delta = |i: usize| (c[c.len() - 1].relay[i] - c[0].relay[i]) as f64 / n;
    let all_bytes = layout.bytes + 5; // + the fixed S2 and S70..73
    let min_requests = all_bytes.div_ceil(1230);
    // A request reads one area: at least one request per area.
    let per_area_min: u64 = layout
        .per_area
        .iter()
        .map(|&(area, _, bytes)| (bytes + if area == 'S' { 5 } else { 0 }).div_ceil(1230))
        .sum();
    // An answer datagram carries at most MAX_DPLEN bytes: one 1230-byte
    // READ answer (13 bytes of frame) and a second, smaller one.
    let per_datagram = (plccoms_plc::epsnet::frame::MAX_DPLEN - 2 * 13) as u64;
    let min_datagrams = all_bytes.div_ceil(per_datagram);
    let _ = writeln!(
        out,
        "### Per poll cycle (COMM_LOOP_DELAY {} ms, {} cycles)\n",
        args.delay,
        c.len() - 1
    );
    let _ = writeln!(out, "| | measured | minimum |");
    let _ = writeln!(out, "|---|---:|---:|");
    let _ = writeln!(
        out,
        "| EPSNET READ requests | {} | {} (= ceil({} B / 1230)); {} with one area per request |",
        counted.plan_requests, min_requests, all_bytes, per_area_min
    );

    let _ = writeln!(
        out,
        "| memory bytes read | {} | {} |",
        counted.plan_bytes, all_bytes
    );
    let _ = writeln!(
        out,
        "| request datagrams / frames | {:.1} / {:.1} | {min_datagrams} (= ceil({all_bytes} B / {per_datagram})) |",
        delta(0),
        delta(1)
    );
    let _ = writeln!(
        out,
        "| answer datagrams / frames | {:.1} / {:.1} | {min_datagrams} |",
        delta(3),
        delta(4)
    );
    let _ = writeln!(
        out,
        "| UDP payload bytes to PLC / from PLC | {:.0} / {:.0} | |\n",
        delta(2),
        delta(5)
    );

    // Timing.
    let _ = writeln!(
        out,
        "### Timing ({} cycles each; ms, p50 / p99 / max)\n",
        args.cycles
    );
    let _ = writeln!(
        out,
        "| COMM_LOOP_DELAY | window | EPSNET exchange per cycle | start-to-start interval | start jitter vs schedule | DIFF bytes to the client per cycle |"
    );
    let _ = writeln!(out, "|---:|---:|---:|---:|---:|---:|");
    for (delay, window) in [(args.delay, 4), (args.fast_delay, 4), (args.fast_delay, 1)] {
        let timed = run(&args, &layout, delay, window, false, args.cycles).await;
        let (exchange, interval, mut late) = timing(&timed, delay);
        if delay < 10 {
            // Cycles as long as the period: ticks are skipped, and the
            // distance to the schedule is bounded by half a period.
            late = "–".to_string();
        }
        let _ = writeln!(
            out,
            "| {delay} ms | {window} | {exchange} | {interval} | {late} | {:.0} |",
            timed.client_bytes
        );
        eprintln!("done: delay {delay} ms, window {window}");
    }
    println!("{out}");
}
