//! The OPC UA server (north side): every section's variables as
//! Objects / plccoms / <Section> / <Variable>, with Read, Write through the
//! core's one write path, subscriptions that enable their variables in the
//! poll, HistoryRead from the historian, and the security of OPC UA
//! (signed and encrypted channels, users). On when `[*]` has OPCUA_PORT.
//!
//! The stack is async-opcua (server only): it does the binary protocol,
//! secure channels, sessions, browsing, subscriptions and monitored items
//! (sampling, deadbands, queues). Ours:
//!
//! - `ids.rs`: our string NodeIds, made and read back;
//! - `convert.rs`: IEC types and values as OPC UA types and Variants, and
//!   back for writes; qualities and refusals as StatusCodes;
//! - `space.rs`: each section's view of its table, and its object;
//! - `manager.rs`: the root folder and section objects (in the stack's
//!   address space);
//! - `vars.rs`: the variables, served from the tables, and the services
//!   that reach the PLC or the historian;
//! - `feed.rs`: one task per section, change stream -> monitored items;
//! - `follow.rs`: sections added, removed and restarted by a reload;
//! - `auth.rs`, `users.rs`: who may connect and who may write.

pub mod auth;
pub mod convert;
mod feed;
mod follow;
pub mod ids;
pub mod manager;
pub mod space;
pub mod users;
pub mod vars;

/// The stack, for the types our functions take.
pub use opcua;

use std::net::{IpAddr, SocketAddr, ToSocketAddrs};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use opcua::crypto::SecurityPolicy;
use opcua::server::node_manager::memory::{InMemoryNodeManager, InMemoryNodeManagerBuilder};
use opcua::server::{ServerBuilder, ServerEndpoint, ServerHandle};
use opcua::types::MessageSecurityMode;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use plccoms_core::config::{self, Global};
use plccoms_core::history_source::HistorySource;

use manager::Manager;
use space::Shared;
use users::Users;

/// How often the stack looks for subscriptions due to publish (ms).
const SUBSCRIPTION_TIMER_MS: u64 = 10;

/// The OPC UA port's listener. async-opcua accepts on it and leaves Nagle
/// on: the last chunk of a publish waited for the client's delayed ACK (40
/// ms on Linux; bench/opcua/run's PublishTime -> arrival, p50 48 ms).
/// Accepted sockets inherit TCP_NODELAY from the listener on Linux. Public
/// for the benchmarks' stand-in of a PLC's server, which binds alike.
pub fn listen(addr: std::net::SocketAddr) -> std::io::Result<std::net::TcpListener> {
    let listener = std::net::TcpListener::bind(addr)?;
    listener.set_nonblocking(true)?;
    socket2::SockRef::from(&listener).set_tcp_nodelay(true)?;
    Ok(listener)
}

/// The `[*]` OPC UA keys, resolved.
#[derive(Debug, Clone)]
pub struct Settings {
    pub host: String,
    pub port: u16,
    /// (policy, mode) of each endpoint offered.
    pub endpoints: Vec<(SecurityPolicy, MessageSecurityMode)>,
    pub users: Arc<Users>,
    /// Anonymous sessions allowed: a loopback host, or OPCUA_ANONYMOUS.
    pub anonymous: bool,
    pub pki: PathBuf,
    pub max_sessions: usize,
    pub max_subscriptions: usize,
    pub max_monitored_items: usize,
    pub max_nodes_per_call: usize,
    /// COMM_LOOP_DELAY: no sampling faster than the poll.
    pub loop_delay: Duration,
}

