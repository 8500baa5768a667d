//! From a loaded configuration to running sections: choose each section's
//! backend (a PLC over EPSNET, the embedded simulated PLC, or none yet), load
//! its public files (local first, else fetched from the PLC), and start it.
//! A section that cannot start is reported and skipped; the others run.

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use tracing::{error, info, warn};

use crate::backend::epsnet::{EpsnetBackend, EpsnetConfig};
use crate::backend::PlcBackend;
use crate::config::{Config, Global, Section};
use crate::plc::MemoryMap;
use crate::pubfile::{self, PubFile};
use crate::server::{start_section, RunningSection};
use crate::sim::{self, PubSource, SimConfig, SimHandle};
use crate::vars::VarTable;

/// Largest public file fetched from a PLC.
const MAX_PUBFILE: u64 = 64 * 1024 * 1024;

/// Every section that started, and what keeps them alive.
pub struct Server {
    pub sections: Vec<RunningSection>,
    simulators: Vec<SimHandle>,
    _file_stores: Vec<tempfile::TempDir>,
}

impl Server {
    pub fn simulators(&self) -> &[SimHandle] {
        &self.simulators
    }

    /// Stops accepting and polling, lets every session answer what it has
    /// received (bounded by a grace period), then stops the simulators.
    pub async fn shutdown(self) {
        for section in &self.sections {
            section.abort();
        }
        for section in &self.sections {
            section.wait_sessions(SHUTDOWN_GRACE).await;
        }
        for simulator in self.simulators {
            simulator.stop().await;
        }
    }
}

/// Longest wait for sessions to finish at shutdown.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

/// Starts every section of `config`; fails only when none could start.
pub async fn start(config: &Config) -> Result<Server, String> {
    let global = Arc::new(config.global.clone());
    let dir = config_dir(&config.path);
    let mut server = Server {
        sections: Vec::new(),
        simulators: Vec::new(),
        _file_stores: Vec::new(),
    };
    for section in &config.sections {
        match start_one(&global, section, &dir, &mut server).await {
            Ok(running) => server.sections.push(running),
            Err(message) => error!(section = %section.name, "section not started: {message}"),
        }
    }
    if server.sections.is_empty() {
        return Err("no PLC section could start".to_string());
    }
    Ok(server)
}

/// The folder relative paths in the configuration start from.
pub fn config_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

async fn start_one(
    global: &Arc<Global>,
    section: &Section,
    dir: &Path,
    server: &mut Server,
) -> Result<RunningSection, String> {
    let mut backend = backend_for(section, dir, server).await?;
    let fixed = load_fixed(section, dir)?;
    let user = match &section.pubfile {
        Some(name) => Some(load_user(section, name, dir, backend.as_deref_mut()).await?),
        None => None,
    };
    let mut warnings = Vec::new();
    let table = VarTable::build(
        &fixed.0,
        &fixed.1,
        user.as_ref().map(|(name, file)| (name.as_str(), file)),
        &MemoryMap::FOXTROT,
        &mut warnings,
    )
    .map_err(|e| e.to_string())?;
    for warning in &warnings {
        warn!(section = %section.name, "public file {warning}");
    }
    info!(
        section = %section.name,
        variables = table.len(),
        "public files loaded: {}{}",
        fixed.0,
        user.as_ref().map(|(n, _)| format!(", {n}")).unwrap_or_default()
    );
    let bind_ip = section.ipaddr_local.unwrap_or(Ipv4Addr::UNSPECIFIED);
    let bind = SocketAddr::new(IpAddr::V4(bind_ip), section.server_port);
    start_section(global.clone(), section.clone(), table, backend, bind)
        .await
        .map_err(|e| format!("cannot listen on {bind}: {e}"))
}

/// The section's PLC link; `None` when it has no PLC yet (`IPADDR = 0.0.0.0`).
async fn backend_for(
    section: &Section,
    dir: &Path,
    server: &mut Server,
) -> Result<Option<Box<dyn PlcBackend>>, String> {
    if let Some(simulator) = &section.simulator {
        let plc = spawn_simulator(section, simulator, dir, server).await?;
        return Ok(Some(Box::new(EpsnetBackend::new(epsnet_config(
            section, plc,
        )))));
    }
    if section.serial_device.is_some() {
        return Err("serial lines (SERIAL_DEVICE) are not supported by this server".to_string());
    }
    if section.shm_name.is_some() {
        return Err("shared modules (SHM_NAME) are not supported by this server".to_string());
    }
    match section.ipaddr {
        Some(ip) if !ip.is_unspecified() => {
            let plc = SocketAddr::new(IpAddr::V4(ip), section.epsport);
            Ok(Some(Box::new(EpsnetBackend::new(epsnet_config(
                section, plc,
            )))))
        }
        _ => {
            warn!(section = %section.name, "no PLC address (IPADDR) yet: serving clients without a PLC");
            Ok(None)
        }
    }
}

