//! EPSNET over UDP: the backend that talks to a Tecomat PLC (or `plcsim`).
//!
//! Layers (in the `plccoms-plc` crate): `frame` (plain data) -> `codec`
//! (bytes <-> packets) -> `service` (requests and answers, the one table of service codes) -> this
//! module (the client: packing, matching, retries).
//!
//! How a batch travels:
//! - requests are packed into as few datagrams as fit, so that both the
//!   request datagram and the largest possible answer stay within
//!   [`frame::MAX_PACKET`];
//! - each datagram gets a fresh MESI (counted up per datagram sent, retries
//!   included); an answer is matched by MESI to the datagram whose any attempt
//!   carried it, and must answer every frame in order, so stale, duplicate
//!   and foreign datagrams are dropped and never mismatched;
//! - up to `window` datagrams of a read batch are in flight at once. Whether
//!   a real PLC accepts more than one outstanding datagram is unverified:
//!   window 1 is the safe setting. Writes always go one datagram at a time so
//!   they reach the PLC in order;
//! - a datagram unanswered within `timeout + step * attempt` is sent again, up
//!   to `retries` times, then the batch fails with [`PlcError::Timeout`].

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::ops::Range;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use tokio::net::UdpSocket;
use tokio::time::Instant;

use super::{
    Answer, DirEntry, Exception, FileInfo, PlcBackend, PlcError, PlcStatus, ReadRequest, WriteData,
    WriteRequest,
};
use crate::metrics::BackendCounters;
use plccoms_plc::epsnet::frame::{Frame, Packet, MAX_DPLEN, MAX_PACKET};
use plccoms_plc::epsnet::service::{
    PlcTime, Request, Response, MAX_FILE_BLOCK, MAX_PATH, MAX_READ,
};
use plccoms_plc::epsnet::{codec, service, PLC_EPS_ADDR};
use plccoms_protocol::cp1250;

/// Settings of one EPSNET link (the PLC section's INI keys).
#[derive(Debug, Clone)]
pub struct EpsnetConfig {
    /// The PLC (IPADDR, EPSPORT; the PLC listens on 61682).
    pub plc: SocketAddr,
    /// Local address to bind (IPADDR_LOCAL); the port is chosen by the OS.
    pub local_ip: IpAddr,
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
    /// Datagrams of one read batch in flight at once (1 = strictly one).
    pub window: usize,
}

impl EpsnetConfig {
    pub fn new(plc: SocketAddr) -> Self {
        EpsnetConfig {
            plc,
            local_ip: IpAddr::V4(Ipv4Addr::UNSPECIFIED),
            eps_addr: None,
            timeout: Duration::from_millis(1000),
            timeout_step: Duration::from_millis(500),
            retries: 1,
            window: 4,
        }
    }
}

/// The source address used when the configuration names none.
pub fn auto_eps_addr() -> u8 {
    static COUNTER: AtomicU32 = AtomicU32::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    (1 + (std::process::id().wrapping_add(n.wrapping_mul(37)) % 126)) as u8
}

pub struct EpsnetBackend {
    config: EpsnetConfig,
    sa: u8,
    socket: Option<UdpSocket>,
    next_mesi: u16,
    buf: Box<[u8]>,
    counters: Arc<BackendCounters>,
}

/// One datagram of a batch.
struct Slot {
    range: Range<usize>,
    attempts: u32,
    /// When it was last sent.
    sent: Instant,
    deadline: Instant,
    done: bool,
}

impl EpsnetBackend {
    pub fn new(config: EpsnetConfig) -> Self {
        let sa = match config.eps_addr {
            Some(a) if (1..=126).contains(&a) => a,
            _ => auto_eps_addr(),
        };
        EpsnetBackend {
            config,
            sa,
            socket: None,
            next_mesi: 0,
            // Larger than any valid datagram, so oversize ones are seen whole
            // enough to be rejected rather than silently cut to valid length.
            buf: vec![0; MAX_PACKET + 64].into_boxed_slice(),
            counters: Arc::default(),
        }
    }

