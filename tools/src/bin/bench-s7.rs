//! bench-s7: an S7 section of 10,000 tags of mixed types in DB1 and the
//! merkers, polled every 100 ms through the real server (planner, link, S7
//! backend) against `plcsim --s7` in the same process, and against the
//! Snap7 C server (python-snap7 1.4's wheel) with `--snap7-python`.
//!
//! - requests per cycle against the minimum for the PDU, computed here
//!   independently of the backend's packing: the tags' byte ranges joined
//!   where the gap is below the documented rule's `(PDU - 14) / items`,
//!   each cut to items of at most `PDU - 18` bytes; then the fewest jobs
//!   that hold them, `max(ceil(items / item limit), ceil(answer bytes /
//!   (PDU - 14)))`, a lower bound no packing can beat;
//! - poll cycle time p50/p99 (each `read` of the link timed);
//! - SET -> write confirmed (written and read back) -> DIFF at another
//!   client that has every tag enabled, p50/p99;
//! - at PDU 240, 480 and 960.
//!
//! Run: `cargo run --release -p plccoms-tools --bin bench-s7 -- --help`.

#[path = "../timed.rs"]
mod timed;

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use clap::Parser;

use plccoms_driver_s7::S7Backend;
use plcsim::program::ProgramKind;
use plcsim::{PubSource as SimPub, SimConfig};
use timed::{measure, percentile, Measured};

#[derive(Debug, Parser)]
#[command(name = "bench-s7")]
struct Args {
    /// Tags in the generated tag file (all enabled).
    #[arg(long, default_value_t = 10_000)]
    tags: usize,
    /// Poll cycles timed per run.
    #[arg(long, default_value_t = 100)]
    cycles: usize,
    /// SETs timed per run.
    #[arg(long, default_value_t = 200)]
    sets: usize,
    /// COMM_LOOP_DELAY (ms).
    #[arg(long, default_value_t = 100)]
    delay: u64,
    /// S7_PDU values to run with.
    #[arg(long, value_delimiter = ',', default_value = "240,480,960")]
    pdus: Vec<u16>,
    /// The python of a venv with python-snap7 1.4 (tests/data/s7/venvs.sh
    /// makes target/s7-venvs/c1): also run against the Snap7 C server.
    #[arg(long)]
    snap7_python: Option<PathBuf>,
    /// Append `s7.<metric> value` lines here (bench/run's results).
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

struct Lcg(u64);

impl Lcg {
    fn below(&mut self, n: u64) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) % n
    }
}

/// A tag file and the byte ranges it covers, per region (0 DB1, 1 merkers).
struct Project {
    csv: String,
    spans: [Vec<(u32, u32)>; 2],
}

const SET_TAGS: usize = 16;

/// Tags as a PLC program's data blocks hold them: runs with small holes,
/// now and then a jump; every kind of type.
fn generate(total: usize, seed: u64) -> Project {
    let mut rng = Lcg(seed);
    let mut csv = String::from("name,address,type\n");
    let mut spans: [Vec<(u32, u32)>; 2] = Default::default();
    let mut next = [0u32; 2];
    // The bit of the next BOOL in a run of them.
    let mut bit = [8u8; 2];
    for i in 0..total {
        let r = if i < SET_TAGS || rng.below(3) > 0 {
            0
        } else {
            1
        };
        let (ty, len) = if i < SET_TAGS {
            ("INT", 2)
        } else {
            match rng.below(20) {
                0..=4 => ("INT", 2),
                5..=6 => ("WORD", 2),
                7..=8 => ("DINT", 4),
                9..=11 => ("REAL", 4),
                12 => ("LREAL", 8),
                13 => ("STRING[8]", 10),
                14 => ("DTL", 12),
                15 => ("BYTE", 1),
                _ => ("BOOL", 0),
            }
        };
        if ty == "BOOL" && bit[r] < 8 {
            let byte = next[r] - 1;
            let _ = writeln!(csv, "t{i},{}{byte}.{},BOOL", prefix_bit(r), bit[r]);
            bit[r] += 1;
            continue;
        }
        let gap = match rng.below(100) {
            0 => 200,
            1..=70 => 0,
            _ => rng.below(4) as u32,
        };
        let mut at = next[r] + gap;
        if len >= 2 && at % 2 == 1 {
            at += 1;
        }
        let (address, width) = match ty {
            "BOOL" => {
                bit[r] = 1;
                (format!("{}{at}.0", prefix_bit(r)), 1)
            }
            "STRING[8]" if r == 0 => (format!("DB1.DBS{at}.8"), len),
            _ => (format!("{}{at}", prefix(r, len)), len),
        };
        if ty != "BOOL" {
            bit[r] = 8;
        }
        let ty = if ty == "STRING[8]" && r == 0 { "" } else { ty };
        let _ = writeln!(csv, "t{i},{address},{ty}");
        spans[r].push((at, width));
        next[r] = at + width;
    }
    Project { csv, spans }
}