fn epsnet_config(section: &Section, plc: SocketAddr) -> EpsnetConfig {
    let mut config = EpsnetConfig::new(plc);
    if let Some(local) = section.ipaddr_local {
        config.local_ip = IpAddr::V4(local);
    }
    if plc.ip().is_loopback() {
        config.local_ip = IpAddr::V4(Ipv4Addr::LOCALHOST);
    }
    config.eps_addr = section.epsaddr;
    config.timeout = section.epstout;
    config.timeout_step = section.epstout_step;
    config
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
        None => sim::DEMO_PUB.to_vec(),
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
    let program = simulator
        .program
        .parse()
        .map_err(|e| format!("SIMULATOR_PROGRAM: {e}"))?;
    let config = SimConfig {
        bind: SocketAddr::from((Ipv4Addr::LOCALHOST, 0)),
        pubfile: PubSource::Bytes(bytes),
        files: Some(store.path().to_path_buf()),
        program,
        ..SimConfig::default()
    };
    let handle = sim::spawn(config)
        .await
        .map_err(|e| format!("cannot start the simulated PLC: {e}"))?;
    let addr = handle.local_addr();
    info!(section = %section.name, plc = %addr, "simulated PLC running");
    server.simulators.push(handle);
    server._file_stores.push(store);
    Ok(addr)
}

/// The fixed public file: PUBFILE_FIXED beside the configuration, or the
/// standard one (`__PLC_RUN`, `__PF_CRC`) when the key is not set.
fn load_fixed(section: &Section, dir: &Path) -> Result<(String, PubFile), String> {
    match &section.pubfile_fixed {
        Some(name) => {
            let path = dir.join(name);
            let file = pubfile::load(&path)
                .map_err(|e| format!("fixed public file {}: {e}", path.display()))?;
            Ok((name.clone(), file))
        }
        None => Ok((
            "FIXED.pub (built in)".to_string(),
            pubfile::parse(sim::FIXED_PUB),
        )),
    }
}

/// The name a PUBFILE value has in the PLC's file system.
fn plc_path(name: &str) -> &str {
    name.trim_start_matches('/')
}

/// Where a PUBFILE value lives on this machine: `//name` in the root folder
/// (the configuration's, or the section's subfolder with PUBFILE_WRITE),
/// anything else relative to the configuration.
pub fn local_pubfile_path(section: &Section, name: &str, dir: &Path) -> PathBuf {
    let root = if section.pubfile_write {
        dir.join(&section.name)
    } else {
        dir.to_path_buf()
    };
    match name.strip_prefix("//") {
        Some(rest) => root.join(rest),
        None => dir.join(name),
    }
}

/// The user public file: the local file if there is one, else fetched from
/// the PLC (and stored locally with PUBFILE_WRITE).
async fn load_user(
    section: &Section,
    name: &str,
    dir: &Path,
    backend: Option<&mut (dyn PlcBackend + 'static)>,
) -> Result<(String, PubFile), String> {
    let local = local_pubfile_path(section, name, dir);
    if local.is_file() {
        let file =
            pubfile::load(&local).map_err(|e| format!("public file {}: {e}", local.display()))?;
        return Ok((file_name(name), file));
    }
    if name.starts_with("../") {
        return Err(format!(
            "public file {} not found (paths starting with ../ are local only)",
            local.display()
        ));
    }
    let Some(backend) = backend else {
        return Err(format!(
            "public file {} not found, and there is no PLC to fetch it from",
            local.display()
        ));
    };
    let bytes = fetch_file(backend, plc_path(name).as_bytes())
        .await
        .map_err(|e| {
            format!(
                "public file {name} is neither at {} nor readable from the PLC: {e}",
                local.display()
            )
        })?;
    info!(section = %section.name, "public file {name} fetched from the PLC ({} bytes)", bytes.len());
    if section.pubfile_write {
        if let Some(parent) = local.parent() {
            let _ = std::fs::create_dir_all(parent);
        }
        if let Err(e) = std::fs::write(&local, &bytes) {
            warn!(section = %section.name, "cannot store {}: {e}", local.display());
        }
    }
    Ok((file_name(name), pubfile::parse(&bytes)))
}

fn file_name(name: &str) -> String {
    name.rsplit(['/', '\\']).next().unwrap_or(name).to_string()
}

/// Reads a whole file from the PLC's file system.
pub async fn fetch_file(backend: &mut dyn PlcBackend, path: &[u8]) -> Result<Vec<u8>, String> {
    backend.connect().await.map_err(|e| e.to_string())?;
    let info = backend
        .file_info(path)
        .await
        .map_err(|e| e.to_string())?
        .map_err(|e| format!("the PLC answered {e}"))?;
    if info.size > MAX_PUBFILE {
        return Err(format!(
            "{} bytes is more than the {MAX_PUBFILE} accepted",
            info.size
        ));
    }
    let block = backend.max_file_block().max(1);
    let mut bytes = Vec::with_capacity(info.size as usize);
    loop {
        let chunk = backend
            .read_file(path, bytes.len() as u64, block)
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| format!("the PLC answered {e}"))?;
        let done = (chunk.len() as u32) < block;
        bytes.extend_from_slice(&chunk);
        if done || bytes.len() as u64 >= info.size {
            break;
        }
        if bytes.len() as u64 > MAX_PUBFILE {
            return Err("the file grew past the accepted size while reading".to_string());
        }
    }
    Ok(bytes)
}
