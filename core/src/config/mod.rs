//! The ini file (`PLCComS.ini`): global settings in `[*]`, then one section per
//! PLC.
//!
//! Every key is a row of one table ([`keys()`], in `keys.rs`): its scope,
//! default, kind of value and range, the field it sets and its SETCONF name.
//! The file is read by a line scan of our own (`ini.rs`), which pairs every
//! key with its line, and rust-ini for quotes.
//!
//! Keys are case-insensitive; booleans are `Yes`/`No`, `True`/`False`,
//! `On`/`Off` or `1`/`0` in any case ([`parse_bool`]); numbers are decimal;
//! an empty value leaves the key at its default. Problems are
//! [`Diagnostic`]s (`diag.rs`) naming file and line, all of them reported at
//! once: an unknown key is a warning (with the key it is probably a typo
//! of); a bad value in `[*]` stops start-up ([`ConfigError::Invalid`]); a bad
//! value in a PLC section skips that section and the others load.
//!
//! `SIMULATOR = Yes` (with `SIMULATOR_PROGRAM` and `SIMULATOR_PUB`) is this
//! project's addition: the section is served by a simulated PLC inside the
//! server instead of a real one.

mod broker;
mod diag;
pub mod history;
mod ini;
mod keys;
mod mqtt;
mod opcua;
mod protocol;
pub mod serial;
#[cfg(test)]
mod tests;

use std::collections::HashMap;
use std::fmt;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr};
use std::path::{Path, PathBuf};
use std::time::Duration;

pub use broker::BrokerUrl;
pub use diag::{Diagnostic, Severity};
pub use history::{History, Retention, StampPair};
pub use keys::{
    global_keys, key, keys, parse_bool, parse_ipv4, section_keys, setconf_key, ConfiguredPath, Key,
    Kind, PathUse, Scope, SetConfScope, Value, PROTOCOLS, SIMULATOR_PROGRAMS,
};

use diag::Diags;
use ini::{Entry, RawSection};
use keys::Settings;
pub use mqtt::{check_prefix, split_masks, MqttFormat, MqttGlobal, MqttSection, MQTT_FORMATS};
pub use opcua::{OpcuaGlobal, OpcuaSection, OPCUA_SECURITY_CHOICES};
pub use protocol::Protocol;
pub use serial::DevicePin;

/// A loaded ini file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Config {
    /// The file it was loaded from.
    pub path: PathBuf,
    pub global: Global,
    /// The PLC sections that loaded, in file order.
    pub sections: Vec<Section>,
}

/// The folder relative paths in the configuration start from: the
/// configuration file's.
pub fn config_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// The folder systemd gives the service for its state (`StateDirectory=` in
/// the shipped unit: `/var/lib/plccoms`), when it runs under systemd.
pub fn systemd_state_dir() -> Option<PathBuf> {
    std::env::var_os("STATE_DIRECTORY")
        .and_then(|dirs| std::env::split_paths(&dirs).next())
        .filter(|d| d.is_absolute())
}

/// Where a relative path of a key the server writes (HISTORY_DIR,
/// MQTT_SPOOL) starts: the state directory under systemd, where the
/// configuration's folder (`/etc/plccoms`) is read-only; else the
/// configuration's folder, for a server run by hand.
pub fn state_dir(config_path: &Path) -> PathBuf {
    systemd_state_dir().unwrap_or_else(|| config_dir(config_path))
}

/// A file or folder the configuration names, where it is on this machine.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OwnPath {
    /// The key that names it, and its section (`None`: `[*]`).
    pub key: &'static str,
    pub section: Option<String>,
    pub path: PathBuf,
    pub used: PathUse,
}

impl Config {
    /// Every file and folder the configuration names through a path key
    /// ([`Kind::Path`]), defaults included, resolved as the server's parts
    /// resolve them; and the history folder, which has a computed default.
    /// FILES_ROOT, the clients' own folder, is not among them.
    pub fn own_paths(&self) -> Vec<OwnPath> {
        let dir = config_dir(&self.path);
        let state = state_dir(&self.path);
        let mut own = Vec::new();
        let mut add = |key, section: Option<&Section>, path, used| {
            if used != PathUse::ClientFiles {
                own.push(OwnPath {
                    key,
                    section: section.map(|s| s.name.clone()),
                    path,
                    used,
                });
            }
        };
        for p in &self.global.paths {
            let base = if p.used == PathUse::State {
                &state
            } else {
                &dir
            };
            add(p.key, None, base.join(&p.text), p.used);
        }
        add(
            "HISTORY_DIR",
            None,
            self.global.history_dir(&state),
            PathUse::State,
        );
        for section in &self.sections {
            for p in &section.paths {
                add(p.key, Some(section), section.path_of(&dir, &p.text), p.used);
            }
        }
        own
    }
}

impl Global {
    /// The history folder: HISTORY_DIR, relative to `dir` (the state
    /// folder, [`state_dir`]), by default `history` there.
    pub fn history_dir(&self, dir: &Path) -> PathBuf {
        dir.join(self.history_dir.as_deref().unwrap_or("history"))
    }
}