fn prefix_bit(region: usize) -> &'static str {
    if region == 0 {
        "DB1.DBX"
    } else {
        "M"
    }
}

/// The address prefix of a value of `len` bytes: the width letter of one
/// of 1, 2 or 4 bytes, a byte address for a longer one.
fn prefix(region: usize, len: u32) -> &'static str {
    match (region, len) {
        (0, 2) => "DB1.DBW",
        (0, 4) => "DB1.DBD",
        (0, _) => "DB1.DBB",
        (_, 2) => "MW",
        (_, 4) => "MD",
        _ => "MB",
    }
}

/// The fewest read jobs at `pdu` (see the module's doc), independently of
/// the backend's packing.
fn minimum_jobs(project: &Project, pdu: u32) -> usize {
    let max_items = ((pdu - 12) / 12).min(20) as usize;
    let room = (pdu - 14) as usize;
    let max_item = (pdu - 18) & !1;
    let gap = room as u32 / max_items as u32;
    let (mut items, mut bytes) = (0usize, 0usize);
    for spans in &project.spans {
        let mut sorted = spans.clone();
        sorted.sort_unstable();
        let mut ranges: Vec<(u32, u32)> = Vec::new();
        for (start, len) in sorted {
            match ranges.last_mut() {
                // Joined through a gap of at most `gap` bytes, up to one
                // item's worth (the backend's largest block).
                Some((first, end))
                    if start <= *end + gap && (*end).max(start + len) - *first <= max_item =>
                {
                    *end = (*end).max(start + len)
                }
                _ => ranges.push((start, start + len)),
            }
        }
        for (start, end) in ranges {
            let mut at = start;
            while at < end {
                let len = (end - at).min(max_item);
                items += 1;
                bytes += 4 + len as usize + len as usize % 2;
                at += len;
            }
        }
    }
    items.div_ceil(max_items).max(bytes.div_ceil(room))
}

/// What one run measured.
type Run = Measured;

/// The Snap7 C server with DB1 and the merkers of 65,535 bytes each (its
/// area sizes are 16-bit: 65,536 would be 0).
fn snap7(python: &Path, port: u16) -> std::process::Child {
    let config =
        format!("{{\"port\": {port}, \"areas\": [[\"DB\", 1, 65535], [\"MK\", 0, 65535]]}}");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data/s7/snap7_server.py");
    let mut child = std::process::Command::new(python)
        .arg(script)
        .arg(config)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("start the Snap7 server");
    let mut line = String::new();
    std::io::BufRead::read_line(
        &mut std::io::BufReader::new(child.stdout.as_mut().expect("stdout")),
        &mut line,
    )
    .expect("Snap7 server");
    assert!(line.starts_with("ready"), "Snap7 server: {line}");
    child
}

