//! A UDP relay between the server and the PLC (plcsim) that watches the
//! EPSNET traffic: it counts datagrams and read requests, groups them into
//! poll bursts, and decodes the read answers to learn which animated
//! variables changed in which burst and when that burst's reads completed.
//!
//! The burst's completion time is taken when the relay forwards its last
//! answer datagram to the server, i.e. a few microseconds before the server's
//! poll read completes: a DIFF's latency measured from it is the latency
//! "after the poll read completes", slightly overstated, never understated.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use plccoms_plc::epsnet::codec::decode_packet;
use plccoms_plc::epsnet::frame::Frame;
use plccoms_plc::epsnet::service::{decode_answer, Request, Response};
use plccoms_protocol::Area;
use tokio::net::UdpSocket;

/// Silence that separates two poll bursts.
pub const BURST_GAP: Duration = Duration::from_millis(20);
/// Recent bursts kept (a ring).
pub const BURSTS: usize = 4096;
/// Recent values kept per animated variable (a ring indexed by value).
pub const VALUE_RING: usize = 1024;

/// A variable whose value the relay follows.
#[derive(Debug, Clone)]
pub struct Watched {
    pub area: Area,
    pub offset: u32,
    pub size: u32,
}

#[derive(Debug, Clone, Copy, Default)]
pub struct Burst {
    pub start_ns: u64,
    pub end_ns: u64,
    pub datagrams: u32,
    pub reads: u32,
    pub read_bytes: u64,
    /// Watched variables that changed value in this burst.
    pub changes: u32,
}

/// Counters and bursts, read by the scenarios.
#[derive(Default)]
pub struct Traffic {
    pub request_datagrams: u64,
    pub answer_datagrams: u64,
    pub read_requests: u64,
    pub write_requests: u64,
    pub bursts: Vec<Burst>,
}

pub struct Observer {
    pub epoch: Instant,
    pub traffic: Mutex<Traffic>,
    /// Per watched variable, VALUE_RING slots of `value << 32 | burst id`.
    values: Vec<AtomicU64>,
    /// Per burst id % BURSTS: end time (ns since epoch) of its last answer.
    burst_end: Vec<AtomicU64>,
    burst_start: Vec<AtomicU64>,
    watched: Vec<Watched>,
    pub stop: AtomicBool,
}

impl Observer {
    pub fn new(epoch: Instant, watched: Vec<Watched>) -> Arc<Observer> {
        Arc::new(Observer {
            epoch,
            traffic: Mutex::new(Traffic::default()),
            values: (0..watched.len() * VALUE_RING)
                .map(|_| AtomicU64::new(u64::MAX))
                .collect(),
            burst_end: (0..BURSTS).map(|_| AtomicU64::new(0)).collect(),
            burst_start: (0..BURSTS).map(|_| AtomicU64::new(0)).collect(),
            watched,
            stop: AtomicBool::new(false),
        })
    }

    /// The burst in which watched variable `var` first showed `value`:
    /// (burst id, burst start ns, burst end ns).
    pub fn lookup(&self, var: usize, value: u64) -> Option<(u32, u64, u64)> {
        let slot =
            self.values[var * VALUE_RING + (value as usize % VALUE_RING)].load(Ordering::Acquire);
        if slot == u64::MAX || slot >> 32 != value & 0xFFFF_FFFF {
            return None;
        }
        let id = slot as u32;
        let i = id as usize % BURSTS;
        Some((
            id,
            self.burst_start[i].load(Ordering::Acquire),
            self.burst_end[i].load(Ordering::Acquire),
        ))
    }

    pub fn snapshot(&self) -> (u64, u64, u64, Vec<Burst>) {
        let t = self.traffic.lock().unwrap();
        (
            t.request_datagrams,
            t.read_requests,
            t.answer_datagrams,
            t.bursts.clone(),
        )
    }
}

/// Relay state owned by the relay task.
struct Relay {
    obs: Arc<Observer>,
    pending: HashMap<u16, Vec<Request>>,
    /// Shadow of the PLC areas, filled from read answers.
    shadow: [Vec<u8>; 4],
    last_value: Vec<Option<u64>>,
    /// Watched variables sorted by (area, end offset).
    order: Vec<usize>,
    burst: u32,
    last_activity: Option<Instant>,
}

impl Relay {
    fn on_request(&mut self, bytes: &[u8], now: Instant) {
        let Ok(packet) = decode_packet(bytes) else {
            return;
        };
        let new_burst = self
            .last_activity
            .is_none_or(|last| now.duration_since(last) > BURST_GAP);
        self.last_activity = Some(now);
        let now_ns = now_ns_at(self.obs.epoch, now);
        let mut guard = self.obs.traffic.lock().unwrap();
        let traffic = &mut *guard;
        traffic.request_datagrams += 1;
        if new_burst || traffic.bursts.is_empty() {
            self.burst = traffic.bursts.len() as u32;
            traffic.bursts.push(Burst {
                start_ns: now_ns,
                end_ns: now_ns,
                ..Burst::default()
            });
            let i = self.burst as usize % BURSTS;
            self.obs.burst_start[i].store(now_ns, Ordering::Release);
            self.obs.burst_end[i].store(now_ns, Ordering::Release);
        }
        let burst = traffic.bursts.last_mut().expect("pushed above");
        burst.datagrams += 1;
        let mut requests = Vec::new();
        for frame in &packet.frames {
            let Frame::Data(f) = frame else { continue };
            let Ok(request) = Request::decode(f.fc, &f.data) else {
                continue;
            };
            match &request {
                Request::Read { len, .. } => {
                    burst.reads += 1;
                    burst.read_bytes += u64::from(*len);
                    traffic.read_requests += 1;
                }
                Request::Write { .. } | Request::WriteBits { .. } => traffic.write_requests += 1,
                _ => {}
            }
            requests.push(request);
        }
        drop(guard);
        if self.pending.len() > 4096 {
            self.pending.clear();
        }
        self.pending.insert(packet.mesi, requests);
    }

