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
//! Measured on the client side: its CPU (utime + stime from /proc over a
//! steady window, in cores), its peak and current RSS, OPC UA requests per
//! 1 s cycle (its `/metrics` `plccoms_backend_requests_total`), and SET ->
//! confirmed DIFF (the SET's answer) and SET -> another client's DIFF
//! (min/avg/max/p99, through `timed::time_sets` as bench-s7 and
//! bench-modbus time them).
//!
//! Run: `cargo run --release -p plccoms-tools --bin bench-opcua -- --help`.

#[path = "../procfs.rs"]
mod procfs;
#[path = "../timed.rs"]
#[allow(dead_code)]
mod timed;

use std::fmt::Write as _;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
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

/// A plccoms process; killed when dropped.
struct Server {
    child: Child,
}

impl Server {
    fn start(binary: &Path, dir: &Path, name: &str, ini: &str) -> Server {
        std::fs::write(dir.join(format!("{name}.ini")), ini).expect("ini");
        let log = std::fs::File::create(dir.join(format!("{name}.log"))).expect("log");
        let child = Command::new(binary)
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

/// The section's OPC UA requests so far, from the client side's /metrics.
fn requests(http: u16) -> Option<f64> {
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
    text.lines()
        .find(|l| l.starts_with("plccoms_backend_requests_total{section=\"Via\"}"))
        .and_then(|l| l.rsplit(' ').next()?.parse().ok())
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
    vars: usize,
    ready_s: f64,
    cpu_cores: f64,
    rss_peak_mib: f64,
    rss_mib: f64,
    requests_per_cycle: f64,
    confirm: Vec<f64>,
    diff: Vec<f64>,
}

async fn run(args: &Args, binary: &Path, n: usize) -> Row {
    let dir = tempfile::tempdir().expect("tempdir");
    let pubfile = public_file(n);
    std::fs::write(dir.path().join("bench.pub"), &pubfile).expect("pub");
    let plc = plcsim::spawn(SimConfig {
        bind: SocketAddr::from(([127, 0, 0, 1], 0)),
        pubfile: SimPub::Bytes(pubfile.into_bytes()),
        program: ProgramKind::Idle,
        animate: vec!["V*".into()],
        cycle: Duration::from_millis(args.delay),
        ..SimConfig::default()
    })
    .await
    .expect("plcsim");
    let (ua, sim_port, via_port, http) = (free_port(), free_port(), free_port(), free_port());
    let delay = args.delay;
    // A user of role write, so that the client side's SETs reach the PLC.
    let users = plccoms_opcua::users::hash_line("bench", "write", "bench", b"bench-salt", 1000);
    std::fs::write(dir.path().join("opcua-users"), users).expect("users");
    let _serving = Server::start(
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
    );
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
             OPCUA_BROWSE = nsu=urn:plccoms;s=Sim\nOPCUA_USER = bench\nOPCUA_PASSWORD = bench\nSERVER_PORT = {via_port}\n{keys}"
        ),
    );
    let pid = client.child.id();
    let last = format!("V{}", n - 1);
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
    let arrivals = timed::watch(addr).await;
    // The subscription made (three poll periods), its first values in.
    tokio::time::sleep(Duration::from_millis(10 * delay)).await;
    let (c0, r0, t0) = (procfs::cpu_seconds(pid), requests(http), Instant::now());
    tokio::time::sleep(Duration::from_secs(args.window)).await;
    let (c1, r1, t1) = (procfs::cpu_seconds(pid), requests(http), Instant::now());
    let seconds = (t1 - t0).as_secs_f64();
    let cycles = seconds * 1000.0 / delay as f64;
    let requests_per_cycle = match (r0, r1) {
        (Some(a), Some(b)) => (b - a) / cycles,
        _ => f64::NAN,
    };
    let log = dir.path().join("client.log");
    let sets = tokio::spawn(timed::time_sets(
        addr,
        arrivals.clone(),
        delay,
        args.sets,
        SET_TAGS,
    ));
    let Ok((confirm, diff)) = sets.await else {
        let log = std::fs::read_to_string(&log).unwrap_or_default();
        let tail: Vec<&str> = log.lines().rev().take(30).collect();
        panic!(
            "SETs failed; the client side's log ends:\n{}",
            tail.into_iter().rev().collect::<Vec<_>>().join("\n")
        );
    };
    Row {
        vars: n,
        ready_s,
        cpu_cores: (c1 - c0) / seconds,
        rss_peak_mib: procfs::status_field(pid, "VmHWM")
            .map_or(f64::NAN, |kib| kib as f64 / 1024.0),
        rss_mib: procfs::status_field(pid, "VmRSS").map_or(f64::NAN, |kib| kib as f64 / 1024.0),
        requests_per_cycle,
        confirm,
        diff,
    }
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
        "## bench-opcua\n\nOPC UA client section (subscribe) reading plccoms's own OPC UA server, every variable changing each {} ms cycle, on 127.0.0.1; client side's process measured over {} s\n",
        args.delay, args.window
    );
    let _ = writeln!(
        out,
        "| variables | ready after | client CPU | client RSS peak / now | requests per cycle | SET confirmed min / avg / max / p99 | SET -> DIFF min / avg / max / p99 | DIFFs seen |"
    );
    let _ = writeln!(out, "| --- | --- | --- | --- | --- | --- | --- | --- |");
    for &n in &args.vars {
        let r = run(&args, &binary, n.max(SET_TAGS + 1)).await;
        let (c_min, c_avg, c_max, c_p99) = summary(&r.confirm);
        let (d_min, d_avg, d_max, d_p99) = summary(&r.diff);
        let _ = writeln!(
            out,
            "| {} | {:.1} s | {:.3} cores | {:.1} / {:.1} MiB | {:.2} | {c_min:.2} / {c_avg:.2} / {c_max:.2} / {c_p99:.2} ms | {d_min:.2} / {d_avg:.2} / {d_max:.2} / {d_p99:.2} ms | {} of {} |",
            r.vars,
            r.ready_s,
            r.cpu_cores,
            r.rss_peak_mib,
            r.rss_mib,
            r.requests_per_cycle,
            r.diff.len(),
            r.confirm.len()
        );
        for (metric, value) in [
            ("ready_s", r.ready_s),
            ("cpu_cores", r.cpu_cores),
            ("rss_peak_mib", r.rss_peak_mib),
            ("rss_mib", r.rss_mib),
            ("requests_per_cycle", r.requests_per_cycle),
            ("set_confirm_min_ms", c_min),
            ("set_confirm_avg_ms", c_avg),
            ("set_confirm_max_ms", c_max),
            ("set_confirm_p99_ms", c_p99),
            ("set_diff_min_ms", d_min),
            ("set_diff_avg_ms", d_avg),
            ("set_diff_max_ms", d_max),
            ("set_diff_p99_ms", d_p99),
        ] {
            let _ = writeln!(results, "opcua_{}.{metric} {value:.3}", r.vars);
        }
    }
    print!("{out}");
    if let Some(path) = &args.out {
        timed::append(path, &results);
    }
}
