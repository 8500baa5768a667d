//! The PLC backend: the one interface through which the server touches a PLC.
//!
//! Errors come in two levels, as in tokio-modbus: the outer `Result` is the
//! link (`PlcError`: timeout, unreachable, garbage on the wire), the inner one
//! is what the device itself answered for one request (`Refusal`: an EPSNET
//! error byte, a Modbus exception). A caller cannot mistake a lost PLC for "address out of range".

pub mod epsnet;
pub mod memory;
pub mod modbus;
pub mod plugin;

use async_trait::async_trait;
use plccoms_protocol::Area;

use crate::config::Protocol;

pub use plccoms_plc::files::{
    DirEntry, FileInfo, FILE_ATTRIBUTE_ARCHIVE, FILE_ATTRIBUTE_DIRECTORY, FILE_ATTRIBUTE_HIDDEN,
    FILE_ATTRIBUTE_READONLY, FILE_ATTRIBUTE_SYSTEM,
};
pub use plccoms_plc::memory::WriteData;
pub use plccoms_plc::Refusal;

/// Pause after the first failed probe; doubles up to [`PROBE_MAX`]. The
/// defaults of [`PlcBackend::probe_backoff`], which the link's health uses.
pub const PROBE_MIN: std::time::Duration = std::time::Duration::from_millis(100);
/// Longest pause between probes: with a probe taking at most EPSTOUT plus a
/// retry, a PLC that returns is found again within about a second.
pub const PROBE_MAX: std::time::Duration = std::time::Duration::from_secs(1);

/// A block of PLC memory to read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ReadRequest {
    pub area: Area,
    pub offset: u32,
    pub len: u32,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WriteRequest {
    pub area: Area,
    pub offset: u32,
    pub data: WriteData,
}

/// The link to the PLC failed: nothing is known about what the PLC did.
#[derive(Debug, thiserror::Error)]
pub enum PlcError {
    #[error("no PLC configured")]
    NotConfigured,
    #[error("PLC does not answer: {0}")]
    Timeout(String),
    #[error("PLC link error: {0}")]
    Io(#[from] std::io::Error),
    #[error("malformed answer from PLC: {0}")]
    Protocol(String),
    #[error("the PLC refused the request: {0}")]
    Refused(Refusal),
    #[error("not supported by this backend: {0}")]
    Unsupported(&'static str),
}

impl PlcError {
    /// Whether the PLC itself is unreachable (as opposed to answering
    /// garbage or refusing a request).
    pub fn is_link_failure(&self) -> bool {
        matches!(
            self,
            PlcError::NotConfigured | PlcError::Timeout(_) | PlcError::Io(_)
        )
    }
}

/// Answer to one request inside a batch: data, or the device's refusal.
pub type Answer<T> = Result<T, Refusal>;

/// PLC run state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlcStatus {
    pub run: bool,
}

/// One PLC, reached some way. The server owns one per PLC section, driven by
/// one task (the section's link), so methods take `&mut self`.
#[async_trait]
pub trait PlcBackend: Send {
    /// Where the PLC is, for logs and GETINFO (e.g. `127.0.0.1:61682`).
    fn describe(&self) -> String;

    /// The link's own address on the PLC's network (EPSNET source address),
    /// for GETINFO.
    fn source_address(&self) -> Option<u8> {
        None
    }

    /// Largest block one memory read request of `area` may carry; the
    /// poller plans around it.
    fn max_read_block(&self, area: Area) -> u32;

    /// Widest run of unwanted bytes of `area` a read may span to join two
    /// wanted ranges; `None`: any within the block limit.
    fn read_gap(&self, _area: Area) -> Option<u32> {
        None
    }

    /// Reads of `area` start and end on multiples of this many bytes.
    fn read_align(&self, _area: Area) -> u32 {
        1
    }

    /// Pause after the first failed connection attempt of an outage, and
    /// the longest it doubles to (see `link::health`).
    fn probe_backoff(&self) -> (std::time::Duration, std::time::Duration) {
        (PROBE_MIN, PROBE_MAX)
    }

