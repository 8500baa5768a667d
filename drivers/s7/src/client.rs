//! One ISO-on-TCP connection to an S7 CPU: TCP, the COTP connection
//! (CR/CC with the TSAPs), setup communication (the PDU size and parallel
//! jobs the CPU grants), then jobs pipelined up to that many in flight,
//! answers matched by their PDU reference.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use bytes::BytesMut;
use futures::{SinkExt, StreamExt};
use tokio::net::TcpStream;
use tokio::time::Instant;
use tokio_util::codec::Framed;

use plccoms_core::driver::PlcError;
use plccoms_core::metrics::BackendCounters;
use plccoms_plc::s7::codec::{CodecError, TpktCodec};
use plccoms_plc::s7::frame::{Answer, Job, Tpdu, Tsaps};

/// Resends of a job that got no answer within the timeout, before the
/// link is declared lost (none while probing).
const RETRIES: u32 = 1;

/// Parallel jobs asked for in setup communication; the CPU answers what it
/// allows (an S7-300 1, an S7-1500 3, Snap7 as asked).
const JOBS_ASKED: u16 = 8;

pub struct Connection {
    device: SocketAddr,
    framed: Framed<TcpStream, TpktCodec>,
    next_ref: u16,
    retries: u32,
    /// The PDU size and parallel jobs the CPU granted.
    pub pdu: u16,
    pub jobs: u16,
}

fn codec_error(device: SocketAddr, e: CodecError) -> PlcError {
    match e {
        CodecError::Io(e) => PlcError::Io(e),
        other => PlcError::Protocol(format!("{device}: {other}")),
    }
}

fn closed(device: SocketAddr) -> PlcError {
    PlcError::Io(std::io::Error::new(
        std::io::ErrorKind::UnexpectedEof,
        format!("{device} closed the connection"),
    ))
}

impl Connection {
    /// TCP, COTP and setup communication, each within `timeout`, sent once.
    pub async fn open(
        device: SocketAddr,
        tsaps: Tsaps,
        pdu: u16,
        timeout: Duration,
        counters: &Arc<BackendCounters>,
    ) -> Result<Connection, PlcError> {
        let stream = tokio::time::timeout(timeout, TcpStream::connect(device))
            .await
            .map_err(|_| {
                PlcError::Timeout(format!("no TCP connection to {device} within {timeout:?}"))
            })??;
        stream.set_nodelay(true)?;
        let mut framed = Framed::new(stream, TpktCodec);
        counters.requests.inc();
        framed
            .send(Tpdu::ConnectRequest(tsaps))
            .await
            .map_err(|e| codec_error(device, e))?;
        let confirm = tokio::time::timeout(timeout, framed.next())
            .await
            .map_err(|_| PlcError::Timeout(format!("{device}: no COTP connect confirm")))?;
        match confirm {
            Some(Ok(Tpdu::ConnectConfirm(_))) => {}
            Some(Ok(other)) => {
                return Err(PlcError::Protocol(format!(
                    "{device} refused the ISO connection (TSAP {:04X}/{:04X}: check S7_RACK/S7_SLOT or S7_TSAP): {other:?}",
                    tsaps.local, tsaps.remote
                )))
            }
            Some(Err(e)) => return Err(codec_error(device, e)),
            None => {
                return Err(PlcError::Protocol(format!(
                    "{device} closed the connection at the ISO connect (TSAP {:04X}/{:04X}: check S7_RACK/S7_SLOT or S7_TSAP)",
                    tsaps.local, tsaps.remote
                )))
            }
        }
        let mut connection = Connection {
            device,
            framed,
            next_ref: 1,
            retries: 0,
            pdu,
            jobs: 1,
        };
        let setup = Job::Setup {
            jobs: JOBS_ASKED,
            pdu,
        };
        let answer = connection
            .exchange(std::slice::from_ref(&setup), timeout, counters)
            .await?;
        match answer.first() {
            Some(Answer::Setup { jobs, pdu: granted }) => {
                if *granted < 64 {
                    return Err(PlcError::Protocol(format!(
                        "{device} granted a PDU of {granted} bytes"
                    )));
                }
                connection.pdu = (*granted).min(pdu.max(240));
                connection.jobs = (*jobs).clamp(1, JOBS_ASKED);
            }
            Some(Answer::Refused(code)) => {
                return Err(PlcError::Protocol(format!(
                    "{device} refused setup communication: {code}"
                )))
            }
            other => {
                return Err(PlcError::Protocol(format!(
                    "{device} answered setup communication with {other:?}"
                )))
            }
        }
        connection.retries = RETRIES;
        Ok(connection)
    }

