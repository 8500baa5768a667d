//! bench-serial: a poll read of N variables (1,000 by default) over EPSNET
//! on a serial line at 115200 baud, against the physical limit, and the
//! same read through the example backend plugin.
//!
//! The line is a pty pair made by socat; the simulated PLC on its other end
//! holds each answer back for the time the request and the answer take on a
//! real line at the speed (`plcsim --emulate-line`), since a pty passes
//! bytes at memory speed. The server (a real section, started from an ini
//! file, COMM_LOOP_DELAY = 1: cycles back to back) polls every variable a
//! client enabled (`EN:*`). Per cycle: the bytes both ways on the line (the
//! simulator's counters), the physical limit (bytes x 10 bits / baud, half
//! duplex) and the measured cycle time (the section's poll-cycle
//! histogram); the ratio is the server's overhead over the line.
//!
//! Run: `cargo run --release -p plccoms-tools --bin bench-serial` (needs
//! socat and the demo plugin built: `cargo build --release --workspace`).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Duration;

use clap::Parser;

use plcsim::serial::SerialLine;

#[path = "common/line.rs"]
mod line;
use plcsim::{PubSource, SimConfig};

#[derive(Debug, Parser)]
#[command(name = "bench-serial")]
struct Args {
    /// Variables in the generated public file (all enabled).
    #[arg(long, default_value_t = 1000)]
    vars: usize,
    /// Line speed, baud.
    #[arg(long, default_value_t = 115_200)]
    speed: u32,
    /// Seconds measured per run.
    #[arg(long, default_value_t = 10)]
    seconds: u64,
    /// The example plugin (default: beside this binary).
    #[arg(long)]
    plugin: Option<PathBuf>,
    /// Client port of the server (127.0.0.1).
    #[arg(long, default_value_t = 21190)]
    port: u16,
    /// Append `label value` lines here (for bench/report).
    #[arg(long)]
    out: Option<PathBuf>,
}

/// A public file of `n` variables in the R area, of a typical mix of types,
/// each in its own place.
fn generate(n: usize) -> Vec<u8> {
    const TYPES: [(&str, u32); 6] = [
        ("REAL", 4),
        ("INT", 2),
        ("DINT", 4),
        ("BYTE", 1),
        ("LREAL", 8),
        ("WORD", 2),
    ];
    let mut text = String::from("; bench-serial\r\n");
    let mut offset = 1000u32;
    for i in 0..n {
        if i % 8 == 7 {
            let _ = write!(text, " v{i} R B {offset} .{} BOOL PUB_INOUT\r\n", i % 8);
            offset += 1;
            continue;
        }
        let (ty, len) = TYPES[i % TYPES.len()];
        let kind = if ty.ends_with("REAL") { "F" } else { "B" };
        let _ = write!(text, " v{i} R {kind} {offset} {ty} PUB_INOUT\r\n");
        offset += len;
    }
    text.into_bytes()
}

/// What a run measured over its window.
struct Run {
    cycles: u64,
    mean: Duration,
    /// The backend's requests (retries included), and its failed exchanges
    /// (timeouts and bad answers): a sound run has none.
    requests: u64,
    failures: u64,
    /// Bytes and request frames on the line (serial only).
    bytes: u64,
    frames: u64,
}

/// A running server on `ini`, a client with `EN:*`, and the measurement
/// over `seconds`; `line` reads the line's (bytes, frames) counters.
async fn measure(
    dir: &Path,
    ini: &str,
    port: u16,
    seconds: u64,
    line: &dyn Fn() -> (u64, u64),
) -> Run {
    let path = dir.join("PLCComS.ini");
    std::fs::write(&path, ini).unwrap();
    let loaded = plccoms_core::config::load(&path).expect("ini");
    let server = plccoms::startup::start(&loaded.config)
        .await
        .expect("start");
    let metrics = server.sections[0].section.metrics().clone();
    line::enable_all(port).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    // Both ends of the window just after a cycle ends, so the line's bytes
    // are those of whole cycles.
    let cycle_end = || async {
        let count = metrics.poll_cycle.count();
        let waited = std::time::Instant::now();
        while metrics.poll_cycle.count() == count {
            assert!(
                waited.elapsed() < Duration::from_secs(10),
                "no poll cycle in 10 s: is the PLC reachable?"
            );
            tokio::time::sleep(Duration::from_micros(200)).await;
        }
        let backend = &metrics.backend;
        (
            metrics.poll_cycle.count(),
            metrics.poll_cycle.sum(),
            backend.requests.get(),
            backend.timeouts.get() + backend.errors.get(),
            line(),
        )
    };
    let (count0, sum0, requests0, failures0, line0) = cycle_end().await;
    tokio::time::sleep(Duration::from_secs(seconds)).await;
    let (count1, sum1, requests1, failures1, line1) = cycle_end().await;
    drop(server);
    let cycles = count1 - count0;
    Run {
        cycles,
        mean: (sum1 - sum0) / cycles.max(1) as u32,
        requests: requests1 - requests0,
        failures: failures1 - failures0,
        bytes: line1.0 - line0.0,
        frames: line1.1 - line0.1,
    }
}

