//! One Modbus TCP connection and the transactions on it.
//!
//! - Each transaction gets a fresh transaction id (counted up, retries
//!   included). An answer is matched by id to the transaction any attempt of
//!   which carried it, and its unit and function must fit the request; a
//!   late answer (of an attempt already answered, or of an earlier batch)
//!   or a foreign one is dropped, never mismatched.
//! - Up to `window` transactions are in flight at once (MODBUS_INFLIGHT;
//!   1 = strictly one, what every device accepts).
//! - A transaction unanswered within the timeout is sent once more (not
//!   while the connection only probes the device, [`Connection::probing`]);
//!   then the exchange fails with [`PlcError::Timeout`] and the connection is
//!   given up (the backend opens a new one at its next `connect`).
//! - A stream that cannot be framed or is closed fails the exchange at once.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;
use tokio::io::AsyncWriteExt;
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpSocket, TcpStream};
use tokio::time::Instant;
use tokio_util::codec::FramedRead;

use plccoms_core::driver::PlcError;
use plccoms_core::metrics::BackendCounters;
use plccoms_plc::modbus::codec::{decode_response, encode_request, AduDecoder, FrameError, Header};
use plccoms_plc::modbus::frame::{Request, Response};
use plccoms_plc::modbus::ExceptionCode;

/// Retries of a transaction after its first attempt.
pub const RETRIES: u32 = 1;

/// What one transaction got: the data, or the device's exception.
pub type Outcome = Result<Response, ExceptionCode>;

pub struct Connection {
    device: SocketAddr,
    unit: u8,
    reader: FramedRead<OwnedReadHalf, AduDecoder>,
    writer: OwnedWriteHalf,
    next_id: u16,
    out: Vec<u8>,
    /// Retries of a transaction: [`RETRIES`], or none while probing.
    retries: u32,
}

/// One transaction of an exchange.
struct Slot {
    attempts: u32,
    sent: Instant,
    deadline: Instant,
    done: bool,
}

/// A TCP connection to `device` (from `local`, when given) within
/// `timeout`.
pub async fn connect_tcp(
    device: SocketAddr,
    local: Option<std::net::IpAddr>,
    timeout: Duration,
) -> Result<TcpStream, PlcError> {
    let connect = async {
        let socket = if device.is_ipv4() {
            TcpSocket::new_v4()?
        } else {
            TcpSocket::new_v6()?
        };
        if let Some(ip) = local {
            socket.bind(SocketAddr::new(ip, 0))?;
        }
        socket.connect(device).await
    };
    let stream: TcpStream = tokio::time::timeout(timeout, connect).await.map_err(|_| {
        PlcError::Timeout(format!("no TCP connection to {device} within {timeout:?}"))
    })??;
    // Requests are small and waited for: never hold one back.
    stream.set_nodelay(true)?;
    Ok(stream)
}

impl Connection {
    /// Connects to `device` (from `local`, when given) within `timeout`.
    pub async fn open(
        device: SocketAddr,
        local: Option<std::net::IpAddr>,
        unit: u8,
        timeout: Duration,
    ) -> Result<Connection, PlcError> {
        let stream = connect_tcp(device, local, timeout).await?;
        let (read, write) = stream.into_split();
        Ok(Connection {
            device,
            unit,
            reader: FramedRead::new(read, AduDecoder),
            writer: write,
            next_id: 0,
            out: Vec::with_capacity(512),
            retries: RETRIES,
        })
    }

    /// Whether transactions only probe the device (sent once, no retry:
    /// the link probes an absent device about every second).
    pub fn probing(&mut self, probing: bool) {
        self.retries = if probing { 0 } else { RETRIES };
    }

    async fn send(
        &mut self,
        request: &Request,
        slot: &mut Slot,
        ids: &mut HashMap<u16, usize>,
        index: usize,
        timeout: Duration,
        counters: &BackendCounters,
    ) -> Result<(), PlcError> {
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1);
        self.out.clear();
        encode_request(
            Header {
                transaction: id,
                unit: self.unit,
            },
            request,
            &mut self.out,
        );
        counters.requests.inc();
        if slot.attempts > 0 {
            counters.retries.inc();
        }
        slot.attempts += 1;
        slot.sent = Instant::now();
        slot.deadline = slot.sent + timeout;
        ids.insert(id, index);
        self.writer.write_all(&self.out).await?;
        Ok(())
    }

    /// Sends every request, at most `window` in flight, and returns the
    /// outcomes in request order.
    pub async fn exchange(
        &mut self,
        requests: &[Request],
        window: usize,
        timeout: Duration,
        counters: &Arc<BackendCounters>,
    ) -> Result<Vec<Outcome>, PlcError> {
        let now = Instant::now();
        let mut slots: Vec<Slot> = requests
            .iter()
            .map(|_| Slot {
                attempts: 0,
                sent: now,
                deadline: now,
                done: false,
            })
            .collect();
        let mut results: Vec<Option<Outcome>> = vec![None; requests.len()];
        let mut ids: HashMap<u16, usize> = HashMap::new();
        let mut in_flight: Vec<usize> = Vec::new();
        let mut next = 0;
        let mut last_problem: Option<String> = None;
        let window = window.max(1);
        loop {
            while in_flight.len() < window && next < requests.len() {
                self.send(
                    &requests[next],
                    &mut slots[next],
                    &mut ids,
                    next,
                    timeout,
                    counters,
                )
                .await?;
                in_flight.push(next);
                next += 1;
            }
            let Some(deadline) = in_flight.iter().map(|&i| slots[i].deadline).min() else {
                break;
            };
            match tokio::time::timeout_at(deadline, self.reader.next()).await {
                Err(_elapsed) => {
                    let now = Instant::now();
                    for i in in_flight.clone() {
                        if slots[i].deadline > now {
                            continue;
                        }
                        if slots[i].attempts > self.retries {
                            counters.timeouts.inc();
                            let mut text = format!(
                                "no answer from {} after {} attempts",
                                self.device, slots[i].attempts
                            );
                            if let Some(problem) = &last_problem {
                                text.push_str(&format!(" (last bad answer: {problem})"));
                            }
                            return Err(PlcError::Timeout(text));
                        }
                        self.send(&requests[i], &mut slots[i], &mut ids, i, timeout, counters)
                            .await?;
                    }
                }
                Ok(None) => {
                    return Err(PlcError::Io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        format!("{} closed the connection", self.device),
                    )))
                }
                Ok(Some(Err(FrameError::Io(e)))) => return Err(PlcError::Io(e)),
                Ok(Some(Err(e))) => {
                    counters.errors.inc();
                    return Err(PlcError::Protocol(format!("{}: {e}", self.device)));
                }
                Ok(Some(Ok(adu))) => {
                    let Some(&index) = ids.get(&adu.header.transaction) else {
                        // Foreign, or of an earlier batch: not ours to take.
                        counters.errors.inc();
                        continue;
                    };
                    if slots[index].done {
                        continue;
                    }
                    if adu.header.unit != self.unit {
                        counters.errors.inc();
                        last_problem = Some(format!(
                            "answer from unit {}, not {}",
                            adu.header.unit, self.unit
                        ));
                        continue;
                    }
                    match decode_response(&requests[index], &adu.pdu) {
                        Ok(outcome) => {
                            counters.round_trip.observe(slots[index].sent.elapsed());
                            results[index] = Some(outcome);
                            slots[index].done = true;
                            in_flight.retain(|&i| i != index);
                        }
                        Err(problem) => {
                            tracing::debug!(device = %self.device, "bad answer: {problem}");
                            counters.errors.inc();
                            last_problem = Some(problem.to_string());
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
