//! The ini file (`PLCComS.ini`): global settings in `[*]`, then one section per
//! PLC.
//!
//! The file is read with rust-ini, after a line-preserving pass of our own that
//! rust-ini cannot do: it strips trailing `#`/`;` comments outside quotes (a
//! comment starts at the value's start, after whitespace or right after a
//! closing quote), reports lines that are neither `[SECTION]` nor
//! `KEY = VALUE`, and remembers the line of every key so that every message
//! names file and line. rust-ini then handles quotes; escapes stay off so
//! Windows paths keep their backslashes.
//!
//! Keys are case-insensitive; booleans are `Yes`/`No`, `True`/`False`,
//! `On`/`Off` or `1`/`0` in any case; numbers are decimal; an empty value
//! leaves the key at its default. Problems are [`Diagnostic`]s: an unknown key
//! is a warning; a bad value in `[*]` stops start-up
//! ([`ConfigError::Invalid`]); a bad value in a PLC section skips that section
//! and the others load.
//!
//! `SIMULATOR = Yes` (with `SIMULATOR_PROGRAM` and `SIMULATOR_PUB`) is this
//! project's addition: the section is served by a simulated PLC inside the
//! server instead of a real one.

use std::collections::HashMap;
use std::fmt;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr};
use std::path::{Path, PathBuf};
use std::time::Duration;

use ini::{Ini, ParseOption};

/// A loaded ini file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Config {
    /// The file it was loaded from.
    pub path: PathBuf,
    pub global: Global,
    /// The PLC sections that loaded, in file order.
    pub sections: Vec<Section>,
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
    pub serial_device_cfg: Option<String>,
    /// OUTPUT_HARD_LIMIT: output queued for one client, in bytes, beyond
    /// which it is disconnected at once (this server's own key).
    pub output_hard_limit: usize,
    /// OUTPUT_SOFT_LIMIT: output queued for one client, in bytes, that it may
    /// hold only for OUTPUT_SOFT_TIMEOUT; DIFF lines wait (coalesced) while
    /// it is reached.
    pub output_soft_limit: usize,
    /// OUTPUT_SOFT_TIMEOUT.
    pub output_soft_timeout: Duration,
}

impl Default for Global {
    /// The values the manual gives for keys that are not set.
    fn default() -> Self {
        Global {
            comm_loop_delay: Duration::from_millis(100),
            comm_sched_pri: 0,
            net_connect_max: 128,
            mem_blksize: 4096,
            mem_use_threads: true,
            ffile_blksize: 4096,
            ffile_timeout: Duration::from_secs(300),
            ffile_timeout_wr: Duration::from_secs(5),
            ffile_maxrecs: 256,
            end_line_crlf: true,
            pf_var_disabled: true,
            diff_var_enabled: true,
            sync_var_enabled: true,
            date_time_decimal: false,
            lim_of_decimals: false,
            num_of_decimals: 10,
            scient_notation: false,
            serial_device_cfg: None,
            output_hard_limit: 16 * 1024 * 1024,
            output_soft_limit: 1024 * 1024,
            output_soft_timeout: Duration::from_secs(30),
        }
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
    pub shm_name: Option<String>,
    pub shm_socket: Option<u32>,
    pub shm_port: Option<u32>,
    pub pubfile_crc: bool,
    pub pubfile_write: bool,
    pub pubfile: Option<String>,
    pub pubfile_fixed: Option<String>,
    /// Set when `SIMULATOR = Yes`.
    pub simulator: Option<Simulator>,
    /// `ALLOW`: the client addresses and networks admitted; `None` admits
    /// every client, as PLCComS does (this server's own key).
    pub allow: Option<Vec<Network>>,
    /// `READ_ONLY = Yes`: requests that would change the PLC or the section
    /// answer ERROR:30 (this server's own key).
    pub read_only: bool,
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

/// The simulator programs `SIMULATOR_PROGRAM` accepts.
pub const SIMULATOR_PROGRAMS: [&str; 2] = ["demo", "idle"];

/// A loaded file with the warnings and skipped-section errors found on the way.
#[derive(Debug, Clone)]
pub struct Loaded {
    pub config: Config,
    pub diagnostics: Vec<Diagnostic>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Severity {
    Warning,
    Error,
}

/// A problem at one line of the ini file. Displays as `PLCComS.ini:12: message`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Diagnostic {
    pub severity: Severity,
    pub file: PathBuf,
    /// 1-based.
    pub line: usize,
    pub message: String,
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}: {}", self.file.display(), self.line, self.message)
    }
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
    /// that is not ini syntax there. Start-up stops.
    #[error("{0}")]
    Invalid(Diagnostic),
    #[error("{}: no usable PLC section (at least one section besides [*], with a SERVER_PORT, is needed)", path.display())]
    NoSections { path: PathBuf },
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
/// diagnostic.
pub fn parse(path_for_messages: &Path, text: &str) -> Result<Loaded, ConfigError> {
    let mut diags = Diags {
        file: path_for_messages,
        list: Vec::new(),
    };
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let scanned = scan(text, &diags);
    if let Some(first) = scanned.general_errors.first() {
        return Err(ConfigError::Invalid(first.clone()));
    }

    let ini = Ini::load_from_str_opt(
        &scanned.normalized,
        ParseOption {
            enabled_quote: true,
            enabled_escape: false,
            enabled_indented_mutiline_value: false,
            enabled_preserve_key_leading_whitespace: false,
        },
    )
    .map_err(|e| ConfigError::Invalid(diags.make(Severity::Error, e.line, e.msg.into_owned())))?;

    // rust-ini keeps sections and keys in file order, as the scan saw them:
    // pair them up to know each key's line.
    let mut scanned_sections = scanned.sections.into_iter();
    let mut raw_sections = Vec::new();
    for (name, props) in ini.iter() {
        let scanned_section = name.and_then(|_| scanned_sections.next());
        let (header_line, lines) = match &scanned_section {
            Some(s) => (s.line, &s.key_lines),
            None => (0, &scanned.general),
        };
        let entries: Vec<Entry> = props
            .iter()
            .enumerate()
            .map(|(i, (key, value))| Entry {
                key: key.to_ascii_uppercase(),
                value: value.to_string(),
                line: lines.get(i).copied().unwrap_or(header_line.max(1)),
            })
            .collect();
        match scanned_section {
            None => {
                for entry in entries {
                    diags.push(
                        Severity::Warning,
                        entry.line,
                        format!("{} is outside any section; ignored", entry.key),
                    );
                }
            }
            Some(s) => raw_sections.push(RawSection {
                name: s.name,
                line: s.line,
                entries,
                errors: s.errors,
            }),
        }
    }

    // [*]: exactly one, and it must be clean.
    let mut global = None;
    let mut global_line = 0;
    for section in raw_sections.iter().filter(|s| s.name == "*") {
        if global.is_some() {
            return Err(ConfigError::Invalid(diags.make(
                Severity::Error,
                section.line,
                format!("second [*] section (the first is on line {global_line})"),
            )));
        }
        global_line = section.line;
        let mut errors = section.errors.clone();
        let g = read_global(section, &mut diags, &mut errors);
        if let Some(first) = errors.into_iter().next() {
            return Err(ConfigError::Invalid(first));
        }
        global = Some(g);
    }
    let Some(global) = global else {
        return Err(ConfigError::Invalid(diags.make(
            Severity::Error,
            1,
            "the mandatory [*] section is missing".to_string(),
        )));
    };

    let mut sections: Vec<Section> = Vec::new();
    let mut names: HashMap<String, usize> = HashMap::new();
    let mut ports: HashMap<u16, (String, usize)> = HashMap::new();
    for raw in raw_sections.iter().filter(|s| s.name != "*") {
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
                let port_line = raw
                    .entries
                    .iter()
                    .rev()
                    .find(|e| e.key == "SERVER_PORT")
                    .map_or(raw.line, |e| e.line);
                errors.push(diags.make(
                    Severity::Error,
                    port_line,
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
                let count = errors.len();
                diags.push(
                    Severity::Error,
                    raw.line,
                    format!(
                        "section [{}] skipped ({count} error{})",
                        raw.name,
                        if count == 1 { "" } else { "s" }
                    ),
                );
                diags.list.extend(errors);
            }
        }
    }
    if sections.is_empty() {
        return Err(ConfigError::NoSections {
            path: path_for_messages.to_path_buf(),
        });
    }
    diags.list.sort_by_key(|d| d.line);
    Ok(Loaded {
        config: Config {
            path: path_for_messages.to_path_buf(),
            global,
            sections,
        },
        diagnostics: diags.list,
    })
}

struct Diags<'a> {
    file: &'a Path,
    list: Vec<Diagnostic>,
}

