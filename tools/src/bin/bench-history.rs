//! Figures of the historian's store that need no running server:
//!
//! - `bench-history sizes`: bytes on disk per sample, by type, for 10,000
//!   variables changing every 100 ms (values as `plcsim --animate` makes
//!   them), written through the store as the writer writes (one transaction
//!   per second of samples), then packed into blocks as HISTORY_COMPACT
//!   packs them (bytes per sample of the finished day, and the cost).
//! - `bench-history day --dir D --section S [--packed]`: a day file holding
//!   one LREAL sampled every 100 ms (864,000 samples), as rows or packed,
//!   for timing `plccoms history`.
//!
//! Prints `label.metric value` lines (bench/run appends them to its
//! results).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use clap::{Parser, Subcommand};
use plccoms_core::changes::Quality;
use plccoms_core::vars::VarTable;
use plccoms_historian::sample::{Sample, Stored};
use plccoms_historian::store::{day_of, file_bytes, DayFile, DAY_MS};

#[derive(Parser)]
struct Args {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Bytes per sample by type.
    Sizes {
        /// Variables of each type.
        #[arg(long, default_value_t = 10_000)]
        vars: usize,
        /// Seconds of samples (10 polls each).
        #[arg(long, default_value_t = 20)]
        seconds: usize,
    },
    /// A day of one LREAL every 100 ms.
    Day {
        #[arg(long)]
        dir: PathBuf,
        #[arg(long, default_value = "Bench")]
        section: String,
        /// UTC day, as days since 1970 (default: yesterday).
        #[arg(long)]
        day: Option<i64>,
        /// Pack the samples into blocks, as a finished day is.
        #[arg(long)]
        packed: bool,
    },
}

fn table(ty: &str, n: usize) -> Arc<VarTable> {
    let size = match ty {
        "BOOL" => 1,
        "STRING[16]" => 17,
        "LREAL" => 8,
        _ => 4,
    };
    let mut text = String::new();
    for i in 0..n {
        let kind = if ty.contains("REAL") { "F" } else { "B" };
        text.push_str(&format!(
            " V_{i:05} R {kind} {} {ty} PUB_INOUT\r\n",
            i * size
        ));
    }
    Arc::new(VarTable::from_public_text("bench.pub", text.as_bytes()).expect("table"))
}

/// The value `plcsim --animate` gives variable `k` of type `ty` at cycle
/// `cycle`.
fn animated(ty: &str, cycle: u64, k: usize) -> Stored {
    match ty {
        "BOOL" => Stored::Int((cycle % 2) as i64),
        "INT" => Stored::Int(i64::from(cycle as u16 as i16)),
        "UDINT" => Stored::Int(i64::from(cycle as u32)),
        "REAL" => Stored::Real(f64::from(
            ((cycle as f64 * 0.01 + k as f64 * 0.5).sin() * 100.0) as f32,
        )),
        "LREAL" => Stored::Real((cycle as f64 * 0.01 + k as f64 * 0.5).sin() * 100.0),
        _ => Stored::Text(format!("count {cycle}")),
    }
}

/// What to write: `seconds` of 10 polls of `vars`, from cycle 1000 at
/// `start_ms + 100 s`, one transaction per `commit_every` seconds.
struct Run<'a> {
    dir: &'a Path,
    section: &'a str,
    table: &'a Arc<VarTable>,
    vars: &'a [u32],
    start_ms: i64,
    seconds: usize,
    commit_every: usize,
}

fn write_seconds(run: Run<'_>, mut value: impl FnMut(u64, usize) -> Stored) -> (PathBuf, u64, f64) {
    let Run {
        dir,
        section,
        table,
        vars,
        start_ms,
        seconds,
        commit_every,
    } = run;
    let day = day_of(start_ms + 100_000);
    let mut file = DayFile::open(dir, section, day).expect("day file");
    let path = file.path.clone();
    let mut written = 0;
    let mut busy = 0.0;
    let mut samples = Vec::new();
    for second in 0..seconds {
        for poll in 0..10u64 {
            let cycle = second as u64 * 10 + poll + 1_000;
            let t = start_ms + cycle as i64 * 100;
            for (k, &var) in vars.iter().enumerate() {
                samples.push(Sample {
                    t,
                    var,
                    value: value(cycle, k),
                    quality: Quality::Good,
                    plc_time: None,
                });
            }
        }
        if (second + 1) % commit_every == 0 || second + 1 == seconds {
            let started = Instant::now();
            let counts = file.write(&[(table, &samples)], &[]).expect("write");
            busy += started.elapsed().as_secs_f64();
            written += counts.written;
            samples.clear();
        }
    }
    file.close();
    (path, written, busy)
}

