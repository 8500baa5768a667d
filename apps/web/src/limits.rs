//! What one party may hold of the web server: connections and live streams,
//! in all and per address, and how long a connection may sit idle.
//!
//! The web side shares the process's descriptors with the line protocol's
//! listeners; its connections are capped at a quarter of the descriptor
//! limit (and at [`MAX_CONNECTIONS`]), so a flood of half-sent requests
//! leaves the sections' clients their descriptors. A connection over a cap
//! is closed as soon as it is accepted.

use std::collections::HashMap;
use std::future::Ready;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tracing::warn;

use plccoms_core::ratelimit::{more, RateLimited};

/// Connections open at once, at most (fewer under a small descriptor limit).
pub const MAX_CONNECTIONS: usize = 256;
/// Connections from one address (an IPv6 /64) at once: a browser opens 6.
pub const MAX_CONNECTIONS_PER_ADDRESS: usize = 32;
/// Live-value streams open at once, and from one address: each is a
/// subscription the link polls for.
pub const MAX_LIVE_STREAMS: usize = 64;
pub const MAX_LIVE_STREAMS_PER_ADDRESS: usize = 8;
/// Streams at once on one HTTP/2 connection.
pub const MAX_HTTP2_STREAMS: u32 = 16;
/// Time to send a request's headers, and for the first request on a new
/// connection (the TLS handshake has its own 10 s).
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// A connection that moves no byte either way this long is closed (live
/// streams send a keep-alive every 15 s).
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(60);

/// Counts of something held, in all and per address.
pub struct Limiter {
    what: &'static str,
    per_address: usize,
    held: Mutex<Held>,
}

#[derive(Default)]
struct Held {
    total: usize,
    by_address: HashMap<IpAddr, usize>,
}

/// Why a [`Limiter`] refused.
#[derive(Debug)]
pub enum Refused {
    Total(usize),
    Address(usize),
}

impl Refused {
    pub fn describe(&self, what: &str) -> String {
        match self {
            Refused::Total(n) => format!("too many {what} open ({n}, the most the server keeps)"),
            Refused::Address(n) => {
                format!("too many {what} open from this address ({n}, the most one address keeps)")
            }
        }
    }
}

/// One held place; given back when dropped.
pub struct Permit {
    limiter: Arc<Limiter>,
    address: IpAddr,
}

impl Limiter {
    pub fn new(what: &'static str, per_address: usize) -> Arc<Limiter> {
        Arc::new(Limiter {
            what,
            per_address,
            held: Mutex::new(Held::default()),
        })
    }

    /// A place for `peer`, if fewer than `total` are held in all and fewer
    /// than the per-address cap by its address.
    pub fn acquire(self: &Arc<Self>, peer: IpAddr, total: usize) -> Result<Permit, Refused> {
        let address = address_key(peer);
        let mut held = self.held.lock().unwrap_or_else(|p| p.into_inner());
        if held.total >= total {
            return Err(Refused::Total(total));
        }
        let mine = held.by_address.entry(address).or_insert(0);
        if *mine >= self.per_address {
            return Err(Refused::Address(self.per_address));
        }
        *mine += 1;
        held.total += 1;
        Ok(Permit {
            limiter: self.clone(),
            address,
        })
    }

    pub fn what(&self) -> &'static str {
        self.what
    }
}

impl Drop for Permit {
    fn drop(&mut self) {
        let mut held = self.limiter.held.lock().unwrap_or_else(|p| p.into_inner());
        held.total -= 1;
        if let Some(mine) = held.by_address.get_mut(&self.address) {
            *mine -= 1;
            if *mine == 0 {
                held.by_address.remove(&self.address);
            }
        }
    }
}

/// The address as counted: IPv4 (mapped or not) whole, IPv6 by its /64,
/// what one subscriber usually has.
fn address_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(v4) => IpAddr::V4(v4),
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let bits = u128::from(v6) & !((1u128 << 64) - 1);
                IpAddr::V6(bits.into())
            }
        },
    }
}

/// The connections the web side may hold now: a quarter of the process's
/// descriptor limit (read at each connection: it may be changed while the
/// server runs), at most [`MAX_CONNECTIONS`].
pub fn connection_budget() -> usize {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes the struct it is given.
    let soft = if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } == 0 {
        usize::try_from(limit.rlim_cur).unwrap_or(usize::MAX)
    } else {
        1024
    };
    (soft / 4).clamp(1, MAX_CONNECTIONS)
}

