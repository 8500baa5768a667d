//! EPSNET over UDP: requests packed into datagrams, matched by MESI.
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
//! - a datagram unanswered within its attempt's wait is sent again, up to
//!   the retries, then the batch fails (see [`Exchange`]).
//!
//! [`frame::MAX_PACKET`]: plccoms_plc::epsnet::frame::MAX_PACKET

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::ops::Range;
use std::time::Duration;

use async_trait::async_trait;
use tokio::net::UdpSocket;
use tokio::time::Instant;

use super::{EpsnetClient, Exchange, Timing, Transport};
use plccoms_core::driver::{Answer, PlcError};
use plccoms_plc::epsnet::codec;
use plccoms_plc::epsnet::frame::{Packet, MAX_DPLEN, MAX_PACKET};
use plccoms_plc::epsnet::service::{Request, Response};

/// Settings of one EPSNET/UDP link (the PLC section's INI keys).
#[derive(Debug, Clone)]
pub struct EpsnetConfig {
    /// The PLC (IPADDR, EPSPORT; the PLC listens on 61682).
    pub plc: SocketAddr,
    /// Local address to bind (IPADDR_LOCAL); the port is chosen by the OS.
    pub local_ip: IpAddr,
    /// See [`Timing::eps_addr`].
    pub eps_addr: Option<u8>,
    /// EPSTOUT: answer timeout of the first attempt.
    pub timeout: Duration,
    /// EPSTOUT_STEP: added to the timeout on each retry.
    pub timeout_step: Duration,
    /// See [`Timing::retries`].
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

    fn timing(&self) -> Timing {
        Timing {
            eps_addr: self.eps_addr,
            timeout: self.timeout,
            timeout_step: self.timeout_step,
            retries: self.retries,
        }
    }
}

/// The UDP transport.
pub struct Udp {
    config: EpsnetConfig,
    socket: Option<UdpSocket>,
    next_mesi: u16,
    buf: Box<[u8]>,
}

/// EPSNET over UDP.
pub type EpsnetBackend = EpsnetClient<Udp>;

impl EpsnetClient<Udp> {
    pub fn new(config: EpsnetConfig) -> Self {
        let timing = config.timing();
        EpsnetClient::with_transport(
            Udp {
                config,
                socket: None,
                next_mesi: 0,
                // Larger than any valid datagram, so oversize ones are seen
                // whole enough to be rejected rather than silently cut to
                // valid length.
                buf: vec![0; MAX_PACKET + 64].into_boxed_slice(),
            },
            timing,
        )
    }

    pub fn config(&self) -> &EpsnetConfig {
        &self.transport().config
    }

    /// The local UDP address, once bound.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.transport()
            .socket
            .as_ref()
            .and_then(|s| s.local_addr().ok())
    }
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

impl Udp {
    async fn bind(&mut self) -> Result<(), PlcError> {
        let socket = UdpSocket::bind(SocketAddr::new(self.config.local_ip, 0)).await?;
        self.socket = Some(socket);
        Ok(())
    }

    /// Packs requests into datagrams: consecutive requests while both the
    /// request and the largest possible answer fit.
    fn plan(&self, x: &Exchange<'_>, requests: &[Request]) -> Result<Vec<Range<usize>>, PlcError> {
        let mut ranges = Vec::new();
        let mut start = 0;
        let (mut req_len, mut ans_len) = (0, 0);
        for (i, request) in requests.iter().enumerate() {
            let r = x.request_frame(request).encoded_len();
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
        x: &Exchange<'_>,
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
                .map(|r| x.request_frame(r))
                .collect(),
        };
        let bytes = codec::encode_packet(&packet)
            .map_err(|e| PlcError::Protocol(format!("cannot encode request: {e}")))?;
        x.sent(slot.attempts);
        slot.deadline = Instant::now() + x.wait(slot.attempts);
        slot.attempts += 1;
        slot.sent = Instant::now();
        mesis.insert(mesi, index);
        let socket = self.socket.as_ref().ok_or(PlcError::NotConfigured)?;
        match socket.send_to(&bytes, self.config.plc).await {
            Ok(_) => Ok(()),
            // A transient send failure is just a lost datagram: retried.
            Err(e) if is_transient(&e) => Ok(()),
            Err(e) => Err(PlcError::Io(e)),
        }
    }

    fn match_answers(
        x: &Exchange<'_>,
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
            .map(|(request, frame)| x.match_answer(request, frame))
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
}

#[async_trait]
impl Transport for Udp {
    fn describe(&self) -> String {
        format!("EPSNET/UDP {}", self.config.plc)
    }

    async fn open(&mut self) -> Result<(), PlcError> {
        self.bind().await
    }

    fn is_open(&self) -> bool {
        self.socket.is_some()
    }

    fn read_window(&self) -> usize {
        self.config.window
    }

    async fn exchange(
        &mut self,
        x: &Exchange<'_>,
        requests: &[Request],
        window: usize,
    ) -> Result<Vec<Answer<Response>>, PlcError> {
        self.drain();
        let plc = self.config.plc.to_string();
        let mut slots: Vec<Slot> = self
            .plan(x, requests)?
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
                self.send(x, requests, &mut slots[next], &mut mesis, next)
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
                        if !x.may_try(slots[i].attempts) {
                            let what = format!(
                                "no answer from {plc} after {} attempts",
                                slots[i].attempts
                            );
                            return Err(x.timed_out(what, last_problem.as_deref()));
                        }
                        self.send(x, requests, &mut slots[i], &mut mesis, i).await?;
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
                            let problem = e.to_string();
                            x.bad_answer(&plc, &problem);
                            last_problem = Some(problem);
                            continue;
                        }
                    };
                    let Some(&index) = mesis.get(&packet.mesi) else {
                        continue;
                    };
                    if slots[index].done {
                        continue;
                    }
                    match Self::match_answers(x, &requests[slots[index].range.clone()], &packet) {
                        Ok(answers) => {
                            for (slot_result, answer) in
                                results[slots[index].range.clone()].iter_mut().zip(answers)
                            {
                                *slot_result = Some(answer);
                            }
                            slots[index].done = true;
                            x.answered(slots[index].sent);
                            in_flight.retain(|&i| i != index);
                        }
                        Err(problem) => {
                            x.bad_answer(&plc, &problem);
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
}

fn is_transient(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    matches!(
        e.kind(),
        ConnectionRefused | ConnectionReset | WouldBlock | Interrupted
    )
}

#[cfg(test)]
mod tests {
    use plccoms_protocol::Area;

    use super::*;
    use plccoms_core::metrics::BackendCounters;

    #[test]
    fn plan_keeps_answers_within_a_datagram() {
        let udp = EpsnetBackend::new(EpsnetConfig::new("127.0.0.1:1".parse().unwrap()));
        let timing = udp.config().timing();
        let counters = BackendCounters::default();
        let x = Exchange {
            sa: 5,
            timing: &timing,
            counters: &counters,
        };
        let udp = udp.transport();
        let requests: Vec<Request> = (0..10)
            .map(|i| Request::Read {
                area: Area::R,
                offset: i * 600,
                len: 600,
            })
            .collect();
        let plan = udp.plan(&x, &requests).unwrap();
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
        assert_eq!(udp.plan(&x, &small).unwrap().len(), 1);
    }
}
