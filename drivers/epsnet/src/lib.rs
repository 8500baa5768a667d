//! EPSNET: the backend that talks to a Tecomat PLC (or `plcsim`), over UDP
//! ([`udp`]) or a serial line ([`serial`]).
//!
//! Layers (in the `plccoms-plc` crate): `frame` (plain data) -> `codec` /
//! `stream` (bytes <-> datagrams / frames on a line) -> `service` (requests
//! and answers, the one table of service codes) -> this module: one client,
//! [`EpsnetClient`], that turns the backend's calls into EPSNET requests
//! (splitting blocks at the service limits) and answers, over a
//! [`Transport`] that carries them. What the transports share, they take
//! from [`Exchange`]: our source address, the attempt timing (a request
//! unanswered within `EPSTOUT + EPSTOUT_STEP * attempt` is sent again, up to
//! `retries` times, then the exchange fails with [`PlcError::Timeout`]), the
//! matching of an answer frame to its request, and the counting.

pub mod serial;
pub mod udp;

use std::ops::Range;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use tokio::time::Instant;

use plccoms_core::config::Protocol;
use plccoms_core::driver::{
    Answer, DirEntry, FileInfo, PlcBackend, PlcError, PlcStatus, ReadRequest, Refusal, WriteData,
    WriteRequest,
};
use plccoms_core::driver::{Driver, Opened};
use plccoms_core::metrics::BackendCounters;
use plccoms_plc::epsnet::frame::Frame;
use plccoms_plc::epsnet::service::{
    PlcTime, Request, Response, MAX_FILE_BLOCK, MAX_PATH, MAX_READ,
};
use plccoms_plc::epsnet::{service, PLC_EPS_ADDR};
use plccoms_protocol::cp1250;

pub use serial::{SerialBackend, SerialConfig};
pub use udp::{EpsnetBackend, EpsnetConfig};

/// The source address used when the configuration names none.
pub fn auto_eps_addr() -> u8 {
    static COUNTER: AtomicU32 = AtomicU32::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    (1 + (std::process::id().wrapping_add(n.wrapping_mul(37)) % 126)) as u8
}

/// What every EPSNET link is set up with, whatever carries it.
#[derive(Debug, Clone)]
pub struct Timing {
    /// Our source address 1..=126 (EPSADDR). `None`: chosen from the process
    /// id and a per-process counter, so two servers (or two links in one
    /// process) rarely pick the same one; set it explicitly when several
    /// servers share a PLC.
    pub eps_addr: Option<u8>,
    /// EPSTOUT: answer timeout of the first attempt.
    pub timeout: Duration,
    /// EPSTOUT_STEP: added to the timeout on each retry.
    pub timeout_step: Duration,
    /// Retries after the first attempt. One: a silent PLC is declared lost
    /// within EPSTOUT + (EPSTOUT + EPSTOUT_STEP), 2.5 s at the defaults.
    pub retries: u32,
}

/// Carries EPSNET requests to the PLC and brings the answers back.
#[async_trait]
pub trait Transport: Send {
    /// Where the PLC is, for logs and GETINFO.
    fn describe(&self) -> String;

    /// A fresh channel to the PLC (a new socket, the device opened again),
    /// so that nothing from an earlier session can be taken for an answer.
    async fn open(&mut self) -> Result<(), PlcError>;

    /// Whether [`Transport::open`] has succeeded (exchanges open it first).
    fn is_open(&self) -> bool;

    /// Sends every request and returns the answers in request order, or the
    /// link failure. `window`: how many requests may be outstanding at once
    /// where the transport can have several (1 = strictly one at a time,
    /// as writes must be).
    async fn exchange(
        &mut self,
        x: &Exchange<'_>,
        requests: &[Request],
        window: usize,
    ) -> Result<Vec<Answer<Response>>, PlcError>;

    /// The window for poll reads.
    fn read_window(&self) -> usize {
        1
    }
}

/// What the transports share in an exchange: our address, the attempt
/// timing, answer matching and the counters.
pub struct Exchange<'a> {
    pub sa: u8,
    timing: &'a Timing,
    counters: &'a BackendCounters,
}