impl Section {
    /// Where a file name of this section's keys lives on this machine:
    /// `//name` in the root folder (`dir`, the configuration's, or the
    /// section's subfolder of it with PUBFILE_WRITE), anything else relative
    /// to `dir` (an absolute path as it is).
    pub fn path_of(&self, dir: &Path, name: &str) -> PathBuf {
        match name.strip_prefix("//") {
            Some(rest) if self.pubfile_write => dir.join(&self.name).join(rest),
            Some(rest) => dir.join(rest),
            None => dir.join(name),
        }
    }
}

/// The `[*]` section.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Global {
    pub comm_loop_delay: Duration,
    pub comm_sched_pri: u8,
    pub net_connect_max: usize,
    pub mem_blksize: usize,
    pub mem_use_threads: bool,
    pub ffile_blksize: usize,
    pub ffile_timeout: Duration,
    pub ffile_timeout_wr: Duration,
    pub ffile_maxrecs: usize,
    pub end_line_crlf: bool,
    pub pf_var_disabled: bool,
    pub diff_var_enabled: bool,
    pub sync_var_enabled: bool,
    pub date_time_decimal: bool,
    pub lim_of_decimals: bool,
    pub num_of_decimals: u8,
    pub scient_notation: bool,
    /// `SERIAL_DEVICE_CFG`, parsed.
    pub serial_device_cfg: Option<Vec<DevicePin>>,
    /// OUTPUT_HARD_LIMIT: output queued for one client, in bytes, beyond
    /// which it is disconnected at once (this server's own key).
    pub output_hard_limit: usize,
    /// OUTPUT_SOFT_LIMIT: output queued for one client, in bytes, that it may
    /// hold only for OUTPUT_SOFT_TIMEOUT; DIFF lines wait (coalesced) while
    /// it is reached.
    pub output_soft_limit: usize,
    /// OUTPUT_SOFT_TIMEOUT.
    pub output_soft_timeout: Duration,
    /// FILES_ROOT: the folder of PC files (relative to the configuration's
    /// folder); `None`: the configuration's folder, as PLCComS.
    pub files_root: Option<PathBuf>,
    /// FILES_QUOTA: bytes clients may fill the files root to with WRITEFILE
    /// (`None`: see [`crate::files_quota::default_quota`]).
    pub files_quota: Option<u64>,
    /// The built-in web page (src/web): HTTP_PORT (`None` = off),
    /// HTTP_BIND, HTTP_TOKEN, and TLS with HTTP_CERT and HTTP_KEY (paths
    /// relative to the configuration's folder).
    pub http_port: Option<u16>,
    pub http_bind: IpAddr,
    pub http_token: Option<String>,
    /// HTTP_HOSTS: more names the page answers to (lower case).
    pub http_hosts: Vec<String>,
    pub http_cert: Option<String>,
    pub http_key: Option<String>,
    /// HISTORY_DIR as written; `None`: `history` beside the configuration.
    pub history_dir: Option<String>,
    pub history_retention: Retention,
    /// HISTORY_SYNC: time between durable commits of the history.
    pub history_sync: Duration,
    /// HISTORY_COMPACT: age at which samples are packed (zero: never).
    pub history_compact: Duration,
    /// HISTORY_QUERY_TIMEOUT: the longest a `/api/history` answer may take.
    pub history_query_timeout: Duration,
    /// The MQTT_* keys (this server's own).
    pub mqtt: MqttGlobal,
    /// The OPCUA_* keys (this server's own).
    pub opcua: OpcuaGlobal,
    /// Every path a `[*]` key names ([`Kind::Path`]), for [`Config::own_paths`].
    pub paths: Vec<ConfiguredPath>,
}

impl Default for Global {
    /// The defaults of the table of keys.
    fn default() -> Self {
        keys::with_defaults(Global {
            // Placeholders: every field is set by its key's default.
            comm_loop_delay: Duration::ZERO,
            comm_sched_pri: 0,
            net_connect_max: 0,
            mem_blksize: 0,
            mem_use_threads: false,
            ffile_blksize: 0,
            ffile_timeout: Duration::ZERO,
            ffile_timeout_wr: Duration::ZERO,
            ffile_maxrecs: 0,
            end_line_crlf: false,
            pf_var_disabled: false,
            diff_var_enabled: false,
            sync_var_enabled: false,
            date_time_decimal: false,
            lim_of_decimals: false,
            num_of_decimals: 0,
            scient_notation: false,
            serial_device_cfg: None,
            output_hard_limit: 0,
            output_soft_limit: 0,
            output_soft_timeout: Duration::ZERO,
            files_root: None,
            files_quota: None,
            http_port: None,
            http_bind: IpAddr::V4(Ipv4Addr::LOCALHOST),
            http_token: None,
            http_hosts: Vec::new(),
            http_cert: None,
            http_key: None,
            history_dir: None,
            history_retention: Retention::default(),
            history_sync: Duration::ZERO,
            history_compact: Duration::ZERO,
            history_query_timeout: Duration::ZERO,
            mqtt: MqttGlobal::default(),
            opcua: OpcuaGlobal::default(),
            paths: Vec::new(),
        })
    }
}

