//! The benchmarks' backend decorator (bench-modbus, bench-s7): each `read`
//! of the link timed and its requests counted, and the poll cycles found in
//! them; and the run both measure with it ([`measure`]).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use plccoms_core::driver::{Answer, PlcBackend, PlcError, PlcStatus, ReadRequest, WriteRequest};
use plccoms_core::metrics::BackendCounters;
use plccoms_protocol::Area;

/// One `read` call of the link.
#[derive(Clone, Copy)]
pub struct Read {
    start: Instant,
    end: Instant,
    /// Its first block.
    first: ReadRequest,
    transactions: u64,
    /// A SET's read-back (the read right after a write), not a poll slice.
    readback: bool,
}

/// A backend, each `read` timed and its requests counted.
pub struct Timed {
    inner: Box<dyn PlcBackend>,
    counters: Arc<BackendCounters>,
    reads: Arc<Mutex<Vec<Read>>>,
    after_write: bool,
}

impl Timed {
    pub fn new(inner: Box<dyn PlcBackend>, reads: Arc<Mutex<Vec<Read>>>) -> Timed {
        Timed {
            inner,
            counters: Arc::default(),
            reads,
            after_write: false,
        }
    }
}

/// Poll cycles in `reads` (the link reads a poll in slices, SETs between
/// them): each begins with the plan's first block. The partial cycles at
/// either end are left out. Per cycle: duration and transactions.
pub fn cycles(reads: &[Read]) -> Vec<(Duration, u64)> {
    let polls: Vec<&Read> = reads.iter().filter(|r| !r.readback).collect();
    let Some(first) = polls
        .iter()
        .map(|r| r.first)
        .min_by_key(|r| (r.area, r.offset))
    else {
        return Vec::new();
    };
    let starts: Vec<usize> = (0..polls.len())
        .filter(|&i| polls[i].first == first)
        .collect();
    starts
        .windows(2)
        .map(|w| {
            let slices = &polls[w[0]..w[1]];
            let end = slices.last().map_or(slices[0].end, |r| r.end);
            (
                end - slices[0].start,
                slices.iter().map(|r| r.transactions).sum(),
            )
        })
        .collect()
}

#[async_trait]
impl PlcBackend for Timed {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn max_read_block(&self, area: Area) -> u32 {
        self.inner.max_read_block(area)
    }
    fn read_gap(&self, area: Area) -> Option<u32> {
        self.inner.read_gap(area)
    }
    fn read_align(&self, area: Area) -> u32 {
        self.inner.read_align(area)
    }
    fn probe_backoff(&self) -> (Duration, Duration) {
        self.inner.probe_backoff()
    }
    fn max_file_block(&self) -> u32 {
        self.inner.max_file_block()
    }
    fn answer_timeout(&self) -> Duration {
        self.inner.answer_timeout()
    }
    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters.clone();
        self.inner.set_counters(counters);
    }
    async fn connect(&mut self) -> Result<String, PlcError> {
        self.inner.connect().await
    }
    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let before = self.counters.requests.get();
        let start = Instant::now();
        let answers = self.inner.read(requests).await;
        if let Some(&first) = requests.first() {
            self.reads.lock().unwrap().push(Read {
                start,
                end: Instant::now(),
                first,
                transactions: self.counters.requests.get() - before,
                readback: std::mem::take(&mut self.after_write),
            });
        }
        answers
    }
    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        self.after_write = true;
        self.inner.write(requests).await
    }
    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        self.inner.status().await
    }
}

/// What [`measure`] found.
pub struct Measured {
    /// Requests of each poll cycle, and its duration in ms.
    pub requests: Vec<u64>,
    pub cycle_ms: Vec<f64>,
    /// SET -> its answer (the confirmed DIFF), and SET -> the watcher's DIFF.
    pub confirm_ms: Vec<f64>,
    pub diff_ms: Vec<f64>,
}

pub fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

/// Runs the section of `ini` (its tag file in `dir`) on the backend
/// `open` makes, timed: a watcher enables every tag, the polls of `cycles`
/// cycles of `delay` ms are counted, then `sets` SETs of `t0`..`t<set_tags>`
/// are sent one by one, each timed to its answer and to the watcher's DIFF.
pub async fn measure(
    dir: &std::path::Path,
    ini: &str,
    open: impl FnOnce(&plccoms_core::config::Section) -> Box<dyn PlcBackend>,
    delay: u64,
    cycles_wanted: usize,
    sets: usize,
    set_tags: usize,
) -> Measured {
    use plccoms::startup::start_section;
    use plccoms_core::link::tables::PubSource;
    use plccoms_core::link::Tables;
    use std::net::SocketAddr;

    let loaded = plccoms_core::config::parse(&dir.join("bench.ini"), ini).expect("ini");
    let section = loaded.config.sections.into_iter().next().expect("section");
    let source = PubSource::new(&section, dir).expect("source");
    let user = source
        .load_local(&section, plccoms_core::link::tables::NamedBy::Configuration)
        .expect("tags");
    let table = source.build(&section.name, user.as_ref()).expect("table");
    let reads = Arc::new(Mutex::new(Vec::new()));
    let backend = Timed::new(open(&section), reads.clone());
    let running = start_section(
        Arc::new(loaded.config.global),
        section,
        table,
        Some(Box::new(backend)),
        SocketAddr::from(([127, 0, 0, 1], 0)),
        dir.to_path_buf(),
        Some(Tables::new(source, user, false)),
    )
    .await
    .expect("section");

    let arrivals = watch(running.local_addr).await;
    tokio::time::sleep(Duration::from_millis(10 * delay + 500)).await;

    reads.lock().unwrap().clear();
    tokio::time::sleep(Duration::from_millis(cycles_wanted as u64 * delay)).await;
    let polls = cycles(&std::mem::take(&mut *reads.lock().unwrap()));

    let (confirm_ms, diff_ms) =
        time_sets(running.local_addr, arrivals, delay, sets, set_tags).await;
    drop(running);
    Measured {
        requests: polls.iter().map(|(_, n)| *n).collect(),
        cycle_ms: polls.iter().map(|(d, _)| ms(*d)).collect(),
        confirm_ms,
        diff_ms,
    }
}