    pub fn config(&self) -> &EpsnetConfig {
        &self.config
    }

    /// Our EPSNET source address.
    pub fn eps_addr(&self) -> u8 {
        self.sa
    }

    /// The local UDP address, once bound.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.socket.as_ref().and_then(|s| s.local_addr().ok())
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

    async fn bind(&mut self) -> Result<(), PlcError> {
        let socket = UdpSocket::bind(SocketAddr::new(self.config.local_ip, 0)).await?;
        self.socket = Some(socket);
        Ok(())
    }

    /// Packs requests into datagrams: consecutive requests while both the
    /// request and the largest possible answer fit.
    fn plan(&self, requests: &[Request]) -> Result<Vec<Range<usize>>, PlcError> {
        let mut ranges = Vec::new();
        let mut start = 0;
        let (mut req_len, mut ans_len) = (0, 0);
        for (i, request) in requests.iter().enumerate() {
            let r = request.to_frame(PLC_EPS_ADDR, self.sa).encoded_len();
            let a = request.max_answer_len();
            if r > MAX_DPLEN || a > MAX_DPLEN {
                return Err(PlcError::Protocol(format!(
                    "request 0x{:02X} too large for one datagram",
                    request.code()
                )));
            }
            if i > start && (req_len + r > MAX_DPLEN || ans_len + a > MAX_DPLEN) {
                ranges.push(start..i);
                start = i;
                req_len = 0;
                ans_len = 0;
            }
            req_len += r;
            ans_len += a;
        }
        if start < requests.len() {
            ranges.push(start..requests.len());
        }
        Ok(ranges)
    }

    async fn send(
        &mut self,
        requests: &[Request],
        slot: &mut Slot,
        mesis: &mut HashMap<u16, usize>,
        index: usize,
    ) -> Result<(), PlcError> {
        let mesi = self.next_mesi;
        self.next_mesi = self.next_mesi.wrapping_add(1);
        let packet = Packet {
            mesi,
            frames: requests[slot.range.clone()]
                .iter()
                .map(|r| r.to_frame(PLC_EPS_ADDR, self.sa))
                .collect(),
        };
        let bytes = codec::encode_packet(&packet)
            .map_err(|e| PlcError::Protocol(format!("cannot encode request: {e}")))?;
        let wait = self.config.timeout + self.config.timeout_step * slot.attempts;
        self.counters.requests.inc();
        if slot.attempts > 0 {
            self.counters.retries.inc();
        }
        slot.attempts += 1;
        slot.sent = Instant::now();
        slot.deadline = Instant::now() + wait;
        mesis.insert(mesi, index);
        let socket = self.socket.as_ref().ok_or(PlcError::NotConfigured)?;
        match socket.send_to(&bytes, self.config.plc).await {
            Ok(_) => Ok(()),
            // A transient send failure is just a lost datagram: retried.
            Err(e) if is_transient(&e) => Ok(()),
            Err(e) => Err(PlcError::Io(e)),
        }
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
        if self.socket.is_none() {
            self.bind().await?;
        }
        self.drain();
        let mut slots: Vec<Slot> = self
            .plan(requests)?
            .into_iter()
            .map(|range| Slot {
                range,
                attempts: 0,
                sent: Instant::now(),
                deadline: Instant::now(),
                done: false,
            })
            .collect();
        let mut results: Vec<Option<Answer<Response>>> = vec![None; requests.len()];
        let mut mesis: HashMap<u16, usize> = HashMap::new();
        let mut in_flight: Vec<usize> = Vec::new();
        let mut next = 0;
        let mut last_problem: Option<String> = None;
        let window = window.max(1);
        loop {
            while in_flight.len() < window && next < slots.len() {
                self.send(requests, &mut slots[next], &mut mesis, next)
                    .await?;
                in_flight.push(next);
                next += 1;
            }
            let Some(deadline) = in_flight.iter().map(|&i| slots[i].deadline).min() else {
                break;
            };
            let socket = self.socket.as_ref().ok_or(PlcError::NotConfigured)?;
            let received = tokio::time::timeout_at(deadline, socket.recv_from(&mut self.buf)).await;
            match received {
                Err(_elapsed) => {
                    let now = Instant::now();
                    for &i in &in_flight {
                        if slots[i].deadline > now {
                            continue;
                        }
                        if slots[i].attempts > self.config.retries {
                            let mut text = format!(
                                "no answer from {} after {} attempts",
                                self.config.plc, slots[i].attempts
                            );
                            if let Some(problem) = &last_problem {
                                text.push_str(&format!(" (last bad answer: {problem})"));
                            }
                            self.counters.timeouts.inc();
                            return Err(PlcError::Timeout(text));
                        }
                        self.send(requests, &mut slots[i], &mut mesis, i).await?;
                    }
                }
                Ok(Err(e)) if is_transient(&e) => {}
                Ok(Err(e)) => return Err(PlcError::Io(e)),
                Ok(Ok((len, from))) => {
                    if from != self.config.plc {
                        continue;
                    }
                    let packet = match codec::decode_packet(&self.buf[..len]) {
                        Ok(p) => p,
                        Err(e) => {
                            tracing::debug!(plc = %self.config.plc, "bad datagram: {e}");
                            self.counters.errors.inc();
                            last_problem = Some(e.to_string());
                            continue;
                        }
                    };
                    let Some(&index) = mesis.get(&packet.mesi) else {
                        continue;
                    };
                    if slots[index].done {
                        continue;
                    }
                    match self.match_answers(&requests[slots[index].range.clone()], &packet) {
                        Ok(answers) => {
                            for (slot_result, answer) in
                                results[slots[index].range.clone()].iter_mut().zip(answers)
                            {
                                *slot_result = Some(answer);
                            }
                            slots[index].done = true;
                            self.counters
                                .round_trip
                                .observe(slots[index].sent.elapsed());
                            in_flight.retain(|&i| i != index);
                        }
                        Err(problem) => {
                            tracing::debug!(plc = %self.config.plc, "bad answer: {problem}");
                            self.counters.errors.inc();
                            last_problem = Some(problem);
                        }
                    }
                }
            }
        }
        results
            .into_iter()
            .map(|r| r.ok_or_else(|| PlcError::Protocol("request left unanswered".into())))
            .collect()
    }