/// A PLC section.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Section {
    /// The section name as written (used in log entries and as the folder for
    /// `PUBFILE_WRITE = Yes`).
    pub name: String,
    /// The PLC's address; `Some(0.0.0.0)` means "no PLC yet, wait for
    /// `SETCONF:ipaddr`". `None` when the key is absent (serial, shared module
    /// or simulator sections).
    pub ipaddr: Option<Ipv4Addr>,
    pub ipaddr_local: Option<Ipv4Addr>,
    /// EPSNET source address; `None` = chosen automatically.
    pub epsaddr: Option<u8>,
    pub epstout: Duration,
    pub epstout_step: Duration,
    pub epsport: u16,
    pub server_port: u16,
    pub serial_device: Option<String>,
    pub serial_speed: Option<u32>,
    pub serial_rts: Option<u32>,
    /// SERIAL_PARITY, SERIAL_DATA_BITS, SERIAL_STOP_BITS (MODBUS_RTU).
    pub serial_parity: Option<serial::Parity>,
    pub serial_data_bits: Option<u8>,
    pub serial_stop_bits: Option<u8>,
    pub shm_name: Option<String>,
    pub shm_socket: Option<u32>,
    pub shm_port: Option<u32>,
    /// `[*] SERIAL_DEVICE_CFG`, which every section inherits: the RTS GPIO
    /// pin of each serial device.
    pub serial_device_cfg: Option<Vec<DevicePin>>,
    pub pubfile_crc: bool,
    pub pubfile_write: bool,
    pub pubfile: Option<String>,
    pub pubfile_fixed: Option<String>,
    /// `PROTOCOL`: the backend.
    pub protocol: Protocol,
    /// Set when `SIMULATOR = Yes`.
    pub simulator: Option<Simulator>,
    /// `ALLOW`: the client addresses and networks admitted; `None` admits
    /// every client, as PLCComS does (this server's own key).
    pub allow: Option<Vec<Network>>,
    /// `READ_ONLY = Yes`: requests that would change the PLC or the section
    /// answer ERROR:30 (this server's own key).
    pub read_only: bool,
    /// `TRACE = Yes`: the section's frame trace is on from the start
    /// (`SETCONF:trace` switches it at run time; see `crate::trace`).
    pub trace: bool,
    /// `SETCONF_KEYS`: the SETCONF names clients may use; `None`: all.
    pub setconf_keys: Option<Vec<&'static str>>,
    /// `HISTORY*`: what the historian records (this server's own keys).
    pub history: History,
    /// The MQTT_* keys (this server's own).
    pub mqtt: MqttSection,
    /// The OPCUA_* keys (this server's own).
    pub opcua: OpcuaSection,
    /// The `MODBUS_*` keys (a Modbus `PROTOCOL`).
    pub modbus: Modbus,
    /// The `S7_*` keys (`PROTOCOL = S7`).
    pub s7: S7,

    /// The `ADS_*` keys (`PROTOCOL = ADS`).
    pub ads: Ads,
    /// The OPC UA client's `OPCUA_*` keys (`PROTOCOL = OPCUA`).
    pub opcua_client: OpcuaClient,
    /// Every path the section's keys name ([`Kind::Path`]), for
    /// [`Config::own_paths`].
    pub paths: Vec<ConfiguredPath>,
}

/// An address or CIDR network of `ALLOW`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Network {
    /// The network address (host bits cleared).
    pub addr: IpAddr,
    /// Leading bits that must match: 32 (IPv4) or 128 (IPv6) for a single
    /// address.
    pub prefix: u8,
}

impl Network {
    /// `a.b.c.d`, `a.b.c.d/n`, an IPv6 address, or `ipv6/n`.
    pub fn parse(text: &str) -> Option<Network> {
        let (addr, prefix) = match text.split_once('/') {
            Some((addr, prefix)) => (addr.trim(), Some(prefix.trim())),
            None => (text.trim(), None),
        };
        let addr = match parse_ipv4(addr) {
            Some(v4) => IpAddr::V4(v4),
            None => IpAddr::V6(addr.parse::<Ipv6Addr>().ok()?),
        };
        let max = if addr.is_ipv4() { 32 } else { 128 };
        let prefix = match prefix {
            None => max,
            Some(p) if !p.is_empty() && p.len() <= 3 && p.bytes().all(|b| b.is_ascii_digit()) => {
                p.parse::<u8>().ok().filter(|&n| n <= max)?
            }
            Some(_) => return None,
        };
        let addr = match addr {
            IpAddr::V4(a) => IpAddr::V4(Ipv4Addr::from(u32::from(a) & mask32(prefix))),
            IpAddr::V6(a) => IpAddr::V6(Ipv6Addr::from(u128::from(a) & mask128(prefix))),
        };
        Some(Network { addr, prefix })
    }

    /// Whether `peer` is in this network. An IPv4 client seen on an IPv6
    /// socket (`::ffff:a.b.c.d`) counts as its IPv4 address.
    pub fn contains(&self, peer: IpAddr) -> bool {
        let peer = match peer {
            IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(peer, IpAddr::V4),
            v4 => v4,
        };
        match (self.addr, peer) {
            (IpAddr::V4(net), IpAddr::V4(p)) => {
                u32::from(p) & mask32(self.prefix) == u32::from(net)
            }
            (IpAddr::V6(net), IpAddr::V6(p)) => {
                u128::from(p) & mask128(self.prefix) == u128::from(net)
            }
            _ => false,
        }
    }
}

