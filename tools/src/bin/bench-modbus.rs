//! bench-modbus: a Modbus section of 10,000 tags of mixed types across the
//! four tables, polled every 100 ms through the real server (planner, link,
//! Modbus backend) against `plcsim --modbus` on 127.0.0.1.
//!
//! - requests per cycle against the minimum: the fewest reads that cover
//!   every tag within the request limits (125 registers, 2000 bits), found
//!   here by greedy covering per table, independently of the planner;
//! - poll cycle time p50/p99: each cycle's `read` timed by a decorator
//!   around the backend;
//! - SET -> write confirmed -> DIFF: one client SETs tags another one has
//!   enabled (with every other tag polled): from sending the SET to its
//!   answer (written and read back), and to the DIFF at the other client;
//! - all of it with MODBUS_INFLIGHT 1 and 4, with the device answering at
//!   once and after a latency.
//!
//! Run: `cargo run --release -p plccoms-tools --bin bench-modbus -- --help`.

#[path = "../timed.rs"]
mod timed;

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::time::Duration;

use clap::Parser;

use plccoms_driver_modbus::ModbusBackend;
use plcsim::program::ProgramKind;
use plcsim::{PubSource as SimPub, SimConfig};
use timed::{measure, percentile};

#[derive(Debug, Parser)]
#[command(name = "bench-modbus")]
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
    /// Device answer latencies to run at (ms).
    #[arg(long, value_delimiter = ',', default_value = "0,2")]
    latencies: Vec<u64>,
    /// MODBUS_INFLIGHT values to run with.
    #[arg(long, value_delimiter = ',', default_value = "1,4")]
    inflight: Vec<u8>,
    /// Append `modbus.<metric> value` lines here (bench/run's results).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
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

/// A tag file and what it covers: per table, (first address, span).
struct Project {
    csv: String,
    spans: [Vec<(u32, u32)>; 4],
}

const SET_TAGS: usize = 16;

/// Tags as a device program would publish them: runs of registers with
/// small holes, now and then a jump; types mixed, orders mixed.
fn generate(total: usize, seed: u64) -> Project {
    let mut rng = Lcg(seed);
    let mut csv = String::from("name,type,table,address,bit,order,scale,offset\n");
    let mut spans: [Vec<(u32, u32)>; 4] = Default::default();
    let mut next = [0u32; 4];
    let tables = ["coil", "discrete", "holding", "input"];
    for i in 0..total {
        // The tags SET writes are holding INTs.
        let t = if i < SET_TAGS {
            2
        } else {
            match rng.below(100) {
                0..=14 => 0,
                15..=29 => 1,
                30..=74 => 2,
                _ => 3,
            }
        };
        let (ty, span, extra) = if t < 2 {
            ("BOOL", 1, String::new())
        } else if i < SET_TAGS {
            ("INT", 1, String::new())
        } else {
            match rng.below(20) {
                0..=4 => ("INT", 1, String::new()),
                5..=6 => ("UINT", 1, String::new()),
                7..=8 => ("DINT", 2, String::new()),
                9..=12 => (
                    "REAL",
                    2,
                    if rng.below(2) == 0 {
                        ",,CDAB".into()
                    } else {
                        String::new()
                    },
                ),
                13 => ("LREAL", 4, String::new()),
                14 => ("STRING[8]", 4, String::new()),
                15 => ("TS48", 3, String::new()),
                16..=17 => ("INT", 1, ",,,0.1,-40".into()),
                _ => ("BOOL", 1, format!(",{}", rng.below(16))),
            }
        };
        let gap = match rng.below(100) {
            0 => 300,
            1..=70 => 0,
            _ => rng.below(3) as u32,
        };
        let address = next[t] + if t < 2 { gap * 8 } else { gap };
        next[t] = address + span;
        spans[t].push((address, span));
        let extra = if ty == "BOOL" && t >= 2 && extra.is_empty() {
            ",0".into()
        } else {
            extra
        };
        let _ = writeln!(csv, "t{i},{ty},{},{address}{extra}", tables[t]);
    }
    Project { csv, spans }
}