    /// Called before the answer is forwarded.
    fn on_answer(&mut self, bytes: &[u8], now: Instant) {
        self.last_activity = Some(now);
        let now_ns = now_ns_at(self.obs.epoch, now);
        let Ok(packet) = decode_packet(bytes) else {
            return;
        };
        let requests = self.pending.remove(&packet.mesi).unwrap_or_default();
        let mut changes = 0u32;
        for (request, frame) in requests.iter().zip(&packet.frames) {
            let Request::Read { area, offset, .. } = request else {
                continue;
            };
            let Ok(Ok(Response::Data(data))) = decode_answer(request, frame) else {
                continue;
            };
            changes += self.apply(*area, *offset, &data);
        }
        let mut traffic = self.obs.traffic.lock().unwrap();
        traffic.answer_datagrams += 1;
        if let Some(burst) = traffic.bursts.last_mut() {
            burst.end_ns = now_ns;
            burst.changes += changes;
        }
        drop(traffic);
        self.obs.burst_end[self.burst as usize % BURSTS].store(now_ns, Ordering::Release);
    }

    /// Copies read data into the shadow and records the watched variables
    /// whose last byte lies in it (blocks arrive in ascending order, so a
    /// variable split over two blocks is complete with the second).
    fn apply(&mut self, area: Area, offset: u32, data: &[u8]) -> u32 {
        let shadow = &mut self.shadow[area.index()];
        let end = offset as usize + data.len();
        if shadow.len() < end {
            shadow.resize(end, 0);
        }
        shadow[offset as usize..end].copy_from_slice(data);
        let watched = &self.obs.watched;
        let first = self.order.partition_point(|&i| {
            let w = &watched[i];
            (w.area, w.offset + w.size) <= (area, offset)
        });
        let mut changes = 0;
        for &i in &self.order[first..] {
            let w = &watched[i];
            if w.area != area || (w.offset + w.size) as usize > end {
                break;
            }
            let mut raw = [0u8; 8];
            let size = w.size.min(8) as usize;
            raw[..size].copy_from_slice(&shadow[w.offset as usize..w.offset as usize + size]);
            let value = u64::from_le_bytes(raw);
            if self.last_value[i] != Some(value) {
                self.last_value[i] = Some(value);
                let slot = (value & 0xFFFF_FFFF) << 32 | u64::from(self.burst);
                self.obs.values[i * VALUE_RING + (value as usize % VALUE_RING)]
                    .store(slot, Ordering::Release);
                changes += 1;
            }
        }
        changes
    }
}

fn now_ns_at(epoch: Instant, at: Instant) -> u64 {
    at.duration_since(epoch).as_nanos() as u64
}

/// Starts relaying `listen` (where the server sends) to `upstream` (the PLC).
pub async fn spawn(
    listen: SocketAddr,
    upstream: SocketAddr,
    obs: Arc<Observer>,
) -> std::io::Result<tokio::task::JoinHandle<()>> {
    let front = UdpSocket::bind(listen).await?;
    let back = UdpSocket::bind("127.0.0.1:0").await?;
    back.connect(upstream).await?;
    let mut order: Vec<usize> = (0..obs.watched.len()).collect();
    order.sort_by_key(|&i| {
        let w = &obs.watched[i];
        (w.area, w.offset + w.size)
    });
    let mut relay = Relay {
        pending: HashMap::new(),
        shadow: Default::default(),
        last_value: vec![None; obs.watched.len()],
        order,
        burst: 0,
        last_activity: None,
        obs: obs.clone(),
    };
    Ok(tokio::spawn(async move {
        let mut client: Option<SocketAddr> = None;
        let mut a = vec![0u8; 65536];
        let mut b = vec![0u8; 65536];
        while !obs.stop.load(Ordering::Relaxed) {
            tokio::select! {
                got = front.recv_from(&mut a) => {
                    let Ok((n, from)) = got else { continue };
                    relay.on_request(&a[..n], Instant::now());
                    client = Some(from);
                    let _ = back.send(&a[..n]).await;
                }
                got = back.recv(&mut b) => {
                    let Ok(n) = got else { continue };
                    relay.on_answer(&b[..n], Instant::now());
                    if let Some(to) = client {
                        let _ = front.send_to(&b[..n], to).await;
                    }
                }
                _ = tokio::time::sleep(Duration::from_millis(200)) => {}
            }
        }
    }))
}

/// Parses `LISTEN,UPSTREAM`.
pub fn parse_spec(spec: &str) -> Result<(SocketAddr, SocketAddr), String> {
    let (a, b) = spec
        .split_once(',')
        .ok_or("expected LISTEN_ADDR,PLC_ADDR")?;
    let a: SocketAddr = a.trim().parse().map_err(|e| format!("{a}: {e}"))?;
    let b: SocketAddr = b.trim().parse().map_err(|e| format!("{b}: {e}"))?;
    if !a.ip().is_loopback() || !b.ip().is_loopback() {
        return Err("the relay works on 127.0.0.1 only".into());
    }
    Ok((a, b))
}