#[tokio::main]
async fn main() {
    let args = Args::parse();
    let dir = tempfile::tempdir().unwrap();
    let project = generate(args.vars);
    std::fs::write(dir.path().join("bench.pub"), &project).unwrap();
    let port = args.port;

    // The line: socat's pty pair.
    let pty = line::PtyPair::new(dir.path()).await;
    let (plc_end, server_end) = (&pty.plc, &pty.server);
    let sim = plcsim::spawn(SimConfig {
        pubfile: PubSource::Bytes(project.clone()),
        program: "idle".parse().unwrap(),
        serial: Some(SerialLine {
            device: plc_end.display().to_string(),
            speed: args.speed,
            emulate: true,
        }),
        ..SimConfig::default()
    })
    .await
    .expect("plcsim on the line");
    let global = "[*]\nCOMM_LOOP_DELAY = 1\n";
    let serial_ini = format!(
        "{global}[Line]\nSERIAL_DEVICE = {}\nSERIAL_SPEED = {}\nSERVER_PORT = {port}\nPUBFILE = bench.pub\n",
        server_end.display(),
        args.speed
    );
    let stats = sim.line_stats();
    let counters = || {
        let get = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        (
            get(&stats.rx_bytes) + get(&stats.tx_bytes),
            get(&stats.rx_frames),
        )
    };
    let serial = measure(dir.path(), &serial_ini, port, args.seconds, &counters).await;
    drop(sim);
    drop(pty);

    let plugin = args.plugin.unwrap_or_else(|| {
        std::env::current_exe()
            .unwrap()
            .parent()
            .unwrap()
            .join("libplccoms_demo_plugin.so")
    });
    if !plugin.exists() {
        eprintln!(
            "bench-serial: no plugin at {} (cargo build --release -p plccoms-demo-plugin)",
            plugin.display()
        );
        std::process::exit(2);
    }
    let plugin_ini = format!(
        "{global}[Plugin]\nSHM_NAME = {}\nSERVER_PORT = {port}\nPUBFILE = bench.pub\n",
        plugin.display()
    );
    let plugged = measure(dir.path(), &plugin_ini, port, args.seconds, &|| (0, 0)).await;

    let per_cycle = |n: u64, run: &Run| n as f64 / run.cycles.max(1) as f64;
    let bytes = per_cycle(serial.bytes, &serial);
    let limit_ms = bytes * 10.0 / f64::from(args.speed) * 1000.0;
    let ms = |d: Duration| d.as_secs_f64() * 1000.0;
    let figures = [
        ("serial.cycles", serial.cycles.to_string()),
        (
            "serial.requests_per_cycle",
            format!("{:.1}", per_cycle(serial.frames, &serial)),
        ),
        ("serial.bytes_per_cycle", format!("{bytes:.0}")),
        ("serial.cycle_ms", format!("{:.2}", ms(serial.mean))),
        ("serial.limit_ms", format!("{limit_ms:.2}")),
        ("serial.ratio", format!("{:.3}", ms(serial.mean) / limit_ms)),
        ("serial.failures", serial.failures.to_string()),
        ("plugin.cycles", plugged.cycles.to_string()),
        (
            "plugin.requests_per_cycle",
            format!("{:.1}", per_cycle(plugged.requests, &plugged)),
        ),
        ("plugin.cycle_ms", format!("{:.3}", ms(plugged.mean))),
        ("plugin.failures", plugged.failures.to_string()),
    ];
    let figure = |label: &str| &figures.iter().find(|(l, _)| *l == label).unwrap().1;
    println!(
        "bench-serial: {} variables enabled (EN:*), {} s measured per run",
        args.vars, args.seconds
    );
    println!(
        "serial line, {} baud 8N1 (socat pty pair, line time emulated): {} cycles, \
         {} requests and {bytes:.0} bytes on the line per cycle",
        args.speed,
        serial.cycles,
        figure("serial.requests_per_cycle"),
    );
    println!(
        "serial line: poll cycle {} ms, physical limit {limit_ms:.2} ms (bytes x 10 / baud), \
         ratio {}; failed exchanges {}",
        figure("serial.cycle_ms"),
        figure("serial.ratio"),
        serial.failures
    );
    println!(
        "plugin {}: {} cycles, {} requests per cycle, poll cycle {} ms; failed calls {}",
        plugin.display(),
        plugged.cycles,
        figure("plugin.requests_per_cycle"),
        figure("plugin.cycle_ms"),
        plugged.failures
    );
    if let Some(out) = args.out {
        let lines: String = figures.iter().map(|(l, v)| format!("{l} {v}\n")).collect();
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&out)
            .expect("--out file");
        std::io::Write::write_all(&mut file, lines.as_bytes()).expect("write --out");
    }
    if serial.failures + plugged.failures > 0 || serial.cycles == 0 || plugged.cycles == 0 {
        eprintln!("bench-serial: failed exchanges or no cycles: the figures are not sound");
        std::process::exit(1);
    }
}
