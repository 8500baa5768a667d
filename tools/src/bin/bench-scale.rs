//! bench-scale: one gateway, many devices (issue 36). Generates a
//! PLCComS.ini of N sections (Modbus TCP devices x T tags from a generated
//! tag file, or EPSNET PLCs x V variables from a generated public file),
//! starts `plcsim --devices N` and the `plccoms` binary as processes of
//! their own (pinned with taskset when asked) and measures:
//!
//! - start-up: from starting plccoms until `/metrics` shows
//!   `plccoms_link_up 1` for every section;
//! - plccoms' RSS (sampled each second: max and last) and CPU in cores
//!   (utime + stime over the window), its threads;
//! - cycle-start jitter p99 over all sections (`plccoms_poll_start_late_seconds`)
//!   and missed cycles (`plccoms_poll_overruns_total`), diffed over the window;
//! - one dead device: one device stops answering (plcsim's control port,
//!   `device <i> loss 1`); the others' jitter and missed cycles over a second
//!   window;
//! - the consumers: by default one telnet client per section (`EN:*`), its
//!   DIFF lines counted; with `--mqtt` a local Mosquitto and a subscriber
//!   counting the messages, with `--history` the historian's rows: each
//!   against the changes plcsim made (`--change-rate`), none lost.
//!
//! One line per run with the goals next to the figures; `--out` appends
//! `scale_<label>.<metric> value` lines (bench/run's results).
//!
//! Run: `cargo run --release -p plccoms-tools --bin bench-scale -- --help`.

#[path = "../pinned.rs"]
mod pinned;
#[path = "../procfs.rs"]
mod procfs;

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::{Parser, ValueEnum};
use plccoms_core::metrics::LATENESS_BUCKETS;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Protocol {
    Modbus,
    Epsnet,
}

#[derive(Debug, Parser)]
#[command(name = "bench-scale")]
struct Args {
    /// Backend of every section.
    #[arg(long, value_enum, default_value = "modbus")]
    protocol: Protocol,
    /// Sections (devices in the one plcsim).
    #[arg(long, default_value_t = 1000)]
    devices: u16,
    /// Tags (Modbus INT registers) or variables (EPSNET UDINT) per device.
    #[arg(long, default_value_t = 100)]
    tags: u32,
    /// COMM_LOOP_DELAY (ms).
    #[arg(long, default_value_t = 1000)]
    period: u64,
    /// Fraction of all tags changing per second (plcsim --change-rate).
    #[arg(long, default_value_t = 0.1)]
    change_rate: f64,
    /// Seconds measured (each window: the main one and the dead device's).
    #[arg(long, default_value_t = 10)]
    seconds: u64,
    /// Minutes measured instead (the 10 minutes).
    #[arg(long)]
    minutes: Option<u64>,
    /// Seconds after every section is online before measuring.
    #[arg(long, default_value_t = 3)]
    warmup: u64,
    /// Publish every tag to a local Mosquitto (QoS 1) and count what a
    /// subscriber receives.
    #[arg(long)]
    mqtt: bool,
    /// Record every tag in the historian and count the rows written.
    #[arg(long)]
    history: bool,
    /// Leave out the dead-device window.
    #[arg(long)]
    no_dead: bool,
    /// First of the ports used: plcsim's devices from here, the sections'
    /// client ports after them, then the web page, control port and broker
    /// (127.0.0.1 only; keep the block below 32768, the ephemeral range).
    #[arg(long, default_value_t = 12_000)]
    port: u16,
    /// CPUs for plccoms (taskset -c list, e.g. 0-7).
    #[arg(long)]
    pin_server: Option<String>,
    /// CPUs for plcsim and Mosquitto (taskset -c list, e.g. 8-11).
    #[arg(long)]
    pin_sim: Option<String>,
    /// Folder of the plccoms and plcsim binaries (default: this program's).
    #[arg(long)]
    bin_dir: Option<PathBuf>,
    /// Working folder (generated files, logs); default a temporary one.
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Name of the run in the results (default from the figures).
    #[arg(long)]
    label: Option<String>,
    /// Append `scale_<label>.<metric> value` lines here.
    #[arg(long)]
    out: Option<PathBuf>,
}