impl Diags<'_> {
    fn make(&self, severity: Severity, line: usize, message: String) -> Diagnostic {
        Diagnostic {
            severity,
            file: self.file.to_path_buf(),
            line,
            message,
        }
    }

    fn push(&mut self, severity: Severity, line: usize, message: String) {
        let d = self.make(severity, line, message);
        self.list.push(d);
    }
}

// ---------------------------------------------------------------------------
// The line scan.

struct Scanned {
    /// The text rust-ini reads: one line per input line, comments and bad
    /// lines blanked, keys as `KEY=value`.
    normalized: String,
    /// Lines of keys before the first section header.
    general: Vec<usize>,
    /// Malformed lines before the first section header.
    general_errors: Vec<Diagnostic>,
    sections: Vec<ScannedSection>,
}

struct ScannedSection {
    name: String,
    line: usize,
    key_lines: Vec<usize>,
    /// Malformed lines in the section, its header included.
    errors: Vec<Diagnostic>,
}

/// Every line that is not blank, a comment, `[SECTION]` or `KEY = VALUE` is an
/// error of the section it is in (a bad header is an error of its own
/// section); such lines are blanked for rust-ini.
fn scan(text: &str, diags: &Diags<'_>) -> Scanned {
    let mut out = Scanned {
        normalized: String::with_capacity(text.len()),
        general: Vec::new(),
        general_errors: Vec::new(),
        sections: Vec::new(),
    };
    for (index, raw) in text.split('\n').enumerate() {
        let line_no = index + 1;
        let line = raw.strip_suffix('\r').unwrap_or(raw).trim();
        let mut error = None;
        if line.is_empty() || line.starts_with('#') || line.starts_with(';') {
            // blank or comment
        } else if let Some(rest) = line.strip_prefix('[') {
            let (name, problem) = scan_section(rest);
            // rust-ini only sees a placeholder name: the real one is ours.
            out.normalized
                .push_str(&format!("[s{}]", out.sections.len()));
            out.sections.push(ScannedSection {
                name,
                line: line_no,
                key_lines: Vec::new(),
                errors: Vec::new(),
            });
            error = problem;
        } else {
            match scan_key(line) {
                Ok((key, value)) => {
                    out.normalized.push_str(key);
                    out.normalized.push('=');
                    out.normalized.push_str(&value);
                    match out.sections.last_mut() {
                        Some(s) => s.key_lines.push(line_no),
                        None => out.general.push(line_no),
                    }
                }
                Err(problem) => error = Some(problem),
            }
        }
        if let Some(message) = error {
            let d = diags.make(Severity::Error, line_no, message);
            match out.sections.last_mut() {
                Some(s) => s.errors.push(d),
                None => out.general_errors.push(d),
            }
        }
        out.normalized.push('\n');
    }
    out
}

/// The section name after `[`, and what is wrong with the header, if anything.
fn scan_section(rest: &str) -> (String, Option<String>) {
    let Some(close) = rest.find(']') else {
        return (
            rest.trim().to_string(),
            Some(format!("section header [{rest} has no closing ']'")),
        );
    };
    let name = rest[..close].trim().to_string();
    let after = rest[close + 1..].trim_start();
    let problem = if !(after.is_empty() || after.starts_with('#') || after.starts_with(';')) {
        Some(format!(
            "unexpected '{after}' after section header [{name}]"
        ))
    } else if name.is_empty() {
        Some("empty section name []".to_string())
    } else if name.contains('[') {
        Some(format!("invalid character '[' in section name [{name}]"))
    } else {
        None
    };
    (name, problem)
}

/// `(key, value)` with the value's comment removed but its quotes kept for
/// rust-ini.
fn scan_key(line: &str) -> Result<(&str, String), String> {
    let Some(eq) = line.find('=') else {
        return Err(format!(
            "'{line}' is neither a [SECTION] header nor KEY = VALUE"
        ));
    };
    let key = line[..eq].trim();
    if key.is_empty() {
        return Err(format!("'{line}' has no key before '='"));
    }
    if let Some(bad) = key.chars().find(|&c| matches!(c, ':' | '\\' | '"' | '\'')) {
        return Err(format!("invalid character '{bad}' in key '{key}'"));
    }
    let value = strip_value_comment(line[eq + 1..].trim_start())
        .map_err(|quote| format!("{key}: unterminated {quote} quote in value"))?;
    Ok((key, value))
}

/// Cuts a trailing comment the way rust-ini would read quotes: a quote opens
/// only at the start of the value or right after a closing quote, and a
/// backslash inside quotes takes the next character with it. A `#` or `;`
/// starts a comment at those same places or after whitespace.
fn strip_value_comment(value: &str) -> Result<String, char> {
    let bytes = value.as_bytes();
    let mut i = 0;
    let mut end = bytes.len();
    let mut part_start = true;
    while i < bytes.len() {
        let b = bytes[i];
        if part_start && (b == b'"' || b == b'\'') {
            let mut j = i + 1;
            loop {
                match bytes.get(j) {
                    None => return Err(b as char),
                    Some(b'\\') => j += 2,
                    Some(&c) if c == b => break,
                    Some(_) => j += 1,
                }
            }
            i = j + 1;
            continue;
        }
        if (b == b'#' || b == b';')
            && (part_start || i == 0 || matches!(bytes[i - 1], b' ' | b'\t'))
        {
            end = i;
            break;
        }
        part_start = false;
        i += 1;
    }
    let mut kept = value[..end].trim_end().to_string();
    // A trailing backslash would make rust-ini join the next line; a space
    // after it stops that and is trimmed away again.
    if kept.ends_with('\\') {
        kept.push(' ');
    }
    Ok(kept)
}

// ---------------------------------------------------------------------------
// Values.

struct Entry {
    key: String,
    value: String,
    line: usize,
}

struct RawSection {
    name: String,
    line: usize,
    entries: Vec<Entry>,
    /// Malformed lines found by the scan.
    errors: Vec<Diagnostic>,
}

