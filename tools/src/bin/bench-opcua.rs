//! bench-opcua: the OPC UA client backend (issue 31) reading N variables
//! every second from a local OPC UA server, plccoms's own: loopback
//! through both sides, each side its own process.
//!
//! - the PLC: `plcsim` in this process, every `V*` variable changing each
//!   1 s cycle (`T0`..`T15`, the SET targets, only when set);
//! - the serving side: a `plccoms` process with an EPSNET section `Sim` of
//!   those variables, served by its OPC UA app (OPCUA_PORT);
//! - the client side, measured: a second `plccoms` process with an OPCUA
//!   section browsing `Sim`'s node (OPCUA_MODE = subscribe, default
//!   OPCUA_REBROWSE), one client with EN:* taking the DIFFs.
//!
//! With `--against node` the server is node-opcua's instead
//! (bench/opcua/node/server.js, `npm ci` there first): it answers a Write
//! at once, so that row shows the client side's own SET latency apart
//! from a serving plccoms's link. With `--against ua` it is
//! `bench-opcua-plc` (async-opcua's in-memory server, as a PLC's own
//! server: a Write is set in memory at once, and its variables change
//! without a second link behind them). `--split` splits each SET's time into
//! its parts on both sides (the `plccoms::set_timing` debug lines).
//!
//! Measured on the client side: its CPU (utime + stime from /proc over a
//! steady window, in cores), its peak and current RSS, OPC UA requests per
//! 1 s cycle (its `/metrics` `plccoms_backend_requests_total`), and SET ->
//! confirmed DIFF (the SET's answer) and SET -> another client's DIFF
//! (min/avg/max/p99, through `timed::time_sets` as bench-s7 and
//! bench-modbus time them).
//!
//! Run: `cargo run --release -p plccoms-tools --bin bench-opcua -- --help`.

#[path = "../pinned.rs"]
mod pinned;
#[path = "../procfs.rs"]
mod procfs;
#[path = "../timed.rs"]
#[allow(dead_code)]
mod timed;

use std::fmt::Write as _;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;

use plcsim::program::ProgramKind;
use plcsim::{PubSource as SimPub, SimConfig};
use timed::percentile;