/// Children stopped (by their pid) when the bench ends, however it ends.
#[derive(Default)]
struct Children(Vec<(String, Child, PathBuf)>);

impl Children {
    fn spawn(
        &mut self,
        name: &str,
        pin: Option<&str>,
        bin: &Path,
        args: &[String],
        log_path: &Path,
    ) -> u32 {
        let mut command = pinned::command(bin, pin);
        let log = std::fs::File::create(log_path).expect("log file");
        let child = command
            .args(args)
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("log file"))
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("start {}: {e}", bin.display()));
        let pid = child.id();
        self.0
            .push((name.to_string(), child, log_path.to_path_buf()));
        pid
    }

    /// Fails when a child has exited.
    fn check(&mut self) {
        for (name, child, log) in &mut self.0 {
            if let Ok(Some(status)) = child.try_wait() {
                // The log's end: a temporary folder goes with the bench.
                let text = std::fs::read_to_string(&*log).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(5).collect();
                let tail: Vec<&str> = tail.into_iter().rev().collect();
                panic!("{name} exited ({status}):\n{}", tail.join("\n"));
            }
        }
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        for (_, child, _) in &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// One scrape of `/metrics`, the figures this bench reads.
#[derive(Debug, Default, Clone)]
struct Scrape {
    /// Per section: link up.
    up: HashMap<String, bool>,
    /// Per section: cumulative lateness buckets (LATENESS_BUCKETS, +Inf).
    late: HashMap<String, Vec<u64>>,
    overruns: HashMap<String, u64>,
    /// Unlabelled or summed families (historian, MQTT).
    totals: HashMap<String, f64>,
    bytes: usize,
    took: Duration,
}

fn label<'a>(line: &'a str, name: &str) -> Option<&'a str> {
    let start = line.find(&format!("{name}=\""))? + name.len() + 2;
    let end = start + line[start..].find('"')?;
    Some(&line[start..end])
}

impl Scrape {
    fn parse(text: &str) -> Scrape {
        let mut scrape = Scrape {
            bytes: text.len(),
            ..Scrape::default()
        };
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            let Some((key, value)) = line.rsplit_once(' ') else {
                continue;
            };
            let Ok(value) = value.parse::<f64>() else {
                continue;
            };
            let name = key.split('{').next().unwrap_or(key);
            let section = label(key, "section").map(str::to_string);
            match (name, section) {
                ("plccoms_link_up", Some(s)) => {
                    scrape.up.insert(s, value == 1.0);
                }
                ("plccoms_poll_overruns_total", Some(s)) => {
                    scrape.overruns.insert(s, value as u64);
                }
                ("plccoms_poll_start_late_seconds_bucket", Some(s)) => {
                    let le = label(key, "le").unwrap_or("+Inf");
                    let index = LATENESS_BUCKETS
                        .iter()
                        .position(|b| b.to_string() == le)
                        .unwrap_or(LATENESS_BUCKETS.len());
                    let buckets = scrape
                        .late
                        .entry(s)
                        .or_insert_with(|| vec![0; LATENESS_BUCKETS.len() + 1]);
                    buckets[index] = value as u64;
                }
                (name, _) => *scrape.totals.entry(name.to_string()).or_default() += value,
            }
        }
        scrape
    }

    fn total(&self, name: &str) -> f64 {
        self.totals.get(name).copied().unwrap_or(0.0)
    }
}

/// Jitter p99 (the upper bound of the bucket that holds it; `None`: none
/// observed) and missed cycles from `a` to `b`, of the sections `keep` takes.
fn window(a: &Scrape, b: &Scrape, keep: impl Fn(&str) -> bool) -> (Option<f64>, u64, u64) {
    let mut buckets = vec![0u64; LATENESS_BUCKETS.len() + 1];
    let mut missed = 0;
    for (section, after) in &b.late {
        if !keep(section) {
            continue;
        }
        let before = a.late.get(section);
        for (i, count) in after.iter().enumerate() {
            buckets[i] += count - before.map_or(0, |v| v[i]).min(*count);
        }
        missed += b.overruns.get(section).copied().unwrap_or(0)
            - a.overruns.get(section).copied().unwrap_or(0);
    }
    let total = *buckets.last().unwrap_or(&0);
    let p99 = (total > 0).then(|| {
        let rank = (total as f64 * 0.99).ceil() as u64;
        buckets
            .iter()
            .position(|&c| c >= rank)
            .map_or(f64::INFINITY, |i| {
                LATENESS_BUCKETS.get(i).copied().unwrap_or(f64::INFINITY)
            })
    });
    (p99, missed, total)
}