/// When each `DIFF:T<n>,<v>` line reached a watcher.
pub type Arrivals = Arc<Mutex<std::collections::HashMap<String, Instant>>>;

/// A watcher on the section at `addr`: every tag enabled, the arrival of
/// each `DIFF:T...` line noted (the rest read and dropped).
pub async fn watch(addr: std::net::SocketAddr) -> Arrivals {
    watch_of(addr, "T").await
}

/// [`watch`] of the `DIFF` lines of the variables named `prefix...`.
pub async fn watch_of(addr: std::net::SocketAddr, prefix: &str) -> Arrivals {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let prefix = format!("DIFF:{prefix}");
    let watcher = tokio::net::TcpStream::connect(addr).await.expect("watcher");
    let (read, mut write) = watcher.into_split();
    write.write_all(b"EN:*\r\n").await.unwrap();
    let arrivals: Arrivals = Arc::default();
    let seen = arrivals.clone();
    tokio::spawn(async move {
        // Dropping the write half would shut the connection down.
        let _write = write;
        let mut lines = BufReader::new(read).lines();
        while let Ok(Some(line)) = lines.next_line().await {
            if line.starts_with(&prefix) && line.len() < prefix.len() + 20 {
                // The first arrival: a value that comes again later (set
                // back and forth) is not late.
                seen.lock()
                    .unwrap()
                    .entry(line)
                    .or_insert_with(Instant::now);
            }
        }
    });
    arrivals
}

/// `sets` SETs of `t0`..`t<set_tags>` to the section at `addr`, one by
/// one, with the polls going on: each timed to its answer (the confirmed
/// DIFF) and to the DIFF at the watcher of `arrivals`, in ms.
pub async fn time_sets(
    addr: std::net::SocketAddr,
    arrivals: Arrivals,
    delay: u64,
    sets: usize,
    set_tags: usize,
) -> (Vec<f64>, Vec<f64>) {
    let names = (0..set_tags).map(|tag| format!("T{tag}")).collect();
    time_sets_of(addr, arrivals, delay, sets, names).await
}

/// [`time_sets`] of the variables `names` (upper case, as DIFF lines
/// name them), in turn.
pub async fn time_sets_of(
    addr: std::net::SocketAddr,
    arrivals: Arrivals,
    delay: u64,
    sets: usize,
    names: Vec<String>,
) -> (Vec<f64>, Vec<f64>) {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let writer = tokio::net::TcpStream::connect(addr).await.expect("writer");
    let (read, mut write) = writer.into_split();
    let mut answers = BufReader::new(read).lines();
    let mut sent = Vec::new();
    let mut confirm_ms = Vec::new();
    for i in 0..sets {
        let name = &names[i % names.len()];
        let value = 1000 + i;
        let started = Instant::now();
        write
            .write_all(format!("SET:{name},{value}\r\n").as_bytes())
            .await
            .unwrap();
        // A SET is answered or refused within the link's timeouts: one
        // that is not is a fault to name, not a benchmark that hangs.
        let answer = tokio::time::timeout(Duration::from_secs(30), answers.next_line())
            .await
            .unwrap_or_else(|_| panic!("SET:{name},{value} unanswered after 30 s"))
            .unwrap()
            .unwrap_or_default();
        confirm_ms.push(ms(started.elapsed()));
        assert_eq!(answer, format!("DIFF:{name},{value}"), "SET answer");
        sent.push((answer, started));
        // Spread over the poll cycle.
        tokio::time::sleep(Duration::from_millis(7)).await;
    }
    tokio::time::sleep(Duration::from_millis(3 * delay)).await;
    let arrivals = arrivals.lock().unwrap();
    let diff_ms: Vec<f64> = sent
        .iter()
        .filter_map(|(line, started)| arrivals.get(line).map(|at| ms(at.duration_since(*started))))
        .collect();
    // What the watcher saw of a variable whose SET's DIFF it never got
    // (ms from that SET's answer): a loss, or a value that came back.
    for (line, started) in sent.iter().filter(|(line, _)| !arrivals.contains_key(line)) {
        let name = line.split(',').next().unwrap_or_default();
        let mut seen: Vec<(f64, &str)> = arrivals
            .iter()
            .filter(|(other, _)| other.split(',').next() == Some(name))
            .map(|(other, at)| {
                let ms = match at.checked_duration_since(*started) {
                    Some(after) => ms(after),
                    None => -ms(started.duration_since(*at)),
                };
                (ms, other.as_str())
            })
            .filter(|(ms, _)| ms.abs() < 5_000.0)
            .collect();
        seen.sort_by(|a, b| a.0.total_cmp(&b.0));
        eprintln!("no watcher DIFF for the SET answered {line}; it saw, within 5 s (ms from the SET): {seen:?}");
    }
    (confirm_ms, diff_ms)
}

/// The value at fraction `p` of `sorted` (NaN when empty).
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Appends `text` to the results file `path` (bench/run's `--out`).
pub fn append(path: &std::path::Path, text: &str) {
    use std::io::Write;
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .expect("--out");
    file.write_all(text.as_bytes()).expect("--out");
}