    fn match_answers(
        &self,
        requests: &[Request],
        packet: &Packet,
    ) -> Result<Vec<Answer<Response>>, String> {
        if packet.frames.len() != requests.len() {
            return Err(format!(
                "{} answer frames for {} requests",
                packet.frames.len(),
                requests.len()
            ));
        }
        requests
            .iter()
            .zip(&packet.frames)
            .map(|(request, frame)| {
                if let Frame::Data(f) = frame {
                    if f.da != self.sa {
                        return Err(format!("answer addressed to {}, not to us", f.da));
                    }
                }
                service::decode_answer(request, frame).map_err(|e| e.to_string())
            })
            .collect()
    }

    /// Drops datagrams left over from an earlier, failed batch.
    fn drain(&mut self) {
        if let Some(socket) = &self.socket {
            let mut count = 0;
            while count < 1024 && socket.try_recv_from(&mut self.buf).is_ok() {
                count += 1;
            }
        }
    }

    async fn file_request(&mut self, request: Request) -> Result<Answer<Response>, PlcError> {
        self.one(request).await
    }
}

fn is_transient(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    matches!(
        e.kind(),
        ConnectionRefused | ConnectionReset | WouldBlock | Interrupted
    )
}

fn unexpected(response: Response) -> PlcError {
    PlcError::Protocol(format!("unexpected answer {response:?}"))
}

/// Requests that one caller-level request became, and how to join answers.
struct Split {
    requests: Vec<Request>,
    /// Per caller request: the range of `requests` it became, or a local
    /// answer given without asking the PLC.
    parts: Vec<Result<Range<usize>, Exception>>,
}