/// Every key of the `[*]` section.
pub const GLOBAL_KEYS: [&str; 21] = [
    "COMM_LOOP_DELAY",
    "COMM_SCHED_PRI",
    "NET_CONNECT_MAX",
    "MEM_BLKSIZE",
    "MEM_USE_THREADS",
    "FFILE_BLKSIZE",
    "FFILE_TIMEOUT",
    "FFILE_TIMEOUT_WR",
    "FFILE_MAXRECS",
    "END_LINE_CRLF",
    "PF_VAR_DISABLED",
    "DIFF_VAR_ENABLED",
    "SYNC_VAR_ENABLED",
    "DATE_TIME_DECIMAL",
    "LIM_OF_DECIMALS",
    "NUM_OF_DECIMALS",
    "SCIENT_NOTATION",
    "SERIAL_DEVICE_CFG",
    // This server's own keys.
    "OUTPUT_HARD_LIMIT",
    "OUTPUT_SOFT_LIMIT",
    "OUTPUT_SOFT_TIMEOUT",
];

/// Every key of a PLC section.
pub const SECTION_KEYS: [&str; 23] = [
    "IPADDR",
    "IPADDR_LOCAL",
    "EPSADDR",
    "EPSTOUT",
    "EPSTOUT_STEP",
    "EPSPORT",
    "SERVER_PORT",
    "SERIAL_DEVICE",
    "SERIAL_SPEED",
    "SERIAL_RTS",
    "SHM_NAME",
    "SHM_SOCKET",
    "SHM_PORT",
    "PUBFILE_CRC",
    "PUBFILE_WRITE",
    "PUBFILE",
    "PUBFILE_FIXED",
    "SIMULATOR",
    "SIMULATOR_PROGRAM",
    "SIMULATOR_PUB",
    "ALLOW",
    "READ_ONLY",
    // Accepted in a PLC section for symmetry with [*]: no effect there.
    "SERIAL_DEVICE_CFG",
];

