//! soak: runs `plccoms` against a `plcsim` process with faults (packet loss,
//! latency, HALT/RUN, the simulator killed and restarted) while clients do
//! GET/SET/EN without pause and check every answer; samples the server's
//! RSS and descriptor count every 10 s and prints a summary. Run it through
//! `bench/soak`, which builds the release binaries first.
//!
//! Checks: every answer is the one expected or a documented error (ERROR:10,
//! 20, 21); a GET behind an acknowledged SET of the same client reads that
//! value back unless the PLC was restarted in between (its memory starts at
//! zero); no request goes unanswered for 30 s (a wedged server); the server
//! process stays alive.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use clap::Parser;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use tokio::process::{Child, Command};

#[derive(Debug, Parser)]
#[command(name = "soak")]
struct Args {
    /// How long to run, in minutes (fractions allowed).
    #[arg(default_value_t = 30.0)]
    minutes: f64,
    /// Clients doing GET/SET/EN.
    #[arg(long, default_value_t = 8)]
    clients: usize,
    /// Base port: the server listens on it, the simulator on +1 (UDP) and
    /// its control port on +2.
    #[arg(long, default_value_t = 21100)]
    port: u16,
    /// Pause of each client between rounds, in milliseconds (0: flat out).
    #[arg(long, default_value_t = 20)]
    pause_ms: u64,
}

#[derive(Default)]
struct Stats {
    requests: AtomicU64,
    diffs: AtomicU64,
    errors: Mutex<BTreeMap<String, u64>>,
    problems: Mutex<Vec<String>>,
    problem_count: AtomicU64,
    lost: AtomicU64,
    acked_sets: AtomicU64,
}

impl Stats {
    fn error(&self, line: &str) {
        let code = line.split_whitespace().next().unwrap_or(line).to_string();
        *self.errors.lock().unwrap().entry(code).or_default() += 1;
    }

    fn problem(&self, text: String) {
        self.problem_count.fetch_add(1, Ordering::Relaxed);
        let mut list = self.problems.lock().unwrap();
        if list.len() < 100 {
            eprintln!("soak: PROBLEM: {text}");
            list.push(text);
        }
    }
}

/// Bumped whenever the simulator is restarted (its memory is zero again).
static EPOCH: AtomicU64 = AtomicU64::new(0);

const DOCUMENTED: [&str; 3] = ["ERROR:10 ", "ERROR:20 ", "ERROR:21 "];
const ANSWER_TIMEOUT: Duration = Duration::from_secs(30);

fn bin_dir() -> PathBuf {
    std::env::current_exe()
        .expect("current exe")
        .parent()
        .expect("bin dir")
        .to_path_buf()
}

fn spawn_sim(port: u16) -> std::io::Result<Child> {
    Command::new(bin_dir().join("plcsim"))
        .args([
            "--bind",
            &format!("127.0.0.1:{}", port + 1),
            "--control",
            &format!("127.0.0.1:{}", port + 2),
            "--program",
            "demo",
            "--animate",
            "v_*",
        ])
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .kill_on_drop(true)
        .spawn()
}

async fn control(port: u16, command: &str) -> Result<String, String> {
    let stream = tokio::time::timeout(
        Duration::from_secs(5),
        TcpStream::connect(("127.0.0.1", port + 2)),
    )
    .await
    .map_err(|_| "control connect timed out".to_string())?
    .map_err(|e| e.to_string())?;
    let (read, mut write) = stream.into_split();
    write
        .write_all(format!("{command}\n").as_bytes())
        .await
        .map_err(|e| e.to_string())?;
    let mut line = String::new();
    tokio::time::timeout(
        Duration::from_secs(5),
        BufReader::new(read).read_line(&mut line),
    )
    .await
    .map_err(|_| "control answer timed out".to_string())?
    .map_err(|e| e.to_string())?;
    Ok(line.trim().to_string())
}

struct Conn {
    reader: BufReader<tokio::net::tcp::OwnedReadHalf>,
    writer: tokio::net::tcp::OwnedWriteHalf,
}

