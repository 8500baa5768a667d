//! From a loaded configuration to running sections: choose each section's
//! backend (by its PROTOCOL, the embedded simulated PLC, or none yet), load
//! its local public files, and start it. Nothing here waits for a PLC: every
//! section listens at once, and a public file that must come from the PLC is
//! fetched by the section's link when the PLC answers. A section that cannot
//! start is reported and skipped; the others run.

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use tracing::{error, info, warn};

use plccoms_core::config::{config_dir, Config, Global, Protocol, Section};
use plccoms_core::driver::PlcBackend;
use plccoms_core::link::tables::{plc_path, LoadError, NamedBy, PubSource};
use plccoms_core::link::Tables;
use plccoms_core::vars::VarTable;
use plcsim::{SimConfig, SimHandle};

use crate::DRIVERS;

use plccoms_core::sections::Sections;

/// A section that is serving: its link, and its telnet port.
pub struct RunningSection {
    pub section: Arc<plccoms_core::section::Section>,
    pub local_addr: SocketAddr,
    link: plccoms_core::section::run::Running,
    listener: plccoms_telnet::server::Listener,
    /// The section as configured (before a simulated PLC's address was put
    /// in), to tell what a reload changes.
    configured: Option<Section>,
    /// Its simulated PLC (`SIMULATOR = Yes`) and that PLC's files.
    simulators: Vec<SimHandle>,
    file_stores: Vec<tempfile::TempDir>,
}

impl RunningSection {
    /// Stops accepting and polling. Sessions end when their link is gone.
    pub fn abort(&self) {
        self.stop_accepting();
        self.link.stop();
    }

    /// Stops accepting and tells every session to close once it has
    /// answered what it received; the link keeps serving their reads.
    pub fn stop_accepting(&self) {
        self.listener.stop_accepting();
    }

    /// Waits until every session has answered what it received and closed,
    /// at most `grace`.
    pub async fn wait_sessions(&self, grace: std::time::Duration) {
        self.listener.wait_sessions(grace).await;
    }

    /// Waits, at most `grace`, for the link's thread to finish what it is
    /// doing with the PLC after [`RunningSection::abort`].
    pub async fn wait_link(&self, grace: std::time::Duration) {
        self.link.wait(grace).await;
    }
}

impl Drop for RunningSection {
    fn drop(&mut self) {
        self.abort();
    }
}

/// Starts serving one section: its link on `backend` (none: no PLC yet)
/// and its telnet port on `bind`, at once, whatever the PLC does.
/// `config_dir` is the configuration file's folder, the root of the
/// section's local files; `tables` how to (re)load its public files
/// (`None`: `table` stays). The port is bound first: a port in use starts
/// nothing.
pub async fn start_section(
    global: Arc<Global>,
    config: Section,
    table: VarTable,
    backend: Option<Box<dyn PlcBackend>>,
    bind: SocketAddr,
    config_dir: PathBuf,
    tables: Option<Tables>,
) -> std::io::Result<RunningSection> {
    let port = plccoms_telnet::server::bind(bind)?;
    let link = plccoms_core::section::run::start(plccoms_core::section::run::Setup {
        global,
        config,
        table,
        backend,
        drivers: DRIVERS,
        config_dir,
        tables,
    })?;
    let listener = plccoms_telnet::server::serve(port, link.section.clone())?;
    Ok(RunningSection {
        section: link.section.clone(),
        local_addr: listener.local_addr,
        link,
        listener,
        configured: None,
        simulators: Vec::new(),
        file_stores: Vec::new(),
    })
}

/// Stops `sections` together: no more clients, each session answers what
/// it received and closes (bounded), then polling stops and their
/// simulated PLCs.
async fn stop_sections(sections: &mut [RunningSection]) {
    for section in sections.iter() {
        section.stop_accepting();
    }
    futures::future::join_all(sections.iter().map(|s| s.wait_sessions(SESSIONS_GRACE))).await;
    for section in sections.iter() {
        section.abort();
    }
    futures::future::join_all(sections.iter().map(|s| s.wait_link(LINK_GRACE))).await;
    for section in sections.iter_mut() {
        for simulator in std::mem::take(&mut section.simulators) {
            simulator.stop().await;
        }
        section.file_stores.clear();
    }
}

