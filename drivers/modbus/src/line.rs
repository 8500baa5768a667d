//! One Modbus RTU line (a serial port, or a TCP connection to a serial
//! device server in RTU-over-TCP mode) shared by every section on it.
//!
//! - One owner task per line holds the port; sections find it in a registry
//!   keyed by the device path or server address ([`attach`], a `Weak` there,
//!   the `Arc`s in the sections) and send it their transactions over a
//!   channel. It serves them in turn, one frame on the line at a time: a
//!   request, then its answer or its timeout. When the last section lets go,
//!   the channel closes and the task closes the port.
//! - Before each request, whatever the line brought since (a late answer, a
//!   foreign master's frame, noise) is discarded, and on a serial line the
//!   3.5-character silence is kept after the last byte seen or sent.
//! - A request's timeout is MODBUS_TIMEOUT plus the time the request and its
//!   answer take on the line at its speed.
//! - A unit that did not answer is tried again at most once a second
//!   ([`RETRY_SILENT`]): meanwhile its requests fail at once without line
//!   time, so a dead unit costs the others at most one timeout a second.
//! - Broadcast (unit 0) writes are sent and not waited for (the units need
//!   [`TURNAROUND`] before the next frame); reads cannot be broadcast.
//! - Damaged, foreign and unexpected frames are dropped, counted as bad
//!   answers and named in the timeout's error; a port error closes the
//!   port, which is opened again at the next request (an adapter unplugged
//!   and plugged back is found again).

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::os::fd::AsRawFd;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock, Weak};
use std::time::Duration;

use bytes::BytesMut;
use futures::FutureExt;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};
use tokio_util::codec::Decoder;
use tracing::{debug, warn};

use plccoms_core::config::serial::Parity;
use plccoms_core::driver::PlcError;
use plccoms_core::metrics::BackendCounters;
use plccoms_core::rs485::{self, Gpio, SYSFS_GPIO};
use plccoms_plc::modbus::codec::decode_response;
use plccoms_plc::modbus::frame::{Request, Response};
use plccoms_plc::modbus::rtu::{self, RtuDecoder, RtuItem, Side, BROADCAST, MAX_FRAME};
use plccoms_plc::modbus::ExceptionCode;

use crate::client::{connect_tcp, Outcome};

/// How often a unit that did not answer is tried again, start to start.
pub const RETRY_SILENT: Duration = Duration::from_millis(950);
/// Quiet after a broadcast, for the units to act on it.
pub const TURNAROUND: Duration = Duration::from_millis(100);
/// SERIAL_SPEED of a Modbus RTU section that does not set it.
pub const DEFAULT_SPEED: u32 = 9600;

/// A serial line's settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SerialLine {
    pub device: String,
    pub speed: u32,
    pub parity: Parity,
    pub data_bits: u8,
    pub stop_bits: u8,
    /// The GPIO pin driven high while a frame is sent (RS-485 direction).
    pub rts: Option<u32>,
    /// The GPIO sysfs folder ([`SYSFS_GPIO`]; another for tests).
    pub gpio_root: PathBuf,
}

impl SerialLine {
    /// `device` at the Modbus defaults: 9600 baud, 8E1.
    pub fn new(device: &str) -> SerialLine {
        SerialLine {
            device: device.to_string(),
            speed: DEFAULT_SPEED,
            parity: Parity::Even,
            data_bits: 8,
            stop_bits: 1,
            rts: None,
            gpio_root: PathBuf::from(SYSFS_GPIO),
        }
    }

    /// Bits of one character on the line.
    pub fn char_bits(&self) -> u32 {
        rtu::char_bits(self.data_bits, self.parity != Parity::None, self.stop_bits)
    }
}

/// Where a line is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Endpoint {
    Serial(SerialLine),
    /// A serial device server taking RTU frames over TCP.
    Tcp {
        server: SocketAddr,
        local: Option<IpAddr>,
    },
}

impl Endpoint {
    /// What sections on the same line share.
    fn key(&self) -> String {
        match self {
            Endpoint::Serial(serial) => format!("serial {}", serial.device),
            Endpoint::Tcp { server, .. } => format!("tcp {server}"),
        }
    }
}

impl std::fmt::Display for Endpoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Endpoint::Serial(s) => {
                write!(
                    f,
                    "{} {} {}{}{}",
                    s.device,
                    s.speed,
                    s.data_bits,
                    s.parity.letter(),
                    s.stop_bits
                )?;
                match s.rts {
                    Some(pin) => write!(f, " RTS on GPIO {pin}"),
                    None => Ok(()),
                }
            }
            Endpoint::Tcp { server, .. } => write!(f, "{server} (RTU over TCP)"),
        }
    }
}