impl fmt::Display for Network {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.addr, self.prefix)
    }
}

fn mask32(prefix: u8) -> u32 {
    u32::MAX.checked_shl(32 - u32::from(prefix)).unwrap_or(0)
}

fn mask128(prefix: u8) -> u128 {
    u128::MAX.checked_shl(128 - u32::from(prefix)).unwrap_or(0)
}

/// Whether `allow` (a section's ALLOW) admits `peer`.
pub fn allowed(allow: Option<&[Network]>, peer: IpAddr) -> bool {
    allow.is_none_or(|nets| nets.iter().any(|n| n.contains(peer)))
}

/// A simulated PLC that serves the section (`SIMULATOR = Yes`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Simulator {
    /// `SIMULATOR_PROGRAM`: `demo` (default) or `idle`, lower case.
    pub program: String,
    /// `SIMULATOR_PUB`: the public file the simulated PLC serves.
    pub pubfile: Option<String>,
}

/// The settings of a Modbus TCP section (`MODBUS_*`); the key table sets
/// every field's default.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Modbus {
    /// `MODBUS_PORT`: the device's TCP port.
    pub port: u16,
    /// `MODBUS_UNIT`: the unit id in every request.
    pub unit: u8,
    /// `MODBUS_TAGS`: the tag file (path rules as PUBFILE).
    pub tags: Option<String>,
    /// `MODBUS_TIMEOUT`: how long a transaction may take.
    pub timeout: Duration,
    /// `MODBUS_MAX_REGS`: registers one read may ask for.
    pub max_regs: u16,
    /// `MODBUS_MAX_BITS`: coils or inputs one read may ask for.
    pub max_bits: u16,
    /// `MODBUS_GAP`: unwanted registers a read may span to join two blocks.
    pub gap: u16,
    /// `MODBUS_INFLIGHT`: transactions in flight at once.
    pub inflight: u8,
}

/// The settings of a Siemens S7 section (`S7_*`); the key table sets every
/// field's default.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct S7 {
    /// `S7_PORT`: the CPU's ISO-on-TCP port.
    pub port: u16,
    /// `S7_RACK`, `S7_SLOT`: where the CPU sits (its remote TSAP).
    pub rack: u8,
    pub slot: u8,
    /// `S7_TSAP`: local and remote TSAP, instead of rack and slot; `None`
    /// also when the value is not two hex words (an error on load).
    pub tsap: Option<(u16, u16)>,
    /// `S7_PDU`: the PDU size asked for.
    pub pdu: u16,
    /// `S7_TAGS`: the tag file (path rules as PUBFILE).
    pub tags: Option<String>,
    /// `S7_TIMEOUT`: how long one request may take.
    pub timeout: Duration,
}

impl S7 {
    /// `0100/0200` (or `01.00/02.00`, as TIA Portal shows TSAPs): local and
    /// remote TSAP.
    pub fn parse_tsap(text: &str) -> Option<(u16, u16)> {
        let word = |t: &str| {
            let hex: String = t.trim().chars().filter(|&c| c != '.').collect();
            (hex.len() == 4)
                .then(|| u16::from_str_radix(&hex, 16).ok())
                .flatten()
        };
        let (local, remote) = text.split_once('/')?;
        Some((word(local)?, word(remote)?))
    }
}

/// The settings of a Beckhoff ADS section (`ADS_*`); the key table sets
/// every field's default. Net IDs are checked here and parsed by the driver.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Ads {
    /// `ADS_NET_ID`: the PLC's AMS Net ID; `None`: IPADDR and `.1.1`.
    pub net_id: Option<String>,
    /// `ADS_PORT`: the PLC runtime's ADS port (851 TwinCAT 3, 801 TwinCAT 2).
    pub port: u16,
    /// `ADS_SOURCE_NET_ID`: ours, as the PLC's route names it; `None`: the
    /// connection's local address and `.1.1`.
    pub source_net_id: Option<String>,
    /// `ADS_TCP_PORT`: the AMS/TCP port (48898; another for a test server).
    pub tcp_port: u16,
    /// `ADS_TIMEOUT`: how long one request may take.
    pub timeout: Duration,
    /// `ADS_NOTIFY`: masks of the variables that come by device notification.
    pub notify: Vec<String>,
    /// `ADS_CYCLE`: the PLC's check cycle for notifications.
    pub cycle: Duration,
    /// `ADS_TAGS`: a tag file naming the variables instead of the PLC's
    /// symbol table (path rules as PUBFILE).
    pub tags: Option<String>,
}