/// Every section that started, and what keeps them alive.
pub struct Server {
    pub sections: Vec<RunningSection>,
    /// The running sections, as the north apps follow them.
    pub running: Sections,
    /// The configuration running, and its keys as written (empty when it
    /// was not read from a file: a reload then restarts what differs
    /// without naming keys).
    config: Config,
    pub written: Vec<plccoms_core::config::Written>,
    /// `[*]` as running: a reload keeps it (see [`Server::reload`]).
    global: Arc<Global>,
    dir: PathBuf,
    /// Every section's metrics, and whatever else reports (`/metrics`).
    pub metrics: Arc<plccoms_core::metrics::Registry>,
    /// The web page, `/metrics` and the API, when HTTP_PORT is set.
    #[cfg(feature = "web")]
    pub web: Option<plccoms_web::WebServer>,
    /// The historian, when a section records (HISTORY).
    #[cfg(feature = "historian")]
    pub historian: Option<plccoms_historian::Historian>,
    /// The MQTT north side, when MQTT_URL is set.
    #[cfg(feature = "mqtt")]
    mqtt: Option<plccoms_mqtt::Mqtt>,
    /// The OPC UA server, when OPCUA_PORT is set.
    #[cfg(feature = "opcua")]
    pub opcua: Option<plccoms_opcua::Opcua>,
}

impl Server {
    /// The simulated PLCs, in section order.
    pub fn simulators(&self) -> Vec<&SimHandle> {
        self.sections.iter().flat_map(|s| &s.simulators).collect()
    }

    /// Stops accepting, lets every session answer what it has received
    /// (bounded by a grace period; the links still serve their reads), then
    /// stops polling (waiting, bounded, for each link's thread to end) and
    /// the simulators. Sections stop together: the whole takes at most
    /// [`SESSIONS_GRACE`] + [`LINK_GRACE`] (plus half a second for MQTT),
    /// however many there are.
    pub async fn shutdown(mut self) {
        #[cfg(feature = "web")]
        if let Some(web) = self.web.take() {
            web.shutdown().await;
        }
        #[cfg(feature = "opcua")]
        if let Some(opcua) = self.opcua.take() {
            opcua.shutdown(OPCUA_GRACE).await;
        }
        for section in &self.sections {
            section.stop_accepting();
        }
        // MQTT first, while the links still answer: `offline`, DISCONNECT,
        // the queue saved.
        #[cfg(feature = "mqtt")]
        if let Some(mqtt) = self.mqtt.take() {
            mqtt.shutdown(MQTT_GRACE).await;
        }
        stop_sections(&mut self.sections).await;
        #[cfg(feature = "fanout-trace")]
        if let Some(summary) = plccoms_telnet::session::trace::summary() {
            info!("{summary}");
        }
        // After the links: what they published last is recorded.
        #[cfg(feature = "historian")]
        if let Some(historian) = self.historian.take() {
            historian.stop().await;
        }
    }
}

/// What a reload did, as the log tells it.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Reloaded {
    pub added: Vec<String>,
    pub removed: Vec<String>,
    /// Restarted sections and the keys that changed (empty when the
    /// running configuration was not read from a file).
    pub restarted: Vec<(String, Vec<String>)>,
    pub unchanged: Vec<String>,
    /// Sections of the new file that could not start, and why.
    pub failed: Vec<(String, String)>,
    /// `[*]` keys that changed: they take effect at the next restart.
    pub global_keys: Vec<String>,
}