/// One section's transactions, served in turn.
struct Job {
    unit: u8,
    requests: Vec<Request>,
    timeout: Duration,
    retries: u32,
    counters: Arc<BackendCounters>,
    reply: oneshot::Sender<Result<Vec<Outcome>, PlcError>>,
}

/// A section's hold on a line: the line stays open while one is held.
pub struct Line {
    endpoint: Endpoint,
    jobs: mpsc::Sender<Job>,
}

fn registry() -> &'static Mutex<HashMap<String, Weak<Line>>> {
    static LINES: OnceLock<Mutex<HashMap<String, Weak<Line>>>> = OnceLock::new();
    LINES.get_or_init(Mutex::default)
}

/// The line at `endpoint`: the one other sections hold, or a new one (its
/// owner task spawned on the current runtime).
pub fn attach(endpoint: &Endpoint) -> Arc<Line> {
    let mut lines = registry().lock().unwrap_or_else(|e| e.into_inner());
    lines.retain(|_, line| line.strong_count() > 0);
    let key = endpoint.key();
    if let Some(line) = lines.get(&key).and_then(Weak::upgrade) {
        if line.endpoint != *endpoint {
            warn!(
                "{key} is open as {}, as another section set it; this section's {endpoint} is not used",
                line.endpoint
            );
        }
        return line;
    }
    let (jobs, queue) = mpsc::channel(64);
    let line = Arc::new(Line {
        endpoint: endpoint.clone(),
        jobs,
    });
    lines.insert(key, Arc::downgrade(&line));
    tokio::spawn(Owner::new(endpoint.clone()).run(queue));
    line
}

impl Line {
    pub fn endpoint(&self) -> &Endpoint {
        &self.endpoint
    }

    /// Runs `requests` to `unit`, in order, when the line's turn comes;
    /// each unanswered one is sent `retries` more times.
    pub async fn exchange(
        &self,
        unit: u8,
        requests: &[Request],
        timeout: Duration,
        retries: u32,
        counters: &Arc<BackendCounters>,
    ) -> Result<Vec<Outcome>, PlcError> {
        let (reply, answer) = oneshot::channel();
        let job = Job {
            unit,
            requests: requests.to_vec(),
            timeout,
            retries,
            counters: counters.clone(),
            reply,
        };
        let gone = || {
            PlcError::Io(std::io::Error::new(
                std::io::ErrorKind::BrokenPipe,
                format!("the owner of {} has stopped", self.endpoint),
            ))
        };
        self.jobs.send(job).await.map_err(|_| gone())?;
        answer.await.map_err(|_| gone())?
    }
}

enum Port {
    Serial(SerialStream),
    Tcp(TcpStream),
}

impl Port {
    async fn write_all(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        match self {
            Port::Serial(port) => {
                port.write_all(bytes).await?;
                port.flush().await
            }
            Port::Tcp(stream) => stream.write_all(bytes).await,
        }
    }

    async fn read_buf(&mut self, buf: &mut BytesMut) -> std::io::Result<usize> {
        match self {
            Port::Serial(port) => port.read_buf(buf).await,
            Port::Tcp(stream) => stream.read_buf(buf).await,
        }
    }

    /// Drops what has arrived and not been read; the bytes dropped.
    fn discard(&mut self) -> usize {
        if let Port::Serial(port) = self {
            let _ = port.clear(tokio_serial::ClearBuffer::Input);
        }
        let mut scratch = BytesMut::with_capacity(MAX_FRAME);
        let mut dropped = 0;
        for _ in 0..64 {
            scratch.clear();
            match self.read_buf(&mut scratch).now_or_never() {
                Some(Ok(n)) if n > 0 => dropped += n,
                _ => break,
            }
        }
        dropped
    }
}

/// The task that owns the port.
struct Owner {
    endpoint: Endpoint,
    port: Option<Port>,
    /// The RTS pin, high while a frame is sent.
    gpio: Option<Gpio>,
    buf: BytesMut,
    decoder: RtuDecoder,
    /// When the line went quiet (last byte sent or seen).
    quiet_since: Instant,
    /// Units that did not answer, and when they were last tried.
    silent: HashMap<u8, Instant>,
    out: Vec<u8>,
}

impl Owner {
    fn new(endpoint: Endpoint) -> Owner {
        Owner {
            endpoint,
            port: None,
            gpio: None,
            buf: BytesMut::with_capacity(MAX_FRAME),
            decoder: RtuDecoder::new(Side::Responses),
            quiet_since: Instant::now(),
            silent: HashMap::new(),
            out: Vec::with_capacity(MAX_FRAME),
        }
    }