/// The name the symbol table of an ADS section is served under (LIST,
/// GETINFO, PUBFILE_WRITE's copy).
pub const ADS_SYMBOLS: &str = "ADS_SYMBOLS.pub";
/// The `OPCUA_*` keys of a PLC section: the OPC UA client's settings
/// (checked by the OPC UA driver when it opens the section).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct OpcuaClient {
    /// `OPCUA_URL`: the server's endpoint.
    pub url: Option<String>,
    /// `OPCUA_SECURITY`: `None` or `mode:policy`.
    pub security: String,
    /// `OPCUA_USER`, `OPCUA_PASSWORD`: anonymous when unset.
    pub user: Option<String>,
    pub password: Option<String>,
    /// `OPCUA_PKI`: the client's certificate store.
    pub pki: Option<String>,
    /// `OPCUA_BROWSE`: node ids to browse from.
    pub browse: Option<String>,
    /// `OPCUA_TAGS`: the tag file (path rules as PUBFILE).
    pub tags: Option<String>,
    /// `OPCUA_MODE = subscribe` (else read).
    pub subscribe: bool,
    /// `OPCUA_TIMEOUT`: how long one request may take.
    pub timeout: Duration,
    /// `OPCUA_REBROWSE`: how often the variables are looked for again.
    pub rebrowse: Duration,
    /// `OPCUA_WRITE_SESSION`: SETs on a session of their own.
    pub write_session: bool,
    /// `OPCUA_SESSION_ITEMS`: monitored items one session holds; more go
    /// on further sessions (0: no limit).
    pub session_items: usize,
}

/// `OPCUA_MODE` choices.
pub const OPCUA_MODES: [&str; 2] = ["subscribe", "read"];

/// A loaded file with the warnings and skipped-section errors found on the way.
#[derive(Debug, Clone)]
pub struct Loaded {
    pub config: Config,
    pub diagnostics: Vec<Diagnostic>,
    /// Every section as written (`[*]` included), for telling what a
    /// reload changed.
    pub written: Vec<Written>,
}

/// A section's keys as written: the value that counts (the last) of each
/// key, keys upper-case and sorted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Written {
    pub name: String,
    pub keys: std::collections::BTreeMap<String, String>,
}

impl Loaded {
    /// The keys of section `name` as written (`*`: the global section).
    pub fn written(&self, name: &str) -> Option<&Written> {
        self.written.iter().find(|w| w.name == name)
    }

    /// Whether a problem made the loader skip something (a section, a
    /// key's value): such a file is used at start, its good sections
    /// running, but a reload refuses it whole.
    pub fn has_errors(&self) -> bool {
        self.diagnostics
            .iter()
            .any(|d| d.severity == Severity::Error)
    }
}

/// The keys whose values differ between `old` and `new` (added and removed
/// keys included), sorted.
pub fn changed_keys(old: &Written, new: &Written) -> Vec<String> {
    let mut keys: Vec<String> = old
        .keys
        .iter()
        .filter(|(k, v)| new.keys.get(*k) != Some(v))
        .map(|(k, _)| k.clone())
        .chain(
            new.keys
                .keys()
                .filter(|k| !old.keys.contains_key(*k))
                .cloned(),
        )
        .collect();
    keys.sort();
    keys
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file cannot be used: a bad `[*]` section, a missing `[*]`, or a line
    /// that is not ini syntax there. Start-up stops. `diagnostics` holds every
    /// problem found in the file, in line order, at least one an error.
    #[error("{}: the configuration cannot be used (an error in [*] or outside the PLC sections)", path.display())]
    Invalid {
        path: PathBuf,
        diagnostics: Vec<Diagnostic>,
    },
    /// No PLC section loaded; `diagnostics` holds every problem found, in line
    /// order.
    #[error("{}: no usable PLC section (at least one section besides [*], with a SERVER_PORT, is needed)", path.display())]
    NoSections {
        path: PathBuf,
        diagnostics: Vec<Diagnostic>,
    },
}

impl ConfigError {
    /// Every problem found in the file, in line order; none for
    /// [`ConfigError::Io`].
    pub fn diagnostics(&self) -> &[Diagnostic] {
        match self {
            ConfigError::Io { .. } => &[],
            ConfigError::Invalid { diagnostics, .. }
            | ConfigError::NoSections { diagnostics, .. } => diagnostics,
        }
    }
}

/// `1 error`, `3 errors`.
fn count_errors(n: usize) -> String {
    format!("{n} error{}", if n == 1 { "" } else { "s" })
}