    /// Largest block one file read or write request may carry.
    fn max_file_block(&self) -> u32;

    /// How long the PLC has to answer one request (EPSTOUT): the freshness
    /// bound of polled values and the longest a SET may wait to be sent
    /// build on it.
    fn answer_timeout(&self) -> std::time::Duration {
        std::time::Duration::from_secs(1)
    }

    /// Where to count requests, retries, timeouts, errors and round trips
    /// (the section's, kept across new links).
    fn set_counters(&mut self, _counters: std::sync::Arc<crate::metrics::BackendCounters>) {}

    /// (Re)initialise the link and return the PLC's identification string.
    async fn connect(&mut self) -> Result<String, PlcError>;

    /// Read every block; answers come back in request order. The backend packs
    /// and splits requests as its transport allows.
    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError>;

    /// Write every block, in order; answers in request order.
    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError>;

    async fn status(&mut self) -> Result<PlcStatus, PlcError>;

    // File services. A backend without a file system (a Modbus device)
    // keeps the defaults: "service not activated", as from a PLC without one.

    /// Information about a file or directory in the PLC.
    async fn file_info(&mut self, _path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        Ok(Err(Refusal::NOT_ACTIVATED))
    }

    /// Up to `len` (at most `max_file_block`) bytes of a file from `offset`;
    /// fewer at its end.
    async fn read_file(
        &mut self,
        _path: &[u8],
        _offset: u64,
        _len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        Ok(Err(Refusal::NOT_ACTIVATED))
    }

    /// Write a block (at most `max_file_block` bytes; the link splits
    /// uploads) of a file. The PLC commits the file only when `last` is
    /// set; a write at offset 0 starts the file anew.
    async fn write_file(
        &mut self,
        _path: &[u8],
        _offset: u64,
        _data: &[u8],
        _last: bool,
    ) -> Result<Answer<()>, PlcError> {
        Ok(Err(Refusal::NOT_ACTIVATED))
    }

    async fn write_file_info(
        &mut self,
        _path: &[u8],
        _info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        Ok(Err(Refusal::NOT_ACTIVATED))
    }

