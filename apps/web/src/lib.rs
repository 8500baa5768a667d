//! The built-in web page, Prometheus metrics and the JSON API, on
//! `HTTP_PORT` (axum).
//!
//! - `/` the page (`assets/`: HTML, JS, CSS and the vendored uPlot chart
//!   library, all compiled into the binary);
//! - `/metrics` the Prometheus text of every section and source (`metrics.rs`);
//! - `/api/...` JSON: sections, clients, variables and values, writes
//!   (`api.rs`), live values over server-sent events (`live.rs`), the
//!   historian's records (`history.rs`), the last warnings and errors;
//! - `auth.rs`: who may read and who may write.
//!
//! The server runs on a thread of its own, with its own single-threaded
//! runtime at a lower CPU priority: however busy the page and its browsers
//! keep it, the poll thread and the telnet sessions' runtime are not
//! slowed. It reads the sections through their public API only (live state,
//! the change stream's subscriptions, `Section::write`).

mod api;
mod assets;
mod auth;
pub mod history;
mod limits;
mod live;
mod metrics;
mod origin;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use axum::routing::{get, post};
use axum::Router;
use tokio_util::sync::CancellationToken;
use tracing::{error, info};

use plccoms_core::config::Global;
use plccoms_core::history_source::HistorySource;
use plccoms_core::section::Section;
use plccoms_core::sections::Sections;

/// What the `[*]` keys ask of the web server.
#[derive(Debug, Clone)]
pub struct WebConfig {
    pub bind: SocketAddr,
    pub token: Option<String>,
    /// HTTP_HOSTS.
    pub hosts: Vec<String>,
    /// Certificate chain and private key (PEM), for HTTPS.
    pub tls: Option<(PathBuf, PathBuf)>,
}

impl WebConfig {
    /// `None` when HTTP_PORT is not set. Relative TLS paths start from
    /// `dir`, the configuration's folder.
    pub fn from_global(global: &Global, dir: &Path) -> Option<WebConfig> {
        let port = global.http_port?;
        let tls = match (&global.http_cert, &global.http_key) {
            (Some(cert), Some(key)) => Some((dir.join(cert), dir.join(key))),
            _ => None,
        };
        Some(WebConfig {
            bind: SocketAddr::new(global.http_bind, port),
            token: global.http_token.clone(),
            hosts: global.http_hosts.clone(),
            tls,
        })
    }
}

/// What the handlers share.
pub(crate) struct Shared {
    /// The running sections (a reload changes them).
    pub sections: Sections,
    pub metrics: Arc<plccoms_core::metrics::Registry>,
    pub history: Option<Arc<dyn HistorySource>>,
    pub auth: auth::Auth,
    /// Cancelled at shutdown: live streams end.
    pub stop: CancellationToken,
    pub web_metrics: Arc<metrics::WebMetrics>,
    /// The names the page answers to.
    pub hosts: origin::Hosts,
    /// Live-value streams open, in all and per address.
    pub live_streams: Arc<limits::Limiter>,
}

impl Shared {
    pub fn section(&self, name: &str) -> Option<Arc<Section>> {
        self.sections.find(name)
    }
}

pub(crate) type State = axum::extract::State<Arc<Shared>>;

/// The running web server.
pub struct WebServer {
    pub local_addr: SocketAddr,
    pub tls: bool,
    handle: axum_server::Handle<SocketAddr>,
    stop: CancellationToken,
    thread: std::thread::JoinHandle<()>,
}

/// Longest wait at shutdown for requests under way.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

/// Binds and starts serving; fails (with a message naming what) when the
/// address cannot be bound or the TLS files cannot be used.
pub fn start(
    config: &WebConfig,
    sections: Sections,
    registry: Arc<plccoms_core::metrics::Registry>,
    history: Option<Arc<dyn HistorySource>>,
) -> Result<WebServer, String> {
    let tls = match &config.tls {
        Some((cert, key)) => Some(tls_config(cert, key)?),
        None => None,
    };
    let listener = std::net::TcpListener::bind(config.bind)
        .map_err(|e| format!("web page: cannot listen on {}: {e}", config.bind))?;
    listener
        .set_nonblocking(true)
        .map_err(|e| format!("web page: {e}"))?;
    let local_addr = listener.local_addr().map_err(|e| e.to_string())?;
    let web_metrics = Arc::new(metrics::WebMetrics::default());
    registry.add_source(web_metrics.clone());
    let stop = CancellationToken::new();
    let shared = Arc::new(Shared {
        sections,
        metrics: registry,
        history,
        auth: auth::Auth::new(
            config.token.clone(),
            !config.bind.ip().is_loopback(),
            tls.is_some(),
        ),
        stop: stop.clone(),
        web_metrics,
        hosts: origin::Hosts::new(config.bind.ip(), config.hosts.clone()),
        live_streams: limits::Limiter::new("live streams", limits::MAX_LIVE_STREAMS_PER_ADDRESS),
    });
    let app = router(shared).into_make_service_with_connect_info::<SocketAddr>();
    let handle = axum_server::Handle::new();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("web page: cannot start its runtime: {e}"))?;
    let is_tls = tls.is_some();
    let server_handle = handle.clone();
    let thread = std::thread::Builder::new()
        .name("plccoms-web".into())
        .spawn(move || {
            lower_priority();
            runtime.block_on(async move {
                let guarded = limits::GuardedAcceptor::new();
                let served = match tls {
                    Some(tls) => {
                        let config = axum_server::tls_rustls::RustlsConfig::from_config(tls);
                        match axum_server::tls_rustls::from_tcp_rustls(listener, config) {
                            Ok(server) => {
                                bounded(server.map(|tls| tls.acceptor(guarded)))
                                    .handle(server_handle)
                                    .serve(app)
                                    .await
                            }
                            Err(e) => Err(e),
                        }
                    }
                    None => match axum_server::from_tcp(listener) {
                        Ok(server) => {
                            bounded(server.acceptor(guarded))
                                .handle(server_handle)
                                .serve(app)
                                .await
                        }
                        Err(e) => Err(e),
                    },
                };
                if let Err(e) = served {
                    error!("web page stopped: {e}");
                }
            });
        })
        .map_err(|e| format!("web page: cannot start its thread: {e}"))?;
    info!(
        "web page on {}://{local_addr}/",
        if is_tls { "https" } else { "http" }
    );
    Ok(WebServer {
        local_addr,
        tls: is_tls,
        handle,
        stop,
        thread,
    })
}