impl std::fmt::Display for Reloaded {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let names = |list: &[String]| {
            list.iter()
                .map(|n| format!("[{n}]"))
                .collect::<Vec<_>>()
                .join(" ")
        };
        let mut parts = Vec::new();
        if !self.added.is_empty() {
            parts.push(format!("added {}", names(&self.added)));
        }
        if !self.removed.is_empty() {
            parts.push(format!("removed {}", names(&self.removed)));
        }
        if !self.restarted.is_empty() {
            let list: Vec<String> = self
                .restarted
                .iter()
                .map(|(name, keys)| match keys.is_empty() {
                    true => format!("[{name}]"),
                    false => format!("[{name}] ({})", keys.join(", ")),
                })
                .collect();
            parts.push(format!("restarted {}", list.join(" ")));
        }
        if !self.failed.is_empty() {
            parts.push(format!(
                "not started {}",
                names(
                    &self
                        .failed
                        .iter()
                        .map(|(n, _)| n.clone())
                        .collect::<Vec<_>>()
                )
            ));
        }
        parts.push(format!("{} unchanged", self.unchanged.len()));
        write!(f, "{}", parts.join(", "))
    }
}

impl Server {
    /// Registers a started section (metrics; [`Server::publish`] tells the
    /// apps).
    fn add(&mut self, running: RunningSection) {
        let probe: std::sync::Weak<dyn plccoms_core::metrics::SectionProbe> =
            Arc::downgrade(&running.section) as _;
        self.metrics.add_section(
            running.section.name(),
            running.section.metrics().clone(),
            probe,
        );
        self.sections.push(running);
    }

    /// Tells the north apps which sections run now.
    fn publish(&self) {
        self.running
            .set(self.sections.iter().map(|r| r.section.clone()).collect());
    }

    /// Applies a new configuration without a restart: sections added start,
    /// removed ones stop (their clients' requests answered, then the
    /// connections closed), changed ones restart alone; unchanged ones keep
    /// their clients, links, subscriptions and MQTT sessions. `[*]` stays as
    /// it runs: its changed keys are named, for the next restart. The
    /// caller refuses a file with errors before this (see
    /// [`plccoms_core::config::Loaded::has_errors`]).
    pub async fn reload(&mut self, loaded: plccoms_core::config::Loaded) -> Reloaded {
        let new = loaded.config;
        let mut report = Reloaded::default();
        if let (Some(old), Some(now)) = (
            self.written("*"),
            loaded.written.iter().find(|w| w.name == "*"),
        ) {
            report.global_keys = plccoms_core::config::changed_keys(old, now);
        } else if self.config.global != new.global {
            report.global_keys.push("*".into());
        }
        for own in new.own_paths() {
            plccoms_core::localfs::protect(
                &own.path,
                own.used != plccoms_core::config::PathUse::Input,
            );
        }
        // What each section of the new file would run with: `[*]` as running.
        let wanted: Vec<Section> = new
            .sections
            .iter()
            .map(|section| Section {
                serial_device_cfg: self.global.serial_device_cfg.clone(),
                ..section.clone()
            })
            .collect();
        let mut stopping = Vec::new();
        let mut kept = Vec::new();
        for running in std::mem::take(&mut self.sections) {
            let name = running.section.name().to_string();
            match wanted.iter().find(|s| s.name == name) {
                None => {
                    report.removed.push(name);
                    stopping.push(running);
                }
                Some(section) if running.configured.as_ref() != Some(section) => {
                    let keys = match (
                        self.written(&name),
                        loaded.written.iter().find(|w| w.name == name),
                    ) {
                        (Some(old), Some(now)) => plccoms_core::config::changed_keys(old, now),
                        _ => Vec::new(),
                    };
                    report.restarted.push((name, keys));
                    stopping.push(running);
                }
                Some(_) => {
                    report.unchanged.push(name);
                    kept.push(running);
                }
            }
        }
        for running in &stopping {
            self.metrics.remove_section(running.section.name());
        }
        // The apps let go of removed sections first (MQTT says `offline`
        // while the link still answers), then they stop. A restarted one
        // stays in the list until its replacement takes its place in one
        // step, so that the apps see a swap (OPC UA keeps its nodes,
        // Sparkplug rebirths once), not a removal and an addition.
        self.sections = kept;
        let interim = self
            .sections
            .iter()
            .chain(stopping.iter().filter(|r| {
                let name = r.section.name();
                report.restarted.iter().any(|(n, _)| n == name)
            }))
            .map(|r| r.section.clone())
            .collect();
        self.running.set(interim);
        stop_sections(&mut stopping).await;
        drop(stopping);
        for section in &wanted {
            if self
                .sections
                .iter()
                .any(|r| r.section.name() == section.name)
            {
                continue;
            }
            // Not running and not restarted: new (or one that failed to
            // start before). A removed section is not in `wanted`.
            if !report.restarted.iter().any(|(n, _)| *n == section.name) {
                report.added.push(section.name.clone());
            }
            match start_one(&self.global, section, &self.dir).await {
                Ok(running) => self.add(running),
                Err(message) => {
                    error!(section = %section.name, "section not started: {message}");
                    report.failed.push((section.name.clone(), message));
                }
            }
        }
        // Configuration order, as at start.
        self.sections.sort_by_key(|r| {
            wanted
                .iter()
                .position(|s| s.name == r.section.name())
                .unwrap_or(usize::MAX)
        });
        self.publish();
        self.start_historian_if_needed();
        // `[*]` stays as it runs, and so do its keys as written.
        let global_written = self.written.iter().find(|w| w.name == "*").cloned();
        self.written = loaded
            .written
            .into_iter()
            .filter(|w| w.name != "*")
            .chain(global_written)
            .collect();
        self.config = Config {
            global: self.config.global.clone(),
            ..new
        };
        report
    }