async fn http_get(port: u16, path: &str) -> std::io::Result<String> {
    let mut stream = TcpStream::connect(("127.0.0.1", port)).await?;
    let request = format!("GET {path} HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n");
    stream.write_all(request.as_bytes()).await?;
    let mut body = Vec::new();
    stream.read_to_end(&mut body).await?;
    let text = String::from_utf8_lossy(&body).into_owned();
    match text.split_once("\r\n\r\n") {
        Some((head, body))
            if head.starts_with("HTTP/1.1 200") || head.starts_with("HTTP/1.0 200") =>
        {
            Ok(body.to_string())
        }
        _ => Err(std::io::Error::other(format!(
            "GET {path}: {}",
            text.lines().next().unwrap_or("no answer")
        ))),
    }
}

async fn scrape(port: u16) -> std::io::Result<Scrape> {
    let started = Instant::now();
    let text = http_get(port, "/metrics").await?;
    let mut scrape = Scrape::parse(&text);
    scrape.took = started.elapsed();
    Ok(scrape)
}

/// One line to plcsim's control port, its answer.
async fn control(port: u16, line: &str) -> String {
    let stream = TcpStream::connect(("127.0.0.1", port))
        .await
        .expect("plcsim control port");
    let mut stream = BufReader::new(stream);
    stream
        .get_mut()
        .write_all(format!("{line}\n").as_bytes())
        .await
        .expect("control");
    let mut answer = String::new();
    stream.read_line(&mut answer).await.expect("control");
    let answer = answer.trim_end().to_string();
    assert!(answer.starts_with("OK"), "plcsim control {line}: {answer}");
    answer
}

async fn changes_made(port: u16) -> u64 {
    let status = control(port, "status").await;
    status
        .split_whitespace()
        .find_map(|w| w.strip_prefix("changes="))
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("changes= in {status}"))
}

/// Raises the open-file limit to the hard limit: the children inherit it
/// (a thousand devices, sections and clients need thousands of sockets).
fn raise_nofile() -> u64 {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) == 0 {
            limit.rlim_cur = limit.rlim_max;
            libc::setrlimit(libc::RLIMIT_NOFILE, &limit);
        }
    }
    limit.rlim_cur
}

/// Telnet clients, one per section, each `EN:*`, DIFF lines counted.
async fn telnet_clients(ports: Vec<u16>, diffs: Arc<AtomicU64>) {
    for port in ports {
        let diffs = diffs.clone();
        let stream = TcpStream::connect(("127.0.0.1", port))
            .await
            .unwrap_or_else(|e| panic!("section port {port}: {e}"));
        tokio::spawn(async move {
            let mut stream = BufReader::with_capacity(1 << 16, stream);
            if stream.get_mut().write_all(b"EN:*\r\n").await.is_err() {
                return;
            }
            let mut line = Vec::new();
            loop {
                line.clear();
                match stream.read_until(b'\n', &mut line).await {
                    Ok(0) | Err(_) => return,
                    Ok(_) if line.starts_with(b"DIFF:") => {
                        diffs.fetch_add(1, Ordering::Relaxed);
                    }
                    Ok(_) => {}
                }
            }
        });
    }
}