    async fn run(mut self, mut queue: mpsc::Receiver<Job>) {
        while let Some(job) = queue.recv().await {
            if job.reply.is_closed() {
                continue;
            }
            let result = self.serve(&job).await;
            if let Err(PlcError::Io(_)) = &result {
                self.port = None;
            }
            let _ = job.reply.send(result);
        }
        debug!(
            "{}: no section uses the line any more, closed",
            self.endpoint
        );
    }

    /// The line's time for `bytes` characters (none over TCP: the server
    /// keeps its line's timing).
    fn line_time(&self, bytes: usize) -> Duration {
        match &self.endpoint {
            Endpoint::Serial(s) => rtu::line_time(s.speed, s.char_bits(), bytes),
            Endpoint::Tcp { .. } => Duration::ZERO,
        }
    }

    fn silence(&self) -> Duration {
        match &self.endpoint {
            Endpoint::Serial(s) => rtu::silence(s.speed, s.char_bits()),
            Endpoint::Tcp { .. } => Duration::ZERO,
        }
    }

    async fn open(&mut self, timeout: Duration) -> Result<(), PlcError> {
        if self.port.is_some() {
            return Ok(());
        }
        let port = match &self.endpoint {
            Endpoint::Serial(s) => {
                if let (Some(pin), None) = (s.rts, &self.gpio) {
                    let gpio = Gpio::open(&s.gpio_root, pin).map_err(|e| {
                        PlcError::Io(std::io::Error::new(
                            e.kind(),
                            format!("RTS GPIO {pin} in {}: {e}", s.gpio_root.display()),
                        ))
                    })?;
                    self.gpio = Some(gpio);
                }
                Port::Serial(open_serial(s).map_err(|e| {
                    PlcError::Io(std::io::Error::new(e.kind(), format!("{}: {e}", s.device)))
                })?)
            }
            Endpoint::Tcp { server, local } => {
                Port::Tcp(connect_tcp(*server, *local, timeout).await?)
            }
        };
        self.port = Some(port);
        self.buf.clear();
        Ok(())
    }

    async fn serve(&mut self, job: &Job) -> Result<Vec<Outcome>, PlcError> {
        if let Some(tried) = self.silent.get(&job.unit) {
            if tried.elapsed() < RETRY_SILENT {
                return Err(PlcError::Timeout(format!(
                    "unit {} on {} did not answer; it is tried again at most once a second",
                    job.unit, self.endpoint
                )));
            }
        }
        self.open(job.timeout).await?;
        let mut outcomes = Vec::with_capacity(job.requests.len());
        for request in &job.requests {
            outcomes.push(self.transact(job, request).await?);
        }
        Ok(outcomes)
    }

    /// One request and its answer, with the job's retries.
    async fn transact(&mut self, job: &Job, request: &Request) -> Result<Outcome, PlcError> {
        let unit = job.unit;
        if unit == BROADCAST && !request.is_write() {
            // Nobody answers a broadcast: a read of unit 0 is refused here.
            return Ok(Err(ExceptionCode::ILLEGAL_FUNCTION));
        }
        self.out.clear();
        rtu::encode_request(unit, request, &mut self.out);
        let mut attempts = 0;
        let mut last_problem: Option<String> = None;
        loop {
            let dropped = self.port.as_mut().map_or(0, Port::discard) + self.buf.len();
            if dropped > 0 {
                debug!(
                    "{}: {dropped} bytes left on the line discarded",
                    self.endpoint
                );
                self.buf.clear();
            }
            wait_until(self.quiet_since + self.silence()).await;
            job.counters.requests.inc();
            if attempts > 0 {
                job.counters.retries.inc();
            }
            attempts += 1;
            let started = Instant::now();
            let frame = std::mem::take(&mut self.out);
            let written = tokio::time::timeout(job.timeout, self.send(&frame, started)).await;
            self.out = frame;
            match written {
                Ok(result) => result?,
                Err(_) => {
                    return Err(PlcError::Timeout(format!(
                        "{} does not take the request (flow control?)",
                        self.endpoint
                    )))
                }
            }
            // The kernel may take the frame before the line has sent it.
            let sent = Instant::now().max(started + self.line_time(self.out.len()));
            self.quiet_since = sent;
            if unit == BROADCAST {
                self.quiet_since = sent + TURNAROUND;
                return Ok(Ok(Response::Written));
            }
            let deadline =
                sent + job.timeout + self.line_time(rtu::answer_len(request).min(MAX_FRAME));
            if let Some(outcome) = self
                .receive(unit, request, deadline, &job.counters, &mut last_problem)
                .await?
            {
                self.silent.remove(&unit);
                job.counters.round_trip.observe(started.elapsed());
                return Ok(outcome);
            }
            if attempts > job.retries {
                job.counters.timeouts.inc();
                self.silent.insert(unit, started);
                let mut text = format!(
                    "no answer from unit {unit} on {} after {attempts} attempts",
                    self.endpoint
                );
                if let Some(problem) = last_problem {
                    text.push_str(&format!(" (last bad answer: {problem})"));
                }
                return Err(PlcError::Timeout(text));
            }
        }
    }