/// The fewest reads that cover every span: greedy windows per table.
fn minimum_requests(project: &Project, max_regs: u32, max_bits: u32) -> usize {
    project
        .spans
        .iter()
        .enumerate()
        .map(|(t, spans)| {
            let max = if t < 2 { max_bits } else { max_regs };
            let mut sorted = spans.clone();
            sorted.sort_unstable();
            let (mut count, mut covered) = (0, None::<u32>);
            for (start, span) in sorted {
                let end = start + span;
                let mut from = match covered {
                    Some(covered) if end <= covered => continue,
                    Some(covered) if start < covered => covered,
                    _ => start,
                };
                while from < end {
                    count += 1;
                    from += max;
                    covered = Some(from);
                }
            }
            count
        })
        .sum()
}

/// What one run measured.
struct Run {
    label: String,
    requests: Vec<u64>,
    cycle_ms: Vec<f64>,
    confirm_ms: Vec<f64>,
    diff_ms: Vec<f64>,
}

async fn run(args: &Args, project: &Project, inflight: u8, latency: u64) -> Run {
    let device = plcsim::spawn(SimConfig {
        modbus: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
        pubfile: SimPub::Bytes(project.csv.clone().into_bytes()),
        program: ProgramKind::Idle,
        latency: Duration::from_millis(latency),
        ..SimConfig::default()
    })
    .await
    .expect("plcsim --modbus");
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("tags.csv"), &project.csv).expect("tags");
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = {}\n[Bench]\nPROTOCOL = MODBUS_TCP\nIPADDR = 127.0.0.1\n\
         MODBUS_PORT = {}\nMODBUS_TAGS = tags.csv\nMODBUS_INFLIGHT = {inflight}\nSERVER_PORT = 1\n",
        args.delay,
        device.local_addr().port()
    );
    let measured = measure(
        dir.path(),
        &ini,
        |section| {
            Box::new(ModbusBackend::new(plccoms_driver_modbus::config_of(
                section,
                device.local_addr(),
                dir.path(),
            )))
        },
        args.delay,
        args.cycles,
        args.sets,
        SET_TAGS,
    )
    .await;
    Run {
        label: format!("inflight{inflight}_lat{latency}"),
        requests: measured.requests,
        cycle_ms: measured.cycle_ms,
        confirm_ms: measured.confirm_ms,
        diff_ms: measured.diff_ms,
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    let project = generate(args.tags, args.seed);
    let minimum = minimum_requests(&project, 125, 2000);
    let mut out = String::new();
    let mut results = String::new();
    let _ = writeln!(
        out,
        "## bench-modbus\n\n{} tags (coils {}, discrete {}, holding {}, input {}), COMM_LOOP_DELAY {} ms, \
         plcsim --modbus on 127.0.0.1; minimum reads per cycle {minimum}\n",
        args.tags,
        project.spans[0].len(),
        project.spans[1].len(),
        project.spans[2].len(),
        project.spans[3].len(),
        args.delay
    );
    let _ = writeln!(
        out,
        "| MODBUS_INFLIGHT | device latency | reads per cycle (x minimum) | cycle p50 / p99 | SET confirmed p50 / p99 | SET -> DIFF p50 / p99 | DIFFs seen |"
    );
    let _ = writeln!(out, "| --- | --- | --- | --- | --- | --- | --- |");
    let _ = writeln!(results, "modbus.min_reads_per_cycle {minimum}");
    for &latency in &args.latencies {
        for &inflight in &args.inflight {
            let r = run(&args, &project, inflight, latency).await;
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
                "| {inflight} | {latency} ms | {median} ({ratio:.3}) | {:.2} / {:.2} ms | {:.2} / {:.2} ms | {:.2} / {:.2} ms | {} of {} |",
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
                ("reads_per_cycle", median as f64),
                ("reads_ratio_to_min", ratio),
                ("cycle_p50_ms", percentile(&cycle, 0.5)),
                ("cycle_p99_ms", percentile(&cycle, 0.99)),
                ("set_confirm_p50_ms", percentile(&confirm, 0.5)),
                ("set_confirm_p99_ms", percentile(&confirm, 0.99)),
                ("set_diff_p50_ms", percentile(&diff, 0.5)),
                ("set_diff_p99_ms", percentile(&diff, 0.99)),
            ] {
                let _ = writeln!(results, "modbus_{}.{metric} {value:.3}", r.label);
            }
        }
    }
    print!("{out}");
    if let Some(path) = &args.out {
        timed::append(path, &results);
    }
}
