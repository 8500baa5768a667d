//! Shared pieces: a mergeable latency histogram, a line-oriented client
//! connection, /proc readings of the server, and the result report.

use std::fmt::Write as _;
use std::io;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Log-linear histogram of microseconds: exact below 1024 µs, then 128
/// sub-buckets per power of two (< 0.8 % relative error). Mergeable, so every
/// client keeps its own and nothing is shared on the hot path.
#[derive(Clone)]
pub struct Histogram {
    counts: Vec<u64>,
    total: u64,
    max: u64,
    sum: u128,
}

const LINEAR: u64 = 1024;
const SUB_BITS: u32 = 7;

impl Default for Histogram {
    fn default() -> Self {
        Histogram {
            counts: vec![0; 1024 + 54 * 128],
            total: 0,
            max: 0,
            sum: 0,
        }
    }
}

impl Histogram {
    fn index(us: u64) -> usize {
        if us < LINEAR {
            return us as usize;
        }
        let exp = 63 - us.leading_zeros(); // >= 10
        let sub = (us >> (exp - SUB_BITS)) & ((1 << SUB_BITS) - 1);
        (LINEAR as usize) + ((exp - 10) as usize) * 128 + sub as usize
    }

    fn value_of(index: usize) -> u64 {
        if index < LINEAR as usize {
            return index as u64;
        }
        let i = index - LINEAR as usize;
        let exp = (i / 128) as u32 + 10;
        let sub = (i % 128) as u64;
        // Upper edge of the bucket: percentiles never flatter.
        ((1u64 << SUB_BITS) | sub) << (exp - SUB_BITS) | ((1 << (exp - SUB_BITS)) - 1)
    }

    pub fn record(&mut self, d: Duration) {
        self.record_us(d.as_micros().min(u128::from(u64::MAX >> 8)) as u64);
    }

    pub fn record_us(&mut self, us: u64) {
        let i = Self::index(us).min(self.counts.len() - 1);
        self.counts[i] += 1;
        self.total += 1;
        self.max = self.max.max(us);
        self.sum += u128::from(us);
    }

    pub fn merge(&mut self, other: &Histogram) {
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        self.total += other.total;
        self.max = self.max.max(other.max);
        self.sum += other.sum;
    }

    pub fn count(&self) -> u64 {
        self.total
    }

    pub fn max_us(&self) -> u64 {
        self.max
    }

    pub fn mean_us(&self) -> f64 {
        if self.total == 0 {
            0.0
        } else {
            self.sum as f64 / self.total as f64
        }
    }

    /// The value at quantile `q` (0..=1), in µs.
    pub fn quantile_us(&self, q: f64) -> u64 {
        if self.total == 0 {
            return 0;
        }
        let rank = ((q * self.total as f64).ceil() as u64).clamp(1, self.total);
        let mut seen = 0;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return Self::value_of(i).min(self.max);
            }
        }
        self.max
    }
}

/// A client connection read line by line (line ends stripped).
pub struct LineConn {
    pub stream: TcpStream,
    buf: Vec<u8>,
    start: usize,
    end: usize,
    line: (usize, usize),
    pub bytes_read: u64,
    /// When the last read returned: the receipt time of the lines it held.
    pub read_at: Instant,
    /// Wait at most this long for input; then `next_line` fails with
    /// `TimedOut` (lets a reader check a stop flag).
    pub read_timeout: Option<Duration>,
}

impl LineConn {
    pub async fn connect(addr: SocketAddr) -> io::Result<LineConn> {
        let stream = TcpStream::connect(addr).await?;
        stream.set_nodelay(true)?;
        Ok(LineConn::new(stream))
    }

    pub fn new(stream: TcpStream) -> LineConn {
        LineConn {
            stream,
            buf: vec![0; 64 * 1024],
            start: 0,
            end: 0,
            line: (0, 0),
            bytes_read: 0,
            read_at: Instant::now(),
            read_timeout: None,
        }
    }

    pub async fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.stream.write_all(bytes).await
    }

    /// Next line; `Ok(false)` at end of stream.
    pub async fn next_line(&mut self) -> io::Result<bool> {
        loop {
            if let Some(pos) = self.buf[self.start..self.end]
                .iter()
                .position(|&b| b == b'\n')
            {
                let mut stop = self.start + pos;
                let next = stop + 1;
                if stop > self.start && self.buf[stop - 1] == b'\r' {
                    stop -= 1;
                }
                self.line = (self.start, stop);
                self.start = next;
                return Ok(true);
            }
            if self.start > 0 {
                self.buf.copy_within(self.start..self.end, 0);
                self.end -= self.start;
                self.start = 0;
            }
            if self.end == self.buf.len() {
                let len = self.buf.len() * 2;
                if len > 64 * 1024 * 1024 {
                    return Err(io::Error::other("line longer than 64 MiB"));
                }
                self.buf.resize(len, 0);
            }
            let read = self.stream.read(&mut self.buf[self.end..]);
            let n = match self.read_timeout {
                None => read.await?,
                Some(limit) => tokio::time::timeout(limit, read)
                    .await
                    .map_err(|_| io::Error::from(io::ErrorKind::TimedOut))??,
            };
            self.read_at = Instant::now();
            if n == 0 {
                return Ok(false);
            }
            self.bytes_read += n as u64;
            self.end += n;
        }
    }

    /// Next line or an error at end of stream.
    pub async fn expect_line(&mut self) -> io::Result<&[u8]> {
        if !self.next_line().await? {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "server closed the connection",
            ));
        }
        Ok(self.line())
    }

    pub fn line(&self) -> &[u8] {
        &self.buf[self.line.0..self.line.1]
    }

    /// Sends a command and reads lines until one starts with `prefix`
    /// (skipping DIFF lines); errors out on ERROR lines.
    pub async fn command(&mut self, command: &str, prefix: &[u8]) -> io::Result<Vec<u8>> {
        self.send(format!("{command}\n").as_bytes()).await?;
        loop {
            let line = self.expect_line().await?;
            if line.starts_with(prefix) {
                return Ok(line.to_vec());
            }
            if line.starts_with(b"ERROR:") {
                return Err(io::Error::other(format!(
                    "{command}: {}",
                    String::from_utf8_lossy(line)
                )));
            }
        }
    }
}