/// Reads one section's entries: checks for duplicates, unknown keys and
/// non-UTF-8 text, and returns the value each known key ends up with.
fn collect<'e>(
    section: &'e RawSection,
    known: &[&str],
    other: &[&str],
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
    for entry in &section.entries {
        let key = entry.key.as_str();
        if !known.contains(&key) {
            let message = if other.contains(&key) {
                format!(
                    "{key} does not belong in section [{}]; ignored",
                    section.name
                )
            } else {
                format!("unknown key {key} in section [{}]; ignored", section.name)
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

/// Typed access to one section's values; value errors go to `errors`.
struct Values<'m, 'e, 'd> {
    map: &'m HashMap<&'e str, &'e Entry>,
    diags: &'d Diags<'d>,
    errors: &'m mut Vec<Diagnostic>,
}

impl Values<'_, '_, '_> {
    fn error(&mut self, entry: &Entry, problem: String) {
        let d = self.diags.make(
            Severity::Error,
            entry.line,
            format!("{} = {} {problem}", entry.key, entry.value),
        );
        self.errors.push(d);
    }

    /// A decimal number in `min..=max`; `unit` only decorates the message.
    fn number(&mut self, key: &str, min: u64, max: u64, unit: &str) -> Option<u64> {
        let entry = *self.map.get(key)?;
        let allowed = if unit.is_empty() {
            format!("(allowed {min}-{max})")
        } else {
            format!("(allowed {min}-{max} {unit})")
        };
        let text = entry.value.as_str();
        if text.is_empty() || !text.bytes().all(|b| b.is_ascii_digit()) {
            self.error(entry, format!("is not a number {allowed}"));
            return None;
        }
        match text.parse::<u64>() {
            Ok(n) if (min..=max).contains(&n) => Some(n),
            _ => {
                self.error(entry, format!("is out of range {allowed}"));
                None
            }
        }
    }

    fn bool(&mut self, key: &str, default: bool) -> bool {
        let Some(entry) = self.map.get(key).copied() else {
            return default;
        };
        match entry.value.to_ascii_lowercase().as_str() {
            "yes" | "true" | "on" | "1" => true,
            "no" | "false" | "off" | "0" => false,
            _ => {
                self.error(entry, "is not Yes or No".into());
                default
            }
        }
    }

    fn string(&self, key: &str) -> Option<String> {
        self.map.get(key).map(|e| e.value.clone())
    }

    fn ipv4(&mut self, key: &str) -> Option<Ipv4Addr> {
        let entry = *self.map.get(key)?;
        let parsed = parse_ipv4(&entry.value);
        if parsed.is_none() {
            self.error(entry, "is not an IPv4 address (a.b.c.d)".into());
        }
        parsed
    }

    /// A comma-separated list of addresses and CIDR networks.
    fn networks(&mut self, key: &str) -> Option<Vec<Network>> {
        let entry = *self.map.get(key)?;
        let mut list = Vec::new();
        for part in entry.value.split(',').map(str::trim) {
            match Network::parse(part) {
                Some(net) => list.push(net),
                None => {
                    self.error(
                        entry,
                        format!("has '{part}', which is not an IPv4 or IPv6 address or network (a.b.c.d, a.b.c.d/n, x:y::z, x:y::/n)"),
                    );
                    return None;
                }
            }
        }
        Some(list)
    }

    fn millis(&mut self, key: &str, min: u64, max: u64, default: u64) -> Duration {
        Duration::from_millis(self.number(key, min, max, "ms").unwrap_or(default))
    }

    fn secs(&mut self, key: &str, min: u64, max: u64, default: u64) -> Duration {
        Duration::from_secs(self.number(key, min, max, "s").unwrap_or(default))
    }
}

/// Dotted decimal with 1 to 3 digits per part; leading zeros are decimal
/// (`192.168.001.010` is 192.168.1.10), as the vendor's files write them.
pub fn parse_ipv4(text: &str) -> Option<Ipv4Addr> {
    let mut octets = [0u8; 4];
    let mut parts = text.split('.');
    for octet in &mut octets {
        let part = parts.next()?;
        if part.is_empty() || part.len() > 3 || !part.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        *octet = part.parse().ok()?;
    }
    if parts.next().is_some() {
        return None;
    }
    Some(Ipv4Addr::from(octets))
}

fn read_global(
    section: &RawSection,
    diags: &mut Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) -> Global {
    let map = collect(section, &GLOBAL_KEYS, &SECTION_KEYS, diags);
    let mut v = Values {
        map: &map,
        diags,
        errors,
    };
    let d = Global::default();
    let output_hard_limit = v
        .number("OUTPUT_HARD_LIMIT", 4096, 1 << 30, "bytes")
        .map_or(d.output_hard_limit, |n| n as usize);
    let output_soft_limit = match v.number("OUTPUT_SOFT_LIMIT", 1024, 1 << 30, "bytes") {
        Some(n) if n as usize > output_hard_limit => {
            let entry = map["OUTPUT_SOFT_LIMIT"];
            v.error(
                entry,
                format!("is above OUTPUT_HARD_LIMIT ({output_hard_limit} bytes)"),
            );
            d.output_soft_limit.min(output_hard_limit)
        }
        Some(n) => n as usize,
        None => d.output_soft_limit.min(output_hard_limit),
    };
    // Ranges fit the field types, so the casts below cannot truncate.
    Global {
        comm_loop_delay: v.millis("COMM_LOOP_DELAY", 1, 1000, 100),
        comm_sched_pri: v
            .number("COMM_SCHED_PRI", 0, 99, "")
            .map_or(d.comm_sched_pri, |n| n as u8),
        net_connect_max: v
            .number("NET_CONNECT_MAX", 1, 1024, "")
            .map_or(d.net_connect_max, |n| n as usize),
        mem_blksize: v
            .number("MEM_BLKSIZE", 1, 65536, "bytes")
            .map_or(d.mem_blksize, |n| n as usize),
        mem_use_threads: v.bool("MEM_USE_THREADS", d.mem_use_threads),
        ffile_blksize: v
            .number("FFILE_BLKSIZE", 1, 65536, "bytes")
            .map_or(d.ffile_blksize, |n| n as usize),
        ffile_timeout: v.secs("FFILE_TIMEOUT", 0, 3600, 300),
        ffile_timeout_wr: v.secs("FFILE_TIMEOUT_WR", 1, 60, 5),
        ffile_maxrecs: v
            .number("FFILE_MAXRECS", 0, 1024, "")
            .map_or(d.ffile_maxrecs, |n| n as usize),
        end_line_crlf: v.bool("END_LINE_CRLF", d.end_line_crlf),
        pf_var_disabled: v.bool("PF_VAR_DISABLED", d.pf_var_disabled),
        diff_var_enabled: v.bool("DIFF_VAR_ENABLED", d.diff_var_enabled),
        sync_var_enabled: v.bool("SYNC_VAR_ENABLED", d.sync_var_enabled),
        date_time_decimal: v.bool("DATE_TIME_DECIMAL", d.date_time_decimal),
        lim_of_decimals: v.bool("LIM_OF_DECIMALS", d.lim_of_decimals),
        num_of_decimals: v
            .number("NUM_OF_DECIMALS", 0, 15, "")
            .map_or(d.num_of_decimals, |n| n as u8),
        scient_notation: v.bool("SCIENT_NOTATION", d.scient_notation),
        serial_device_cfg: v.string("SERIAL_DEVICE_CFG"),
        output_hard_limit,
        output_soft_limit,
        output_soft_timeout: v.secs("OUTPUT_SOFT_TIMEOUT", 1, 3600, 30),
    }
}

/// `None` when SERVER_PORT is missing or invalid (the error is in `errors`).
fn read_section(
    raw: &RawSection,
    diags: &mut Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) -> Option<Section> {
    let map = collect(raw, &SECTION_KEYS, &GLOBAL_KEYS, diags);
    let simulated = {
        let mut v = Values {
            map: &map,
            diags,
            errors,
        };
        v.bool("SIMULATOR", false)
    };
    if !simulated {
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
    let mut v = Values {
        map: &map,
        diags,
        errors,
    };
    let u32_max = u64::from(u32::MAX);
    let simulator = if simulated {
        let program = match map.get("SIMULATOR_PROGRAM") {
            None => Some("demo".to_string()),
            Some(entry) => {
                let lower = entry.value.to_ascii_lowercase();
                if SIMULATOR_PROGRAMS.contains(&lower.as_str()) {
                    Some(lower)
                } else {
                    v.error(
                        entry,
                        format!(
                            "is not a simulator program (allowed {})",
                            SIMULATOR_PROGRAMS.join(", ")
                        ),
                    );
                    None
                }
            }
        };
        program.map(|program| Simulator {
            program,
            pubfile: v.string("SIMULATOR_PUB"),
        })
    } else {
        None
    };
    let section = Section {
        name: raw.name.clone(),
        ipaddr: v.ipv4("IPADDR"),
        ipaddr_local: v.ipv4("IPADDR_LOCAL"),
        epsaddr: v.number("EPSADDR", 1, 126, "").map(|n| n as u8),
        epstout: v.millis("EPSTOUT", 1, 15000, 1000),
        epstout_step: v.millis("EPSTOUT_STEP", 0, 5000, 500),
        epsport: v
            .number("EPSPORT", 1, 65535, "")
            .map_or(61682, |n| n as u16),
        server_port: 0,
        serial_device: v.string("SERIAL_DEVICE"),
        serial_speed: v
            .number("SERIAL_SPEED", 1, u32_max, "baud")
            .map(|n| n as u32),
        serial_rts: v.number("SERIAL_RTS", 0, u32_max, "").map(|n| n as u32),
        shm_name: v.string("SHM_NAME"),
        shm_socket: v.number("SHM_SOCKET", 0, u32_max, "").map(|n| n as u32),
        shm_port: v.number("SHM_PORT", 0, u32_max, "").map(|n| n as u32),
        pubfile_crc: v.bool("PUBFILE_CRC", false),
        pubfile_write: v.bool("PUBFILE_WRITE", false),
        pubfile: v.string("PUBFILE"),
        pubfile_fixed: v.string("PUBFILE_FIXED"),
        simulator,
        allow: v.networks("ALLOW"),
        read_only: v.bool("READ_ONLY", false),
    };
    let server_port = if map.contains_key("SERVER_PORT") {
        v.number("SERVER_PORT", 1, 65535, "").map(|n| n as u16)
    } else {
        let d = v.diags.make(
            Severity::Error,
            raw.line,
            format!("section [{}] has no SERVER_PORT", raw.name),
        );
        v.errors.push(d);
        None
    };
    Some(Section {
        server_port: server_port?,
        ..section
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const FILE: &str = "PLCComS.ini";

    fn ok(text: &str) -> Loaded {
        match parse(Path::new(FILE), text) {
            Ok(loaded) => loaded,
            Err(e) => panic!("{e}"),
        }
    }

    fn messages(loaded: &Loaded) -> Vec<String> {
        loaded.diagnostics.iter().map(ToString::to_string).collect()
    }

    /// A file whose `[*]` is `global` (line 2 onwards) and with one PLC section.
    fn with_global(global: &str) -> Result<Loaded, ConfigError> {
        parse(
            Path::new(FILE),
            &format!("[*]\n{global}\n[PLC]\nSERVER_PORT = 5010\n"),
        )
    }

    /// The message of the error that a `[*]` line 2 of `global` causes.
    fn global_error(global: &str) -> String {
        match with_global(global) {
            Err(ConfigError::Invalid(d)) => {
                assert_eq!(d.severity, Severity::Error);
                d.to_string()
            }
            Err(e) => panic!("{global}: {e}"),
            Ok(_) => panic!("{global}: loaded"),
        }
    }

    fn global(global: &str) -> Global {
        let loaded = with_global(global).unwrap_or_else(|e| panic!("{global}: {e}"));
        assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
        loaded.config.global
    }

    /// A file with `[*]` and one PLC section `[PLC]` whose body starts at
    /// line 3.
    fn with_section(body: &str) -> Result<Loaded, ConfigError> {
        parse(Path::new(FILE), &format!("[*]\n[PLC]\n{body}\n"))
    }

    fn section(body: &str) -> Section {
        let loaded = with_section(body).unwrap_or_else(|e| panic!("{body}: {e}"));
        assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
        loaded.config.sections.into_iter().next().unwrap()
    }

    /// The first error of a section body that makes the only section fail.
    fn section_error(body: &str) -> String {
        let text = format!("[*]\n[PLC]\n{body}\n[OTHER]\nSERVER_PORT = 6000\n");
        let loaded = parse(Path::new(FILE), &text).unwrap_or_else(|e| panic!("{body}: {e}"));
        assert_eq!(loaded.config.sections.len(), 1, "{body}: not skipped");
        assert_eq!(loaded.config.sections[0].name, "OTHER");
        let errors: Vec<_> = loaded
            .diagnostics
            .iter()
            .filter(|d| d.severity == Severity::Error)
            .map(ToString::to_string)
            .collect();
        assert_eq!(
            errors[0], "PLCComS.ini:2: section [PLC] skipped (1 error)",
            "{body}"
        );
        assert_eq!(errors.len(), 2, "{body}: {errors:?}");
        errors[1].clone()
    }

    #[test]
    fn vendor_file_loads_unchanged() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/vendor/PLCComS.ini");
        let loaded = load(&path).unwrap();
        assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
        let config = loaded.config;
        assert_eq!(config.path, path);
        assert_eq!(
            config.global,
            Global {
                comm_sched_pri: 10,
                ffile_maxrecs: 0,
                sync_var_enabled: false,
                serial_device_cfg: Some("/dev/ttyS0 -1, /dev/ttyS1 -1".into()),
                ..Global::default()
            }
        );
        assert_eq!(
            config.sections,
            vec![Section {
                name: "Foxtrot".into(),
                ipaddr: Some(Ipv4Addr::new(192, 168, 89, 1)),
                ipaddr_local: None,
                epsaddr: None,
                epstout: Duration::from_millis(1000),
                epstout_step: Duration::from_millis(500),
                epsport: 61682,
                server_port: 5011,
                serial_device: None,
                serial_speed: None,
                serial_rts: None,
                shm_name: None,
                shm_socket: None,
                shm_port: None,
                pubfile_crc: true,
                pubfile_write: false,
                pubfile: Some("//VARLIST.PUB".into()),
                pubfile_fixed: Some("FIXED_Foxtrot.pub".into()),
                simulator: None,
                allow: None,
                read_only: false,
            }]
        );
    }

    #[test]
    fn vendor_file_with_every_sample_section_uncommented() {
        let vendor = include_str!("../tests/data/vendor/PLCComS.ini");
        // Uncomment the sample sections and their keys, not the key catalogue
        // under [Alias for PLC] (its values are prose).
        let mut text = String::new();
        let mut in_samples = false;
        for line in vendor.lines() {
            if line.starts_with("#[") {
                in_samples = line != "#[Alias for PLC]";
            } else if line.starts_with('[') {
                in_samples = false;
            }
            if in_samples && line.starts_with('#') {
                text.push_str(&line[1..]);
            } else {
                text.push_str(line);
            }
            text.push_str("\r\n");
        }
        // And the commented IPADDR_LOCAL in [Foxtrot], with its trailing comment.
        let text = text.replace(
            "\n#IPADDR_LOCAL  = 192.168.1.100 #IP",
            "\nIPADDR_LOCAL  = 192.168.1.100 #IP",
        );
        let loaded = ok(&text);
        assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
        let names: Vec<_> = loaded
            .config
            .sections
            .iter()
            .map(|s| s.name.as_str())
            .collect();
        assert_eq!(
            names,
            ["iFoxtrot", "Foxtrot", "TC700", "TC700 RS232", "SoftPLC"]
        );
        let foxtrot = &loaded.config.sections[1];
        assert_eq!(foxtrot.ipaddr_local, Some(Ipv4Addr::new(192, 168, 1, 100)));
        assert_eq!(foxtrot.pubfile.as_deref(), Some("//VARLIST.PUB"));
        let ifoxtrot = &loaded.config.sections[0];
        assert_eq!(ifoxtrot.ipaddr, Some(Ipv4Addr::new(192, 168, 134, 176)));
        assert_eq!(ifoxtrot.pubfile.as_deref(), Some("//iFoxtrot.pub"));
        let rs232 = &loaded.config.sections[3];
        assert_eq!(rs232.serial_device.as_deref(), Some("/dev/ttyS0"));
        assert_eq!(rs232.serial_speed, Some(115200));
        assert_eq!(rs232.ipaddr, None);
        let soft = &loaded.config.sections[4];
        assert_eq!(soft.shm_name.as_deref(), Some("ShmSrv.dll"));
        assert_eq!((soft.shm_socket, soft.shm_port), (Some(0), Some(5)));
    }

    #[test]
    fn defaults() {
        assert_eq!(global(""), Global::default());
        let d = Global::default();
        assert_eq!(d.comm_loop_delay, Duration::from_millis(100));
        assert_eq!(d.comm_sched_pri, 0);
        assert_eq!(d.net_connect_max, 128);
        assert_eq!(d.mem_blksize, 4096);
        assert!(d.mem_use_threads);
        assert_eq!(d.ffile_blksize, 4096);
        assert_eq!(d.ffile_timeout, Duration::from_secs(300));
        assert_eq!(d.ffile_timeout_wr, Duration::from_secs(5));
        assert_eq!(d.ffile_maxrecs, 256);
        assert!(d.end_line_crlf);
        assert!(d.pf_var_disabled);
        assert!(d.diff_var_enabled);
        assert!(d.sync_var_enabled);
        assert!(!d.date_time_decimal);
        assert!(!d.lim_of_decimals);
        assert_eq!(d.num_of_decimals, 10);
        assert!(!d.scient_notation);
        assert_eq!(d.serial_device_cfg, None);

        let s = section("SERVER_PORT = 5010");
        assert_eq!(
            s,
            Section {
                name: "PLC".into(),
                ipaddr: None,
                ipaddr_local: None,
                epsaddr: None,
                epstout: Duration::from_millis(1000),
                epstout_step: Duration::from_millis(500),
                epsport: 61682,
                server_port: 5010,
                serial_device: None,
                serial_speed: None,
                serial_rts: None,
                shm_name: None,
                shm_socket: None,
                shm_port: None,
                pubfile_crc: false,
                pubfile_write: false,
                pubfile: None,
                pubfile_fixed: None,
                simulator: None,
                allow: None,
                read_only: false,
            }
        );
    }

    #[test]
    fn an_empty_value_means_the_default() {
        assert_eq!(
            global("COMM_LOOP_DELAY =\nEND_LINE_CRLF =  "),
            Global::default()
        );
    }

    /// (key, min, max, unit in messages, how to read the value back)
    type GlobalRange = (&'static str, u64, u64, &'static str, fn(&Global) -> u64);

    #[test]
    fn global_ranges() {
        let ranges: [GlobalRange; 11] = [
            ("COMM_LOOP_DELAY", 1, 1000, " ms", |g| {
                g.comm_loop_delay.as_millis() as u64
            }),
            ("COMM_SCHED_PRI", 0, 99, "", |g| u64::from(g.comm_sched_pri)),
            ("NET_CONNECT_MAX", 1, 1024, "", |g| g.net_connect_max as u64),
            ("MEM_BLKSIZE", 1, 65536, " bytes", |g| g.mem_blksize as u64),
            ("FFILE_BLKSIZE", 1, 65536, " bytes", |g| {
                g.ffile_blksize as u64
            }),
            ("FFILE_TIMEOUT", 0, 3600, " s", |g| {
                g.ffile_timeout.as_secs()
            }),
            ("FFILE_TIMEOUT_WR", 1, 60, " s", |g| {
                g.ffile_timeout_wr.as_secs()
            }),
            ("FFILE_MAXRECS", 0, 1024, "", |g| g.ffile_maxrecs as u64),
            ("NUM_OF_DECIMALS", 0, 15, "", |g| {
                u64::from(g.num_of_decimals)
            }),
            ("OUTPUT_HARD_LIMIT", 4096, 1 << 30, " bytes", |g| {
                g.output_hard_limit as u64
            }),
            ("OUTPUT_SOFT_TIMEOUT", 1, 3600, " s", |g| {
                g.output_soft_timeout.as_secs()
            }),
        ];
        for (key, min, max, unit, read) in ranges {
            assert_eq!(read(&global(&format!("{key} = {min}"))), min, "{key}");
            assert_eq!(read(&global(&format!("{key} = {max}"))), max, "{key}");
            if min > 0 {
                assert_eq!(
                    global_error(&format!("{key} = {}", min - 1)),
                    format!(
                        "PLCComS.ini:2: {key} = {} is out of range (allowed {min}-{max}{unit})",
                        min - 1
                    )
                );
            }
            assert_eq!(
                global_error(&format!("{key} = {}", max + 1)),
                format!(
                    "PLCComS.ini:2: {key} = {} is out of range (allowed {min}-{max}{unit})",
                    max + 1
                )
            );
            assert_eq!(
                global_error(&format!("{key} = -1")),
                format!("PLCComS.ini:2: {key} = -1 is not a number (allowed {min}-{max}{unit})")
            );
            assert_eq!(
                global_error(&format!("{key} = 99999999999999999999999")),
                format!("PLCComS.ini:2: {key} = 99999999999999999999999 is out of range (allowed {min}-{max}{unit})")
            );
        }
        assert_eq!(
            global_error("COMM_LOOP_DELAY = 5000"),
            "PLCComS.ini:2: COMM_LOOP_DELAY = 5000 is out of range (allowed 1-1000 ms)"
        );
        assert_eq!(
            global_error("COMM_LOOP_DELAY = 10ms"),
            "PLCComS.ini:2: COMM_LOOP_DELAY = 10ms is not a number (allowed 1-1000 ms)"
        );
        assert_eq!(
            global("COMM_LOOP_DELAY = 0050").comm_loop_delay,
            Duration::from_millis(50)
        );
    }

    #[test]
    fn output_limits() {
        let d = Global::default();
        assert_eq!(d.output_hard_limit, 16 << 20);
        assert_eq!(d.output_soft_limit, 1 << 20);
        assert_eq!(d.output_soft_timeout, Duration::from_secs(30));
        let g = global("OUTPUT_SOFT_LIMIT = 1024\nOUTPUT_HARD_LIMIT = 4096");
        assert_eq!((g.output_soft_limit, g.output_hard_limit), (1024, 4096));
        // Without its own value the soft limit follows a lower hard limit.
        assert_eq!(global("OUTPUT_HARD_LIMIT = 65536").output_soft_limit, 65536);
        assert_eq!(
            global("OUTPUT_SOFT_LIMIT = 16777216").output_soft_limit,
            16 << 20
        );
        assert_eq!(
            global_error("OUTPUT_SOFT_LIMIT = 1023"),
            "PLCComS.ini:2: OUTPUT_SOFT_LIMIT = 1023 is out of range (allowed 1024-1073741824 bytes)"
        );
        assert_eq!(
            global_error("OUTPUT_SOFT_LIMIT = 16777217"),
            "PLCComS.ini:2: OUTPUT_SOFT_LIMIT = 16777217 is above OUTPUT_HARD_LIMIT (16777216 bytes)"
        );
        assert_eq!(
            global_error("OUTPUT_HARD_LIMIT = 8192\nOUTPUT_SOFT_LIMIT = 8193"),
            "PLCComS.ini:3: OUTPUT_SOFT_LIMIT = 8193 is above OUTPUT_HARD_LIMIT (8192 bytes)"
        );
    }

    type SectionRange = (&'static str, u64, u64, &'static str, fn(&Section) -> u64);

    #[test]
    fn section_ranges() {
        let ranges: [SectionRange; 5] = [
            ("EPSADDR", 1, 126, "", |s| u64::from(s.epsaddr.unwrap())),
            ("EPSTOUT", 1, 15000, " ms", |s| s.epstout.as_millis() as u64),
            ("EPSTOUT_STEP", 0, 5000, " ms", |s| {
                s.epstout_step.as_millis() as u64
            }),
            ("EPSPORT", 1, 65535, "", |s| u64::from(s.epsport)),
            ("SERVER_PORT", 1, 65535, "", |s| u64::from(s.server_port)),
        ];
        for (key, min, max, unit, read) in ranges {
            let port = if key == "SERVER_PORT" {
                ""
            } else {
                "SERVER_PORT = 5010\n"
            };
            for value in [min, max] {
                let s = section(&format!("{port}{key} = {value}"));
                assert_eq!(read(&s), value, "{key}");
            }
            let line = if port.is_empty() { 3 } else { 4 };
            if min > 0 {
                assert_eq!(
                    section_error(&format!("{port}{key} = {}", min - 1)),
                    format!("PLCComS.ini:{line}: {key} = {} is out of range (allowed {min}-{max}{unit})", min - 1)
                );
            }
            assert_eq!(
                section_error(&format!("{port}{key} = {}", max + 1)),
                format!(
                    "PLCComS.ini:{line}: {key} = {} is out of range (allowed {min}-{max}{unit})",
                    max + 1
                )
            );
            assert_eq!(
                section_error(&format!("{port}{key} = x")),
                format!(
                    "PLCComS.ini:{line}: {key} = x is not a number (allowed {min}-{max}{unit})"
                )
            );
        }
        let s = section(
            "SERVER_PORT = 1\nSERIAL_SPEED = 115200\nSERIAL_RTS = 17\nSHM_SOCKET = 0\nSHM_PORT = 5",
        );
        assert_eq!(
            (s.serial_speed, s.serial_rts, s.shm_socket, s.shm_port),
            (Some(115200), Some(17), Some(0), Some(5))
        );
        assert_eq!(
            section_error("SERVER_PORT = 1\nSERIAL_SPEED = 0"),
            "PLCComS.ini:4: SERIAL_SPEED = 0 is out of range (allowed 1-4294967295 baud)"
        );
        assert_eq!(
            section_error("SERVER_PORT = 1\nSHM_PORT = 4294967296"),
            "PLCComS.ini:4: SHM_PORT = 4294967296 is out of range (allowed 0-4294967295)"
        );
    }

    #[test]
    fn server_port_is_required() {
        assert_eq!(
            section_error("IPADDR = 10.0.0.1"),
            "PLCComS.ini:2: section [PLC] has no SERVER_PORT"
        );
    }

    #[test]
    fn ip_addresses() {
        let s = section("SERVER_PORT = 1\nIPADDR = 192.168.001.010\nIPADDR_LOCAL = 010.0.0.1");
        assert_eq!(s.ipaddr, Some(Ipv4Addr::new(192, 168, 1, 10)));
        assert_eq!(s.ipaddr_local, Some(Ipv4Addr::new(10, 0, 0, 1)));
        assert_eq!(
            section("SERVER_PORT = 1\nIPADDR = 0.0.0.0").ipaddr,
            Some(Ipv4Addr::UNSPECIFIED)
        );
        for bad in [
            "192.168.1",
            "192.168.1.256",
            "1.2.3.4.5",
            "1..2.3",
            "a.b.c.d",
            "0001.2.3.4",
            "1.2.3.4 5",
        ] {
            assert_eq!(
                section_error(&format!("SERVER_PORT = 1\nIPADDR = {bad}")),
                format!("PLCComS.ini:4: IPADDR = {bad} is not an IPv4 address (a.b.c.d)")
            );
        }
    }

    #[test]
    fn booleans() {
        for (text, value) in [
            ("Yes", true),
            ("YES", true),
            ("yes", true),
            ("yEs", true),
            ("true", true),
            ("TRUE", true),
            ("1", true),
            ("On", true),
            ("No", false),
            ("NO", false),
            ("no", false),
            ("False", false),
            ("0", false),
            ("off", false),
        ] {
            let g = global(&format!("SCIENT_NOTATION = {text}\nEND_LINE_CRLF = {text}"));
            assert_eq!(
                (g.scient_notation, g.end_line_crlf),
                (value, value),
                "{text}"
            );
            let s = section(&format!(
                "SERVER_PORT = 1\nPUBFILE_CRC = {text}\nPUBFILE_WRITE = {text}"
            ));
            assert_eq!((s.pubfile_crc, s.pubfile_write), (value, value), "{text}");
        }
        assert_eq!(
            global_error("MEM_USE_THREADS = maybe"),
            "PLCComS.ini:2: MEM_USE_THREADS = maybe is not Yes or No"
        );
        assert_eq!(
            section_error("SERVER_PORT = 1\nPUBFILE_CRC = 2"),
            "PLCComS.ini:4: PUBFILE_CRC = 2 is not Yes or No"
        );
    }

    #[test]
    fn comments_and_quotes() {
        let g = global(concat!(
            "SERIAL_DEVICE_CFG   = \"/dev/ttyS0 -1, /dev/ttyS1 -1\"  # (Device_name RTS_gpio_pin_number)\n",
            "COMM_LOOP_DELAY = 20 ; semicolon comment\n",
        ));
        assert_eq!(
            g.serial_device_cfg.as_deref(),
            Some("/dev/ttyS0 -1, /dev/ttyS1 -1")
        );
        assert_eq!(g.comm_loop_delay, Duration::from_millis(20));

        let s = section(concat!(
            "SERVER_PORT = 1 # the port\n",
            "PUBFILE = \"//dir with spaces/a#b;c.pub\" ; comment\n",
            "PUBFILE_FIXED = 'FIXED # Foxtrot.pub'\n",
            "SHM_NAME = C:\\PLC\\ShmSrv.dll\n",
            "SERIAL_DEVICE = C:\\dev\\\n",
        ));
        assert_eq!(s.pubfile.as_deref(), Some("//dir with spaces/a#b;c.pub"));
        assert_eq!(s.pubfile_fixed.as_deref(), Some("FIXED # Foxtrot.pub"));
        assert_eq!(s.shm_name.as_deref(), Some("C:\\PLC\\ShmSrv.dll"));
        assert_eq!(s.serial_device.as_deref(), Some("C:\\dev\\"));
        assert_eq!(
            section_error("SERVER_PORT = 1\nIPADDR = 10.0.0.1#x"),
            "PLCComS.ini:4: IPADDR = 10.0.0.1#x is not an IPv4 address (a.b.c.d)"
        );
    }

    #[test]
    fn unterminated_quote() {
        assert_eq!(
            global_error("SERIAL_DEVICE_CFG = \"/dev/ttyS0 -1"),
            "PLCComS.ini:2: SERIAL_DEVICE_CFG: unterminated \" quote in value"
        );
    }

    #[test]
    fn sections_with_spaces_and_case_insensitive_keys() {
        let loaded = ok("[*]\ncomm_loop_delay = 7\n[TC700 RS232]\nserver_port = 5013\nSerial_Device = /dev/ttyS0\n  [ Indented ]  # comment\n\tServer_Port\t=\t5014\t\n");
        assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
        assert_eq!(
            loaded.config.global.comm_loop_delay,
            Duration::from_millis(7)
        );
        let s = &loaded.config.sections;
        assert_eq!(
            (s[0].name.as_str(), s[0].server_port),
            ("TC700 RS232", 5013)
        );
        assert_eq!(s[0].serial_device.as_deref(), Some("/dev/ttyS0"));
        assert_eq!((s[1].name.as_str(), s[1].server_port), ("Indented", 5014));
    }

    #[test]
    fn unknown_and_misplaced_keys_are_warnings() {
        let loaded = ok("[*]\nFOO = 1\nSERVER_PORT = 1\n[PLC]\nSERVER_PORT = 5010\nBAR = x\nNUM_OF_DECIMALS = 3\n");
        assert_eq!(
            messages(&loaded),
            [
                "PLCComS.ini:2: unknown key FOO in section [*]; ignored",
                "PLCComS.ini:3: SERVER_PORT does not belong in section [*]; ignored",
                "PLCComS.ini:6: unknown key BAR in section [PLC]; ignored",
                "PLCComS.ini:7: NUM_OF_DECIMALS does not belong in section [PLC]; ignored",
            ]
        );
        assert!(loaded
            .diagnostics
            .iter()
            .all(|d| d.severity == Severity::Warning));
        assert_eq!(loaded.config.sections.len(), 1);
    }

    #[test]
    fn duplicate_keys_keep_the_later_value() {
        let loaded =
            ok("[*]\nCOMM_LOOP_DELAY = 5\ncomm_loop_delay = 6\n[PLC]\nSERVER_PORT = 5010\n");
        assert_eq!(
            loaded.config.global.comm_loop_delay,
            Duration::from_millis(6)
        );
        assert_eq!(
            messages(&loaded),
            ["PLCComS.ini:3: COMM_LOOP_DELAY is given twice (first on line 2); this value counts"]
        );
    }

    #[test]
    fn a_bad_plc_section_is_skipped_and_the_others_load() {
        let text = "[*]\n[A]\nSERVER_PORT = 5010\n[B]\nSERVER_PORT = 5011\nEPSTOUT = 0\n[C]\nSERVER_PORT = 5012\n";
        let loaded = ok(text);
        let names: Vec<_> = loaded
            .config
            .sections
            .iter()
            .map(|s| s.name.as_str())
            .collect();
        assert_eq!(names, ["A", "C"]);
        assert_eq!(
            messages(&loaded),
            [
                "PLCComS.ini:4: section [B] skipped (1 error)",
                "PLCComS.ini:6: EPSTOUT = 0 is out of range (allowed 1-15000 ms)",
            ]
        );
        assert!(loaded
            .diagnostics
            .iter()
            .all(|d| d.severity == Severity::Error));
    }

    #[test]
    fn malformed_lines() {
        assert_eq!(
            global_error("COMM_LOOP_DELAY 100"),
            "PLCComS.ini:2: 'COMM_LOOP_DELAY 100' is neither a [SECTION] header nor KEY = VALUE"
        );
        assert_eq!(
            global_error("= 100"),
            "PLCComS.ini:2: '= 100' has no key before '='"
        );
        assert_eq!(
            global_error("A:B = 1"),
            "PLCComS.ini:2: invalid character ':' in key 'A:B'"
        );
        assert_eq!(
            section_error("SERVER_PORT = 1\nSERIAL_SPEED"),
            "PLCComS.ini:4: 'SERIAL_SPEED' is neither a [SECTION] header nor KEY = VALUE"
        );
        // A broken header keeps its keys: they do not leak into the section above.
        let loaded = ok("[*]\n[A]\nSERVER_PORT = 5010\n[B\nSERVER_PORT = 5011\nEPSTOUT = 9\n");
        assert_eq!(loaded.config.sections.len(), 1);
        assert_eq!(
            loaded.config.sections[0].epstout,
            Duration::from_millis(1000)
        );
        assert_eq!(
            messages(&loaded),
            [
                "PLCComS.ini:4: section [B] skipped (1 error)",
                "PLCComS.ini:4: section header [B has no closing ']'",
            ]
        );
        let loaded = ok("[*]\n[A] junk\nSERVER_PORT = 5010\n[C]\nSERVER_PORT = 5011\n");
        assert_eq!(loaded.config.sections[0].name, "C");
        assert_eq!(
            messages(&loaded)[1],
            "PLCComS.ini:2: unexpected 'junk' after section header [A]"
        );
    }

    #[test]
    fn duplicate_server_port_and_section_name() {
        let loaded =
            ok("[*]\n[A]\nSERVER_PORT = 5010\n[B]\nSERVER_PORT = 5010\n[a]\nSERVER_PORT = 5011\n");
        let names: Vec<_> = loaded
            .config
            .sections
            .iter()
            .map(|s| s.name.as_str())
            .collect();
        assert_eq!(names, ["A"]);
        assert_eq!(
            messages(&loaded),
            [
                "PLCComS.ini:4: section [B] skipped (1 error)",
                "PLCComS.ini:5: SERVER_PORT = 5010 is already used by section [A] (line 2)",
                "PLCComS.ini:6: section [a] skipped (1 error)",
                "PLCComS.ini:6: duplicate section [a] (the first is on line 2)",
            ]
        );
    }

    #[test]
    fn the_global_section_is_mandatory_and_unique() {
        match parse(Path::new(FILE), "[PLC]\nSERVER_PORT = 5010\n") {
            Err(ConfigError::Invalid(d)) => {
                assert_eq!(
                    d.to_string(),
                    "PLCComS.ini:1: the mandatory [*] section is missing"
                )
            }
            other => panic!("{other:?}"),
        }
        match parse(Path::new(FILE), "[*]\n[PLC]\nSERVER_PORT = 5010\n[*]\n") {
            Err(ConfigError::Invalid(d)) => {
                assert_eq!(
                    d.to_string(),
                    "PLCComS.ini:4: second [*] section (the first is on line 1)"
                )
            }
            other => panic!("{other:?}"),
        }
        // Junk before any section stops start-up too.
        match parse(Path::new(FILE), "junk\n[*]\n[PLC]\nSERVER_PORT = 5010\n") {
            Err(ConfigError::Invalid(d)) => assert_eq!(d.line, 1),
            other => panic!("{other:?}"),
        }
        let loaded = ok("KEY = 1\n[*]\n[PLC]\nSERVER_PORT = 5010\n");
        assert_eq!(
            messages(&loaded),
            ["PLCComS.ini:1: KEY is outside any section; ignored"]
        );
    }

    #[test]
    fn no_plc_section() {
        for text in ["[*]\n", "[*]\n[PLC]\nSERVER_PORT = 0\n"] {
            match parse(Path::new(FILE), text) {
                Err(e @ ConfigError::NoSections { .. }) => assert_eq!(
                    e.to_string(),
                    "PLCComS.ini: no usable PLC section (at least one section besides [*], with a SERVER_PORT, is needed)"
                ),
                other => panic!("{text}: {other:?}"),
            }
        }
    }

    #[test]
    fn io_error_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("missing.ini");
        let err = load(&path).unwrap_err();
        assert!(matches!(err, ConfigError::Io { .. }));
        assert!(err
            .to_string()
            .starts_with(&format!("cannot read {}: ", path.display())));
    }

    #[test]
    fn allow_and_read_only() {
        let s = section("SERVER_PORT = 5000");
        assert_eq!((s.allow, s.read_only), (None, false));
        let s = section(
            "SERVER_PORT = 5000\nALLOW = 127.0.0.1, 192.168.1.0/24 ,::1,fd00::/8, 10.1.2.3/8\nREAD_ONLY = Yes",
        );
        assert!(s.read_only);
        let allow = s.allow.unwrap();
        let shown: Vec<String> = allow.iter().map(ToString::to_string).collect();
        assert_eq!(
            shown,
            [
                "127.0.0.1/32",
                "192.168.1.0/24",
                "::1/128",
                "fd00::/8",
                "10.0.0.0/8"
            ]
        );
        let ok = |ip: &str| allowed(Some(&allow), ip.parse().unwrap());
        assert!(ok("127.0.0.1"));
        assert!(!ok("127.0.0.2"));
        assert!(ok("192.168.1.200"));
        assert!(!ok("192.168.2.1"));
        assert!(ok("10.255.0.1"));
        assert!(ok("::1"));
        assert!(ok("fd12::5"));
        assert!(!ok("fe80::1"));
        // An IPv4 client on an IPv6 socket.
        assert!(ok("::ffff:192.168.1.7"));
        assert!(!ok("::ffff:8.8.8.8"));
        assert!(allowed(None, "8.8.8.8".parse().unwrap()));
        let any = [Network::parse("0.0.0.0/0").unwrap()];
        assert!(allowed(Some(&any), "8.8.8.8".parse().unwrap()));
        assert!(!allowed(Some(&any), "::2".parse().unwrap()));
        for bad in [
            "10.0.0.0/33",
            "10.0.0/8",
            "host.example",
            "::1/129",
            "1.2.3.4/",
            "1.2.3.4/-1",
            "",
        ] {
            assert_eq!(
                section_error(&format!("SERVER_PORT = 5000\nALLOW = 127.0.0.1,{bad}")),
                format!("PLCComS.ini:4: ALLOW = 127.0.0.1,{bad} has '{bad}', which is not an IPv4 or IPv6 address or network (a.b.c.d, a.b.c.d/n, x:y::z, x:y::/n)"),
            );
        }
        assert_eq!(
            section_error("SERVER_PORT = 5000\nREAD_ONLY = maybe"),
            "PLCComS.ini:4: READ_ONLY = maybe is not Yes or No"
        );
    }

    #[test]
    fn simulator() {
        let s = section("SERVER_PORT = 1\nSIMULATOR = Yes");
        assert_eq!(
            s.simulator,
            Some(Simulator {
                program: "demo".into(),
                pubfile: None
            })
        );
        let s = section("SERVER_PORT = 1\nSIMULATOR = yes\nSIMULATOR_PROGRAM = Idle\nSIMULATOR_PUB = sim/demo.pub");
        assert_eq!(
            s.simulator,
            Some(Simulator {
                program: "idle".into(),
                pubfile: Some("sim/demo.pub".into())
            })
        );
        assert_eq!(
            section_error("SERVER_PORT = 1\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = fast"),
            "PLCComS.ini:5: SIMULATOR_PROGRAM = fast is not a simulator program (allowed demo, idle)"
        );
        let loaded =
            with_section("SERVER_PORT = 1\nIPADDR = 10.0.0.1\nSIMULATOR_PROGRAM = idle").unwrap();
        assert_eq!(loaded.config.sections[0].simulator, None);
        assert_eq!(
            messages(&loaded),
            ["PLCComS.ini:5: SIMULATOR_PROGRAM has no effect without SIMULATOR = Yes"]
        );
    }

    #[test]
    fn crlf_bom_and_non_utf8() {
        let loaded = ok("\u{feff}[*]\r\nCOMM_LOOP_DELAY = 9\r\n[PLC]\r\nSERVER_PORT = 5010\r\n");
        assert_eq!(
            loaded.config.global.comm_loop_delay,
            Duration::from_millis(9)
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cp1250.ini");
        std::fs::write(
            &path,
            b"# koment\xe1\xf8\n[*]\n[Kuchyn\xec]\nSERVER_PORT = 5010\nPUBFILE = a\xec.pub\n",
        )
        .unwrap();
        let loaded = load(&path).unwrap();
        assert_eq!(loaded.config.sections.len(), 1);
        let warnings: Vec<_> = loaded
            .diagnostics
            .iter()
            .map(|d| (d.line, d.severity))
            .collect();
        assert_eq!(warnings, [(3, Severity::Warning), (5, Severity::Warning)]);
    }
}