impl Exchange<'_> {
    /// The request frame, from us to the PLC.
    pub fn request_frame(&self, request: &Request) -> Frame {
        request.to_frame(PLC_EPS_ADDR, self.sa)
    }

    /// How long attempt `attempt` (0 = the first) waits for its answer.
    pub fn wait(&self, attempt: u32) -> Duration {
        self.timing.timeout + self.timing.timeout_step * attempt
    }

    /// Whether attempt `attempt` may be made.
    pub fn may_try(&self, attempt: u32) -> bool {
        attempt <= self.timing.retries
    }

    /// Counts a request sent; `attempt` > 0 is a retry.
    pub fn sent(&self, attempt: u32) {
        self.counters.requests.inc();
        if attempt > 0 {
            self.counters.retries.inc();
        }
    }

    /// Counts an answer, `sent` being when its request left.
    pub fn answered(&self, sent: Instant) {
        self.counters.round_trip.observe(sent.elapsed());
    }

    /// Counts a bad answer (malformed, foreign, garbage on the line).
    pub fn bad_answer(&self, plc: &str, problem: &str) {
        tracing::debug!(plc, "bad answer: {problem}");
        self.counters.errors.inc();
    }

    /// The exchange failed: no answer after every attempt.
    pub fn timed_out(&self, what: String, last_problem: Option<&str>) -> PlcError {
        self.counters.timeouts.inc();
        match last_problem {
            Some(problem) => PlcError::Timeout(format!("{what} (last bad answer: {problem})")),
            None => PlcError::Timeout(what),
        }
    }

    /// The answer `frame` carries for `request`, or why it is not one.
    pub fn match_answer(
        &self,
        request: &Request,
        frame: &Frame,
    ) -> Result<Answer<Response>, String> {
        if let Frame::Data(f) = frame {
            if f.da != self.sa {
                return Err(format!("answer addressed to {}, not to us", f.da));
            }
        }
        service::decode_answer(request, frame)
            .map(|answer| answer.map_err(Refusal::Epsnet))
            .map_err(|e| e.to_string())
    }
}

/// The EPSNET client over a transport: the backend of EPSNET sections.
pub struct EpsnetClient<T> {
    transport: T,
    timing: Timing,
    sa: u8,
    counters: Arc<BackendCounters>,
}

impl<T: Transport> EpsnetClient<T> {
    pub fn with_transport(transport: T, timing: Timing) -> Self {
        let sa = match timing.eps_addr {
            Some(a) if (1..=126).contains(&a) => a,
            _ => auto_eps_addr(),
        };
        EpsnetClient {
            transport,
            timing,
            sa,
            counters: Arc::default(),
        }
    }

    pub fn transport(&self) -> &T {
        &self.transport
    }

    /// Our EPSNET source address.
    pub fn eps_addr(&self) -> u8 {
        self.sa
    }

    /// Sets the PLC clock (SETTID).
    pub async fn set_time(&mut self, time: PlcTime) -> Result<Answer<()>, PlcError> {
        let answer = self.one(Request::SetTime(time)).await?;
        Ok(answer.map(|_| ()))
    }

    async fn one(&mut self, request: Request) -> Result<Answer<Response>, PlcError> {
        let mut answers = self.exchange(&[request], 1).await?;
        answers
            .pop()
            .ok_or_else(|| PlcError::Protocol("no answer".into()))
    }

    /// Sends every request and returns the answers in request order.
    pub async fn exchange(
        &mut self,
        requests: &[Request],
        window: usize,
    ) -> Result<Vec<Answer<Response>>, PlcError> {
        if requests.is_empty() {
            return Ok(Vec::new());
        }
        if !self.transport.is_open() {
            self.transport.open().await?;
        }
        let x = Exchange {
            sa: self.sa,
            timing: &self.timing,
            counters: &self.counters,
        };
        let answers = self.transport.exchange(&x, requests, window).await?;
        if answers.len() != requests.len() {
            return Err(PlcError::Protocol("request left unanswered".into()));
        }
        Ok(answers)
    }

