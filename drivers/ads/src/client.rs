//! One AMS/TCP connection and the ADS requests on it, one at a time.
//!
//! - Each request gets a fresh invoke id; an answer is matched by it (and
//!   its command), so a late answer to an earlier, timed-out request is
//!   dropped, never mismatched.
//! - A request unanswered within the timeout is sent once more (not while
//!   probing, [`Connection::probing`]); then it fails with
//!   [`PlcError::Timeout`] and the connection is given up.
//! - An AMS-level error in the answer's header (0x6 target port not found,
//!   0x7 target machine not found) is the link's failure: the PLC runtime
//!   cannot be reached behind the router.
//! - Device notifications that arrive between answers are kept, in order,
//!   for [`Connection::take_notifications`].

use std::net::SocketAddr;
use std::time::Duration;

use futures::{SinkExt, StreamExt};
use tokio::net::TcpStream;
use tokio::time::Instant;
use tokio_util::codec::Framed;

use plccoms_core::driver::PlcError;
use plccoms_core::metrics::BackendCounters;
use plccoms_plc::ads::command::{decode_notification, Request, Response, Stamp};
use plccoms_plc::ads::frame::{AmsCodec, AmsHeader, AmsPacket, CommandId, STATE_ADS};
use plccoms_plc::ads::{AdsError, AmsAddr, NetId};

/// Retries of a request after its first attempt.
const RETRIES: u32 = 1;
/// Notification stamps kept between two takes: a reader that stops taking
/// them loses the oldest, never grows without bound.
const MAX_PENDING: usize = 100_000;

/// What one request got: the answer, or the device's refusal.
pub type Outcome = Result<Response, AdsError>;

pub struct Connection {
    device: SocketAddr,
    framed: Framed<TcpStream, AmsCodec>,
    target: AmsAddr,
    source: AmsAddr,
    next_id: u32,
    retries: u32,
    timeout: Duration,
    notifications: std::collections::VecDeque<Stamp>,
    /// Stamps dropped because nobody took them.
    pub dropped: u64,
}

impl Connection {
    /// Connects to `device` within `timeout`. `source`: our Net ID, or
    /// `None` for the connection's local address and `.1.1`.
    pub async fn open(
        device: SocketAddr,
        target: AmsAddr,
        source: Option<NetId>,
        timeout: Duration,
    ) -> Result<Connection, PlcError> {
        let stream = tokio::time::timeout(timeout, TcpStream::connect(device))
            .await
            .map_err(|_| {
                PlcError::Timeout(format!("no TCP connection to {device} within {timeout:?}"))
            })??;
        let _ = stream.set_nodelay(true);
        let local = stream.local_addr()?;
        let net_id = source.unwrap_or_else(|| match local.ip() {
            std::net::IpAddr::V4(ip) => {
                let [a, b, c, d] = ip.octets();
                NetId([a, b, c, d, 1, 1])
            }
            std::net::IpAddr::V6(_) => NetId([127, 0, 0, 1, 1, 1]),
        });
        Ok(Connection {
            device,
            framed: Framed::new(stream, AmsCodec),
            target,
            // The local TCP port as our ADS port: unique per connection,
            // as the ADS router gives its clients.
            source: AmsAddr {
                net_id,
                port: local.port().max(32768),
            },
            next_id: 1,
            retries: RETRIES,
            timeout,
            notifications: Default::default(),
            dropped: 0,
        })
    }

    pub fn source(&self) -> AmsAddr {
        self.source
    }

    /// While probing, a request is sent once: the link makes an attempt
    /// about every second while the device is away.
    pub fn probing(&mut self, probing: bool) {
        self.retries = if probing { 0 } else { RETRIES };
    }

    /// Notification stamps received so far, oldest first.
    pub fn take_notifications(&mut self) -> Vec<Stamp> {
        self.notifications.drain(..).collect()
    }

    /// Waits until a notification has arrived (an answer nobody waits
    /// for is dropped); `Err` when the connection is gone. Cancel-safe.
    pub async fn until_notified(&mut self) -> Result<(), PlcError> {
        while self.notifications.is_empty() {
            let next = self.framed.next().await;
            self.take_packet(next)?;
        }
        Ok(())
    }

    fn take_packet(
        &mut self,
        next: Option<Result<AmsPacket, plccoms_plc::ads::frame::FrameError>>,
    ) -> Result<Option<AmsPacket>, PlcError> {
        let packet = match next {
            None => {
                return Err(PlcError::Io(std::io::Error::new(
                    std::io::ErrorKind::ConnectionReset,
                    format!("{} closed the connection", self.device),
                )))
            }
            Some(Err(e)) => return Err(PlcError::Protocol(format!("{}: {e}", self.device))),
            Some(Ok(packet)) => packet,
        };
        if packet.header.command == CommandId::NOTIFICATION && !packet.header.is_response() {
            let stamps = decode_notification(&packet.data)
                .map_err(|e| PlcError::Protocol(format!("{}: {e}", self.device)))?;
            for stamp in stamps {
                if self.notifications.len() == MAX_PENDING {
                    self.notifications.pop_front();
                    self.dropped += 1;
                }
                self.notifications.push_back(stamp);
            }
            return Ok(None);
        }
        Ok(Some(packet))
    }

    /// One request and its answer.
    pub async fn request(
        &mut self,
        request: &Request,
        counters: &BackendCounters,
    ) -> Result<Outcome, PlcError> {
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1);
        let command = request.command();
        let packet = AmsPacket {
            header: AmsHeader {
                target: self.target,
                source: self.source,
                command,
                state: STATE_ADS,
                error: 0,
                invoke_id: id,
            },
            data: request.encode(),
        };
        let started = Instant::now();
        for attempt in 0..=self.retries {
            counters.requests.inc();
            if attempt > 0 {
                counters.retries.inc();
            }
            self.framed
                .send(packet.clone())
                .await
                .map_err(|e| PlcError::Protocol(e.to_string()))?;
            let deadline = Instant::now() + self.timeout;
            loop {
                let next = match tokio::time::timeout_at(deadline, self.framed.next()).await {
                    Ok(next) => next,
                    Err(_) => break,
                };
                let Some(answer) = self.take_packet(next)? else {
                    continue;
                };
                let h = answer.header;
                if !h.is_response() || h.invoke_id != id || h.command != command {
                    continue;
                }
                counters.round_trip.observe(started.elapsed());
                if h.error != 0 {
                    counters.errors.inc();
                    let error = AdsError(h.error);
                    // The router cannot reach the runtime: the PLC is lost.
                    if matches!(error.0, 0x6 | 0x7 | 0x18 | 0x19 | 0x745 | 0x1861) {
                        let hint = error.hint().map(|h| format!("; {h}")).unwrap_or_default();
                        return Err(PlcError::Timeout(format!("{}: {error}{hint}", self.device)));
                    }
                    return Ok(Err(error));
                }
                return Response::decode(command, &answer.data)
                    .map_err(|e| PlcError::Protocol(format!("{}: {e}", self.device)));
            }
        }
        counters.timeouts.inc();
        Err(PlcError::Timeout(format!(
            "{} did not answer ADS command {} within {:?}",
            self.device, command.0, self.timeout
        )))
    }
}