    fn written(&self, name: &str) -> Option<&plccoms_core::config::Written> {
        self.written.iter().find(|w| w.name == name)
    }

    /// A reload that adds the first section with HISTORY starts the
    /// historian.
    #[cfg(feature = "historian")]
    fn start_historian_if_needed(&mut self) {
        if self.historian.is_some() {
            return;
        }
        let config = self.config.clone();
        let sections = self.running.clone();
        if let Err(message) = start_historian(&config, &sections, self) {
            error!("{message}");
        }
    }

    #[cfg(not(feature = "historian"))]
    fn start_historian_if_needed(&mut self) {}
}

/// Longest wait at shutdown for sessions to answer what they received, and
/// then for the links' threads (a request to a PLC in flight): together
/// at most 4 s, so SIGTERM ends the server within 5 s (the unit and the
/// README promise it).
pub const SESSIONS_GRACE: std::time::Duration = std::time::Duration::from_secs(3);
pub const LINK_GRACE: std::time::Duration = std::time::Duration::from_secs(1);
/// Longest wait at shutdown for MQTT to say `offline` and save its queue.
pub const MQTT_GRACE: std::time::Duration = std::time::Duration::from_millis(500);
/// Longest wait at shutdown for the OPC UA server to close its sessions.
pub const OPCUA_GRACE: std::time::Duration = std::time::Duration::from_millis(500);