async fn run(args: &Args, project: &Project, pdu: u16, device: SocketAddr) -> Run {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("tags.csv"), &project.csv).expect("tags");
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = {}\n[Bench]\nPROTOCOL = S7\nIPADDR = 127.0.0.1\n\
         S7_PORT = {}\nS7_TAGS = tags.csv\nS7_PDU = {pdu}\nSERVER_PORT = 1\n",
        args.delay,
        device.port()
    );
    measure(
        dir.path(),
        &ini,
        |section| {
            Box::new(S7Backend::new(plccoms_driver_s7::config_of(
                section,
                device,
                dir.path(),
            )))
        },
        args.delay,
        args.cycles,
        args.sets,
        SET_TAGS,
    )
    .await
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    let project = generate(args.tags, args.seed);
    let mut out = String::new();
    let mut results = String::new();
    let _ = writeln!(
        out,
        "## bench-s7\n\n{} tags (DB1 {} ranges, merkers {}), COMM_LOOP_DELAY {} ms, on 127.0.0.1\n",
        args.tags,
        project.spans[0].len(),
        project.spans[1].len(),
        args.delay
    );
    let _ = writeln!(
        out,
        "| server | PDU | requests per cycle (minimum, x minimum) | cycle p50 / p99 | SET confirmed p50 / p99 | SET -> DIFF p50 / p99 | DIFFs seen |"
    );
    let _ = writeln!(out, "| --- | --- | --- | --- | --- | --- | --- |");
    let mut servers = vec!["plcsim"];
    if args.snap7_python.is_some() {
        servers.push("snap7");
    }
    for server in servers {
        for &pdu in &args.pdus {
            // plcsim grants the PDU asked; Snap7 as well, up to 960.
            let (r, _guard) = match server {
                "plcsim" => {
                    let device = plcsim::spawn(SimConfig {
                        s7: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
                        pubfile: SimPub::Bytes(project.csv.clone().into_bytes()),
                        program: ProgramKind::Idle,
                        ..SimConfig::default()
                    })
                    .await
                    .expect("plcsim --s7");
                    (run(&args, &project, pdu, device.local_addr()).await, None)
                }
                _ => {
                    let port = std::net::TcpListener::bind("127.0.0.1:0")
                        .and_then(|l| l.local_addr())
                        .expect("a free port")
                        .port();
                    let python = args.snap7_python.as_deref().expect("--snap7-python");
                    let mut child = snap7(python, port);
                    let r = run(
                        &args,
                        &project,
                        pdu,
                        SocketAddr::from(([127, 0, 0, 1], port)),
                    )
                    .await;
                    let _ = child.kill();
                    let _ = child.wait();
                    (r, Some(()))
                }
            };
            let minimum = minimum_jobs(&project, u32::from(pdu));
            let sorted = |v: &[f64]| {
                let mut v = v.to_vec();
                v.sort_by(f64::total_cmp);
                v
            };
            let (cycle, confirm, diff) = (
                sorted(&r.cycle_ms),
                sorted(&r.confirm_ms),
                sorted(&r.diff_ms),
            );
            let mut requests = r.requests.clone();
            requests.sort_unstable();
            let median = requests.get(requests.len() / 2).copied().unwrap_or(0);
            let ratio = median as f64 / minimum.max(1) as f64;
            let _ = writeln!(
                out,
                "| {server} | {pdu} | {median} ({minimum}, {ratio:.3}) | {:.2} / {:.2} ms | {:.2} / {:.2} ms | {:.2} / {:.2} ms | {} of {} |",
                percentile(&cycle, 0.5),
                percentile(&cycle, 0.99),
                percentile(&confirm, 0.5),
                percentile(&confirm, 0.99),
                percentile(&diff, 0.5),
                percentile(&diff, 0.99),
                diff.len(),
                confirm.len()
            );
            for (metric, value) in [
                ("min_requests_per_cycle", minimum as f64),
                ("requests_per_cycle", median as f64),
                ("requests_ratio_to_min", ratio),
                ("cycle_p50_ms", percentile(&cycle, 0.5)),
                ("cycle_p99_ms", percentile(&cycle, 0.99)),
                ("set_confirm_p50_ms", percentile(&confirm, 0.5)),
                ("set_confirm_p99_ms", percentile(&confirm, 0.99)),
                ("set_diff_p50_ms", percentile(&diff, 0.5)),
                ("set_diff_p99_ms", percentile(&diff, 0.99)),
            ] {
                let _ = writeln!(results, "s7_{server}_pdu{pdu}.{metric} {value:.3}");
            }
        }
    }
    print!("{out}");
    if let Some(path) = &args.out {
        timed::append(path, &results);
    }
}