/// Packs a day file whole, as the writer finishes a day; (samples, seconds
/// packing took).
fn pack_all(dir: &Path, section: &str, day: i64) -> (u64, f64) {
    let mut file = DayFile::open(dir, section, day).expect("day file");
    let started = Instant::now();
    let far = started + std::time::Duration::from_secs(24 * 3600);
    let packing = file.pack(i64::MAX, far).expect("pack");
    let took = started.elapsed().as_secs_f64();
    // The pages the rows took go back (once a day, for the rows of the
    // last HISTORY_COMPACT only when the day was packed as it went).
    while !file.shrink(1 << 20).expect("shrink") {}
    file.close();
    (packing.samples, took)
}

fn main() {
    let args = Args::parse();
    match args.command {
        Cmd::Sizes { vars, seconds } => {
            for ty in ["BOOL", "INT", "UDINT", "REAL", "LREAL", "STRING[16]"] {
                let dir = tempfile::tempdir().expect("tempdir");
                let table = table(ty, vars);
                let ids: Vec<u32> = (table.fixed_count()..table.len())
                    .map(|i| i as u32)
                    .collect();
                // Cycle 1000 at noon: a key takes 6 bytes from 17 minutes
                // into the day on (5 before).
                let today = day_of(plccoms_core::changes::unix_ms(std::time::SystemTime::now()));
                let start = today * DAY_MS + DAY_MS / 2 - 100_000;
                let run = Run {
                    dir: dir.path(),
                    section: "S",
                    table: &table,
                    vars: &ids,
                    start_ms: start,
                    seconds,
                    commit_every: 1,
                };
                let (path, written, busy) = write_seconds(run, |c, k| animated(ty, c, k));
                let bytes = file_bytes(&path);
                let label = ty.split('[').next().unwrap_or(ty).to_ascii_lowercase();
                println!(
                    "history_size.{label}_bytes_per_sample {:.2}",
                    bytes as f64 / written as f64
                );
                println!(
                    "history_size.{label}_insert_us_per_sample {:.3}",
                    busy * 1e6 / written as f64
                );
                let (packed, took) = pack_all(dir.path(), "S", day_of(start + 100_000));
                assert_eq!(packed, written, "every sample packed");
                println!(
                    "history_size.{label}_packed_bytes_per_sample {:.2}",
                    file_bytes(&path) as f64 / written as f64
                );
                println!(
                    "history_size.{label}_pack_us_per_sample {:.3}",
                    took * 1e6 / written as f64
                );
            }
        }
        Cmd::Day {
            dir,
            section,
            day,
            packed,
        } => {
            let now = plccoms_core::changes::unix_ms(std::time::SystemTime::now());
            let day = day.unwrap_or(day_of(now) - 1);
            let table = table("LREAL", 1);
            let id = table.fixed_count() as u32;
            let start = day * DAY_MS - 100_000; // cycle 1000 at midnight
            let run = Run {
                dir: &dir,
                section: &section,
                table: &table,
                vars: &[id],
                start_ms: start,
                seconds: 86_400,
                commit_every: 3600,
            };
            let (path, written, busy) =
                write_seconds(run, |c, _| Stored::Real((c as f64 * 0.001).sin()));
            let label = if packed {
                let (n, took) = pack_all(&dir, &section, day);
                assert_eq!(n, written, "every sample packed");
                println!("history_day_packed.pack_s {took:.2}");
                "history_day_packed"
            } else {
                "history_day"
            };
            println!("{label}.rows {written}");
            println!(
                "{label}.file_mib {:.1}",
                file_bytes(&path) as f64 / 1048576.0
            );
            println!("{label}.write_s {busy:.2}");
        }
    }
}