/// An MQTT subscriber to `bench/#`, counting value messages of `prefix` tags.
async fn subscriber(
    port: u16,
    prefix: &'static str,
    received: Arc<AtomicU64>,
    errors: Arc<AtomicU64>,
) {
    use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
    let mut options = MqttOptions::new(
        format!("bench-scale-{}", std::process::id()),
        "127.0.0.1",
        port,
    );
    options
        .set_max_packet_size(1 << 20, 1 << 20)
        .set_keep_alive(Duration::from_secs(30));
    let (client, mut eventloop) = AsyncClient::new(options, 1024);
    client
        .subscribe("bench/#", QoS::AtLeastOnce)
        .await
        .expect("subscribe");
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::Publish(p))) => {
                let last = p.topic.rsplit('/').next().unwrap_or("");
                // The server names variables in capitals.
                if last
                    .get(..prefix.len())
                    .is_some_and(|p| p.eq_ignore_ascii_case(prefix))
                {
                    received.fetch_add(1, Ordering::Relaxed);
                }
            }
            Ok(_) => {}
            Err(_) => {
                // Shown in the result: a broken connection may lose messages.
                errors.fetch_add(1, Ordering::Relaxed);
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

/// Waits until `count` stays the same for `quiet`, at most `limit`.
async fn settle(count: impl Fn() -> u64, quiet: Duration, limit: Duration) -> u64 {
    let started = Instant::now();
    let mut last = count();
    let mut since = Instant::now();
    while started.elapsed() < limit {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let now = count();
        if now != last {
            last = now;
            since = Instant::now();
        } else if since.elapsed() >= quiet {
            break;
        }
    }
    last
}

fn fmt_p99(p99: Option<f64>) -> String {
    match p99 {
        Some(s) if s.is_finite() => format!("<= {} ms", s * 1000.0),
        Some(_) => "> 1000 ms".into(),
        None => "none".into(),
    }
}

#[tokio::main]
async fn main() {
    let args = Args::parse();
    let window_s = args.minutes.map_or(args.seconds, |m| m * 60).max(1);
    let n = args.devices.max(1);
    // plccoms per section: the device's socket, the client port, a client,
    // the link thread's epoll and eventfd; MQTT: a connection, two spool
    // segments and a lock; the historian: the day file, its WAL and SHM.
    let nofile = raise_nofile();
    let per_section = 5 + 4 * u64::from(args.mqtt) + 3 * u64::from(args.history);
    let needed = per_section * u64::from(n) + 256;
    assert!(
        nofile >= needed,
        "open files limit {nofile} (hard) is below the {needed} that {n} sections need here: raise it (ulimit -Hn, limits.conf)"
    );
    let label = args.label.clone().unwrap_or_else(|| {
        format!(
            "{}_{}x{}_{}ms{}{}",
            match args.protocol {
                Protocol::Modbus => "modbus",
                Protocol::Epsnet => "epsnet",
            },
            n,
            args.tags,
            args.period,
            if args.mqtt { "_mqtt" } else { "" },
            if args.history { "_history" } else { "" },
        )
    });

    let bin_dir = args.bin_dir.clone().unwrap_or_else(|| {
        std::env::current_exe()
            .ok()
            .and_then(|p| p.parent().map(Path::to_path_buf))
            .unwrap_or_else(|| PathBuf::from("target/release"))
    });
    let temp = tempfile::tempdir().expect("temporary folder");
    let dir = args
        .dir
        .clone()
        .unwrap_or_else(|| temp.path().to_path_buf());
    std::fs::create_dir_all(&dir).expect("working folder");
    let base = u32::from(args.port);
    let last_port = base + 2 * u32::from(n) + 3;
    assert!(
        last_port <= 65_535,
        "--port {base} leaves no room for {n} devices"
    );
    let device_port = |i: u16| base as u16 + i;
    let section_port = |i: u16| base as u16 + n + i;
    let http_port = base as u16 + 2 * n;
    let control_port = http_port + 1;
    let broker_port = http_port + 2;

    // The project: a tag file or public file every device shares.
    let (project, mask, prefix) = match args.protocol {
        Protocol::Modbus => {
            let mut csv = String::from("name,type,table,address\n");
            for k in 0..args.tags {
                let _ = writeln!(csv, "tag_{k:05},INT,holding,{k}");
            }
            let path = dir.join("tags.csv");
            std::fs::write(&path, csv).expect("tag file");
            (path, "tag_*", "tag_")
        }
        Protocol::Epsnet => {
            let bytes = plcsim::genpub::generate(&plcsim::genpub::Layout {
                vars: args.tags as usize,
                animated: args.tags as usize,
                setvars: 0,
            });
            let path = dir.join("scale.pub");
            std::fs::write(&path, bytes).expect("public file");
            (path, "ANIM_*", "ANIM_")
        }
    };
    let history_dir = dir.join("history");
    let _ = std::fs::remove_dir_all(&history_dir);
    let mut ini = String::new();
    let _ = writeln!(ini, "[*]\nCOMM_LOOP_DELAY = {}\nHTTP_PORT = {http_port}\nHTTP_BIND = 127.0.0.1\nPF_VAR_DISABLED = Yes\nDIFF_VAR_ENABLED = Yes", args.period);
    if args.history {
        let _ = writeln!(ini, "HISTORY_DIR = {}", history_dir.display());
    }
    if args.mqtt {
        let _ = writeln!(
            ini,
            "MQTT_URL = mqtt://127.0.0.1:{broker_port}\nMQTT_PREFIX = bench\nMQTT_SPOOL = {}",
            dir.join("spool").display()
        );
        let _ = std::fs::remove_dir_all(dir.join("spool"));
    }
    for i in 0..n {
        let _ = writeln!(
            ini,
            "\n[D{i:04}]\nIPADDR = 127.0.0.1\nIPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {}",
            section_port(i)
        );
        match args.protocol {
            Protocol::Modbus => {
                let _ = writeln!(
                    ini,
                    "PROTOCOL = MODBUS_TCP\nMODBUS_PORT = {}\nMODBUS_TAGS = {}",
                    device_port(i),
                    project.display()
                );
            }
            Protocol::Epsnet => {
                let _ = writeln!(
                    ini,
                    "EPSPORT = {}\nPUBFILE = {}\nPUBFILE_CRC = No\nPUBFILE_WRITE = No",
                    device_port(i),
                    project.display()
                );
            }
        }
        if args.history {
            let _ = writeln!(ini, "HISTORY = *");
        }
        if args.mqtt {
            let _ = writeln!(ini, "MQTT_PUBLISH = *\nMQTT_QOS = 1");
        }
    }
    let ini_path = dir.join("scale.ini");
    std::fs::write(&ini_path, ini).expect("ini");

    let mut children = Children::default();
    let plcsim = bin_dir.join("plcsim");
    let plccoms = bin_dir.join("plccoms");
    // The simulator's own cycle: every change seen by a poll of --period.
    let sim_cycle = args.period.clamp(10, 100);
    let mut sim_args: Vec<String> = vec![
        match args.protocol {
            Protocol::Modbus => "--modbus".into(),
            Protocol::Epsnet => "--bind".into(),
        },
        format!("127.0.0.1:{}", device_port(0)),
        "--devices".into(),
        n.to_string(),
        "--control".into(),
        format!("127.0.0.1:{control_port}"),
        "--program".into(),
        "idle".into(),
        "--cycle".into(),
        sim_cycle.to_string(),
        "--animate".into(),
        mask.into(),
        "--change-rate".into(),
        args.change_rate.to_string(),
    ];
    sim_args.push(match args.protocol {
        Protocol::Modbus => "--tags".into(),
        Protocol::Epsnet => "--pub".into(),
    });
    sim_args.push(project.display().to_string());
    children.spawn(
        "plcsim",
        args.pin_sim.as_deref(),
        &plcsim,
        &sim_args,
        &dir.join("plcsim.log"),
    );
    let mut ready = false;
    for _ in 0..600 {
        if TcpStream::connect(("127.0.0.1", control_port))
            .await
            .is_ok()
        {
            ready = true;
            break;
        }
        children.check();
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(ready, "plcsim's control port did not open");
    // Quiet until everything is online and the first values are out: the
    // changes counted are the window's alone.
    control(control_port, "animate").await;

    let received = Arc::new(AtomicU64::new(0));
    let subscriber_errors = Arc::new(AtomicU64::new(0));
    if args.mqtt {
        let conf = dir.join("mosquitto.conf");
        std::fs::write(
            &conf,
            format!("listener {broker_port} 127.0.0.1\nallow_anonymous true\npersistence false\nmax_queued_messages 10000000\nmax_inflight_messages 1000\nset_tcp_nodelay true\n"),
        )
        .expect("mosquitto.conf");
        let mosquitto = which("mosquitto").unwrap_or_else(|| PathBuf::from("/usr/sbin/mosquitto"));
        children.spawn(
            "mosquitto",
            args.pin_sim.as_deref(),
            &mosquitto,
            &["-c".into(), conf.display().to_string()],
            &dir.join("mosquitto.log"),
        );
        let mut up = false;
        for _ in 0..200 {
            if TcpStream::connect(("127.0.0.1", broker_port)).await.is_ok() {
                up = true;
                break;
            }
            children.check();
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(up, "mosquitto did not open port {broker_port}");
        tokio::spawn(subscriber(
            broker_port,
            prefix,
            received.clone(),
            subscriber_errors.clone(),
        ));
        tokio::time::sleep(Duration::from_millis(300)).await;
    }

    // Start-up: from the process start to every section online.
    let started = Instant::now();
    let server_pid = children.spawn(
        "plccoms",
        args.pin_server.as_deref(),
        &plccoms,
        &["-c".into(), ini_path.display().to_string()],
        &dir.join("plccoms.log"),
    );
    let mut online = 0;
    let mut startup = None;
    while started.elapsed() < Duration::from_secs(120) {
        children.check();
        if let Ok(s) = scrape(http_port).await {
            online = s.up.values().filter(|&&up| up).count();
            if online == usize::from(n) {
                startup = Some(started.elapsed());
                break;
            }
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let Some(startup) = startup else {
        panic!(
            "{online} of {n} sections online after 120 s; see {}",
            dir.join("plccoms.log").display()
        );
    };

    let diffs = Arc::new(AtomicU64::new(0));
    let telnet = !args.mqtt && !args.history;
    if telnet {
        telnet_clients((0..n).map(section_port).collect(), diffs.clone()).await;
    }
    tokio::time::sleep(Duration::from_secs(args.warmup)).await;
    // The first values settled: counted from here.
    let delivered = || {
        if args.mqtt {
            received.load(Ordering::Relaxed)
        } else {
            diffs.load(Ordering::Relaxed)
        }
    };
    let history_rows = |s: &Scrape| s.total("plccoms_historian_samples_written_total") as u64;
    let quiet = Duration::from_millis((args.period * 3).max(2000));
    settle(&delivered, quiet, Duration::from_secs(60)).await;
    let first = scrape(http_port).await.expect("scrape");
    let delivered0 = delivered();
    let rows0 = history_rows(&first);
    let changes0 = changes_made(control_port).await;
    control(control_port, &format!("animate {mask}")).await;

    // The window: RSS each second, CPU over it.
    let cpu0 = procfs::cpu_seconds(server_pid);
    let t0 = Instant::now();
    let a = scrape(http_port).await.expect("scrape");
    let (mut rss_max, mut rss_last, mut threads) = (0, 0, 0);
    while t0.elapsed() < Duration::from_secs(window_s) {
        tokio::time::sleep(Duration::from_secs(1)).await;
        children.check();
        (rss_last, threads) = (
            procfs::status_field(server_pid, "VmRSS").unwrap_or(0) * 1024,
            procfs::status_field(server_pid, "Threads").unwrap_or(0),
        );
        rss_max = rss_max.max(rss_last);
    }
    let b = scrape(http_port).await.expect("scrape");
    let cpu = (procfs::cpu_seconds(server_pid) - cpu0) / t0.elapsed().as_secs_f64();
    let (p99, missed, cycles) = window(&a, &b, |_| true);
    control(control_port, "animate").await;
    let changes = changes_made(control_port).await - changes0;
    let delivered1 = settle(&delivered, quiet, Duration::from_secs(120)).await;
    let last = scrape(http_port).await.expect("scrape");
    let rows = history_rows(&last) - rows0;
    let delivered = delivered1 - delivered0;

    // One dead device: the others' polls go on as before.
    let dead = if args.no_dead {
        None
    } else {
        let victim = n / 2;
        let name = format!("D{victim:04}");
        control(control_port, &format!("device {victim} loss 1")).await;
        let lost_at = Instant::now();
        let mut down = None;
        while lost_at.elapsed() < Duration::from_secs(30) {
            let s = scrape(http_port).await.expect("scrape");
            if s.up.get(&name) == Some(&false) {
                down = Some((lost_at.elapsed(), s.up.values().filter(|&&u| u).count()));
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let a = scrape(http_port).await.expect("scrape");
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(window_s) {
            tokio::time::sleep(Duration::from_secs(1)).await;
            children.check();
        }
        let b = scrape(http_port).await.expect("scrape");
        let others_up = b.up.iter().filter(|(s, &u)| **s != name && u).count();
        let (p99, missed, _) = window(&a, &b, |s| s != name);
        Some((down, p99, missed, others_up))
    };
    children.check();

    let mib = |b: u64| b as f64 / 1048576.0;
    let tags_total = u64::from(n) * u64::from(args.tags);
    let mut line = format!(
        "scale {label}: {n} sections x {} tags = {tags_total} at {} ms: start-up {:.2} s (goal <= 2 s); \
         RSS max {:.1} MiB, last {:.1} MiB; CPU {:.3} cores; threads {threads}; \
         cycle start jitter p99 {} (goal <= 5 ms) over {cycles} cycles; missed cycles {missed} (goal 0) in {window_s} s; \
         /metrics {:.0} KiB in {:.0} ms",
        args.tags,
        args.period,
        startup.as_secs_f64(),
        mib(rss_max),
        mib(rss_last),
        cpu,
        fmt_p99(p99),
        b.bytes as f64 / 1024.0,
        b.took.as_secs_f64() * 1000.0,
    );
    if tags_total >= 100_000 {
        let goal_cpu = if args.period >= 1000 { 0.15 } else { 1.0 };
        if args.period >= 1000 {
            let _ = write!(
                line,
                " [goals at 1 s: RSS <= 100 MiB, CPU <= {goal_cpu} core]"
            );
        } else {
            let _ = write!(line, " [goal: CPU <= {goal_cpu} core]");
        }
    }
    let consumer = if args.mqtt {
        "MQTT messages"
    } else {
        "DIFF lines"
    };
    if args.mqtt || telnet {
        let _ = write!(
            line,
            "; changes made {changes}, {consumer} {delivered}, lost {} (goal 0)",
            changes.saturating_sub(delivered)
        );
        let errors = subscriber_errors.load(Ordering::Relaxed);
        if errors > 0 {
            let _ = write!(line, " (the subscriber's connection failed {errors} times)");
        }
    }
    if args.history {
        let _ = write!(
            line,
            "; history rows {rows}, lost {} (goal 0), dropped {}",
            changes.saturating_sub(rows),
            last.total("plccoms_historian_samples_dropped_total")
        );
    }
    if let Some((down, p99, missed, others_up)) = &dead {
        let _ = write!(
            line,
            "; one dead device: {}, others {others_up}/{} online, their jitter p99 {}, missed {missed}",
            down.map_or("never declared lost".into(), |(t, _)| format!("lost after {:.2} s", t.as_secs_f64())),
            n - 1,
            fmt_p99(*p99),
        );
    }
    println!("{line}");
    if let Some(out) = &args.out {
        let mut text = String::new();
        let mut put = |metric: &str, value: String| {
            let _ = writeln!(text, "scale_{label}.{metric} {value}");
        };
        put("startup_s", format!("{:.3}", startup.as_secs_f64()));
        put("rss_max_mib", format!("{:.1}", mib(rss_max)));
        put("rss_last_mib", format!("{:.1}", mib(rss_last)));
        put("cpu_cores", format!("{cpu:.3}"));
        put("threads", threads.to_string());
        put(
            "jitter_p99_ms",
            p99.map_or("none".into(), |s| format!("{}", s * 1000.0)),
        );
        put("missed_cycles", missed.to_string());
        put("metrics_kib", format!("{:.0}", b.bytes as f64 / 1024.0));
        put("changes", changes.to_string());
        if args.mqtt || telnet {
            put("delivered", delivered.to_string());
            put("lost", changes.saturating_sub(delivered).to_string());
        }
        if args.history {
            put("history_rows", rows.to_string());
            put("history_lost", changes.saturating_sub(rows).to_string());
        }
        if let Some((_, p99, missed, others_up)) = &dead {
            put("dead_others_online", others_up.to_string());
            put(
                "dead_jitter_p99_ms",
                p99.map_or("none".into(), |s| format!("{}", s * 1000.0)),
            );
            put("dead_missed_cycles", missed.to_string());
        }
        use std::io::Write as _;
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(out)
            .expect("--out");
        let _ = file.write_all(text.as_bytes());
    }
}

fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")?
        .to_str()?
        .split(':')
        .map(|d| Path::new(d).join(name))
        .find(|p| p.is_file())
}