#[derive(Debug, Parser)]
#[command(name = "bench-opcua")]
struct Args {
    /// Variable counts to run with (one run each).
    #[arg(long, value_delimiter = ',', default_value = "10000,100000")]
    vars: Vec<usize>,
    /// COMM_LOOP_DELAY of both sides and the PLC's cycle (ms).
    #[arg(long, default_value_t = 1000)]
    delay: u64,
    /// How often the PLC's variables change (ms; default: `--delay`). A
    /// long one (`3600000`) leaves the server quiet after the first
    /// values: a SET's time without the burst of every variable changing.
    #[arg(long)]
    plc_cycle: Option<u64>,
    /// Steady window over which CPU and requests are taken (s).
    #[arg(long, default_value_t = 60)]
    window: u64,
    /// SETs timed per run.
    #[arg(long, default_value_t = 1000)]
    sets: usize,
    /// The plccoms binary (default: next to this one).
    #[arg(long)]
    plccoms: Option<PathBuf>,
    /// Longest wait for the client side's variables (s): browsing 100,000
    /// nodes takes a while.
    #[arg(long, default_value_t = 600)]
    ready_within: u64,
    /// A key of the client side's section, `KEY=VALUE` (repeatable): e.g.
    /// `OPCUA_TIMEOUT=5000` for a debug build or one under heaptrack,
    /// whose CreateMonitoredItems at 100,000 takes longer than the
    /// default allows, or `OPCUA_REBROWSE=0` to see what the rebrowse costs.
    #[arg(long = "client-key")]
    client_keys: Vec<String>,
    /// Append `opcua_<n>.<metric> value` lines here (bench/run's results).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Split each SET's time into its parts on both sides (both logs at
    /// `plccoms::set_timing=debug`): queued in the link before the Write,
    /// the Write, the confirmation, the publish; and what a SET may wait
    /// behind (a take of pushed values, a poll slice, a piece of a poll's
    /// end, a heap trim).
    #[arg(long)]
    split: bool,
    /// The servers measured against (one row each): `plccoms` (a second
    /// plccoms over plcsim: its own link and write path are part of what
    /// is measured) and `node` (node-opcua's server, bench/opcua/node,
    /// answering a Write at once: the client side's own latency) and `ua`
    /// (`bench-opcua-plc`: async-opcua's in-memory server, likewise).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "plccoms")]
    against: Vec<Against>,
    /// CPUs of the client side, the process measured (`taskset -c` list,
    /// e.g. `0`). The bench itself (its SETs and, against plccoms, its
    /// plcsim) runs where it is started: `taskset -c 0 bench-opcua ...`.
    #[arg(long)]
    pin_client: Option<String>,
    /// CPUs of the server process (plccoms serving, node-opcua's or
    /// bench-opcua-plc), e.g. `1`: so that its burst of changed values
    /// and the client side do not take turns on the same cores.
    #[arg(long)]
    pin_server: Option<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Against {
    Plccoms,
    Node,
    Ua,
}

const SET_TAGS: usize = 16;

/// A public file of `n` variables: `T0`..`T15` INT, then `V16`.. of
/// numeric types in turn.
fn public_file(n: usize) -> String {
    let mut text = String::new();
    let mut at = 0u32;
    for i in 0..n {
        let (name, ty, size, letter) = if i < SET_TAGS {
            (format!("T{i}"), "INT", 2, 'B')
        } else {
            match i % 4 {
                0 => (format!("V{i}"), "DINT", 4, 'B'),
                1 => (format!("V{i}"), "REAL", 4, 'F'),
                2 => (format!("V{i}"), "LREAL", 8, 'F'),
                _ => (format!("V{i}"), "UINT", 2, 'B'),
            }
        };
        let _ = writeln!(text, " {name} R {letter} {at} {ty} PUB_INOUT");
        at += size;
    }
    text
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

/// A server process (plccoms, node-opcua's, bench-opcua-plc); killed when
/// dropped.
struct Server {
    child: Child,
}

impl Server {
    /// node-opcua's server of `n` variables, all but the SET targets
    /// (`VAR_00000`..) changing each `delay` ms; once it listens.
    fn node(dir: &Path, port: u16, n: usize, delay: u64, pin: Option<&str>) -> Server {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../bench/opcua/node/server.js");
        let log = std::fs::File::create(dir.join("node.log")).expect("log");
        let child = pinned::command("node", pin)
            .arg(&script)
            .args([
                port.to_string(),
                n.to_string(),
                (n - SET_TAGS).to_string(),
                delay.to_string(),
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "node {}: {e} (npm ci --prefix bench/opcua/node)",
                    script.display()
                )
            });
        Server::once_ready(child, "node-opcua's server", &dir.join("node.log"))
    }

    /// The server `child` once it printed `ready` on its stdout.
    fn once_ready(mut child: Child, what: &str, log: &Path) -> Server {
        use std::io::{BufRead, BufReader};
        let mut out = BufReader::new(child.stdout.take().expect("stdout")).lines();
        let ready = out.any(|l| l.is_ok_and(|l| l == "ready"));
        assert!(ready, "{what} did not start; see {}", log.display());
        // Read on: a closed pipe would end it at its next line (EPIPE).
        std::thread::spawn(move || out.for_each(drop));
        Server { child }
    }

    /// `bench-opcua-plc` (next to this binary) of `n` variables, the
    /// `V*` changing each `delay` ms; once it listens.
    fn ua(dir: &Path, port: u16, n: usize, delay: u64, pin: Option<&str>) -> Server {
        let binary = std::env::current_exe()
            .expect("this binary's path")
            .with_file_name("bench-opcua-plc");
        let log = std::fs::File::create(dir.join("ua.log")).expect("log");
        let child = pinned::command(&binary, pin)
            .args([
                "--port",
                &port.to_string(),
                "--vars",
                &n.to_string(),
                "--delay",
                &delay.to_string(),
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("{}: {e}", binary.display()));
        Server::once_ready(child, "bench-opcua-plc", &dir.join("ua.log"))
    }

    fn start(
        binary: &Path,
        dir: &Path,
        name: &str,
        ini: &str,
        split: bool,
        pin: Option<&str>,
    ) -> Server {
        std::fs::write(dir.join(format!("{name}.ini")), ini).expect("ini");
        let log = std::fs::File::create(dir.join(format!("{name}.log"))).expect("log");
        let mut command = pinned::command(binary, pin);
        if split {
            command.env("RUST_LOG", "info,plccoms::set_timing=debug");
        }
        let child = command
            .args(["-c", &format!("{name}.ini")])
            .current_dir(dir)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("{}: {e}", binary.display()));
        Server { child }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The section's OPC UA requests and DIFF lines so far, from the client
/// side's /metrics.
fn requests(http: u16) -> Option<(f64, f64)> {
    use std::io::{Read, Write};
    let mut stream = TcpStream::connect(("127.0.0.1", http)).ok()?;
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .ok()?;
    write!(
        stream,
        "GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut text = String::new();
    stream.read_to_string(&mut text).ok()?;
    let value = |name: &str| -> Option<f64> {
        let prefix = format!("{name}{{section=\"Via\"}} ");
        text.lines()
            .find_map(|l| l.strip_prefix(prefix.as_str()))
            .and_then(|v| v.trim().parse().ok())
    };
    Some((
        value("plccoms_backend_requests_total")?,
        value("plccoms_diff_lines_total")?,
    ))
}

/// The answer to one line asked of the section at `port`.
fn ask(port: u16, line: &str) -> String {
    use std::io::{BufRead, BufReader, Write};
    let Ok(mut stream) = TcpStream::connect(("127.0.0.1", port)) else {
        return String::new();
    };
    let _ = stream.set_read_timeout(Some(Duration::from_secs(10)));
    let _ = write!(stream, "{line}\r\n");
    let mut answer = String::new();
    let mut reader = BufReader::new(stream);
    loop {
        answer.clear();
        if reader.read_line(&mut answer).unwrap_or(0) == 0 {
            return String::new();
        }
        if !answer.starts_with("WARNING:") {
            return answer.trim_end().to_string();
        }
    }
}

struct Row {
    against: Against,
    /// The SET's parts, a table (`--split`).
    split: String,
    vars: usize,
    ready_s: f64,
    cpu_cores: f64,
    rss_peak_mib: f64,
    rss_mib: f64,
    requests_per_cycle: f64,
    /// DIFF lines a second to the clients (the watcher's EN:*): every
    /// value changing once a cycle comes as one.
    diffs_per_s: f64,
    confirm: Vec<f64>,
    diff: Vec<f64>,
}

async fn run(args: &Args, binary: &Path, n: usize, against: Against) -> Row {
    let dir = tempfile::tempdir().expect("tempdir");
    let (ua, sim_port, via_port, http) = (free_port(), free_port(), free_port(), free_port());
    let delay = args.delay;
    let plc_cycle = args.plc_cycle.unwrap_or(delay);
    // The server: (process, its plcsim, the client's browse and identity
    // keys, the last variable, the SET targets, their DIFF prefix).
    let (_serving, _plc, browse, last, targets, prefix) = match against {
        Against::Plccoms => {
            let pubfile = public_file(n);
            std::fs::write(dir.path().join("bench.pub"), &pubfile).expect("pub");
            let plc = plcsim::spawn(SimConfig {
                bind: SocketAddr::from(([127, 0, 0, 1], 0)),
                pubfile: SimPub::Bytes(pubfile.into_bytes()),
                program: ProgramKind::Idle,
                animate: vec!["V*".into()],
                cycle: Duration::from_millis(plc_cycle),
                ..SimConfig::default()
            })
            .await
            .expect("plcsim");
            // A user of role write, so that the client side's SETs reach the PLC.
            let users =
                plccoms_opcua::users::hash_line("bench", "write", "bench", b"bench-salt", 1000);
            std::fs::write(dir.path().join("opcua-users"), users).expect("users");
            let serving = Server::start(
                binary,
                dir.path(),
                "serving",
                &format!(
                    "[*]\nCOMM_LOOP_DELAY = {delay}\nOPCUA_PORT = {ua}\nOPCUA_USERS = opcua-users\n\
                     OPCUA_MAX_MONITORED_ITEMS = {}\n\
                     [Sim]\nIPADDR = 127.0.0.1\nIPADDR_LOCAL = 127.0.0.1\nEPSPORT = {}\n\
                     SERVER_PORT = {sim_port}\nPUBFILE = //bench.pub\nPUBFILE_CRC = No\nPUBFILE_WRITE = No\nOPCUA_WRITE = T*\n",
                    // Its default, 100,000 a subscription, is one short of N
                    // variables and ServerStatus.State (the client makes one).
                    n + 1000,
                    plc.local_addr().port()
                ),
                args.split,
                args.pin_server.as_deref(),
            );
            (
                serving,
                Some(plc),
                "OPCUA_BROWSE = nsu=urn:plccoms;s=Sim\nOPCUA_USER = bench\nOPCUA_PASSWORD = bench\n",
                format!("V{}", n - 1),
                (0..SET_TAGS).map(|i| format!("T{i}")).collect::<Vec<_>>(),
                "T",
            )
        }
        Against::Node => (
            Server::node(dir.path(), ua, n, plc_cycle, args.pin_server.as_deref()),
            None,
            "OPCUA_BROWSE = nsu=urn:node-opcua-bench;s=Bench\n",
            format!("ANIM_{:05}", n - SET_TAGS - 1),
            (0..SET_TAGS).map(|i| format!("VAR_{i:05}")).collect(),
            "VAR_",
        ),
        Against::Ua => (
            Server::ua(dir.path(), ua, n, plc_cycle, args.pin_server.as_deref()),
            None,
            "OPCUA_BROWSE = nsu=urn:bench-plc;s=Bench\n",
            format!("V{}", n - 1),
            (0..SET_TAGS).map(|i| format!("T{i}")).collect(),
            "T",
        ),
    };
    // For bench/opcua/wire, which captures both ports on the loopback.
    eprintln!("bench-opcua: ports: server {ua} section {via_port}");
    let started = Instant::now();
    let keys: String = args
        .client_keys
        .iter()
        .map(|key| match key.split_once('=') {
            Some((name, value)) => format!("{} = {}\n", name.trim(), value.trim()),
            None => panic!("--client-key {key}: expected KEY=VALUE"),
        })
        .collect();
    let client = Server::start(
        binary,
        dir.path(),
        "client",
        &format!(
            "[*]\nCOMM_LOOP_DELAY = {delay}\nHTTP_PORT = {http}\n\
             [Via]\nPROTOCOL = OPCUA\nOPCUA_URL = opc.tcp://127.0.0.1:{ua}/\n\
             {browse}SERVER_PORT = {via_port}\n{keys}"
        ),
        args.split,
        args.pin_client.as_deref(),
    );
    let pid = client.child.id();
    loop {
        if ask(via_port, &format!("GET:{last}")).starts_with("GET:") {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(args.ready_within),
            "the client side has no {last} after {} s; see {}/client.log",
            args.ready_within,
            dir.keep().display()
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    let ready_s = started.elapsed().as_secs_f64();
    let addr = SocketAddr::from(([127, 0, 0, 1], via_port));
    let arrivals = timed::watch_of(addr, prefix).await;
    // The subscription made (three poll periods), its first values in.
    tokio::time::sleep(Duration::from_millis(10 * delay)).await;
    let (c0, r0, t0) = (procfs::cpu_seconds(pid), requests(http), Instant::now());
    tokio::time::sleep(Duration::from_secs(args.window)).await;
    let (c1, r1, t1) = (procfs::cpu_seconds(pid), requests(http), Instant::now());
    let seconds = (t1 - t0).as_secs_f64();
    let cycles = seconds * 1000.0 / delay as f64;
    let (requests_per_cycle, diffs_per_s) = match (r0, r1) {
        (Some(a), Some(b)) => ((b.0 - a.0) / cycles, (b.1 - a.1) / seconds),
        _ => (f64::NAN, f64::NAN),
    };
    let log = dir.path().join("client.log");
    let serving_log = dir.path().join("serving.log");
    let log_from = |path: &Path| std::fs::metadata(path).map_or(0, |m| m.len());
    let (client_from, serving_from) = (log_from(&log), log_from(&serving_log));
    let sets = tokio::spawn(timed::time_sets_of(
        addr,
        arrivals.clone(),
        delay,
        args.sets,
        targets,
    ));
    let Ok((confirm, diff)) = sets.await else {
        let log = std::fs::read_to_string(&log).unwrap_or_default();
        let tail: Vec<&str> = log.lines().rev().take(30).collect();
        panic!(
            "SETs failed; the client side's log ends:\n{}",
            tail.into_iter().rev().collect::<Vec<_>>().join("\n")
        );
    };
    let split = match args.split {
        true => split_table(&[
            ("client", &log, client_from),
            ("serving", &serving_log, serving_from),
        ]),
        false => String::new(),
    };
    Row {
        against,
        split,
        vars: n,
        ready_s,
        cpu_cores: (c1 - c0) / seconds,
        rss_peak_mib: procfs::status_field(pid, "VmHWM")
            .map_or(f64::NAN, |kib| kib as f64 / 1024.0),
        rss_mib: procfs::status_field(pid, "VmRSS").map_or(f64::NAN, |kib| kib as f64 / 1024.0),
        requests_per_cycle,
        diffs_per_s,
        confirm,
        diff,
    }
}

/// The `plccoms::set_timing` lines of each side's log written during the
/// SETs, as p50 / p99 / max of each part (ms); `sides`: each side's
/// (name, log, where its SETs' lines begin).
fn split_table(sides: &[(&str, &Path, u64)]) -> String {
    // (event message, its fields in µs) that make a row.
    const PARTS: [(&str, &[&str]); 5] = [
        (
            "set round",
            &["queued_us", "write_us", "confirm_us", "publish_us"],
        ),
        ("pushed", &["take_us", "apply_us"]),
        ("poll slice", &["slice_us"]),
        ("poll finish", &["finish_us"]),
        ("heap trim", &["trim_us"]),
    ];
    let mut out = String::from(
        "| side | part | count | p50 | p99 | max |\n| --- | --- | --- | --- | --- | --- |\n",
    );
    let mut tails = String::new();
    for (side, path, from) in sides {
        let text = std::fs::read(path).unwrap_or_default();
        let text = String::from_utf8_lossy(text.get(*from as usize..).unwrap_or_default());
        tails.push_str(&tail_of_rounds(side, &text, PARTS[0]));
        for (event, fields) in PARTS {
            let lines: Vec<&str> = text.lines().filter(|l| l.contains(event)).collect();
            for field in fields {
                let mut ms: Vec<f64> = lines.iter().filter_map(|l| field_ms(l, field)).collect();
                if ms.is_empty() {
                    continue;
                }
                ms.sort_by(f64::total_cmp);
                let _ = writeln!(
                    out,
                    "| {side} | {event}: {} | {} | {:.2} ms | {:.2} ms | {:.2} ms |",
                    field.trim_end_matches("_us"),
                    ms.len(),
                    percentile(&ms, 0.5),
                    percentile(&ms, 0.99),
                    ms[ms.len() - 1]
                );
            }
        }
    }
    out + &tails
}

/// The value of a log line's `name=<µs>` field, in ms.
fn field_ms(line: &str, name: &str) -> Option<f64> {
    let value = line
        .split_whitespace()
        .find_map(|w| w.strip_prefix(name)?.strip_prefix('='))?;
    Some(value.parse::<f64>().ok()? / 1000.0)
}

/// The slowest 1 % of a side's SET rounds (at least one), each with its
/// parts: what the tail waits on, which the parts' own p99s, taken from
/// different rounds, do not tell.
fn tail_of_rounds(side: &str, text: &str, (event, fields): (&str, &[&str])) -> String {
    let mut rounds: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| l.contains(event))
        .filter_map(|l| fields.iter().map(|f| field_ms(l, f)).collect())
        .collect();
    if rounds.is_empty() {
        return String::new();
    }
    rounds.sort_by(|a, b| b.iter().sum::<f64>().total_cmp(&a.iter().sum::<f64>()));
    let slowest = &rounds[..rounds.len().div_ceil(100)];
    let names: Vec<&str> = fields.iter().map(|f| f.trim_end_matches("_us")).collect();
    let each: Vec<String> = slowest
        .iter()
        .map(|round| {
            let parts: Vec<String> = round.iter().map(|ms| format!("{ms:.1}")).collect();
            parts.join(" / ")
        })
        .collect();
    format!(
        "\n{side}: the slowest {} of {} {event}s, {} (ms): {}\n",
        slowest.len(),
        rounds.len(),
        names.join(" / "),
        each.join("; ")
    )
}

fn summary(values: &[f64]) -> (f64, f64, f64, f64) {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let avg = v.iter().sum::<f64>() / v.len().max(1) as f64;
    (
        v.first().copied().unwrap_or(f64::NAN),
        avg,
        v.last().copied().unwrap_or(f64::NAN),
        percentile(&v, 0.99),
    )
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    let binary = args.plccoms.clone().unwrap_or_else(|| {
        std::env::current_exe()
            .expect("this binary")
            .with_file_name("plccoms")
    });
    let mut out = String::new();
    let mut results = String::new();
    let _ = writeln!(
        out,
        "## bench-opcua\n\nOPC UA client section (subscribe) reading a local OPC UA server (plccoms: a second plccoms over plcsim; node: node-opcua's), every variable changing each {} ms (the sections' cycle: {} ms), on 127.0.0.1; client side's process measured over {} s\n",
        args.plc_cycle.unwrap_or(args.delay),
        args.delay,
        args.window
    );
    if args.pin_client.is_some() || args.pin_server.is_some() {
        let cpus = |pin: &Option<String>| pin.clone().unwrap_or_else(|| "any".into());
        let _ = writeln!(
            out,
            "CPUs: client side {}, server {}\n",
            cpus(&args.pin_client),
            cpus(&args.pin_server)
        );
    }
    let _ = writeln!(
        out,
        "| server | variables | ready after | client CPU | client RSS peak / now | requests per cycle | DIFF lines/s | SET confirmed min / avg / max / p99 | SET -> DIFF min / avg / max / p99 | DIFFs seen |"
    );
    let _ = writeln!(
        out,
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"
    );
    let mut splits = Vec::new();
    for (&n, &against) in args
        .vars
        .iter()
        .flat_map(|n| args.against.iter().map(move |a| (n, a)))
    {
        let r = run(&args, &binary, n.max(SET_TAGS + 1), against).await;
        let server = match r.against {
            Against::Plccoms => "plccoms",
            Against::Node => "node",
            Against::Ua => "ua",
        };
        if args.split {
            splits.push(format!(
                "SET's parts at {} variables against {server}:\n\n{}",
                r.vars, r.split
            ));
        }
        let (c_min, c_avg, c_max, c_p99) = summary(&r.confirm);
        let (d_min, d_avg, d_max, d_p99) = summary(&r.diff);
        let _ = writeln!(
            out,
            "| {server} | {} | {:.1} s | {:.3} cores | {:.1} / {:.1} MiB | {:.2} | {:.0} | {c_min:.2} / {c_avg:.2} / {c_max:.2} / {c_p99:.2} ms | {d_min:.2} / {d_avg:.2} / {d_max:.2} / {d_p99:.2} ms | {} of {} |",
            r.vars,
            r.ready_s,
            r.cpu_cores,
            r.rss_peak_mib,
            r.rss_mib,
            r.requests_per_cycle,
            r.diffs_per_s,
            r.diff.len(),
            r.confirm.len()
        );
        for (metric, value) in [
            ("ready_s", r.ready_s),
            ("cpu_cores", r.cpu_cores),
            ("rss_peak_mib", r.rss_peak_mib),
            ("rss_mib", r.rss_mib),
            ("requests_per_cycle", r.requests_per_cycle),
            ("diffs_per_s", r.diffs_per_s),
            ("set_confirm_min_ms", c_min),
            ("set_confirm_avg_ms", c_avg),
            ("set_confirm_max_ms", c_max),
            ("set_confirm_p99_ms", c_p99),
            ("set_diff_min_ms", d_min),
            ("set_diff_avg_ms", d_avg),
            ("set_diff_max_ms", d_max),
            ("set_diff_p99_ms", d_p99),
        ] {
            // bench/run's names for plccoms, as before.
            let label = match r.against {
                Against::Plccoms => format!("opcua_{}", r.vars),
                Against::Node => format!("opcua_node_{}", r.vars),
                Against::Ua => format!("opcua_ua_{}", r.vars),
            };
            let _ = writeln!(results, "{label}.{metric} {value:.3}");
        }
    }
    print!("{out}");
    for split in &splits {
        print!("\n{split}");
    }
    if let Some(path) = &args.out {
        timed::append(path, &results);
    }
}