/// Reads and parses an ini file. Text that is not UTF-8 is decoded lossily;
/// a value or section name that lost characters that way gets a warning.
pub fn load(path: &Path) -> Result<Loaded, ConfigError> {
    let bytes = std::fs::read(path).map_err(|source| ConfigError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let text = String::from_utf8_lossy(&bytes);
    parse(path, &text)
}

/// Parses ini text; `path_for_messages` goes into [`Config::path`] and every
/// diagnostic. Every section is read even when an earlier one failed, so that
/// every problem of the file is reported at once.
pub fn parse(path_for_messages: &Path, text: &str) -> Result<Loaded, ConfigError> {
    let mut diags = Diags::new(path_for_messages);
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let invalid = |mut diagnostics: Vec<Diagnostic>| {
        diagnostics.sort_by_key(|d| d.line);
        ConfigError::Invalid {
            path: path_for_messages.to_path_buf(),
            diagnostics,
        }
    };
    let raw = match ini::read(text, &mut diags) {
        Ok(raw) => raw,
        Err(d) => {
            diags.list.push(d);
            return Err(invalid(diags.list));
        }
    };
    // Whether start-up stops: a problem outside the PLC sections.
    let mut unusable = !raw.errors.is_empty();
    diags.list.extend(raw.errors);

    // [*]: exactly one, and it must be clean.
    let mut global = None;
    let mut global_line = 0;
    for section in raw.sections.iter().filter(|s| s.name == "*") {
        if global.is_some() {
            diags.push(
                Severity::Error,
                section.line,
                format!("second [*] section (the first is on line {global_line})"),
            );
            unusable = true;
            continue;
        }
        global_line = section.line;
        let mut errors = section.errors.clone();
        global = Some(read_global(section, &mut diags, &mut errors));
        unusable |= !errors.is_empty();
        diags.list.extend(errors);
    }
    if global.is_none() {
        diags.push(
            Severity::Error,
            1,
            "the mandatory [*] section is missing".to_string(),
        );
        unusable = true;
    }

    let mut sections: Vec<Section> = Vec::new();
    let mut names: HashMap<String, usize> = HashMap::new();
    let mut ports: HashMap<u16, (String, usize)> = HashMap::new();
    for raw in raw.sections.iter().filter(|s| s.name != "*") {
        let mut errors = raw.errors.clone();
        if let Some(first) = names.get(&raw.name.to_lowercase()) {
            errors.push(diags.make(
                Severity::Error,
                raw.line,
                format!(
                    "duplicate section [{}] (the first is on line {first})",
                    raw.name
                ),
            ));
        }
        let section = read_section(raw, &mut diags, &mut errors);
        if let Some(section) = &section {
            if let Some((other, line)) = ports.get(&section.server_port) {
                errors.push(diags.make(
                    Severity::Error,
                    line_of(raw, "SERVER_PORT"),
                    format!(
                        "SERVER_PORT = {} is already used by section [{other}] (line {line})",
                        section.server_port
                    ),
                ));
            }
        }
        match section {
            Some(section) if errors.is_empty() => {
                names.insert(raw.name.to_lowercase(), raw.line);
                ports.insert(section.server_port, (section.name.clone(), raw.line));
                sections.push(section);
            }
            _ => {
                diags.push(
                    Severity::Error,
                    raw.line,
                    format!(
                        "section [{}] skipped ({})",
                        raw.name,
                        count_errors(errors.len())
                    ),
                );
                diags.list.extend(errors);
            }
        }
    }
    let path = path_for_messages.to_path_buf();
    let (Some(global), false) = (global, unusable) else {
        return Err(invalid(diags.list));
    };
    for section in &mut sections {
        section.serial_device_cfg = global.serial_device_cfg.clone();
    }
    diags.list.sort_by_key(|d| d.line);
    if sections.is_empty() {
        return Err(ConfigError::NoSections {
            path,
            diagnostics: diags.list,
        });
    }
    let written = raw
        .sections
        .iter()
        .map(|section| Written {
            name: section.name.clone(),
            keys: section
                .entries
                .iter()
                .map(|e| (e.key.clone(), e.value.clone()))
                .collect(),
        })
        .collect();
    Ok(Loaded {
        config: Config {
            path,
            global,
            sections,
        },
        diagnostics: diags.list,
        written,
    })
}

/// The line of the key's last entry (the one that counts), else of the
/// section header.
fn line_of(section: &RawSection, key: &str) -> usize {
    section
        .entries
        .iter()
        .rev()
        .find(|e| e.key == key)
        .map_or(section.line, |e| e.line)
}

/// Reads one section's entries: checks for duplicates, unknown keys and
/// non-UTF-8 text, and returns the value each key of `scope` ends up with.
fn collect<'e>(
    section: &'e RawSection,
    scope: Scope,
    diags: &mut Diags<'_>,
) -> HashMap<&'e str, &'e Entry> {
    let mut map: HashMap<&str, &Entry> = HashMap::new();
    if section.name.contains('\u{fffd}') {
        diags.push(
            Severity::Warning,
            section.line,
            format!("section name [{}] is not valid UTF-8 text", section.name),
        );
    }
    let other = match scope {
        Scope::Global => Scope::Section,
        Scope::Section => Scope::Global,
    };
    for entry in &section.entries {
        let key = entry.key.as_str();
        if keys::key(scope, key).is_none() {
            let (name, value) = (&section.name, &entry.value);
            let message = if keys::key(other, key).is_some() {
                format!("{key} does not belong in section [{name}]; ignored")
            } else if let Some(near) = keys::suggest(scope, key) {
                format!("{key} = {value} is an unknown key in section [{name}] (did you mean {near}?); ignored")
            } else {
                format!("{key} = {value} is an unknown key in section [{name}]; ignored")
            };
            diags.push(Severity::Warning, entry.line, message);
            continue;
        }
        if entry.value.contains('\u{fffd}') {
            diags.push(
                Severity::Warning,
                entry.line,
                format!("{key} = {} is not valid UTF-8 text", entry.value),
            );
        }
        if let Some(first) = map.insert(key, entry) {
            diags.push(
                Severity::Warning,
                entry.line,
                format!(
                    "{key} is given twice (first on line {}); this value counts",
                    first.line
                ),
            );
        }
    }
    map.retain(|_, e| !e.value.is_empty());
    map
}