/// Accepts a connection only within the caps, and watches it for idleness.
#[derive(Clone)]
pub struct GuardedAcceptor {
    connections: Arc<Limiter>,
    refusals: Arc<RateLimited>,
}

impl GuardedAcceptor {
    pub fn new() -> GuardedAcceptor {
        GuardedAcceptor {
            connections: Limiter::new("connections", MAX_CONNECTIONS_PER_ADDRESS),
            refusals: Arc::new(RateLimited::new(Duration::from_secs(1))),
        }
    }
}

impl<S> axum_server::accept::Accept<TcpStream, S> for GuardedAcceptor {
    type Stream = Watched<TcpStream>;
    type Service = S;
    type Future = Ready<io::Result<(Self::Stream, S)>>;

    fn accept(&self, stream: TcpStream, service: S) -> Self::Future {
        let peer = stream
            .peer_addr()
            .unwrap_or_else(|_| SocketAddr::from(([0, 0, 0, 0], 0)));
        let result = match self.connections.acquire(peer.ip(), connection_budget()) {
            Ok(permit) => Ok((Watched::new(stream, permit), service)),
            Err(refused) => {
                // Closed without an answer: an answer would need the very
                // time and memory the cap keeps.
                let why = refused.describe(self.connections.what());
                if let Some(quiet) = self.refusals.admit() {
                    warn!(client = %peer, "web page: connection refused: {why}{}", more(quiet));
                }
                Err(io::Error::other(why))
            }
        };
        std::future::ready(result)
    }
}

/// A connection that ends in an error once it has moved no byte for
/// [`IDLE_TIMEOUT`], and holds its place under the caps while it lives.
pub struct Watched<S> {
    inner: S,
    last_progress: Instant,
    deadline: Pin<Box<tokio::time::Sleep>>,
    _permit: Permit,
}

impl<S> Watched<S> {
    fn new(inner: S, permit: Permit) -> Watched<S> {
        Watched {
            inner,
            last_progress: Instant::now(),
            deadline: Box::pin(tokio::time::sleep(IDLE_TIMEOUT)),
            _permit: permit,
        }
    }

    /// Called when the inner stream is not ready: the error once idle too
    /// long (the timer is moved on lazily, not at every byte).
    fn check_idle(&mut self, cx: &mut Context<'_>) -> Poll<io::Error> {
        loop {
            if self.deadline.as_mut().poll(cx).is_pending() {
                return Poll::Pending;
            }
            let due = self.last_progress + IDLE_TIMEOUT;
            if Instant::now() >= due {
                return Poll::Ready(io::Error::new(
                    io::ErrorKind::TimedOut,
                    "web connection idle too long",
                ));
            }
            self.deadline.as_mut().reset(due.into());
        }
    }

    fn progressed<T>(
        &mut self,
        result: Poll<io::Result<T>>,
        cx: &mut Context<'_>,
    ) -> Poll<io::Result<T>> {
        match result {
            Poll::Ready(result) => {
                self.last_progress = Instant::now();
                Poll::Ready(result)
            }
            Poll::Pending => self.check_idle(cx).map(Err),
        }
    }
}

use std::future::Future as _;

impl<S: AsyncRead + Unpin> AsyncRead for Watched<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let result = Pin::new(&mut this.inner).poll_read(cx, buf);
        this.progressed(result, cx)
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Watched<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        let result = Pin::new(&mut this.inner).poll_write(cx, buf);
        this.progressed(result, cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        let result = Pin::new(&mut this.inner).poll_write_vectored(cx, bufs);
        this.progressed(result, cx)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let result = Pin::new(&mut this.inner).poll_flush(cx);
        this.progressed(result, cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn places_are_capped_in_all_and_per_address_and_given_back() {
        let limiter = Limiter::new("things", 2);
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "2001:db8::1".parse().unwrap();
        let b_same_64: IpAddr = "2001:db8::2".parse().unwrap();
        let first = limiter.acquire(a, 3).unwrap();
        let _second = limiter.acquire(a, 3).unwrap();
        assert!(matches!(limiter.acquire(a, 3), Err(Refused::Address(2))));
        let _third = limiter.acquire(b, 3).unwrap();
        assert!(matches!(
            limiter.acquire(b_same_64, 3),
            Err(Refused::Total(3))
        ));
        drop(first);
        assert!(limiter.acquire(b_same_64, 3).is_ok());
    }
}