/// Starts every section of `config`; fails only when none could start.
pub async fn start(config: &Config) -> Result<Server, String> {
    #[cfg(feature = "fanout-trace")]
    plccoms_telnet::session::trace::listen();
    // The configuration holds passwords and tokens: clients neither read
    // nor write it, whatever FILES_ROOT says.
    plccoms_core::localfs::protect(&config.path, true);
    // So is every file and folder a key names: certificates, keys and
    // passwords, plugin libraries, tag and public files, the history and
    // the queues. Registered before anything starts, so that a part that
    // fails to start leaves its files guarded all the same.
    for own in config.own_paths() {
        plccoms_core::localfs::protect(&own.path, own.used != plccoms_core::config::PathUse::Input);
    }
    let dir = config_dir(&config.path);
    let mut global = config.global.clone();
    global.files_root = Some(files_root(&global, &dir)?);
    let global = Arc::new(global);
    let mut server = Server {
        sections: Vec::new(),
        running: Sections::new(Vec::new()),
        config: config.clone(),
        written: Vec::new(),
        global: global.clone(),
        dir: dir.clone(),
        metrics: Arc::default(),
        #[cfg(feature = "web")]
        web: None,
        #[cfg(feature = "historian")]
        historian: None,
        #[cfg(feature = "mqtt")]
        mqtt: None,
        #[cfg(feature = "opcua")]
        opcua: None,
    };
    let mut failures = Vec::new();
    for section in &config.sections {
        match start_one(&global, section, &dir).await {
            Ok(running) => server.add(running),
            Err(message) => {
                error!(section = %section.name, "section not started: {message}");
                failures.push(format!("[{}] {message}", section.name));
            }
        }
    }
    if server.sections.is_empty() {
        // The reasons go into the message: with -d it is all the parent
        // prints.
        return Err(format!(
            "no PLC section could start: {}",
            failures.join("; ")
        ));
    }
    server.publish();
    let sections = server.running.clone();
    start_historian(config, &sections, &mut server)?;
    start_mqtt(config, &dir, &sections, &mut server)?;
    start_opcua(config, &global, &sections, &mut server)?;
    start_web(config, &global, &dir, sections, &mut server)?;
    Ok(server)
}

// The north apps. A configured app that cannot work at start (a folder it
// cannot write, an unreadable password, key or certificate, a port in use,
// or left out of this build) stops the start with one line naming the key
// and the fix: the server never says "running" while a configured part is
// dead. What can heal at run time (a full disk, a broker away) does not
// stop it; the app says what it waits for.

/// Part of a configuration this build cannot serve.
#[cfg(not(all(
    feature = "historian",
    feature = "mqtt",
    feature = "web",
    feature = "opcua"
)))]
fn left_out(what: &str, feature: &str) -> String {
    format!("{what}: this build has no {feature} (built without the cargo feature `{feature}`); remove the key or use a build with it")
}

#[cfg(feature = "historian")]
fn start_historian(
    config: &Config,
    sections: &Sections,
    server: &mut Server,
) -> Result<(), String> {
    server.historian = plccoms_historian::Historian::start(config, sections)
        .map_err(|message| format!("history not started: {message}"))?;
    if let Some(historian) = &server.historian {
        server.metrics.add_source(historian.metrics());
    }
    Ok(())
}

#[cfg(not(feature = "historian"))]
fn start_historian(
    _config: &Config,
    sections: &Sections,
    _server: &mut Server,
) -> Result<(), String> {
    if sections
        .current()
        .iter()
        .any(|section| section.state().config.history.enabled())
    {
        return Err(format!(
            "history not started: {}",
            left_out("HISTORY", "historian")
        ));
    }
    Ok(())
}

#[cfg(feature = "mqtt")]
fn start_mqtt(
    config: &Config,
    dir: &Path,
    sections: &Sections,
    server: &mut Server,
) -> Result<(), String> {
    let mqtt = plccoms_mqtt::settings::Settings::load(&config.global.mqtt, dir, &config.path)
        .and_then(|settings| {
            settings
                .map(|settings| plccoms_mqtt::start(settings, sections))
                .transpose()
        })
        .map_err(|message| format!("MQTT not started: {message}"))?;
    if let Some(mqtt) = mqtt {
        server.metrics.add_source(mqtt.source.clone());
        server.mqtt = Some(mqtt);
    }
    Ok(())
}

#[cfg(not(feature = "mqtt"))]
fn start_mqtt(
    config: &Config,
    _dir: &Path,
    _sections: &Sections,
    _server: &mut Server,
) -> Result<(), String> {
    if config.global.mqtt.url.is_some() {
        return Err(format!(
            "MQTT not started: {}",
            left_out("MQTT_URL", "mqtt")
        ));
    }
    Ok(())
}