    async fn file_request(&mut self, request: Request) -> Result<Answer<Response>, PlcError> {
        self.one(request).await
    }
}

fn unexpected(response: Response) -> PlcError {
    PlcError::Protocol(format!("unexpected answer {response:?}"))
}

/// The PLC's identification from the answers to `Ident` and `Status`.
fn identified(answers: Vec<Answer<Response>>) -> Result<String, PlcError> {
    let mut answers = answers.into_iter();
    let ident = match answers.next() {
        Some(Ok(Response::Ident(bytes))) => cp1250::decode(&bytes).into_owned(),
        Some(Ok(other)) => return Err(unexpected(other)),
        Some(Err(e)) => return Err(PlcError::Refused(e)),
        None => return Err(PlcError::Protocol("no identification".into())),
    };
    match answers.next() {
        Some(Ok(Response::Status { .. })) => Ok(ident.trim_end_matches('\0').to_string()),
        Some(Ok(other)) => Err(unexpected(other)),
        Some(Err(e)) => Err(PlcError::Refused(e)),
        None => Err(PlcError::Protocol("no status".into())),
    }
}

/// Requests that one caller-level request became, and how to join answers.
struct Split {
    requests: Vec<Request>,
    /// Per caller request: the range of `requests` it became, or a local
    /// answer given without asking the PLC.
    parts: Vec<Result<Range<usize>, Refusal>>,
}

fn split_reads(reads: &[ReadRequest]) -> Split {
    let mut requests = Vec::new();
    let mut parts = Vec::new();
    for r in reads {
        if r.offset.checked_add(r.len).is_none() {
            parts.push(Err(Refusal::BAD_PARAMETERS));
            continue;
        }
        let start = requests.len();
        let mut done = 0;
        loop {
            let len = (r.len - done).min(MAX_READ);
            requests.push(Request::Read {
                area: r.area,
                offset: r.offset + done,
                len: len as u16,
            });
            done += len;
            if done >= r.len {
                break;
            }
        }
        parts.push(Ok(start..requests.len()));
    }
    Split { requests, parts }
}

fn split_writes(writes: &[WriteRequest]) -> Split {
    let mut requests = Vec::new();
    let mut parts = Vec::new();
    for w in writes {
        let start = requests.len();
        match &w.data {
            WriteData::Bit { bit, value } => {
                let Some(mask) = 1u8.checked_shl(u32::from(*bit)) else {
                    parts.push(Err(Refusal::BAD_PARAMETERS));
                    continue;
                };
                requests.push(Request::WriteBits {
                    area: w.area,
                    offset: w.offset,
                    mask,
                    value: if *value { mask } else { 0 },
                });
            }
            WriteData::Bytes(bytes) => {
                if w.offset.checked_add(bytes.len() as u32).is_none()
                    || u32::try_from(bytes.len()).is_err()
                {
                    parts.push(Err(Refusal::BAD_PARAMETERS));
                    continue;
                }
                if bytes.is_empty() {
                    requests.push(Request::Write {
                        area: w.area,
                        offset: w.offset,
                        data: Vec::new(),
                    });
                }
                for (i, chunk) in bytes.chunks(MAX_READ as usize).enumerate() {
                    requests.push(Request::Write {
                        area: w.area,
                        offset: w.offset + (i as u32) * MAX_READ,
                        data: chunk.to_vec(),
                    });
                }
            }
        }
        parts.push(Ok(start..requests.len()));
    }
    Split { requests, parts }
}

#[async_trait]
impl<T: Transport> PlcBackend for EpsnetClient<T> {
    fn describe(&self) -> String {
        format!("{} (EPSADDR {})", self.transport.describe(), self.sa)
    }

    fn source_address(&self) -> Option<u8> {
        Some(self.sa)
    }

    fn max_read_block(&self, _area: plccoms_protocol::Area) -> u32 {
        MAX_READ
    }