/// Sets every key of `T`'s scope: to its value in `map` or else its default.
/// A value that does not parse is an error in `errors` (with the key, the
/// value and what is allowed) and leaves the default.
fn fill<T: Settings>(
    target: &mut T,
    map: &HashMap<&str, &Entry>,
    diags: &Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) {
    for key in keys::of_scope(T::SCOPE) {
        let given = map
            .get(key.name)
            .and_then(|entry| match key.parse(&entry.value) {
                Ok(value) => Some(value),
                Err(problem) => {
                    errors.push(diags.make(
                        Severity::Error,
                        entry.line,
                        format!("{} = {} {problem}", entry.key, entry.value),
                    ));
                    None
                }
            });
        if let Some(value) = given.or_else(|| key.default_value()) {
            key.set_recording_path(target, value);
        }
    }
}

fn read_global(
    section: &RawSection,
    diags: &mut Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) -> Global {
    let map = collect(section, Scope::Global, diags);
    let mut global = Global::default();
    fill(&mut global, &map, diags, errors);
    // OUTPUT_SOFT_LIMIT <= OUTPUT_HARD_LIMIT; without a (good) value of its
    // own the soft limit follows a lower hard limit.
    let hard = global.output_hard_limit;
    if global.output_soft_limit > hard {
        if let Some(entry) = map.get("OUTPUT_SOFT_LIMIT") {
            if !errors.iter().any(|d| d.line == entry.line) {
                errors.push(diags.make(
                    Severity::Error,
                    entry.line,
                    format!(
                        "{} = {} is above OUTPUT_HARD_LIMIT ({hard} bytes)",
                        entry.key, entry.value
                    ),
                ));
            }
        }
        global.output_soft_limit = hard;
    }
    check_http(&global, &map, diags, errors);
    mqtt::check_global(&global.mqtt, &map, diags, errors);
    // The key's setter keeps only a good list; a bad one is reported here,
    // once per line.
    if global.serial_device_cfg.is_none() {
        if let Some(entry) = map.get("SERIAL_DEVICE_CFG") {
            let reported = errors.iter().any(|d| d.line == entry.line);
            if let (false, Err(problem)) = (reported, serial::parse_device_cfg(&entry.value)) {
                errors.push(diags.make(Severity::Error, entry.line, problem));
            }
        }
    }
    global
}

/// The web page's keys that depend on each other: a page reachable from
/// other machines needs HTTP_TOKEN, and TLS needs both files.
fn check_http(
    global: &Global,
    map: &HashMap<&str, &Entry>,
    diags: &Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) {
    let Some(port_entry) = map.get("HTTP_PORT") else {
        return;
    };
    let line_of = |key: &str| map.get(key).map_or(port_entry.line, |e| e.line);
    if global.http_port.is_some() && !global.http_bind.is_loopback() && global.http_token.is_none()
    {
        errors.push(diags.make(
            Severity::Error,
            line_of("HTTP_BIND"),
            format!(
                "HTTP_BIND = {} is not a loopback address: HTTP_TOKEN must be set, \
                 or the page would be open to the network",
                global.http_bind
            ),
        ));
    }
    if global.http_cert.is_some() != global.http_key.is_some() {
        let (given, missing) = if global.http_cert.is_some() {
            ("HTTP_CERT", "HTTP_KEY")
        } else {
            ("HTTP_KEY", "HTTP_CERT")
        };
        errors.push(diags.make(
            Severity::Error,
            line_of(given),
            format!("{given} is set without {missing}: TLS needs both"),
        ));
    }
}

/// The defaults of a PLC section (with no SERVER_PORT).
fn section_defaults(name: &str) -> Section {
    keys::with_defaults(Section {
        name: name.to_string(),
        // Placeholders: every field is set by its key's default, or stays
        // unset.
        ipaddr: None,
        ipaddr_local: None,
        epsaddr: None,
        epstout: Duration::ZERO,
        epstout_step: Duration::ZERO,
        epsport: 0,
        server_port: 0,
        serial_device: None,
        serial_speed: None,
        serial_rts: None,
        serial_parity: None,
        serial_data_bits: None,
        serial_stop_bits: None,
        shm_name: None,
        shm_socket: None,
        shm_port: None,
        serial_device_cfg: None,
        pubfile_crc: false,
        pubfile_write: false,
        pubfile: None,
        pubfile_fixed: None,
        protocol: Protocol::Epsnet,
        simulator: None,
        allow: None,
        read_only: false,
        trace: false,
        setconf_keys: None,
        history: History::default(),
        mqtt: MqttSection::default(),
        opcua: OpcuaSection::default(),
        modbus: Modbus::default(),
        s7: S7::default(),

        ads: Ads::default(),
        opcua_client: OpcuaClient::default(),
        paths: Vec::new(),
    })
}