    /// A probe's connection sends each job once.
    pub fn probing(&mut self, probing: bool) {
        self.retries = if probing { 0 } else { RETRIES };
    }

    /// Runs `jobs`, up to the granted number in flight; answers in job
    /// order. A job unanswered after its retries, a closed connection or
    /// a frame that is not S7 fails the whole exchange.
    pub async fn exchange(
        &mut self,
        jobs: &[Job],
        timeout: Duration,
        counters: &Arc<BackendCounters>,
    ) -> Result<Vec<Answer>, PlcError> {
        let window = usize::from(self.jobs.max(1));
        let mut answers: Vec<Option<Answer>> = vec![None; jobs.len()];
        let mut refs: HashMap<u16, usize> = HashMap::new();
        let mut sent: Vec<(Instant, u32)> = vec![(Instant::now(), 0); jobs.len()];
        let mut in_flight: Vec<usize> = Vec::new();
        let mut next = 0;
        loop {
            while in_flight.len() < window && next < jobs.len() {
                self.send(&jobs[next], next, &mut refs, &mut sent, counters)
                    .await?;
                in_flight.push(next);
                next += 1;
            }
            let Some(deadline) = in_flight.iter().map(|&i| sent[i].0 + timeout).min() else {
                break;
            };
            match tokio::time::timeout_at(deadline, self.framed.next()).await {
                Err(_elapsed) => {
                    let now = Instant::now();
                    for i in in_flight.clone() {
                        if sent[i].0 + timeout > now {
                            continue;
                        }
                        if sent[i].1 > self.retries {
                            counters.timeouts.inc();
                            return Err(PlcError::Timeout(format!(
                                "no answer from {} after {} attempts",
                                self.device, sent[i].1
                            )));
                        }
                        self.send(&jobs[i], i, &mut refs, &mut sent, counters)
                            .await?;
                    }
                }
                Ok(None) => return Err(closed(self.device)),
                Ok(Some(Err(e))) => {
                    counters.errors.inc();
                    return Err(codec_error(self.device, e));
                }
                Ok(Some(Ok(Tpdu::Data(pdu)))) => {
                    let (pdu_ref, answer) = Answer::parse(&pdu).map_err(|e| {
                        counters.errors.inc();
                        PlcError::Protocol(format!("{}: {e}", self.device))
                    })?;
                    let Some(index) = refs.remove(&pdu_ref) else {
                        // A late answer to a job resent: already done.
                        continue;
                    };
                    if answers[index].is_some() {
                        continue;
                    }
                    counters.round_trip.observe(sent[index].0.elapsed());
                    answers[index] = Some(answer);
                    in_flight.retain(|&i| i != index);
                }
                Ok(Some(Ok(other))) => {
                    counters.errors.inc();
                    return Err(PlcError::Protocol(format!(
                        "{}: unexpected COTP TPDU {other:?}",
                        self.device
                    )));
                }
            }
        }
        answers
            .into_iter()
            .map(|a| a.ok_or_else(|| PlcError::Protocol("job left unanswered".into())))
            .collect()
    }

    async fn send(
        &mut self,
        job: &Job,
        index: usize,
        refs: &mut HashMap<u16, usize>,
        sent: &mut [(Instant, u32)],
        counters: &BackendCounters,
    ) -> Result<(), PlcError> {
        let pdu_ref = self.next_ref;
        self.next_ref = self.next_ref.checked_add(1).unwrap_or(1);
        let mut pdu = BytesMut::new();
        job.encode(pdu_ref, &mut pdu);
        counters.requests.inc();
        if sent[index].1 > 0 {
            counters.retries.inc();
        }
        sent[index] = (Instant::now(), sent[index].1 + 1);
        refs.insert(pdu_ref, index);
        self.framed
            .send(Tpdu::Data(pdu.freeze()))
            .await
            .map_err(|e| codec_error(self.device, e))
    }
}
