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

use crate::backend::epsnet::EpsnetBackend;
use crate::backend::modbus::ModbusBackend;
use crate::backend::{epsnet_config, modbus_config, PlcBackend};
use crate::config::{config_dir, Config, Global, Protocol, Section};
use crate::link::tables::{plc_path, LoadError, NamedBy, PubSource};
use crate::link::Tables;
use crate::server::{start_section, RunningSection};
use plcsim::{SimConfig, SimHandle};

/// Every section that started, and what keeps them alive.
pub struct Server {
    pub sections: Vec<RunningSection>,
    /// Every section's metrics, and whatever else reports (`/metrics`).
    pub metrics: Arc<crate::metrics::Registry>,
    /// The web page, `/metrics` and the API, when HTTP_PORT is set.
    pub web: Option<crate::web::WebServer>,
    /// The historian, when a section records (HISTORY).
    pub historian: Option<crate::historian::Historian>,
    simulators: Vec<SimHandle>,
    _file_stores: Vec<tempfile::TempDir>,
    /// The MQTT north side, when MQTT_URL is set.
    mqtt: Option<crate::mqtt::Mqtt>,
}

impl Server {
    pub fn simulators(&self) -> &[SimHandle] {
        &self.simulators
    }

    /// Stops accepting, lets every session answer what it has received
    /// (bounded by a grace period; the links still serve their reads), then
    /// stops polling (waiting, bounded, for each link's thread to end) and
    /// the simulators. Sections stop together: the whole takes at most
    /// [`SESSIONS_GRACE`] + [`LINK_GRACE`] (plus half a second for MQTT),
    /// however many there are.
    pub async fn shutdown(mut self) {
        if let Some(web) = self.web.take() {
            web.shutdown().await;
        }
        for section in &self.sections {
            section.stop_accepting();
        }
        // MQTT first, while the links still answer: `offline`, DISCONNECT,
        // the queue saved.
        if let Some(mqtt) = self.mqtt {
            mqtt.shutdown(MQTT_GRACE).await;
        }
        futures::future::join_all(
            self.sections
                .iter()
                .map(|s| s.wait_sessions(SESSIONS_GRACE)),
        )
        .await;
        for section in &self.sections {
            section.abort();
        }
        futures::future::join_all(self.sections.iter().map(|s| s.wait_link(LINK_GRACE))).await;
        #[cfg(feature = "fanout-trace")]
        if let Some(summary) = crate::session::trace::summary() {
            info!("{summary}");
        }
        // After the links: what they published last is recorded.
        if let Some(historian) = self.historian.take() {
            historian.stop().await;
        }
        for simulator in self.simulators {
            simulator.stop().await;
        }
    }
}

/// Longest wait at shutdown for sessions to answer what they received, and
/// then for the links' threads (a request to a PLC in flight): together
/// at most 4 s, so SIGTERM ends the server within 5 s (the unit and the
/// README promise it).
pub const SESSIONS_GRACE: std::time::Duration = std::time::Duration::from_secs(3);
pub const LINK_GRACE: std::time::Duration = std::time::Duration::from_secs(1);
/// Longest wait at shutdown for MQTT to say `offline` and save its queue.
pub const MQTT_GRACE: std::time::Duration = std::time::Duration::from_millis(500);