    async fn list_dir(&mut self, _path: &[u8]) -> Result<Answer<Vec<DirEntry>>, PlcError> {
        Ok(Err(Refusal::NOT_ACTIVATED))
    }
}

/// Adds a page of a directory listing to `all`; `Ok(true)` when the
/// listing is complete. A page announcing more but bringing nothing would
/// page for ever: an error.
pub(crate) fn add_dir_page(
    all: &mut Vec<DirEntry>,
    entries: Vec<DirEntry>,
    more: bool,
) -> Result<bool, PlcError> {
    let empty = entries.is_empty();
    all.extend(entries);
    if more && empty {
        return Err(PlcError::Protocol(
            "empty directory page announcing more".into(),
        ));
    }
    Ok(!more)
}

/// A section's backend, `None` when it has no PLC yet; or why it cannot be
/// made.
pub type Opened = Result<Option<Box<dyn PlcBackend>>, String>;

/// The backend of a section, chosen by its `PROTOCOL` key; `dir` is the
/// configuration's folder (where relative file names start). A new backend
/// is a module, a variant of [`Protocol`] and its arm here.
pub fn open(section: &crate::config::Section, dir: &std::path::Path) -> Opened {
    match section.protocol {
        Protocol::Epsnet => open_epsnet(section, dir),
        Protocol::ModbusTcp => open_modbus(section, dir),
    }
}

/// Modbus TCP to `IPADDR:MODBUS_PORT`, or `None` when the section has no
/// device yet (`IPADDR` unset or `0.0.0.0`).
fn open_modbus(section: &crate::config::Section, dir: &std::path::Path) -> Opened {
    use std::net::{IpAddr, SocketAddr};
    if section.serial_device.is_some() || section.shm_name.is_some() {
        return Err(
            "PROTOCOL = MODBUS_TCP runs over TCP: SERIAL_DEVICE and SHM_NAME do not apply"
                .to_string(),
        );
    }
    match section.ipaddr {
        Some(ip) if !ip.is_unspecified() => {
            let device = SocketAddr::new(IpAddr::V4(ip), section.modbus.port);
            Ok(Some(Box::new(modbus::ModbusBackend::new(modbus_config(
                section, device, dir,
            )))))
        }
        _ => Ok(None),
    }
}

/// Modbus settings from a section's keys, for a device at `device`.
pub fn modbus_config(
    section: &crate::config::Section,
    device: std::net::SocketAddr,
    dir: &std::path::Path,
) -> modbus::ModbusConfig {
    let mut config = modbus::ModbusConfig::new(device);
    config.local_ip = section.ipaddr_local.map(std::net::IpAddr::V4);
    if device.ip().is_loopback() {
        config.local_ip = None;
    }
    config.unit = section.modbus.unit;
    config.timeout = section.modbus.timeout;
    config.limits = modbus::layout::DeviceLimits {
        max_regs: section.modbus.max_regs,
        max_bits: section.modbus.max_bits,
    };
    config.gap = section.modbus.gap;
    config.inflight = usize::from(section.modbus.inflight);
    config.tags = section
        .modbus
        .tags
        .as_deref()
        .map(|name| section.path_of(dir, name));
    config
}

/// A section's link: the backend plugin `SHM_NAME` when set (the vendor's
/// shared module), else EPSNET on the serial line `SERIAL_DEVICE` when set,
/// else over UDP to `IPADDR:EPSPORT`; `None` when the section has no PLC yet
/// (`IPADDR` unset or `0.0.0.0`). Nothing is opened here: the link opens
/// its socket or device when it connects, and again after each loss.
fn open_epsnet(section: &crate::config::Section, dir: &std::path::Path) -> Opened {
    use std::net::{IpAddr, SocketAddr};
    if let Some(library) = &section.shm_name {
        // A path starts from the configuration's folder, as every path key;
        // a bare name is the dynamic loader's to find.
        let library = if library.contains('/') {
            section.path_of(dir, library).to_string_lossy().into_owned()
        } else {
            library.clone()
        };
        let config = plugin::PluginConfig::from_section(section, &library);
        return Ok(Some(Box::new(plugin::PluginBackend::new(config))));
    }
    if let Some(device) = &section.serial_device {
        let config = serial_config(section, device);
        return Ok(Some(Box::new(epsnet::SerialBackend::new(config))));
    }
    match section.ipaddr {
        Some(ip) if !ip.is_unspecified() => {
            let plc = SocketAddr::new(IpAddr::V4(ip), section.epsport);
            Ok(Some(Box::new(epsnet::EpsnetBackend::new(epsnet_config(
                section, plc,
            )))))
        }
        _ => Ok(None),
    }
}

/// EPSNET serial settings from a section's keys, for the line `device`.
pub fn serial_config(section: &crate::config::Section, device: &str) -> epsnet::SerialConfig {
    let mut config = epsnet::SerialConfig::new(device);
    config.speed = section.serial_speed.unwrap_or(config.speed);
    config.rts = epsnet::serial::rts_of(
        device,
        section.serial_rts,
        section.serial_device_cfg.as_deref().unwrap_or_default(),
    );
    config.timing.eps_addr = section.epsaddr;
    config.timing.timeout = section.epstout;
    config.timing.timeout_step = section.epstout_step;
    config
}

/// EPSNET settings from a section's keys, for a PLC at `plc`.
pub fn epsnet_config(
    section: &crate::config::Section,
    plc: std::net::SocketAddr,
) -> epsnet::EpsnetConfig {
    use std::net::{IpAddr, Ipv4Addr};
    let mut config = epsnet::EpsnetConfig::new(plc);
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