    /// Writes a frame, with RTS (when set) high until its last bit is out.
    async fn send(&mut self, frame: &[u8], started: Instant) -> std::io::Result<()> {
        let on_line = self.line_time(frame.len());
        let port = self.port.as_mut().ok_or(std::io::ErrorKind::NotConnected)?;
        if let Some(gpio) = &self.gpio {
            gpio.set(true)?;
        }
        let written = port.write_all(frame).await;
        if let (Some(gpio), Port::Serial(serial)) = (&self.gpio, port) {
            wait_until(started + on_line).await;
            rs485::drain(serial.as_raw_fd());
            gpio.set(false)?;
        }
        written
    }

    /// Waits until `deadline` for `unit`'s answer to `request`; `None`:
    /// none came in time.
    async fn receive(
        &mut self,
        unit: u8,
        request: &Request,
        deadline: Instant,
        counters: &BackendCounters,
        last_problem: &mut Option<String>,
    ) -> Result<Option<Outcome>, PlcError> {
        // A frame that stops half-way is given up after this much quiet.
        let idle = (self.line_time(30) + self.silence()).max(Duration::from_millis(20));
        let name = self.endpoint.to_string();
        let mut bad = |problem: String| {
            debug!("{name}: {problem}");
            counters.errors.inc();
            *last_problem = Some(problem);
        };
        loop {
            while let Some(item) = self.decoder.decode(&mut self.buf)? {
                match item {
                    RtuItem::Frame(frame) if frame.unit != unit => bad(format!(
                        "a frame from unit {} dropped (waiting for unit {unit})",
                        frame.unit
                    )),
                    RtuItem::Frame(frame) => match decode_response(request, &frame.pdu) {
                        Ok(outcome) => return Ok(Some(outcome)),
                        Err(problem) => bad(format!("unit {unit}: {problem}")),
                    },
                    RtuItem::Skipped { bytes, why } => bad(format!("{bytes} bytes dropped: {why}")),
                }
            }
            let wait_until = if self.buf.is_empty() {
                deadline
            } else {
                deadline.min(Instant::now() + idle)
            };
            let port = self.port.as_mut().ok_or(PlcError::NotConfigured)?;
            match tokio::time::timeout_at(wait_until, port.read_buf(&mut self.buf)).await {
                Ok(Ok(0)) => {
                    return Err(PlcError::Io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        format!("{name} closed"),
                    )))
                }
                Ok(Ok(_)) => self.quiet_since = Instant::now(),
                Ok(Err(e)) => return Err(PlcError::Io(e)),
                Err(_elapsed) if Instant::now() >= deadline => {
                    if let Some(RtuItem::Skipped { bytes, why }) =
                        self.decoder.abandon_partial(&mut self.buf)
                    {
                        bad(format!("{bytes} bytes dropped: {why}"));
                    }
                    return Ok(None);
                }
                Err(_idle) => {
                    if let Some(RtuItem::Skipped { bytes, why }) =
                        self.decoder.abandon_partial(&mut self.buf)
                    {
                        bad(format!("{bytes} bytes dropped: {why}"));
                    }
                }
            }
        }
    }
}

/// Waits until `deadline` (at once when it has passed: the timer would
/// round even that up to its next millisecond step). Tokio's timer steps
/// in whole milliseconds, which on a fast line is most of the silence
/// itself (1.75 ms over 19,200 baud): it sleeps to within a millisecond of
/// the deadline, and the thread's own clock sleeps the rest. That blocks
/// the line's owner task, and the link thread it runs on, for under a
/// millisecond, while the line must be quiet anyway.
async fn wait_until(deadline: Instant) {
    const TIMER_STEP: Duration = Duration::from_millis(1);
    let now = Instant::now();
    if deadline <= now {
        return;
    }
    if deadline - now > TIMER_STEP {
        tokio::time::sleep_until(deadline - TIMER_STEP).await;
    }
    let rest = deadline.saturating_duration_since(Instant::now());
    if !rest.is_zero() {
        std::thread::sleep(rest);
    }
}