impl Conn {
    async fn open(port: u16) -> std::io::Result<Conn> {
        let stream = TcpStream::connect(("127.0.0.1", port)).await?;
        let (read, writer) = stream.into_split();
        Ok(Conn {
            reader: BufReader::new(read),
            writer,
        })
    }

    /// The next line that is not a DIFF of a variable (those are counted
    /// and checked); a DIFF starting with `own` (a SET's answer) is one.
    async fn answer(&mut self, stats: &Stats, own: &str) -> Result<String, String> {
        loop {
            let mut raw = Vec::new();
            let n = tokio::time::timeout(ANSWER_TIMEOUT, self.reader.read_until(b'\n', &mut raw))
                .await
                .map_err(|_| "no answer within 30 s".to_string())?
                .map_err(|e| e.to_string())?;
            if n == 0 {
                return Err("connection closed by the server".to_string());
            }
            let line = String::from_utf8_lossy(&raw).trim_end().to_string();
            if !own.is_empty() && line.starts_with(own) {
                return Ok(line);
            }
            if let Some(diff) = line.strip_prefix("DIFF:") {
                if !diff.contains(',') {
                    stats.problem(format!("malformed DIFF {line:?}"));
                }
                stats.diffs.fetch_add(1, Ordering::Relaxed);
                continue;
            }
            if line.starts_with("WARNING:") {
                continue;
            }
            return Ok(line);
        }
    }
}