/// Starts every section of `config`; fails only when none could start.
pub async fn start(config: &Config) -> Result<Server, String> {
    #[cfg(feature = "fanout-trace")]
    crate::session::trace::listen();
    // The configuration holds passwords and tokens: clients neither read
    // nor write it, whatever FILES_ROOT says.
    crate::localfs::protect(&config.path, true);
    // So is every file and folder a key names: certificates, keys and
    // passwords, plugin libraries, tag and public files, the history and
    // the queues. Registered before anything starts, so that a part that
    // fails to start leaves its files guarded all the same.
    for own in config.own_paths() {
        crate::localfs::protect(&own.path, own.used != crate::config::PathUse::Input);
    }
    let dir = config_dir(&config.path);
    let mut global = config.global.clone();
    global.files_root = Some(files_root(&global, &dir)?);
    let global = Arc::new(global);
    let mut server = Server {
        sections: Vec::new(),
        metrics: Arc::default(),
        web: None,
        historian: None,
        simulators: Vec::new(),
        _file_stores: Vec::new(),
        mqtt: None,
    };
    let mut failures = Vec::new();
    for section in &config.sections {
        match start_one(&global, section, &dir, &mut server).await {
            Ok(running) => {
                let probe: std::sync::Weak<dyn crate::metrics::SectionProbe> =
                    Arc::downgrade(&running.section) as _;
                server.metrics.add_section(
                    &running.section.name,
                    running.section.metrics.clone(),
                    probe,
                );
                server.sections.push(running);
            }
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
    let sections: Vec<_> = server.sections.iter().map(|r| r.section.clone()).collect();
    server.historian = crate::historian::Historian::start(config, &sections);
    if let Some(historian) = &server.historian {
        server.metrics.add_source(historian.metrics());
    }
    // Like the web page, an MQTT north side that cannot start (a queue
    // folder locked by another process, an unreadable password or CA file)
    // is reported and the PLC sections serve on.
    let mqtt = crate::mqtt::settings::Settings::load(&config.global.mqtt, &dir, &config.path)
        .and_then(|settings| {
            settings
                .map(|settings| crate::mqtt::start(settings, &sections))
                .transpose()
        });
    match mqtt {
        Ok(Some(mqtt)) => {
            server.metrics.add_source(mqtt.source.clone());
            server.mqtt = Some(mqtt);
        }
        Ok(None) => {}
        Err(message) => error!("MQTT not started: {message}"),
    }
    if let Some(web) = crate::web::WebConfig::from_global(&global, &dir) {
        // /api/history and the chart's range mode read the historian's
        // files; without one they answer "historian not enabled".
        let history = server.historian.as_ref().map(|_| {
            Arc::new(crate::historian::web::Source::new(
                crate::historian::history_dir(&config.path, &global),
                global.history_query_timeout,
            )) as Arc<dyn crate::history_source::HistorySource>
        });
        // Like a section that cannot listen, a page that cannot is
        // reported and the PLC sections serve on.
        match crate::web::start(&web, sections, server.metrics.clone(), history) {
            Ok(running) => server.web = Some(running),
            Err(message) => error!("web page not started: {message}"),
        }
    }
    Ok(server)
}

/// The folder of clients' own files (names beginning with `.`), created if
/// missing, relative to `dir`: FILES_ROOT; else,
/// under systemd (`StateDirectory=`, as the shipped unit sets it), `files`
/// in `$STATE_DIRECTORY`, a folder of their own apart from the server's
/// files; else `dir` itself (empty), the configuration's folder, as the
/// vendor's server.
fn files_root(global: &crate::config::Global, dir: &Path) -> Result<PathBuf, String> {
    let state = std::env::var_os("STATE_DIRECTORY")
        .and_then(|dirs| std::env::split_paths(&dirs).next())
        .filter(|d| d.is_absolute());
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

async fn start_one(
    global: &Arc<Global>,
    section: &Section,
    dir: &Path,
    server: &mut Server,
) -> Result<RunningSection, String> {
    let mut section = section.clone();
    let backend = backend_for(&mut section, dir, server).await?;
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
        "public files loaded: {}{}{}",
        source.fixed_name,
        user.as_ref().map(|u| format!(", {}", u.name)).unwrap_or_default(),
        if from_plc {
            format!(
                "; {} is read from the PLC when it answers",
                source.kind.name(section).map_or("", String::as_str)
            )
        } else {
            String::new()
        }
    );
    let bind_ip = section.ipaddr_local.unwrap_or(Ipv4Addr::UNSPECIFIED);
    let bind = SocketAddr::new(IpAddr::V4(bind_ip), section.server_port);
    start_section(
        global.clone(),
        section.clone(),
        table,
        backend,
        bind,
        dir.to_path_buf(),
        Some(Tables::new(source, user, from_plc)),
    )
    .await
    .map_err(|e| format!("cannot listen on {bind}: {e}"))
}

/// The section's PLC link; `None` when it has no PLC yet (`IPADDR = 0.0.0.0`).
/// A simulated PLC's section is pointed at it (IPADDR, EPSPORT), so GETINFO
/// and SETCONF see where the PLC really is.
async fn backend_for(
    section: &mut Section,
    dir: &Path,
    server: &mut Server,
) -> Result<Option<Box<dyn PlcBackend>>, String> {
    if let Some(simulator) = section.simulator.clone() {
        if section.protocol == Protocol::ModbusTcp {
            let device = spawn_modbus_simulator(section, &simulator, dir, server).await?;
            if let std::net::IpAddr::V4(ip) = device.ip() {
                section.ipaddr = Some(ip);
            }
            section.modbus.port = device.port();
            return Ok(Some(Box::new(ModbusBackend::new(modbus_config(
                section, device, dir,
            )))));
        }
        let plc = spawn_simulator(section, &simulator, dir, server).await?;
        if let std::net::IpAddr::V4(ip) = plc.ip() {
            section.ipaddr = Some(ip);
        }
        section.epsport = plc.port();
        return Ok(Some(Box::new(EpsnetBackend::new(epsnet_config(
            section, plc,
        )))));
    }
    let backend = crate::backend::open(section, dir)?;
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
    simulator: &crate::config::Simulator,
    dir: &Path,
    server: &mut Server,
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
            server._file_stores.push(store);
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
    simulator: &crate::config::Simulator,
    config: SimConfig,
    what: &str,
    server: &mut Server,
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
    simulator: &crate::config::Simulator,
    dir: &Path,
    server: &mut Server,
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
    server._file_stores.push(store);
    Ok(addr)
}