/// The historian as the apps read it (the web page's history, OPC UA's
/// HistoryRead), when one records.
#[cfg(all(feature = "historian", any(feature = "web", feature = "opcua")))]
fn history_source(
    config: &Config,
    global: &Global,
    server: &Server,
) -> Option<Arc<dyn plccoms_core::history_source::HistorySource>> {
    server.historian.as_ref().map(|_| {
        Arc::new(plccoms_historian::web::Source::new(
            plccoms_historian::history_dir(&config.path, global),
            global.history_query_timeout,
        )) as Arc<dyn plccoms_core::history_source::HistorySource>
    })
}

#[cfg(all(not(feature = "historian"), any(feature = "web", feature = "opcua")))]
fn history_source(
    _config: &Config,
    _global: &Global,
    _server: &Server,
) -> Option<Arc<dyn plccoms_core::history_source::HistorySource>> {
    None
}

#[cfg(feature = "opcua")]
fn start_opcua(
    config: &Config,
    global: &Arc<Global>,
    sections: &Sections,
    server: &mut Server,
) -> Result<(), String> {
    let opcua = plccoms_opcua::Settings::load(global, &config.path)
        .and_then(|settings| {
            settings
                .map(|settings| {
                    // HistoryRead reads the historian's files, as the web
                    // page's history does.
                    let history = history_source(config, global, server);
                    plccoms_opcua::start(settings, sections, history)
                })
                .transpose()
        })
        .map_err(|message| format!("OPC UA not started: {message}"))?;
    server.opcua = opcua;
    Ok(())
}

#[cfg(not(feature = "opcua"))]
fn start_opcua(
    _config: &Config,
    global: &Arc<Global>,
    _sections: &Sections,
    _server: &mut Server,
) -> Result<(), String> {
    if global.opcua.port.is_some() {
        return Err(format!(
            "OPC UA not started: {}",
            left_out("OPCUA_PORT", "opcua")
        ));
    }
    Ok(())
}

#[cfg(feature = "web")]
fn start_web(
    config: &Config,
    global: &Arc<Global>,
    dir: &Path,
    sections: Sections,
    server: &mut Server,
) -> Result<(), String> {
    let Some(web) = plccoms_web::WebConfig::from_global(global, dir) else {
        return Ok(());
    };
    // /api/history and the chart's range mode read the historian's files;
    // without one they answer "historian not enabled".
    let history = history_source(config, global, server);
    let running = plccoms_web::start(&web, sections, server.metrics.clone(), history)
        .map_err(|message| format!("web page not started: {message}"))?;
    server.web = Some(running);
    Ok(())
}

#[cfg(not(feature = "web"))]
fn start_web(
    _config: &Config,
    global: &Arc<Global>,
    _dir: &Path,
    _sections: Sections,
    _server: &mut Server,
) -> Result<(), String> {
    if global.http_port.is_some() {
        return Err(format!(
            "web page not started: {}",
            left_out("HTTP_PORT", "web")
        ));
    }
    Ok(())
}

/// The folder of clients' own files (names beginning with `.`), created if
/// missing, relative to `dir`: FILES_ROOT; else,
/// under systemd (`StateDirectory=`, as the shipped unit sets it), `files`
/// in `$STATE_DIRECTORY`, a folder of their own apart from the server's
/// files; else `dir` itself (empty), the configuration's folder, as the
/// vendor's server.
fn files_root(global: &plccoms_core::config::Global, dir: &Path) -> Result<PathBuf, String> {
    let state = plccoms_core::config::systemd_state_dir();
    // As given (relative: from `dir`, which the sections join).
    let root = match (&global.files_root, state) {
        (Some(root), _) => root.clone(),
        (None, Some(state)) => state.join("files"),
        (None, None) => return Ok(PathBuf::new()),
    };
    let on_disk = dir.join(&root);
    std::fs::create_dir_all(&on_disk)
        .map_err(|e| format!("FILES_ROOT {}: {e}", on_disk.display()))?;
    Ok(root)
}