/// `None` when SERVER_PORT is missing or invalid (the error is in `errors`).
fn read_section(
    raw: &RawSection,
    diags: &mut Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) -> Option<Section> {
    let map = collect(raw, Scope::Section, diags);
    let mut section = section_defaults(&raw.name);
    fill(&mut section, &map, diags, errors);
    mqtt::check_section(&section.mqtt, &map, diags, errors);
    if section.simulator.is_none() {
        for key in ["SIMULATOR_PROGRAM", "SIMULATOR_PUB"] {
            if let Some(entry) = map.get(key) {
                diags.push(
                    Severity::Warning,
                    entry.line,
                    format!("{key} has no effect without SIMULATOR = Yes"),
                );
            }
        }
    }
    history::warn_unused(&section.history, &map, diags);
    // Modbus keys: only with a Modbus PROTOCOL; such a section reads a
    // tag file, not public files. The character format is RTU's.
    let modbus = section.protocol.is_modbus();
    for (key, entry) in &map {
        let misplaced = if modbus {
            matches!(*key, "PUBFILE" | "PUBFILE_FIXED").then(|| {
                format!(
                    "{key} has no effect with PROTOCOL = {} (its variables come from MODBUS_TAGS)",
                    section.protocol
                )
            })
        } else {
            key.starts_with("MODBUS_")
                .then(|| format!("{key} has no effect without PROTOCOL = MODBUS_TCP, MODBUS_RTU or MODBUS_RTU_TCP"))
        };
        let misplaced = misplaced.or_else(|| {
            (section.protocol != Protocol::ModbusRtu
                && matches!(
                    *key,
                    "SERIAL_PARITY" | "SERIAL_DATA_BITS" | "SERIAL_STOP_BITS"
                ))
            .then(|| {
                format!("{key} has no effect without PROTOCOL = MODBUS_RTU (EPSNET's line is 8N1)")
            })
        });
        if let Some(message) = misplaced {
            diags.push(Severity::Warning, entry.line, message);
        }
    }
    // S7 keys likewise, with PROTOCOL = S7.
    let s7 = section.protocol == Protocol::S7;
    for (key, entry) in &map {
        let misplaced = if s7 {
            matches!(*key, "PUBFILE" | "PUBFILE_FIXED").then(|| {
                format!("{key} has no effect with PROTOCOL = S7 (its variables come from S7_TAGS)")
            })
        } else {
            key.starts_with("S7_")
                .then(|| format!("{key} has no effect without PROTOCOL = S7"))
        };
        let opcua = section.protocol == Protocol::Opcua;
        let misplaced = misplaced.or_else(|| match (opcua, key.starts_with("OPCUA_")) {
            (true, false) => matches!(*key, "PUBFILE" | "PUBFILE_FIXED" | "IPADDR")
                .then(|| format!("{key} has no effect with PROTOCOL = OPCUA (the server is OPCUA_URL, its variables come from OPCUA_BROWSE or OPCUA_TAGS)")),
            // OPCUA_PUBLISH and OPCUA_WRITE are the OPC UA server's, for any section.
            (false, true) => (!matches!(*key, "OPCUA_PUBLISH" | "OPCUA_WRITE"))
                .then(|| format!("{key} has no effect without PROTOCOL = OPCUA")),
            _ => None,
        });
        if let Some(message) = misplaced {
            diags.push(Severity::Warning, entry.line, message);
        }
    }
    // ADS keys likewise, with PROTOCOL = ADS.
    let ads = section.protocol == Protocol::Ads;
    for (key, entry) in &map {
        let misplaced = if ads {
            matches!(*key, "PUBFILE" | "PUBFILE_FIXED").then(|| {
                format!(
                    "{key} has no effect with PROTOCOL = ADS (its variables are the PLC's symbols)"
                )
            })
        } else {
            key.starts_with("ADS_")
                .then(|| format!("{key} has no effect without PROTOCOL = ADS"))
        };
        if let Some(message) = misplaced {
            diags.push(Severity::Warning, entry.line, message);
        }
    }
    if let Some(entry) = map.get("S7_TSAP") {
        if section.s7.tsap.is_none() {
            errors.push(diags.make(
                Severity::Error,
                entry.line,
                format!(
                    "S7_TSAP = {} is not local/remote TSAP in hex (e.g. 0100/0200)",
                    entry.value
                ),
            ));
        }
    }
    if s7 && section.s7.tags.is_none() && section.simulator.is_none() {
        diags.push(
            Severity::Warning,
            raw.line,
            format!(
                "section [{}] has no S7_TAGS: it serves __PLC_RUN and __PF_CRC only",
                raw.name
            ),
        );
    }

    if ads {
        section.pubfile = Some(ADS_SYMBOLS.to_string());
        for (key, id) in [
            ("ADS_NET_ID", &section.ads.net_id),
            ("ADS_SOURCE_NET_ID", &section.ads.source_net_id),
        ] {
            if let (Some(id), Some(entry)) = (id, map.get(key)) {
                if let Err(why) = plccoms_plc::ads::NetId::parse(id) {
                    errors.push(diags.make(Severity::Error, entry.line, format!("{key}: {why}")));
                }
            }
        }
    }
    if modbus && section.modbus.tags.is_none() && section.simulator.is_none() {
        diags.push(
            Severity::Warning,
            raw.line,
            format!(
                "section [{}] has no MODBUS_TAGS: it serves __PLC_RUN and __PF_CRC only",
                raw.name
            ),
        );
    }
    if !map.contains_key("SERVER_PORT") {
        errors.push(diags.make(
            Severity::Error,
            raw.line,
            format!(
                "section [{}] has no SERVER_PORT (required, allowed {})",
                raw.name,
                key(Scope::Section, "SERVER_PORT").map_or(String::new(), |k| k.kind.allowed())
            ),
        ));
    }
    // SERVER_PORT has no default and is never 0 when its value is good.
    (section.server_port != 0).then_some(section)
}