    fn answer_timeout(&self) -> Duration {
        self.timing.timeout
    }

    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters;
    }

    fn max_file_block(&self) -> u32 {
        MAX_FILE_BLOCK
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        self.transport.open().await?;
        let answers = self.exchange(&[Request::Ident, Request::Status], 1).await?;
        identified(answers)
    }

    /// As `connect`, sent once: a PLC that is away costs one datagram
    /// (over UDP the identification and the status travel together; on a
    /// serial line the status follows only an answered identification) and
    /// EPSTOUT.
    async fn probe(&mut self) -> Result<String, PlcError> {
        self.transport.open().await?;
        let retries = std::mem::replace(&mut self.timing.retries, 0);
        let answers = self.exchange(&[Request::Ident, Request::Status], 1).await;
        self.timing.retries = retries;
        identified(answers?)
    }

    async fn read(&mut self, reads: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let split = split_reads(reads);
        let window = self.transport.read_window();
        let answers = self.exchange(&split.requests, window).await?;
        let mut out = Vec::with_capacity(reads.len());
        for part in split.parts {
            let range = match part {
                Ok(range) => range,
                Err(e) => {
                    out.push(Err(e));
                    continue;
                }
            };
            let mut joined = Vec::new();
            let mut result = Ok(());
            for answer in &answers[range] {
                match answer {
                    Ok(Response::Data(bytes)) => joined.extend_from_slice(bytes),
                    Ok(other) => return Err(unexpected(other.clone())),
                    Err(e) => {
                        result = Err(*e);
                        break;
                    }
                }
            }
            out.push(result.map(|()| joined));
        }
        Ok(out)
    }

    async fn write(&mut self, writes: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let split = split_writes(writes);
        let answers = self.exchange(&split.requests, 1).await?;
        Ok(split
            .parts
            .into_iter()
            .map(|part| {
                let range = part?;
                answers[range]
                    .iter()
                    .try_for_each(|a| a.as_ref().map(|_| ()).map_err(|e| *e))
            })
            .collect())
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        match self.one(Request::Status).await? {
            Ok(Response::Status { run }) => Ok(PlcStatus { run }),
            Ok(other) => Err(unexpected(other)),
            Err(e) => Err(PlcError::Refused(e)),
        }
    }

    async fn file_info(&mut self, path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        if path.len() > MAX_PATH {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        match self
            .file_request(Request::FileInfo {
                path: path.to_vec(),
            })
            .await?
        {
            Ok(Response::FileInfo(info)) => Ok(Ok(info)),
            Ok(other) => Err(unexpected(other)),
            Err(e) => Ok(Err(e)),
        }
    }

    async fn read_file(
        &mut self,
        path: &[u8],
        offset: u64,
        len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        if path.len() > MAX_PATH || len > MAX_FILE_BLOCK {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        match self
            .file_request(Request::FileRead {
                path: path.to_vec(),
                offset,
                len: len as u16,
            })
            .await?
        {
            Ok(Response::Data(data)) => Ok(Ok(data)),
            Ok(other) => Err(unexpected(other)),
            Err(e) => Ok(Err(e)),
        }
    }

    async fn write_file(
        &mut self,
        path: &[u8],
        offset: u64,
        data: &[u8],
        last: bool,
    ) -> Result<Answer<()>, PlcError> {
        // The link splits uploads into max_file_block pieces; a larger one
        // is refused, as read_file refuses a larger len.
        if path.len() > MAX_PATH || data.len() > MAX_FILE_BLOCK as usize {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        match self
            .file_request(Request::FileWrite {
                path: path.to_vec(),
                offset,
                last,
                data: data.to_vec(),
            })
            .await?
        {
            Ok(Response::Done) => Ok(Ok(())),
            Ok(other) => Err(unexpected(other)),
            Err(e) => Ok(Err(e)),
        }
    }

    async fn write_file_info(
        &mut self,
        path: &[u8],
        info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        if path.len() > MAX_PATH {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        match self
            .file_request(Request::FileWriteInfo {
                path: path.to_vec(),
                info: *info,
            })
            .await?
        {
            Ok(Response::Done) => Ok(Ok(())),
            Ok(other) => Err(unexpected(other)),
            Err(e) => Ok(Err(e)),
        }
    }

    async fn list_dir(&mut self, path: &[u8]) -> Result<Answer<Vec<DirEntry>>, PlcError> {
        if path.len() > MAX_PATH {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        let mut all = Vec::new();
        loop {
            let Ok(start) = u16::try_from(all.len()) else {
                return Err(PlcError::Protocol("directory listing too long".into()));
            };
            let answer = self
                .file_request(Request::DirList {
                    path: path.to_vec(),
                    start,
                })
                .await?;
            match answer {
                Ok(Response::DirPage { entries, more }) => {
                    if plccoms_core::driver::add_dir_page(&mut all, entries, more)? {
                        return Ok(Ok(all));
                    }
                }
                Ok(other) => return Err(unexpected(other)),
                Err(e) => return Ok(Err(e)),
            }
        }
    }
}

/// This driver, for the binary's list: sections with `PROTOCOL = EPSNET`
/// over UDP or a serial line (a plugin, `SHM_NAME`, is the plugin host's).
pub const DRIVER: Driver = Driver {
    name: "epsnet",
    open,
};

/// EPSNET on the serial line `SERIAL_DEVICE` when set, else over UDP to
/// `IPADDR:EPSPORT`; `None` when the section has no PLC yet (`IPADDR` unset
/// or `0.0.0.0`).
fn open(section: &plccoms_core::config::Section, _dir: &std::path::Path) -> Option<Opened> {
    use std::net::{IpAddr, SocketAddr};
    if section.protocol != Protocol::Epsnet || section.shm_name.is_some() {
        return None;
    }
    if let Some(device) = &section.serial_device {
        let config = serial_config(section, device);
        return Some(Ok(Some(Box::new(SerialBackend::new(config)))));
    }
    Some(match section.ipaddr {
        Some(ip) if !ip.is_unspecified() => {
            let plc = SocketAddr::new(IpAddr::V4(ip), section.epsport);
            Ok(Some(Box::new(EpsnetBackend::new(config_of(section, plc)))))
        }
        _ => Ok(None),
    })
}

/// EPSNET serial settings from a section's keys, for the line `device`.
pub fn serial_config(section: &plccoms_core::config::Section, device: &str) -> SerialConfig {
    let mut config = SerialConfig::new(device);
    config.speed = section.serial_speed.unwrap_or(config.speed);
    config.rts = serial::rts_of(
        device,
        section.serial_rts,
        section.serial_device_cfg.as_deref().unwrap_or_default(),
    );
    config.timing.eps_addr = section.epsaddr;
    config.timing.timeout = section.epstout;
    config.timing.timeout_step = section.epstout_step;
    config
}

/// EPSNET settings from a section's keys, for a PLC at `plc`.
pub fn config_of(
    section: &plccoms_core::config::Section,
    plc: std::net::SocketAddr,
) -> EpsnetConfig {
    use std::net::{IpAddr, Ipv4Addr};
    let mut config = EpsnetConfig::new(plc);
    if let Some(local) = section.ipaddr_local {
        config.local_ip = IpAddr::V4(local);
    }
    if plc.ip().is_loopback() {
        config.local_ip = IpAddr::V4(Ipv4Addr::LOCALHOST);
    }
    config.eps_addr = section.epsaddr;
    config.timeout = section.epstout;
    config.timeout_step = section.epstout_step;
    config
}

#[cfg(test)]
mod tests {
    use plccoms_protocol::Area;

    use super::*;

    #[test]
    fn reads_split_at_1230() {
        let split = split_reads(&[ReadRequest {
            area: Area::R,
            offset: 100,
            len: 3000,
        }]);
        let lens: Vec<_> = split
            .requests
            .iter()
            .map(|r| match r {
                Request::Read { offset, len, .. } => (*offset, *len),
                _ => unreachable!(),
            })
            .collect();
        assert_eq!(lens, [(100, 1230), (1330, 1230), (2560, 540)]);
    }

    #[test]
    fn auto_address_in_range() {
        for _ in 0..300 {
            assert!((1..=126).contains(&auto_eps_addr()));
        }
    }
}
