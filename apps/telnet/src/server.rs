//! Listeners: one TCP port per PLC section, admitting clients up to
//! NET_CONNECT_MAX and running a session for each.
//!
//! A client whose address is not in the section's ALLOW list is closed right
//! after accept, without any data, and logged (rate-limited). The others get
//! TCP keepalive; one over NET_CONNECT_MAX gets ERROR:11 and is closed.

use std::io;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use socket2::{SockRef, TcpKeepalive};
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::task::JoinHandle;
use tokio_util::task::TaskTracker;
use tracing::{info, warn};

use plccoms_protocol::answer::{write_error, ErrorCode};

use plccoms_core::ratelimit::{more, RateLimited};
use plccoms_core::section::Section;

use crate::session::Session;

/// A section's port: accepting clients and serving a session for each.
pub struct Listener {
    pub local_addr: SocketAddr,
    section: Arc<Section>,
    accept: JoinHandle<()>,
    sessions: TaskTracker,
}

impl Listener {
    /// Stops accepting and tells every session to close once it has
    /// answered what it received; the link keeps serving their reads.
    pub fn stop_accepting(&self) {
        self.accept.abort();
        self.section.shutdown().cancel();
        self.sessions.close();
    }

    /// Waits until every session has answered what it received and closed,
    /// at most `grace`.
    pub async fn wait_sessions(&self, grace: Duration) {
        if tokio::time::timeout(grace, self.sessions.wait())
            .await
            .is_err()
        {
            warn!(section = %self.section.name(), "{} session(s) still busy at shutdown", self.sessions.len());
        }
    }
}

impl Drop for Listener {
    fn drop(&mut self) {
        self.accept.abort();
    }
}

/// Serves `section`'s clients on `listener` (from [`bind`]), at once,
/// whatever the PLC does.
pub fn serve(listener: TcpListener, section: Arc<Section>) -> io::Result<Listener> {
    let local_addr = listener.local_addr()?;
    let sessions = TaskTracker::new();
    let accept = tokio::spawn(accept_loop(listener, section.clone(), sessions.clone()));
    info!(section = %section.name(), listen = %local_addr, "listening");
    Ok(Listener {
        local_addr,
        section,
        accept,
        sessions,
    })
}

/// The port of a section, bound before its link starts so that a port in
/// use starts nothing. SO_REUSEADDR: a restarted server can bind at once
/// while old connections linger in TIME_WAIT.
pub fn bind(bind: SocketAddr) -> io::Result<TcpListener> {
    let socket = if bind.is_ipv4() {
        TcpSocket::new_v4()?
    } else {
        TcpSocket::new_v6()?
    };
    socket.set_reuseaddr(true)?;
    socket.bind(bind)?;
    socket.listen(1024)
}

/// TCP keepalive on client connections: idle clients are kept (PLCComS
/// never drops them), and a peer that vanished (powered off, cable cut) is
/// found within about idle + interval * probes = 110 s, freeing its place
/// under NET_CONNECT_MAX.
pub const KEEPALIVE_IDLE: Duration = Duration::from_secs(60);
pub const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(10);
pub const KEEPALIVE_PROBES: u32 = 5;

fn set_keepalive(stream: &TcpStream) -> io::Result<()> {
    let keepalive = TcpKeepalive::new()
        .with_time(KEEPALIVE_IDLE)
        .with_interval(KEEPALIVE_INTERVAL)
        .with_retries(KEEPALIVE_PROBES);
    SockRef::from(stream).set_tcp_keepalive(&keepalive)
}

/// Refusals a client can cause at will are logged at most once a second per
/// section and kind, with a count of the ones in between.
struct Refusals {
    allow: RateLimited,
    full: RateLimited,
    accept: RateLimited,
}

impl Refusals {
    fn new() -> Refusals {
        Refusals {
            allow: RateLimited::new(Duration::from_secs(1)),
            full: RateLimited::new(Duration::from_secs(1)),
            accept: RateLimited::new(Duration::from_secs(1)),
        }
    }
}

async fn accept_loop(listener: TcpListener, section: Arc<Section>, sessions: TaskTracker) {
    let refusals = Refusals::new();
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(err) => {
                // Out of descriptors and the like: wait instead of spinning.
                if let Some(quiet) = refusals.accept.admit() {
                    warn!(section = %section.name(), "accept failed: {err}{}", more(quiet));
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        if !plccoms_core::config::allowed(section.state().config.allow.as_deref(), peer.ip()) {
            // Closed at once without a word: nothing about the server is
            // told to a client that may not use it.
            if let Some(quiet) = refusals.allow.admit() {
                warn!(section = %section.name(), client = %peer, "refused: not in ALLOW{}", more(quiet));
            }
            drop(stream);
            continue;
        }
        if let Err(err) = set_keepalive(&stream) {
            warn!(section = %section.name(), client = %peer, "cannot set TCP keepalive: {err}");
        }
        match section.admit(peer) {
            Some(client) => {
                let section = section.clone();
                sessions.spawn(async move {
                    let _registration = Registration {
                        section: section.clone(),
                        id: client.id,
                    };
                    Session::serve_client(section, stream, client).await;
                });
            }
            None => {
                if let Some(quiet) = refusals.full.admit() {
                    warn!(section = %section.name(), client = %peer, "refused: NET_CONNECT_MAX ({}) reached{}", section.global().net_connect_max, more(quiet));
                }
                let crlf = section.global().end_line_crlf;
                tokio::spawn(refuse(stream, crlf));
            }
        }
    }
}

/// Removes a client from the section's list however its session ends.
struct Registration {
    section: Arc<Section>,
    id: u64,
}

impl Drop for Registration {
    fn drop(&mut self) {
        self.section.leave(self.id);
    }
}

async fn refuse(mut stream: TcpStream, crlf: bool) {
    let mut line = Vec::new();
    write_error(&mut line, ErrorCode::MaxConnections, b"");
    line.extend_from_slice(if crlf { b"\r\n" } else { b"\n" });
    let _ = stream.write_all(&line).await;
    let _ = stream.shutdown().await;
}