fn split_reads(reads: &[ReadRequest]) -> Split {
    let mut requests = Vec::new();
    let mut parts = Vec::new();
    for r in reads {
        if r.offset.checked_add(r.len).is_none() {
            parts.push(Err(Exception::BadParameters));
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
                    parts.push(Err(Exception::BadParameters));
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
                    parts.push(Err(Exception::BadParameters));
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
impl PlcBackend for EpsnetBackend {
    fn describe(&self) -> String {
        format!("EPSNET/UDP {} (EPSADDR {})", self.config.plc, self.sa)
    }

    fn source_address(&self) -> Option<u8> {
        Some(self.sa)
    }

    fn max_read_block(&self, _area: plccoms_protocol::Area) -> u32 {
        MAX_READ
    }

    fn answer_timeout(&self) -> Duration {
        self.config.timeout
    }

    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters;
    }

    fn max_file_block(&self) -> u32 {
        MAX_FILE_BLOCK
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        // A fresh socket: nothing from an earlier session can be taken for
        // an answer.
        self.bind().await?;
        let mut answers = self
            .exchange(&[Request::Ident, Request::Status], 1)
            .await?
            .into_iter();
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

    async fn read(&mut self, reads: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let split = split_reads(reads);
        let answers = self.exchange(&split.requests, self.config.window).await?;
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
            return Ok(Err(Exception::BadParameters));
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
            return Ok(Err(Exception::BadParameters));
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
        if path.len() > MAX_PATH {
            return Ok(Err(Exception::BadParameters));
        }
        // Blocks larger than the limit go as several, strictly in order.
        let chunks: Vec<&[u8]> = if data.is_empty() {
            vec![data]
        } else {
            data.chunks(MAX_FILE_BLOCK as usize).collect()
        };
        let count = chunks.len();
        let mut at = offset;
        for (i, chunk) in chunks.into_iter().enumerate() {
            let answer = self
                .file_request(Request::FileWrite {
                    path: path.to_vec(),
                    offset: at,
                    last: last && i + 1 == count,
                    data: chunk.to_vec(),
                })
                .await?;
            match answer {
                Ok(Response::Done) => {}
                Ok(other) => return Err(unexpected(other)),
                Err(e) => return Ok(Err(e)),
            }
            at += chunk.len() as u64;
        }
        Ok(Ok(()))
    }

    async fn write_file_info(
        &mut self,
        path: &[u8],
        info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        if path.len() > MAX_PATH {
            return Ok(Err(Exception::BadParameters));
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
            return Ok(Err(Exception::BadParameters));
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
                    let empty = entries.is_empty();
                    all.extend(entries);
                    if !more {
                        return Ok(Ok(all));
                    }
                    if empty {
                        return Err(PlcError::Protocol(
                            "empty directory page announcing more".into(),
                        ));
                    }
                }
                Ok(other) => return Err(unexpected(other)),
                Err(e) => return Ok(Err(e)),
            }
        }
    }
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
    fn plan_keeps_answers_within_a_datagram() {
        let backend = EpsnetBackend::new(EpsnetConfig::new("127.0.0.1:1".parse().unwrap()));
        let requests: Vec<Request> = (0..10)
            .map(|i| Request::Read {
                area: Area::R,
                offset: i * 600,
                len: 600,
            })
            .collect();
        let plan = backend.plan(&requests).unwrap();
        assert_eq!(plan.len(), 5);
        for range in plan {
            let answer: usize = requests[range].iter().map(Request::max_answer_len).sum();
            assert!(plccoms_plc::epsnet::frame::packet_len(answer) <= MAX_PACKET);
        }
        let small: Vec<Request> = (0..50)
            .map(|i| Request::Read {
                area: Area::R,
                offset: i * 4,
                len: 4,
            })
            .collect();
        assert_eq!(backend.plan(&small).unwrap().len(), 1);
    }

    #[test]
    fn auto_address_in_range() {
        for _ in 0..300 {
            assert!((1..=126).contains(&auto_eps_addr()));
        }
    }
}