/// A section's simulated PLC and its files, while it runs.
#[derive(Default)]
struct Simulated {
    simulators: Vec<SimHandle>,
    file_stores: Vec<tempfile::TempDir>,
}

async fn start_one(
    global: &Arc<Global>,
    configured: &Section,
    dir: &Path,
) -> Result<RunningSection, String> {
    let mut section = configured.clone();
    let mut simulated = Simulated::default();
    let backend = backend_for(&mut section, dir, &mut simulated).await?;
    let section = &section;
    let source = PubSource::new(section, dir)?;
    let (user, from_plc) = match source.load_local(section, NamedBy::Configuration) {
        Ok(user) => (user, false),
        Err(LoadError::FromPlc) => (None, true),
        Err(LoadError::Failed(message)) => return Err(message),
    };
    let table = source.build(&section.name, user.as_ref())?;
    info!(
        section = %section.name,
        variables = table.len(),
        "{}",
        source.loaded_line(section, user.as_ref(), from_plc)
    );
    let bind_ip = section.ipaddr_local.unwrap_or(Ipv4Addr::UNSPECIFIED);
    let bind = SocketAddr::new(IpAddr::V4(bind_ip), section.server_port);
    let mut running = start_section(
        global.clone(),
        section.clone(),
        table,
        backend,
        bind,
        dir.to_path_buf(),
        Some(Tables::new(source, user, from_plc)),
    )
    .await
    .map_err(|e| format!("cannot listen on {bind}: {e}"))?;
    running.configured = Some(configured.clone());
    running.simulators = simulated.simulators;
    running.file_stores = simulated.file_stores;
    Ok(running)
}

/// The section's PLC link; `None` when it has no PLC yet (`IPADDR = 0.0.0.0`).
/// A simulated PLC's section is pointed at it (IPADDR, EPSPORT), so GETINFO
/// and SETCONF see where the PLC really is.
async fn backend_for(
    section: &mut Section,
    dir: &Path,
    server: &mut Simulated,
) -> Result<Option<Box<dyn PlcBackend>>, String> {
    if let Some(simulator) = section.simulator.clone() {
        if matches!(
            section.protocol,
            Protocol::ModbusRtu | Protocol::ModbusRtuTcp
        ) {
            return Err(format!(
                "SIMULATOR = Yes with PROTOCOL = {}: the simulated device speaks MODBUS_TCP (set PROTOCOL = MODBUS_TCP)",
                section.protocol
            ));
        }
        let device = if section.protocol == Protocol::ModbusTcp {
            let device = spawn_modbus_simulator(section, &simulator, dir, server).await?;
            section.modbus.port = device.port();
            device
        } else {
            let plc = spawn_simulator(section, &simulator, dir, server).await?;
            section.epsport = plc.port();
            plc
        };
        if let std::net::IpAddr::V4(ip) = device.ip() {
            section.ipaddr = Some(ip);
        }
        // The simulated PLC answers on loopback: a serial line or a plugin
        // named as well does not apply (nor to a SETCONF's new link).
        section.serial_device = None;
        section.shm_name = None;
    }
    let backend = DRIVERS.open(section, dir)?;
    if backend.is_none() {
        warn!(section = %section.name, "no PLC address (IPADDR) yet: serving clients without a PLC until SETCONF:ipaddr");
    }
    Ok(backend)
}