async fn client(id: usize, port: u16, pause: Duration, stats: Arc<Stats>, stop: Arc<AtomicBool>) {
    let offset = 2000 + 2 * id as u32;
    let mut value: u16 = 0;
    // The last acknowledged value and the epoch it was set in.
    let mut acked: Option<(u16, u64)> = None;
    // A SET answered with an error since then: its value may be in the PLC.
    let mut uncertain: Option<u16> = None;
    while !stop.load(Ordering::Relaxed) {
        let mut conn = match Conn::open(port).await {
            Ok(conn) => conn,
            Err(e) => {
                stats.problem(format!("client {id}: cannot connect: {e}"));
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        let result: Result<(), String> = async {
            conn.writer
                .write_all(b"EN:v_*\n")
                .await
                .map_err(|e| e.to_string())?;
            stats.requests.fetch_add(1, Ordering::Relaxed);
            let line = conn.answer(&stats, "WARNING:252").await?;
            if !line.starts_with("WARNING:252") && !line.starts_with("ERROR:") {
                stats.problem(format!("EN answered {line:?}"));
            }
            // Reconnect now and then, to exercise connect/disconnect.
            for _ in 0..2000 {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                value = value.wrapping_add(1).max(1);
                let epoch = EPOCH.load(Ordering::SeqCst);
                let request = format!("SET:%RW{offset},{value}\nGET:%RW{offset}\nGET:v_dint\n");
                conn.writer
                    .write_all(request.as_bytes())
                    .await
                    .map_err(|e| e.to_string())?;
                stats.requests.fetch_add(3, Ordering::Relaxed);
                let own = format!("DIFF:%RW{offset},");
                let set = conn.answer(&stats, &own).await?;
                let get = conn.answer(&stats, "").await?;
                let named = conn.answer(&stats, "").await?;
                let set_ok = set == format!("DIFF:%RW{offset},{value}");
                if !set_ok && set.starts_with("DIFF:") {
                    stats.problem(format!("SET {value} answered {set:?}"));
                }
                if set_ok {
                    acked = Some((value, epoch));
                    uncertain = None;
                    stats.acked_sets.fetch_add(1, Ordering::Relaxed);
                } else if set.starts_with("ERROR:") {
                    check_error(&stats, "SET", &set);
                    uncertain = Some(value);
                }
                check_get(&stats, offset, &get, acked, uncertain, epoch);
                if !pause.is_zero() {
                    tokio::time::sleep(pause).await;
                }
                if named.starts_with("ERROR:") {
                    check_error(&stats, "GET", &named);
                } else if !named.starts_with("GET:V_DINT,") {
                    stats.problem(format!("GET:v_dint answered {named:?}"));
                }
            }
            Ok(())
        }
        .await;
        if let Err(e) = result {
            stats.problem(format!("client {id}: {e}"));
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
    }
}

fn check_error(stats: &Stats, what: &str, line: &str) {
    if DOCUMENTED.iter().any(|p| line.starts_with(p)) {
        stats.error(line);
    } else {
        stats.problem(format!("{what} answered {line:?}"));
    }
}

fn check_get(
    stats: &Stats,
    offset: u32,
    line: &str,
    acked: Option<(u16, u64)>,
    uncertain: Option<u16>,
    epoch: u64,
) {
    if line.starts_with("ERROR:") {
        return check_error(stats, "GET", line);
    }
    let Some(got) = line
        .strip_prefix(&format!("GET:%RW{offset},"))
        .and_then(|v| v.parse::<u16>().ok())
    else {
        return stats.problem(format!("GET:%RW{offset} answered {line:?}"));
    };
    // Only when no restart happened since the SET (a new PLC starts at 0).
    let now = EPOCH.load(Ordering::SeqCst);
    if let Some((want, set_epoch)) = acked {
        if set_epoch == epoch && now == epoch && got != want && Some(got) != uncertain {
            stats.lost.fetch_add(1, Ordering::Relaxed);
            stats.problem(format!(
                "%RW{offset}: read {got} after SET {want} was acknowledged"
            ));
        }
    }
}

fn sample(pid: u32) -> Option<(u64, usize)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let rss = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count();
    Some((rss, fds))
}

fn write_ini(dir: &Path, port: u16) -> PathBuf {
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 50\nNET_CONNECT_MAX = 64\n\n[Soak]\nIPADDR = 127.0.0.1\nIPADDR_LOCAL = 127.0.0.1\nEPSPORT = {}\nEPSTOUT = 300\nEPSTOUT_STEP = 100\nSERVER_PORT = {port}\nPUBFILE_FIXED = FIXED.pub\nPUBFILE = //demo.pub\n",
        port + 1,
    );
    std::fs::write(dir.join("FIXED.pub"), plcsim::FIXED_PUB).unwrap();
    std::fs::write(dir.join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    let path = dir.join("PLCComS.ini");
    std::fs::write(&path, ini).unwrap();
    path
}

#[tokio::main]
async fn main() -> std::process::ExitCode {
    let args = Args::parse();
    let duration = Duration::from_secs_f64(args.minutes * 60.0);
    let port = args.port;
    let dir = tempfile::tempdir().expect("temp dir");
    let ini = write_ini(dir.path(), port);
    let mut sim = spawn_sim(port).expect("start plcsim");
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut server = Command::new(bin_dir().join("plccoms"))
        .arg("-c")
        .arg(&ini)
        .arg("-l")
        .arg(dir.path().join("plccoms.log"))
        .stdin(Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .expect("start plccoms");
    let pid = server.id().expect("server pid");
    for _ in 0..100 {
        if TcpStream::connect(("127.0.0.1", port)).await.is_ok() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    eprintln!(
        "soak: server pid {pid} on port {port}, plcsim on udp {}, {:.1} min, {} clients",
        port + 1,
        args.minutes,
        args.clients
    );

    let stats = Arc::new(Stats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let clients: Vec<_> = (0..args.clients)
        .map(|id| {
            let pause = Duration::from_millis(args.pause_ms);
            tokio::spawn(client(id, port, pause, stats.clone(), stop.clone()))
        })
        .collect();

    let start = Instant::now();
    let mut samples: Vec<(u64, usize)> = Vec::new();
    let mut faults: BTreeMap<&str, u64> = BTreeMap::new();
    let mut next_sample = Instant::now();
    let mut step = 0u64;
    let mut server_died = None;
    // A 60 s fault cycle, one step every 5 s.
    while start.elapsed() < duration {
        if Instant::now() >= next_sample {
            if let Some(s) = sample(pid) {
                eprintln!(
                    "soak: {:>5} s  RSS {} kB  fds {}  requests {}  problems {}",
                    start.elapsed().as_secs(),
                    s.0,
                    s.1,
                    stats.requests.load(Ordering::Relaxed),
                    stats.problem_count.load(Ordering::Relaxed)
                );
                samples.push(s);
            }
            next_sample += Duration::from_secs(10);
        }
        if let Ok(Some(status)) = server.try_wait() {
            server_died = Some(status);
            break;
        }
        let fault = match step % 12 {
            2 => Some(("loss 0.3", "loss 30 %")),
            4 => Some(("loss 0", "")),
            5 => Some(("latency 500", "latency 500 ms")),
            6 => Some(("latency 0", "")),
            7 => Some(("halt", "HALT/RUN")),
            8 => Some(("run", "")),
            _ => None,
        };
        if let Some((command, name)) = fault {
            match control(port, command).await {
                Ok(answer) if answer.starts_with("OK") => {
                    if !name.is_empty() {
                        *faults.entry(name).or_default() += 1;
                    }
                }
                Ok(answer) => stats.problem(format!("plcsim {command}: {answer}")),
                Err(e) => stats.problem(format!("plcsim {command}: {e}")),
            }
        }
        if step % 12 == 10 {
            // The PLC dies (SIGKILL) and comes back 3 s later.
            let _ = sim.start_kill();
            let _ = sim.wait().await;
            tokio::time::sleep(Duration::from_secs(3)).await;
            EPOCH.fetch_add(1, Ordering::SeqCst);
            sim = spawn_sim(port).expect("restart plcsim");
            *faults.entry("plcsim killed and restarted").or_default() += 1;
            tokio::time::sleep(Duration::from_secs(2)).await;
        } else {
            tokio::time::sleep(Duration::from_secs(5)).await;
        }
        step += 1;
    }
    stop.store(true, Ordering::Relaxed);
    for c in clients {
        let _ = tokio::time::timeout(Duration::from_secs(40), c).await;
    }
    if let Some(s) = sample(pid) {
        samples.push(s);
    }
    let alive = server_died.is_none() && matches!(server.try_wait(), Ok(None));
    let _ = server.start_kill();
    let _ = sim.start_kill();

    let elapsed = start.elapsed();
    let requests = stats.requests.load(Ordering::Relaxed);
    let errors = stats.errors.lock().unwrap().clone();
    let problems = stats.problems.lock().unwrap().clone();
    let (rss_min, rss_max) = samples
        .iter()
        .fold((u64::MAX, 0), |(lo, hi), &(r, _)| (lo.min(r), hi.max(r)));
    let (fd_min, fd_max) = samples
        .iter()
        .fold((usize::MAX, 0), |(lo, hi), &(_, f)| (lo.min(f), hi.max(f)));
    println!("soak summary");
    println!(
        "  duration          {:.1} min",
        elapsed.as_secs_f64() / 60.0
    );
    println!("  clients           {}", args.clients);
    println!(
        "  requests          {requests} ({:.0}/s)",
        requests as f64 / elapsed.as_secs_f64()
    );
    println!(
        "  acknowledged SETs {}",
        stats.acked_sets.load(Ordering::Relaxed)
    );
    println!(
        "  DIFF lines        {}",
        stats.diffs.load(Ordering::Relaxed)
    );
    println!("  errors            {errors:?}");
    println!("  faults injected   {faults:?}");
    println!(
        "  lost (acknowledged SET not read back) {}",
        stats.lost.load(Ordering::Relaxed)
    );
    println!(
        "  other problems    {}",
        stats.problem_count.load(Ordering::Relaxed)
    );
    for p in problems.iter().take(20) {
        println!("    {p}");
    }
    println!(
        "  server RSS        {rss_min} - {rss_max} kB ({} samples)",
        samples.len()
    );
    println!("  server fds        {fd_min} - {fd_max}");
    println!("  server alive      {alive}");
    if let Some(status) = server_died {
        println!("  server exited     {status}");
    }
    if alive && problems.is_empty() {
        std::process::ExitCode::SUCCESS
    } else {
        std::process::ExitCode::FAILURE
    }
}