/// Whether `host` names this machine's loopback only.
pub fn is_loopback(host: &str) -> bool {
    host.eq_ignore_ascii_case("localhost")
        || host
            .trim_matches(['[', ']'])
            .parse::<IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// An OPCUA_SECURITY choice as the stack's policy and mode.
pub fn security(choice: &str) -> Option<(SecurityPolicy, MessageSecurityMode)> {
    let (policy, mode) = match choice.split_once(' ') {
        None if choice.eq_ignore_ascii_case("None") => {
            return Some((SecurityPolicy::None, MessageSecurityMode::None))
        }
        None => return None,
        Some(pair) => pair,
    };
    let policy = match policy {
        "Basic256Sha256" => SecurityPolicy::Basic256Sha256,
        "Aes128_Sha256_RsaOaep" => SecurityPolicy::Aes128Sha256RsaOaep,
        "Aes256_Sha256_RsaPss" => SecurityPolicy::Aes256Sha256RsaPss,
        _ => return None,
    };
    let mode = match mode {
        "Sign" => MessageSecurityMode::Sign,
        "SignAndEncrypt" => MessageSecurityMode::SignAndEncrypt,
        _ => return None,
    };
    Some((policy, mode))
}

impl Settings {
    /// `None` when OPCUA_PORT is not set. Fails when the users file cannot
    /// be read or is wrong, or no endpoint is left.
    pub fn load(global: &Global, config_path: &Path) -> Result<Option<Settings>, String> {
        let keys = &global.opcua;
        let Some(port) = keys.port else {
            return Ok(None);
        };
        let loopback = is_loopback(&keys.host);
        let open = loopback || keys.anonymous;
        let mut endpoints = Vec::new();
        for choice in &keys.security {
            let Some(endpoint) = security(choice) else {
                return Err(format!(
                    "OPCUA_SECURITY: '{choice}' is not a policy and mode"
                ));
            };
            if endpoint.0 == SecurityPolicy::None && !open {
                warn!("OPC UA: the None security policy is not offered on {} (not a loopback address); OPCUA_ANONYMOUS = Yes would offer it", keys.host);
                continue;
            }
            if !endpoints.contains(&endpoint) {
                endpoints.push(endpoint);
            }
        }
        if endpoints.is_empty() {
            return Err(
                "OPCUA_SECURITY leaves no endpoint: add Basic256Sha256 SignAndEncrypt".into(),
            );
        }
        let dir = config::config_dir(config_path);
        let users = match &keys.users {
            None => Users::default(),
            Some(file) => {
                let path = dir.join(file);
                let text = std::fs::read_to_string(&path)
                    .map_err(|e| format!("OPCUA_USERS {}: {e}", path.display()))?;
                Users::parse(&text).map_err(|e| format!("OPCUA_USERS {}: {e}", path.display()))?
            }
        };
        if !open && users.is_empty() {
            return Err(format!(
                "OPCUA_HOST {} is not a loopback address: anonymous sessions are refused there, and OPCUA_USERS names no users; add users, or set OPCUA_ANONYMOUS = Yes",
                keys.host
            ));
        }
        Ok(Some(Settings {
            host: keys.host.clone(),
            port,
            endpoints,
            users: Arc::new(users),
            anonymous: open,
            pki: config::state_dir(config_path).join(&keys.pki),
            max_sessions: keys.max_sessions,
            max_subscriptions: keys.max_subscriptions,
            max_monitored_items: keys.max_monitored_items,
            max_nodes_per_call: keys.max_nodes_per_call,
            loop_delay: global.comm_loop_delay,
        }))
    }

    /// The address clients are told to connect to: OPCUA_HOST, or this
    /// machine's name when it binds every address.
    fn url_host(&self) -> String {
        match self.host.parse::<IpAddr>() {
            Ok(ip) if ip.is_unspecified() => nix::unistd::gethostname()
                .ok()
                .and_then(|h| h.into_string().ok())
                .unwrap_or_else(|| self.host.clone()),
            Ok(IpAddr::V6(ip)) => format!("[{ip}]"),
            _ => self.host.clone(),
        }
    }
}

/// The running server.
pub struct Opcua {
    pub local_addr: SocketAddr,
    handle: ServerHandle,
    server: JoinHandle<()>,
    follow: JoinHandle<()>,
    stop: CancellationToken,
}

impl Opcua {
    /// Closes every session and stops listening, waiting at most `grace`.
    pub async fn shutdown(mut self, grace: Duration) {
        self.stop.cancel();
        self.handle.cancel();
        if tokio::time::timeout(grace, self.server).await.is_err() {
            warn!("OPC UA: the server did not stop within {grace:?}");
        }
        // Cancelled, it stops every feed; it waits on nothing long.
        if tokio::time::timeout(grace, &mut self.follow).await.is_err() {
            self.follow.abort();
        }
    }
}

/// Starts the server on `sections`; `history` serves HistoryRead. Fails
/// when the port cannot be bound or the PKI folder cannot be made.
pub fn start(
    settings: Settings,
    sections: &plccoms_core::sections::Sections,
    history: Option<Arc<dyn HistorySource>>,
) -> Result<Opcua, String> {
    // Watched from before the list is read: no reload is missed.
    let mut watched = sections.watch();
    let sections = watched.borrow_and_update().clone();
    let addr = (settings.host.as_str(), settings.port)
        .to_socket_addrs()
        .map_err(|e| format!("OPCUA_HOST {}: {e}", settings.host))?
        .next()
        .ok_or_else(|| format!("OPCUA_HOST {}: no address", settings.host))?;
    let listener =
        listen(addr).map_err(|e| format!("cannot listen on {addr} (OPCUA_PORT): {e}"))?;
    let local_addr = listener.local_addr().map_err(|e| e.to_string())?;
    let listener = tokio::net::TcpListener::from_std(listener).map_err(|e| e.to_string())?;
    std::fs::create_dir_all(&settings.pki).map_err(|e| {
        format!(
            "OPCUA_PKI {}: {e}; make the folder writable by the server's user, or set OPCUA_PKI to one that is",
            settings.pki.display()
        )
    })?;

    let shared = Arc::new(Shared::new(&sections, history, settings.users.clone()));
    let loop_delay_ms = settings.loop_delay.as_secs_f64() * 1000.0;
    let url_host = settings.url_host();
    let url = format!("opc.tcp://{url_host}:{}/", local_addr.port());
    let mut builder = ServerBuilder::new()
        .application_name("plccoms")
        .application_uri(format!("urn:plccoms:{url_host}"))
        .product_uri("urn:plccoms")
        .host(url_host.clone())
        .port(local_addr.port())
        .discovery_urls(vec![url.clone()])
        .pki_dir(&settings.pki)
        .create_sample_keypair(true)
        .trust_client_certs(false)
        .max_sessions(settings.max_sessions)
        .max_browse_continuation_points(10_000)
        // The stack checks every subscription's publishing interval on
        // this timer (100 ms by default): at 100 ms a publish due a hair
        // after a tick waited for the next, every other cycle 200 ms apart.
        .subscription_poll_interval_ms(SUBSCRIPTION_TIMER_MS)
        .with_authenticator(Arc::new(auth::Auth {
            users: settings.users.clone(),
            anonymous: settings.anonymous,
        }))
        // The variables' manager first: the stack gives a node to the
        // first manager that owns it, and both serve our namespace.
        .with_node_manager({
            let shared = shared.clone();
            move |_: opcua::server::node_manager::ServerContext| {
                vars::Vars::new(shared, loop_delay_ms)
            }
        })
        .with_node_manager(InMemoryNodeManagerBuilder::new(manager::Builder {
            shared: shared.clone(),
        }));
    {
        let limits = builder.limits_mut();
        let per_call = settings.max_nodes_per_call;
        let op = &mut limits.operational;
        op.max_nodes_per_read = per_call;
        op.max_nodes_per_write = per_call;
        op.max_nodes_per_browse = per_call;
        op.max_nodes_per_translate_browse_paths_to_node_ids = per_call;
        op.max_nodes_per_register_nodes = per_call;
        op.max_monitored_items_per_call = per_call;
        op.max_references_per_browse_node = per_call;
        let subs = &mut limits.subscriptions;
        subs.max_subscriptions_per_session = settings.max_subscriptions;
        subs.max_monitored_items_per_sub = settings.max_monitored_items;
        // Our values are samples already (at most one per poll, and the
        // variables' MinimumSamplingInterval says COMM_LOOP_DELAY). A
        // floor at the poll's rate made the stack sample them again by
        // their SourceTimestamps: a poll a millisecond early (jitter) was
        // held back with a SourceTimestamp moved forward, or dropped for
        // the next (bench/opcua/run: 1 % lost at 100 ms). Interval 0 (the
        // fastest practical) is revised to 0: every poll's change.
        subs.min_sampling_interval_ms = 0.0;
        // Publishing down to the stack's timer (its own floor is 100 ms),
        // not to the poll's: a change waits for the next publish after
        // its poll, up to a whole interval; a client that wants it sooner
        // (poll -> client within 50 ms) asks for 10 or 20 ms, and an
        // interval without a change costs a counter. (At 20 ms a held-back
        // change used to stall: see View::enable.)
        subs.min_publishing_interval_ms = SUBSCRIPTION_TIMER_MS as f64;
        // Room for every item of a subscription to change in one publish.
        subs.max_queued_notifications = settings.max_monitored_items.saturating_mul(4);
        subs.max_notifications_per_publish = 50_000;
        subs.max_monitored_item_queue_size = 10_000;
        subs.max_pending_publish_requests = 100;
        subs.max_publish_requests_per_subscription = 10;
        limits.max_message_size = 64 << 20;
        limits.max_chunk_count = 8192;
        limits.max_array_length = 1 << 20;
    }
    for (policy, mode) in &settings.endpoints {
        let id = format!("{policy}-{mode}");
        let mut endpoint = ServerEndpoint::new("/", *policy, *mode, &[]);
        if *policy == SecurityPolicy::None {
            // A password sent over None is still encrypted.
            endpoint.password_security_policy = Some(SecurityPolicy::Basic256Sha256.to_string());
        }
        builder = builder.add_endpoint(id, endpoint);
    }
    let (server, handle) = builder
        .build()
        .map_err(|e| format!("OPC UA server not built: {e}"))?;
    match own_thumbprint(&settings.pki) {
        Some(print) => info!(
            "OPC UA: server certificate {} (thumbprint {print}); client certificates are trusted from {}, untrusted ones land in {}",
            settings.pki.join("own/cert.der").display(),
            settings.pki.join("trusted").display(),
            settings.pki.join("rejected").display()
        ),
        None => warn!("OPC UA: no server certificate in {}", settings.pki.display()),
    }
    let Some(manager) = handle
        .node_managers()
        .get_of_type::<InMemoryNodeManager<Manager>>()
    else {
        return Err("OPC UA: our node manager is missing".into());
    };
    let stop = CancellationToken::new();
    let follow = tokio::spawn(
        follow::Follow {
            shared: shared.clone(),
            manager,
            subscriptions: handle.subscriptions().clone(),
            stop: stop.clone(),
        }
        .run(sections, watched),
    );
    let server = tokio::spawn(async move {
        if let Err(e) = server.run_with(listener).await {
            warn!("OPC UA server stopped: {e}");
        }
    });
    let policies: Vec<String> = settings
        .endpoints
        .iter()
        .map(|(p, m)| format!("{p} {m}"))
        .collect();
    info!(
        "OPC UA: serving {url} on {local_addr} ({}), {} users, anonymous {}",
        policies.join(", "),
        settings.users.len(),
        if settings.anonymous {
            "allowed"
        } else {
            "refused"
        }
    );
    Ok(Opcua {
        local_addr,
        handle,
        server,
        follow,
        stop,
    })
}

/// The hex SHA-1 thumbprint of the server's own certificate.
fn own_thumbprint(pki: &Path) -> Option<String> {
    let der = std::fs::read(pki.join("own/cert.der")).ok()?;
    let cert = opcua::crypto::X509::from_der(&der).ok()?;
    Some(cert.thumbprint().as_hex_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accepted_connections_send_without_nagle() {
        let listener = listen("127.0.0.1:0".parse().unwrap()).unwrap();
        let _client = std::net::TcpStream::connect(listener.local_addr().unwrap()).unwrap();
        listener.set_nonblocking(false).unwrap();
        let (accepted, _) = listener.accept().unwrap();
        assert!(socket2::SockRef::from(&accepted).tcp_nodelay().unwrap());
    }

    fn global(keys: &[(&str, &str)]) -> Global {
        let mut global = Global::default();
        global.opcua.port = Some(4840);
        for (key, value) in keys {
            match *key {
                "host" => global.opcua.host = value.to_string(),
                "anonymous" => global.opcua.anonymous = *value == "Yes",
                "users" => global.opcua.users = Some(value.to_string()),
                "security" => {
                    global.opcua.security = config::OPCUA_SECURITY_CHOICES
                        .iter()
                        .copied()
                        .filter(|c| value.split(',').any(|v| v.trim() == *c))
                        .collect()
                }
                _ => unreachable!(),
            }
        }
        global
    }

    #[test]
    fn the_defaults_serve_loopback_with_every_endpoint() {
        let path = Path::new("/nonexistent/plccoms.ini");
        assert!(Settings::load(&Global::default(), path).unwrap().is_none());
        let settings = Settings::load(&global(&[]), path).unwrap().unwrap();
        assert_eq!(settings.host, "127.0.0.1");
        assert!(settings.anonymous);
        assert_eq!(settings.endpoints.len(), 3);
        assert!(settings
            .endpoints
            .contains(&(SecurityPolicy::None, MessageSecurityMode::None)));
        assert_eq!(settings.pki, Path::new("/nonexistent/opcua-pki"));
    }

    #[test]
    fn off_loopback_anonymous_and_none_need_opcua_anonymous() {
        let path = Path::new("/nonexistent/plccoms.ini");
        let refused = Settings::load(&global(&[("host", "0.0.0.0")]), path).unwrap_err();
        assert!(refused.contains("OPCUA_USERS"), "{refused}");
        let open = Settings::load(&global(&[("host", "0.0.0.0"), ("anonymous", "Yes")]), path)
            .unwrap()
            .unwrap();
        assert!(open.anonymous);
        assert!(open.endpoints.iter().any(|e| e.0 == SecurityPolicy::None));
        // Only None asked for, off loopback: nothing left to serve.
        let none_only = global(&[("host", "10.0.0.1"), ("security", "None")]);
        assert!(Settings::load(&none_only, path)
            .unwrap_err()
            .contains("no endpoint"));
        // A users file that is not there stops the start, naming it.
        let missing = global(&[("host", "10.0.0.1"), ("users", "nope")]);
        assert!(Settings::load(&missing, path)
            .unwrap_err()
            .contains("OPCUA_USERS /nonexistent/nope"));
    }

    #[test]
    fn policies_and_loopback_names() {
        for choice in config::OPCUA_SECURITY_CHOICES {
            assert!(security(choice).is_some(), "{choice}");
        }
        assert_eq!(security("Basic256Sha256 Encrypt"), None);
        for host in [
            "127.0.0.1",
            "::1",
            "[::1]",
            "localhost",
            "LocalHost",
            "127.1.2.3",
        ] {
            assert!(is_loopback(host), "{host}");
        }
        for host in ["0.0.0.0", "::", "10.0.0.1", "plc.example"] {
            assert!(!is_loopback(host), "{host}");
        }
    }
}
