//! bench-rtu: a cycle of N holding registers (300 by default) from three
//! Modbus RTU units on one serial line, at 9600 and 115200 baud, against
//! the physical limit.
//!
//! The line is a socat pty pair; plcsim on its other end answers as units
//! 1, 2 and 3 and holds each answer back for the time the request and the
//! answer take on a real line at 11 bits a character (8E1) plus the 3.5
//! characters of silence that end the request (a pty passes bytes at memory
//! speed). The server (three sections on the one SERIAL_DEVICE, each polling
//! N/3 registers back to back, COMM_LOOP_DELAY = 1) keeps the other silence,
//! after each answer, itself. Over the window: the bytes and frames on the
//! line (plcsim's counters); the physical limit is bytes x 11 / baud plus
//! 2 x 3.5 characters per transaction; the ratio is the window over the
//! limit, per cycle of the three units (the line's time not used by frames
//! and silences: the server's and the simulator's turn-around, the pty).
//!
//! Run: `cargo run --release -p plccoms-tools --bin bench-rtu` (needs socat).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use clap::Parser;

use plccoms_plc::modbus::rtu;
use plcsim::serial::SerialLine;

#[path = "common/line.rs"]
mod line;
use plcsim::{PubSource, SimConfig};

#[derive(Debug, Parser)]
#[command(name = "bench-rtu")]
struct Args {
    /// Registers per cycle, over the three units (each polls a third).
    #[arg(long, default_value_t = 300)]
    regs: usize,
    /// Line speeds, baud.
    #[arg(long, value_delimiter = ',', default_value = "9600,115200")]
    speeds: Vec<u32>,
    /// Seconds measured per speed.
    #[arg(long, default_value_t = 10)]
    seconds: u64,
    /// Client port of the first section (127.0.0.1; the next two follow).
    #[arg(long, default_value_t = 21195)]
    port: u16,
    /// Append `label value` lines here (for bench/report).
    #[arg(long)]
    out: Option<PathBuf>,
}

/// A tag file of `n` INT holding registers from 0.
fn tags(n: usize) -> String {
    let mut text = String::from("name,type,table,address\n");
    for i in 0..n {
        let _ = writeln!(text, "r{i},INT,holding,{i}");
    }
    text
}

struct Figures {
    cycles: f64,
    cycle_ms: f64,
    limit_ms: f64,
    bytes: f64,
    failures: u64,
}

async fn run(args: &Args, speed: u32, dir: &Path) -> Figures {
    let per_unit = args.regs.div_ceil(3);
    let tag_file = tags(per_unit);
    std::fs::write(dir.join("tags.csv"), &tag_file).unwrap();
    let pty = line::PtyPair::new(dir).await;
    let (plc_end, server_end) = (&pty.plc, &pty.server);
    let sim = plcsim::spawn(SimConfig {
        pubfile: PubSource::Bytes(tag_file.into_bytes()),
        program: "idle".parse().unwrap(),
        serial: Some(SerialLine {
            device: plc_end.display().to_string(),
            speed,
            emulate: true,
        }),
        modbus_rtu: vec![1, 2, 3],
        ..SimConfig::default()
    })
    .await
    .expect("plcsim on the line");
    let mut ini = String::from("[*]\nCOMM_LOOP_DELAY = 1\n");
    for unit in 1..=3u16 {
        let _ = write!(
            ini,
            "[U{unit}]\nPROTOCOL = MODBUS_RTU\nSERIAL_DEVICE = {}\nSERIAL_SPEED = {speed}\n\
             MODBUS_UNIT = {unit}\nMODBUS_TAGS = tags.csv\nMODBUS_TIMEOUT = 2000\n\
             SERVER_PORT = {}\n",
            server_end.display(),
            args.port + unit - 1
        );
    }
    let path = dir.join("PLCComS.ini");
    std::fs::write(&path, ini).unwrap();
    let loaded = plccoms_core::config::load(&path).expect("ini");
    let server = plccoms::startup::start(&loaded.config)
        .await
        .expect("start");
    for unit in 0..3 {
        line::enable_all(args.port + unit).await;
    }
    let failures = || {
        server
            .sections
            .iter()
            .map(|s| {
                let b = &s.section.metrics().backend;
                b.timeouts.get() + b.errors.get()
            })
            .sum::<u64>()
    };
    let stats = sim.line_stats();
    let line = || {
        let get = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        (
            get(&stats.rx_bytes) + get(&stats.tx_bytes),
            get(&stats.rx_frames),
        )
    };
    // Both ends of the window when a request has just arrived: between
    // them, whole transactions (each request with its answer).
    let at_request = || async {
        let frames = line().1;
        let waited = Instant::now();
        while line().1 == frames {
            assert!(
                waited.elapsed() < Duration::from_secs(10),
                "no request in 10 s: does the server poll?"
            );
            tokio::time::sleep(Duration::from_micros(100)).await;
        }
        (Instant::now(), line(), failures())
    };
    tokio::time::sleep(Duration::from_secs(3)).await;
    let (start, line0, failures0) = at_request().await;
    tokio::time::sleep(Duration::from_secs(args.seconds)).await;
    let (end, line1, failures1) = at_request().await;
    let window = end - start;
    drop(server);
    drop(sim);
    drop(pty);
    let (bytes, frames) = (line1.0 - line0.0, line1.1 - line0.1);
    let silence = rtu::silence(speed, 11).as_secs_f64();
    let limit =
        rtu::line_time(speed, 11, bytes as usize).as_secs_f64() + frames as f64 * 2.0 * silence;
    let cycles = frames as f64 / 3.0;
    Figures {
        cycles,
        cycle_ms: window.as_secs_f64() * 1000.0 / cycles.max(1.0),
        limit_ms: limit * 1000.0 / cycles.max(1.0),
        bytes: bytes as f64 / cycles.max(1.0),
        failures: failures1 - failures0,
    }
}

#[tokio::main]
async fn main() {
    let args = Args::parse();
    let mut lines = String::new();
    let mut sound = true;
    println!(
        "bench-rtu: {} holding registers per cycle from 3 units on one line, {} s per speed",
        args.regs, args.seconds
    );
    for &speed in &args.speeds {
        let dir = tempfile::tempdir().unwrap();
        let f = run(&args, speed, dir.path()).await;
        let ratio = f.cycle_ms / f.limit_ms;
        println!(
            "{speed} baud 8E1 (socat pty pair, line time emulated): {:.1} cycles, {:.0} bytes a cycle; \
             cycle {:.2} ms, physical limit {:.2} ms (bytes x 11 / baud + 2 x 3.5 characters a \
             transaction), ratio {ratio:.3}; failed exchanges {}",
            f.cycles, f.bytes, f.cycle_ms, f.limit_ms, f.failures
        );
        for (label, value) in [
            ("cycles", format!("{:.1}", f.cycles)),
            ("cycle_ms", format!("{:.2}", f.cycle_ms)),
            ("limit_ms", format!("{:.2}", f.limit_ms)),
            ("ratio", format!("{ratio:.3}")),
            ("failures", f.failures.to_string()),
        ] {
            let _ = writeln!(lines, "rtu{speed}.{label} {value}");
        }
        sound &= f.failures == 0 && f.cycles >= 1.0;
    }
    if let Some(out) = args.out {
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&out)
            .expect("--out file");
        std::io::Write::write_all(&mut file, lines.as_bytes()).expect("write --out");
    }
    if !sound {
        eprintln!("bench-rtu: failed exchanges or no cycles: the figures are not sound");
        std::process::exit(1);
    }
}