/// CPU time and memory of a process, from /proc.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProcSample {
    /// user + system, seconds.
    pub cpu_s: f64,
    /// The system (kernel) part of `cpu_s`.
    pub sys_s: f64,
    pub rss_kib: u64,
    pub hwm_kib: u64,
}

/// User and system CPU seconds from a `/proc/<pid>/stat` line.
fn cpu_times(stat: &str) -> Option<(f64, f64)> {
    // Fields after the parenthesised command name (which may hold spaces and
    // parentheses); utime and stime are the 14th and 15th fields of the
    // line, in clock ticks (USER_HZ = 100 on Linux).
    let rest = stat.get(stat.rfind(')')? + 2..)?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime / 100.0, stime / 100.0))
}

pub fn proc_sample(pid: u32) -> Option<ProcSample> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let (user_s, sys_s) = cpu_times(&stat)?;
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kib = |key: &str| {
        status
            .lines()
            .find(|l| l.starts_with(key))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    Some(ProcSample {
        cpu_s: user_s + sys_s,
        sys_s,
        rss_kib: kib("VmRSS:"),
        hwm_kib: kib("VmHWM:"),
    })
}

/// Measures a process (the server, or the load generator itself) over a window.
pub struct ProcWindow {
    pid: Option<u32>,
    start: Option<ProcSample>,
    at: Instant,
}

impl ProcWindow {
    pub fn start(pid: Option<u32>) -> ProcWindow {
        ProcWindow {
            pid,
            start: pid.and_then(proc_sample),
            at: Instant::now(),
        }
    }

    /// CPU seconds (and their kernel part), cores used (CPU s / wall s),
    /// RSS and peak RSS now.
    pub fn finish(&self, report: &mut Report, who: &str) {
        let (Some(pid), Some(start)) = (self.pid, self.start) else {
            return;
        };
        let Some(end) = proc_sample(pid) else { return };
        let wall = self.at.elapsed().as_secs_f64();
        let cpu = end.cpu_s - start.cpu_s;
        report.metric(&format!("{who}_cpu_s"), cpu);
        report.metric(&format!("{who}_sys_s"), end.sys_s - start.sys_s);
        report.metric(&format!("{who}_cpu_cores"), cpu / wall.max(1e-9));
        report.metric(&format!("{who}_rss_mib"), end.rss_kib as f64 / 1024.0);
        report.metric(&format!("{who}_peak_rss_mib"), end.hwm_kib as f64 / 1024.0);
    }
}

/// Results: printed for people, and appended as `label.metric value` lines
/// to `--out` for the bench script.
pub struct Report {
    pub label: String,
    lines: Vec<(String, String)>,
    out: Option<PathBuf>,
}

impl Report {
    pub fn new(label: &str, out: Option<PathBuf>) -> Report {
        Report {
            label: label.to_string(),
            lines: Vec::new(),
            out,
        }
    }

    pub fn metric(&mut self, name: &str, value: f64) {
        let text = if value.fract() == 0.0 && value.abs() < 1e15 {
            format!("{value:.0}")
        } else {
            format!("{value:.3}")
        };
        self.lines.push((name.to_string(), text));
    }

    pub fn text(&mut self, name: &str, value: &str) {
        self.lines
            .push((name.to_string(), value.replace('\n', " ")));
    }

    pub fn latency(&mut self, name: &str, h: &Histogram) {
        self.metric(&format!("{name}_count"), h.count() as f64);
        self.metric(
            &format!("{name}_p50_ms"),
            h.quantile_us(0.5) as f64 / 1000.0,
        );
        self.metric(
            &format!("{name}_p99_ms"),
            h.quantile_us(0.99) as f64 / 1000.0,
        );
        self.metric(
            &format!("{name}_p999_ms"),
            h.quantile_us(0.999) as f64 / 1000.0,
        );
        self.metric(&format!("{name}_max_ms"), h.max_us() as f64 / 1000.0);
        self.metric(&format!("{name}_mean_ms"), h.mean_us() / 1000.0);
    }

    pub fn finish(self) -> io::Result<()> {
        let mut text = String::new();
        for (name, value) in &self.lines {
            let _ = writeln!(text, "{}.{} {}", self.label, name, value);
        }
        print!("{text}");
        if let Some(path) = &self.out {
            use std::io::Write;
            let mut file = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)?;
            file.write_all(text.as_bytes())?;
        }
        Ok(())
    }
}

/// Nanoseconds since `epoch` (the process-wide clock of proxy and clients).
pub fn now_ns(epoch: Instant) -> u64 {
    epoch.elapsed().as_nanos() as u64
}

#[cfg(test)]
mod tests {
    use super::cpu_times;

    #[test]
    fn cpu_times_are_the_14th_and_15th_fields_whatever_the_command_name() {
        let line = "4242 (tokio) (rt x) S 1 4242 4242 0 -1 4194560 1093 0 0 0 \
                    731 254 0 0 20 0 3 0 977 123456 789 18446744073709551615";
        assert_eq!(cpu_times(line), Some((7.31, 2.54)));
        assert_eq!(cpu_times("4242 (plccoms) S 1 2"), None);
        assert_eq!(cpu_times("no command name"), None);
        assert_eq!(cpu_times("4242 (x)"), None);
    }
}