/// Runs the simulated Modbus device of a `SIMULATOR = Yes` section with
/// `PROTOCOL = MODBUS_TCP` on a loopback port. It serves SIMULATOR_PUB (a tag
/// file) if set, else the section's MODBUS_TAGS; a section with neither gets
/// the built-in demo tag file, written to a folder of its own.
async fn spawn_modbus_simulator(
    section: &mut Section,
    simulator: &plccoms_core::config::Simulator,
    dir: &Path,
    server: &mut Simulated,
) -> Result<SocketAddr, String> {
    let read = |path: PathBuf, key: &str| {
        std::fs::read(&path).map_err(|e| format!("{key} {}: {e}", path.display()))
    };
    let bytes = match (&simulator.pubfile, &section.modbus.tags) {
        (Some(path), _) => read(dir.join(path), "SIMULATOR_PUB")?,
        (None, Some(name)) => read(section.path_of(dir, name), "MODBUS_TAGS")?,
        (None, None) => {
            let store = tempfile::Builder::new()
                .prefix("plccoms-sim-")
                .tempdir()
                .map_err(|e| format!("cannot create the simulator's folder: {e}"))?;
            let path = store.path().join("demo-modbus.csv");
            std::fs::write(&path, plcsim::DEMO_TAGS).map_err(|e| e.to_string())?;
            section.modbus.tags = Some(path.to_string_lossy().into_owned());
            server.file_stores.push(store);
            plcsim::DEMO_TAGS.to_vec()
        }
    };
    let config = SimConfig {
        modbus: Some(SocketAddr::from((Ipv4Addr::LOCALHOST, 0))),
        pubfile: plcsim::PubSource::Bytes(bytes),
        ..SimConfig::default()
    };
    run_simulator(
        section,
        simulator,
        config,
        "simulated Modbus device",
        server,
    )
    .await
}

/// Starts `config` with the section's SIMULATOR_PROGRAM; keeps it running
/// with the server.
async fn run_simulator(
    section: &Section,
    simulator: &plccoms_core::config::Simulator,
    config: SimConfig,
    what: &str,
    server: &mut Simulated,
) -> Result<SocketAddr, String> {
    let program = simulator
        .program
        .parse()
        .map_err(|e| format!("SIMULATOR_PROGRAM: {e}"))?;
    let handle = plcsim::spawn(SimConfig { program, ..config })
        .await
        .map_err(|e| format!("cannot start the {what}: {e}"))?;
    let addr = handle.local_addr();
    info!(section = %section.name, plc = %addr, "{what} running");
    server.simulators.push(handle);
    Ok(addr)
}

/// Runs the simulated PLC of a `SIMULATOR = Yes` section on a loopback port.
/// Its file system is a fresh folder holding its public file, under the name
/// the section's PUBFILE asks for, so the server fetches it as from a PLC.
async fn spawn_simulator(
    section: &Section,
    simulator: &plccoms_core::config::Simulator,
    dir: &Path,
    server: &mut Simulated,
) -> Result<SocketAddr, String> {
    let bytes = match &simulator.pubfile {
        Some(path) => {
            let path = dir.join(path);
            std::fs::read(&path).map_err(|e| format!("SIMULATOR_PUB {}: {e}", path.display()))?
        }
        None => plcsim::DEMO_PUB.to_vec(),
    };
    let store = tempfile::Builder::new()
        .prefix("plccoms-sim-")
        .tempdir()
        .map_err(|e| format!("cannot create the simulator's file store: {e}"))?;
    if let Some(name) = &section.pubfile {
        let target = store.path().join(plc_path(name));
        if let Some(parent) = target.parent() {
            std::fs::create_dir_all(parent).map_err(|e| e.to_string())?;
        }
        std::fs::write(&target, &bytes).map_err(|e| e.to_string())?;
    }
    let config = SimConfig {
        bind: SocketAddr::from((Ipv4Addr::LOCALHOST, 0)),
        pubfile: plcsim::PubSource::Bytes(bytes),
        files: Some(store.path().to_path_buf()),
        ..SimConfig::default()
    };
    let addr = run_simulator(section, simulator, config, "simulated PLC", server).await?;
    server.file_stores.push(store);
    Ok(addr)
}