impl WebServer {
    /// Ends the live streams, lets requests under way finish (bounded) and
    /// waits for the server's thread.
    pub async fn shutdown(self) {
        self.stop.cancel();
        self.handle.graceful_shutdown(Some(SHUTDOWN_GRACE));
        let thread = self.thread;
        let joined = tokio::task::spawn_blocking(move || thread.join());
        let _ = tokio::time::timeout(SHUTDOWN_GRACE * 2, joined).await;
    }
}

/// HTTP settings that bound what one connection may hold (see `limits`).
fn bounded<Acc>(
    mut server: axum_server::Server<SocketAddr, Acc>,
) -> axum_server::Server<SocketAddr, Acc> {
    const BUFFER: usize = 64 * 1024;
    let builder = server.http_builder();
    builder
        .http1()
        .header_read_timeout(limits::HEADER_TIMEOUT)
        .max_buf_size(BUFFER);
    builder
        .http2()
        .max_concurrent_streams(limits::MAX_HTTP2_STREAMS)
        .max_send_buf_size(BUFFER)
        .initial_stream_window_size(BUFFER as u32)
        .initial_connection_window_size(4 * BUFFER as u32)
        .max_header_list_size(BUFFER as u32);
    server.first_request_timeout(limits::HEADER_TIMEOUT)
}

fn router(shared: Arc<Shared>) -> Router {
    let api = Router::new()
        .route("/sections", get(api::sections))
        .route("/sections/{section}", get(api::section))
        .route("/sections/{section}/clients", get(api::clients))
        .route("/sections/{section}/vars", get(api::vars))
        .route("/sections/{section}/values", get(api::values))
        .route("/sections/{section}/live", get(live::live))
        .route("/sections/{section}/set", post(api::set))
        .route("/log", get(api::log))
        .route("/history", get(history::history))
        .route_layer(axum::middleware::from_fn_with_state(
            shared.clone(),
            auth::require_read,
        ))
        // The page asks these before it has a token.
        .route("/session", get(auth::session))
        .route("/login", post(auth::login))
        .route("/logout", post(auth::logout));
    Router::new()
        .route("/", get(assets::index))
        .route("/assets/{*file}", get(assets::file))
        .route(
            "/metrics",
            get(metrics::metrics).route_layer(axum::middleware::from_fn_with_state(
                shared.clone(),
                auth::require_read,
            )),
        )
        .route("/api", get(api::index))
        .route("/api/", get(api::index))
        .nest("/api", api)
        .fallback(api::not_found)
        .layer(axum::middleware::from_fn_with_state(
            shared.clone(),
            origin::check,
        ))
        .with_state(shared)
}

/// The certificate chain and key as a rustls server configuration.
fn tls_config(cert: &Path, key: &Path) -> Result<Arc<rustls::ServerConfig>, String> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let chain = CertificateDer::pem_file_iter(cert)
        .and_then(|certs| certs.collect::<Result<Vec<_>, _>>())
        .map_err(|e| format!("HTTP_CERT {}: {e}", cert.display()))?;
    if chain.is_empty() {
        return Err(format!(
            "HTTP_CERT {}: no certificate in the file",
            cert.display()
        ));
    }
    let private = PrivateKeyDer::from_pem_file(key)
        .map_err(|e| format!("HTTP_KEY {}: {e}", key.display()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| format!("TLS: {e}"))?
        .with_no_client_auth()
        .with_single_cert(chain, private)
        .map_err(|e| {
            format!(
                "HTTP_CERT {} and HTTP_KEY {}: {e}",
                cert.display(),
                key.display()
            )
        })?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(Arc::new(config))
}

/// Nice 10 for the calling thread (Linux: per thread): under CPU
/// contention the page yields to the poll thread and the sessions.
fn lower_priority() {
    // SAFETY: plain system calls on the calling thread; failure only means
    // the thread keeps the default priority.
    unsafe {
        let tid = libc::gettid();
        libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, 10);
    }
}