/// Opens a serial line with its character format, no flow control.
fn open_serial(s: &SerialLine) -> std::io::Result<SerialStream> {
    let parity = match s.parity {
        Parity::None => tokio_serial::Parity::None,
        Parity::Even => tokio_serial::Parity::Even,
        Parity::Odd => tokio_serial::Parity::Odd,
    };
    tokio_serial::new(&s.device, s.speed)
        .data_bits(if s.data_bits == 7 {
            tokio_serial::DataBits::Seven
        } else {
            tokio_serial::DataBits::Eight
        })
        .parity(parity)
        .stop_bits(if s.stop_bits == 2 {
            tokio_serial::StopBits::Two
        } else {
            tokio_serial::StopBits::One
        })
        .flow_control(tokio_serial::FlowControl::None)
        .exclusive(false)
        .open_native_async()
        .map_err(std::io::Error::from)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::net::TcpListener;

    fn read(count: u16) -> Request {
        Request::ReadHoldingRegisters { address: 0, count }
    }

    /// Sections on one address share one connection, closed with the last.
    #[tokio::test]
    async fn one_connection_per_line_closed_with_the_last_section() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let endpoint = Endpoint::Tcp {
            server: listener.local_addr().unwrap(),
            local: None,
        };
        let (a, b) = (attach(&endpoint), attach(&endpoint));
        assert!(Arc::ptr_eq(&a, &b));
        let counters = Arc::new(BackendCounters::default());
        let device = tokio::spawn(async move {
            let (mut stream, _) = listener.accept().await.unwrap();
            let mut decoder = RtuDecoder::new(Side::Requests);
            let mut buf = BytesMut::new();
            let mut answered = 0;
            loop {
                while let Some(RtuItem::Frame(frame)) = decoder.decode(&mut buf).unwrap() {
                    let mut out = Vec::new();
                    rtu::encode_response(
                        frame.unit,
                        3,
                        Some(&read(1)),
                        &Ok(Response::Registers(vec![u16::from(frame.unit)])),
                        &mut out,
                    );
                    stream.write_all(&out).await.unwrap();
                    answered += 1;
                }
                if stream.read_buf(&mut buf).await.unwrap() == 0 {
                    // Closed: and no second connection comes.
                    return answered;
                }
            }
        });
        for (line, unit) in [(&a, 1), (&b, 2), (&a, 1)] {
            let outcomes = line
                .exchange(unit, &[read(1)], Duration::from_secs(5), 1, &counters)
                .await
                .unwrap();
            assert_eq!(outcomes, [Ok(Response::Registers(vec![u16::from(unit)]))]);
        }
        drop(a);
        drop(b);
        let closed = tokio::time::timeout(Duration::from_secs(10), device).await;
        assert_eq!(closed.expect("the port closed").unwrap(), 3);
    }

    /// A unit that did not answer is not asked again within the second.
    #[tokio::test]
    async fn a_silent_unit_is_tried_at_most_once_a_second() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let endpoint = Endpoint::Tcp {
            server: listener.local_addr().unwrap(),
            local: None,
        };
        let _silent = tokio::spawn(async move {
            let (mut stream, _) = listener.accept().await.unwrap();
            let mut buf = BytesMut::new();
            while stream.read_buf(&mut buf).await.unwrap_or(0) > 0 {}
        });
        let line = attach(&endpoint);
        let counters = Arc::new(BackendCounters::default());
        let timeout = Duration::from_millis(50);
        let first = line.exchange(7, &[read(1)], timeout, 1, &counters).await;
        assert!(
            matches!(&first, Err(PlcError::Timeout(t)) if t.contains("after 2 attempts")),
            "{first:?}"
        );
        let second = line.exchange(7, &[read(1)], timeout, 0, &counters).await;
        assert!(
            matches!(&second, Err(PlcError::Timeout(t)) if t.contains("at most once a second")),
            "{second:?}"
        );
        assert_eq!(counters.requests.get(), 2, "the second went nowhere");
        // A broadcast write is not waited for.
        let write = Request::WriteSingleRegister {
            address: 0,
            value: 1,
        };
        let outcomes = line
            .exchange(BROADCAST, &[write], timeout, 1, &counters)
            .await
            .unwrap();
        assert_eq!(outcomes, [Ok(Response::Written)]);
    }
}
