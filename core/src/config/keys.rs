//! The table of keys: every key of the ini file once, with its scope,
//! default, kind of value (and range), the field it sets, its SETCONF name
//! and a line of documentation. Loading, validation, messages, defaults,
//! SETCONF and the check of `PLCComS.ini.example` all read it.

use std::net::{IpAddr, Ipv4Addr};
use std::time::Duration;

use super::broker::BrokerUrl;
use super::history::{self, Form};
use super::serial;
use super::{
    split_masks, Global, MqttFormat, Network, Protocol, Section, Simulator, MQTT_FORMATS,
    OPCUA_MODES, OPCUA_SECURITY_CHOICES,
};

pub use super::protocol::PROTOCOLS;

/// The simulator programs `SIMULATOR_PROGRAM` accepts.
pub const SIMULATOR_PROGRAMS: [&str; 2] = ["demo", "idle"];

/// Every SETCONF name, for `SETCONF_KEYS`.
pub const SETCONF_NAMES: [&str; 9] = [
    "crlf",
    "diff",
    "ipaddr",
    "epsaddr",
    "epsport",
    "serial_device",
    "serial_speed",
    "pubfile",
    "trace",
];

/// Where a key is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scope {
    /// `[*]`.
    Global,
    /// A PLC section.
    Section,
}

/// What a SETCONF of a key changes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SetConfScope {
    /// The asking client only.
    Client,
    /// The section, for all its clients.
    Section,
}

/// The values a key takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Decimal digits, `min..=max`; `unit` decorates messages only.
    Number {
        min: u64,
        max: u64,
        unit: &'static str,
    },
    /// See [`parse_bool`].
    Bool,
    /// See [`parse_ipv4`].
    Ipv4,
    /// An IPv4 or IPv6 address.
    IpAddr,
    /// Any text.
    Text,
    /// A comma-separated list of [`Network`]s.
    Networks,
    /// One of `choices` in any case; the value is the choice as listed.
    Choice {
        what: &'static str,
        choices: &'static [&'static str],
    },
    /// A comma-separated list of `choices`, any case.
    Choices {
        what: &'static str,
        choices: &'static [&'static str],
    },
    /// Text of a form of the historian's (`history.rs`), checked on load.
    Form(Form),
    /// A file or folder on this machine, relative to the configuration's
    /// folder unless absolute; what the server does with it decides what
    /// clients may do with it ([`PathUse`]).
    Path(PathUse),
}

/// What the server does with a path a key names. Every such path is the
/// server's own: line-protocol clients never write it (`localfs::protect`,
/// registered from [`super::Config::own_paths`] at start).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PathUse {
    /// Read by the server: certificates, tag and public files, libraries,
    /// devices. Clients may read it.
    Input,
    /// Holds a private key or a password: clients do not read it either.
    Secret,
    /// A folder the server writes (history, queues): clients neither read
    /// nor write it.
    State,
    /// The folder clients' own files live in (FILES_ROOT): theirs.
    ClientFiles,
}

/// A parsed value, of the key's [`Kind`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Value {
    Number(u64),
    Bool(bool),
    Ipv4(Ipv4Addr),
    IpAddr(IpAddr),
    Text(String),
    Networks(Vec<Network>),
    Choice(&'static str),
    Choices(Vec<&'static str>),
}

/// Sets a key's field.
#[derive(Debug, Clone, Copy)]
pub(super) enum Setter {
    Global(fn(&mut Global, Value)),
    Section(fn(&mut Section, Value)),
}

/// One row of the table.
#[derive(Debug)]
pub struct Key {
    /// Upper case, as the manual writes it.
    pub name: &'static str,
    /// The value when the key is absent or empty, as ini text; `None`: unset.
    pub default: Option<&'static str>,
    pub kind: Kind,
    /// One line for people.
    pub doc: &'static str,
    setter: Setter,
    setconf: Option<(&'static str, SetConfScope)>,
}

/// Every key.
pub fn keys() -> &'static [Key] {
    KEYS
}

/// The names of the `[*]` keys.
pub fn global_keys() -> impl Iterator<Item = &'static str> {
    of_scope(Scope::Global).map(|k| k.name)
}

/// The names of the PLC section keys.
pub fn section_keys() -> impl Iterator<Item = &'static str> {
    of_scope(Scope::Section).map(|k| k.name)
}

/// The key of `scope` named `name` (upper case).
pub fn key(scope: Scope, name: &str) -> Option<&'static Key> {
    of_scope(scope).find(|k| k.name == name)
}

/// The key a SETCONF name (any case) changes.
pub fn setconf_key(name: &str) -> Option<&'static Key> {
    KEYS.iter().find(|k| {
        k.setconf_name()
            .is_some_and(|n| n.eq_ignore_ascii_case(name))
    })
}

pub(super) fn of_scope(scope: Scope) -> impl Iterator<Item = &'static Key> {
    KEYS.iter().filter(move |k| k.scope() == scope)
}

impl Key {
    pub fn scope(&self) -> Scope {
        match self.setter {
            Setter::Global(_) => Scope::Global,
            Setter::Section(_) => Scope::Section,
        }
    }

    /// The name SETCONF knows the key by (lower case), if any.
    pub fn setconf_name(&self) -> Option<&'static str> {
        self.setconf.map(|(name, _)| name)
    }

    pub fn setconf_scope(&self) -> Option<SetConfScope> {
        self.setconf.map(|(_, scope)| scope)
    }

    /// Parses a value; `Err` is the problem, as in `is out of range
    /// (allowed 1-126)`.
    pub fn parse(&self, text: &str) -> Result<Value, String> {
        self.kind.parse(text)
    }

    /// The default, parsed; `None` when the key is unset by default.
    pub fn default_value(&self) -> Option<Value> {
        self.default.and_then(|text| self.kind.parse(text).ok())
    }

    /// SETCONF of a section-wide key: parses `value` as the ini key is parsed
    /// (the same kind and range) and sets the field. `Err` says what is
    /// wrong and what is allowed.
    pub fn apply_setconf(&self, section: &mut Section, value: &str) -> Result<(), String> {
        let (Some((name, SetConfScope::Section)), Setter::Section(set)) =
            (self.setconf, self.setter)
        else {
            return Err(format!("{} is not a section-wide SETCONF key", self.name));
        };
        let parsed = self
            .parse(value)
            .map_err(|problem| format!("{name} = {value} {problem}"))?;
        set(section, parsed);
        Ok(())
    }

    pub(super) fn set<T: Settings>(&self, target: &mut T, value: Value) {
        target.apply(self.setter, value);
    }

    /// [`Key::set`], and a path key's value noted for
    /// [`super::Config::own_paths`].
    pub(super) fn set_recording_path<T: Settings>(&self, target: &mut T, value: Value) {
        if let (Kind::Path(used), Value::Text(text)) = (self.kind, &value) {
            let paths = target.paths_mut();
            paths.retain(|p| p.key != self.name);
            paths.push(ConfiguredPath {
                key: self.name,
                text: text.clone(),
                used,
            });
        }
        self.set(target, value);
    }
}

/// The structs rows set: `[*]` and a PLC section.
pub(super) trait Settings {
    const SCOPE: Scope;
    fn apply(&mut self, setter: Setter, value: Value);
    /// The paths the file's keys name, as written.
    fn paths_mut(&mut self) -> &mut Vec<ConfiguredPath>;
}

impl Settings for Global {
    const SCOPE: Scope = Scope::Global;
    fn apply(&mut self, setter: Setter, value: Value) {
        if let Setter::Global(set) = setter {
            set(self, value);
        }
    }
    fn paths_mut(&mut self) -> &mut Vec<ConfiguredPath> {
        &mut self.paths
    }
}

impl Settings for Section {
    const SCOPE: Scope = Scope::Section;
    fn apply(&mut self, setter: Setter, value: Value) {
        if let Setter::Section(set) = setter {
            set(self, value);
        }
    }
    fn paths_mut(&mut self) -> &mut Vec<ConfiguredPath> {
        &mut self.paths
    }
}

/// A path a key of the file names (or its default), as written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfiguredPath {
    pub key: &'static str,
    pub text: String,
    pub used: PathUse,
}

/// `target` with the default of every key of its scope applied.
pub(super) fn with_defaults<T: Settings>(mut target: T) -> T {
    for key in of_scope(T::SCOPE) {
        if let Some(value) = key.default_value() {
            key.set_recording_path(&mut target, value);
        }
    }
    target
}

// ---------------------------------------------------------------------------
// Value parsers.

/// The spellings of a boolean: true, then false.
const BOOLS: [(&str, &str); 4] = [("Yes", "No"), ("True", "False"), ("On", "Off"), ("1", "0")];

/// `Yes`/`No`, `True`/`False`, `On`/`Off` or `1`/`0`, in any case: the one
/// boolean grammar of the ini file and SETCONF.
pub fn parse_bool(text: &str) -> Option<bool> {
    BOOLS.iter().find_map(|(yes, no)| {
        if yes.eq_ignore_ascii_case(text) {
            Some(true)
        } else if no.eq_ignore_ascii_case(text) {
            Some(false)
        } else {
            None
        }
    })
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

impl Kind {
    /// What the kind allows, as messages show it after `allowed`.
    pub fn allowed(&self) -> String {
        match self {
            Kind::Number { min, max, unit: "" } => format!("{min}-{max}"),
            Kind::Number { min, max, unit } => format!("{min}-{max} {unit}"),
            Kind::Bool => BOOLS
                .iter()
                .map(|(yes, no)| format!("{yes}/{no}"))
                .collect::<Vec<_>>()
                .join(", "),
            Kind::Ipv4 => "a.b.c.d, each part 0-255".to_string(),
            Kind::IpAddr => "a.b.c.d or x:y::z".to_string(),
            Kind::Text => "any non-empty text".to_string(),
            Kind::Path(_) => "a file or folder name".to_string(),
            Kind::Networks => "a.b.c.d, a.b.c.d/n, x:y::z, x:y::/n".to_string(),
            Kind::Choice { choices, .. } => choices.join(", "),
            Kind::Choices { choices, .. } => format!("a list of {}", choices.join(", ")),
            Kind::Form(form) => form.allowed().to_string(),
        }
    }

    /// `Err` is the problem with `text` and what is allowed instead.
    pub fn parse(&self, text: &str) -> Result<Value, String> {
        let allowed = format!("(allowed {})", self.allowed());
        match *self {
            Kind::Number { min, max, .. } => {
                if text.is_empty() || !text.bytes().all(|b| b.is_ascii_digit()) {
                    return Err(format!("is not a number {allowed}"));
                }
                match text.parse::<u64>() {
                    Ok(n) if (min..=max).contains(&n) => Ok(Value::Number(n)),
                    _ => Err(format!("is out of range {allowed}")),
                }
            }
            Kind::Bool => parse_bool(text)
                .map(Value::Bool)
                .ok_or_else(|| format!("is not Yes or No {allowed}")),
            Kind::Ipv4 => parse_ipv4(text)
                .map(Value::Ipv4)
                .ok_or_else(|| format!("is not an IPv4 address {allowed}")),
            Kind::IpAddr => text
                .parse()
                .map(Value::IpAddr)
                .map_err(|_| format!("is not an IP address {allowed}")),
            Kind::Text | Kind::Path(_) if text.is_empty() => Err(format!("is empty {allowed}")),
            Kind::Text | Kind::Path(_) => Ok(Value::Text(text.to_string())),
            Kind::Networks => text
                .split(',')
                .map(str::trim)
                .map(|part| {
                    Network::parse(part).ok_or_else(|| {
                        format!("has '{part}', which is not an IPv4 or IPv6 address or network {allowed}")
                    })
                })
                .collect::<Result<Vec<_>, _>>()
                .map(Value::Networks),
            Kind::Choice { what, choices } => choices
                .iter()
                .find(|c| c.eq_ignore_ascii_case(text))
                .map(|&c| Value::Choice(c))
                .ok_or_else(|| format!("is not a {what} {allowed}")),
            Kind::Choices { what, choices } => text
                .split(',')
                .map(str::trim)
                .map(|part| {
                    choices
                        .iter()
                        .find(|c| c.eq_ignore_ascii_case(part))
                        .copied()
                        .ok_or_else(|| format!("has '{part}', which is not a {what} {allowed}"))
                })
                .collect::<Result<Vec<_>, _>>()
                .map(Value::Choices),
            Kind::Form(form) => form
                .check(text)
                .map(|()| Value::Text(text.to_string()))
                .map_err(|problem| format!("{problem} {allowed}")),
        }
    }
}

impl Value {
    // A row's setter reads the value of the row's kind: any other is a bug in
    // the table, which the tests apply row by row.

    fn number(self) -> u64 {
        match self {
            Value::Number(n) => n,
            other => mismatch(&other),
        }
    }

    fn millis(self) -> Duration {
        Duration::from_millis(self.number())
    }

    fn secs(self) -> Duration {
        Duration::from_secs(self.number())
    }

    fn bool(self) -> bool {
        match self {
            Value::Bool(b) => b,
            other => mismatch(&other),
        }
    }

    fn ipv4(self) -> Ipv4Addr {
        match self {
            Value::Ipv4(ip) => ip,
            other => mismatch(&other),
        }
    }

    fn ip_addr(self) -> IpAddr {
        match self {
            Value::IpAddr(ip) => ip,
            other => mismatch(&other),
        }
    }

    fn text(self) -> String {
        match self {
            Value::Text(text) => text,
            Value::Choice(choice) => choice.to_string(),
            other => mismatch(&other),
        }
    }

    fn protocol(self) -> Protocol {
        match self {
            // The key's choices are the enum's names.
            Value::Choice(name) => {
                Protocol::parse(name).unwrap_or_else(|| mismatch(&Value::Choice(name)))
            }
            other => mismatch(&other),
        }
    }

    fn choices(self) -> Vec<&'static str> {
        match self {
            Value::Choices(list) => list,
            other => mismatch(&other),
        }
    }

    fn networks(self) -> Vec<Network> {
        match self {
            Value::Networks(list) => list,
            other => mismatch(&other),
        }
    }
}

fn mismatch(value: &Value) -> ! {
    unreachable!("a key's setter does not take {value:?}")
}

/// The key of `scope` that `unknown` is probably a typo of: at most two edits
/// (Damerau-Levenshtein, a swap of neighbours counting once) away, or one of
/// the two a prefix of the other.
pub(super) fn suggest(scope: Scope, unknown: &str) -> Option<&'static str> {
    of_scope(scope)
        .filter_map(|key| {
            let distance = edit_distance(unknown, key.name);
            let prefix = unknown.len() >= 4
                && (key.name.starts_with(unknown) || unknown.starts_with(key.name));
            ((distance <= 2 && distance * 2 < unknown.len()) || prefix)
                .then_some((distance, key.name))
        })
        .min_by_key(|&(distance, _)| distance)
        .map(|(_, name)| name)
}

/// Optimal string alignment distance, on bytes.
fn edit_distance(a: &str, b: &str) -> usize {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    // d[i][j]: the distance between a[..i] and b[..j].
    let mut d = vec![vec![0usize; b.len() + 1]; a.len() + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    for (j, cell) in d[0].iter_mut().enumerate() {
        *cell = j;
    }
    for i in 1..=a.len() {
        for j in 1..=b.len() {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut best = (d[i - 1][j] + 1)
                .min(d[i][j - 1] + 1)
                .min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                best = best.min(d[i - 2][j - 2] + 1);
            }
            d[i][j] = best;
        }
    }
    d[a.len()][b.len()]
}

// ---------------------------------------------------------------------------
// The table.

const U32_MAX: u64 = u32::MAX as u64;

const fn number(min: u64, max: u64, unit: &'static str) -> Kind {
    Kind::Number { min, max, unit }
}

const fn choice(what: &'static str, choices: &'static [&'static str]) -> Kind {
    Kind::Choice { what, choices }
}

const fn row(
    name: &'static str,
    default: Option<&'static str>,
    kind: Kind,
    doc: &'static str,
    setter: Setter,
) -> Key {
    Key {
        name,
        default,
        kind,
        doc,
        setter,
        setconf: None,
    }
}

impl Key {
    const fn setconf(self, name: &'static str, scope: SetConfScope) -> Key {
        Key {
            setconf: Some((name, scope)),
            ..self
        }
    }
}

// Ranges fit the field types, so the casts below cannot truncate. Keys that
// depend on others (SIMULATOR_PROGRAM and SIMULATOR_PUB on SIMULATOR) come
// after them: rows apply in table order.
#[rustfmt::skip]
static KEYS: &[Key] = &[
    // [*]
    row("COMM_LOOP_DELAY", Some("100"), number(1, 1000, "ms"), "poll period",
        Setter::Global(|g, v| g.comm_loop_delay = v.millis())),
    row("COMM_SCHED_PRI", Some("0"), number(0, 99, ""),
        "real-time priority of the poll loop (0 = off; each section's loop then gets a thread of its own)",
        Setter::Global(|g, v| g.comm_sched_pri = v.number() as u8)),
    row("NET_CONNECT_MAX", Some("128"), number(1, 1024, ""), "client connections per section",
        Setter::Global(|g, v| g.net_connect_max = v.number() as usize)),
    row("MEM_BLKSIZE", Some("4096"), number(1, 65536, "bytes"), "GETMEM: block size",
        Setter::Global(|g, v| g.mem_blksize = v.number() as usize)),
    row("MEM_USE_THREADS", Some("Yes"), Kind::Bool, "accepted for compatibility",
        Setter::Global(|g, v| g.mem_use_threads = v.bool())),
    row("FFILE_BLKSIZE", Some("4096"), number(1, 65536, "bytes"), "GETFILE: block size",
        Setter::Global(|g, v| g.ffile_blksize = v.number() as usize)),
    row("FFILE_TIMEOUT", Some("300"), number(0, 3600, "s"), "how long a PLC file stays cached",
        Setter::Global(|g, v| g.ffile_timeout = v.secs())),
    row("FFILE_TIMEOUT_WR", Some("5"), number(1, 60, "s"), "time allowed between WRITEFILE: blocks",
        Setter::Global(|g, v| g.ffile_timeout_wr = v.secs())),
    row("FFILE_MAXRECS", Some("256"), number(0, 1024, ""), "PLC files cached (0 = no cache)",
        Setter::Global(|g, v| g.ffile_maxrecs = v.number() as usize)),
    row("END_LINE_CRLF", Some("Yes"), Kind::Bool, "line end: Yes = \\r\\n, No = \\n",
        Setter::Global(|g, v| g.end_line_crlf = v.bool()))
        .setconf("crlf", SetConfScope::Client),
    row("PF_VAR_DISABLED", Some("Yes"), Kind::Bool, "new clients start with all variables disabled",
        Setter::Global(|g, v| g.pf_var_disabled = v.bool())),
    row("DIFF_VAR_ENABLED", Some("Yes"), Kind::Bool, "send DIFF: lines",
        Setter::Global(|g, v| g.diff_var_enabled = v.bool()))
        .setconf("diff", SetConfScope::Client),
    row("SYNC_VAR_ENABLED", Some("Yes"), Kind::Bool, "keep polling during file transfers",
        Setter::Global(|g, v| g.sync_var_enabled = v.bool())),
    row("DATE_TIME_DECIMAL", Some("No"), Kind::Bool,
        "DATE and DT as real numbers instead of raw bits",
        Setter::Global(|g, v| g.date_time_decimal = v.bool())),
    row("LIM_OF_DECIMALS", Some("No"), Kind::Bool,
        "compare REAL/LREAL at the printed precision for DIFF:",
        Setter::Global(|g, v| g.lim_of_decimals = v.bool())),
    row("NUM_OF_DECIMALS", Some("10"), number(0, 15, ""), "decimals printed",
        Setter::Global(|g, v| g.num_of_decimals = v.number() as u8)),
    row("SCIENT_NOTATION", Some("No"), Kind::Bool, "REAL/LREAL in scientific notation",
        Setter::Global(|g, v| g.scient_notation = v.bool())),
    row("SERIAL_DEVICE_CFG", None, Kind::Text, "serial devices and their RTS pins",
        Setter::Global(|g, v| g.serial_device_cfg = super::serial::parse_device_cfg(&v.text()).ok())),
    // This server's own keys.
    row("OUTPUT_HARD_LIMIT", Some("16777216"), number(4096, 1 << 30, "bytes"),
        "output queued for one client beyond which it is disconnected at once",
        Setter::Global(|g, v| g.output_hard_limit = v.number() as usize)),
    row("OUTPUT_SOFT_LIMIT", Some("1048576"), number(1024, 1 << 30, "bytes"),
        "output queued for one client that it may hold only for OUTPUT_SOFT_TIMEOUT",
        Setter::Global(|g, v| g.output_soft_limit = v.number() as usize)),
    row("OUTPUT_SOFT_TIMEOUT", Some("30"), number(1, 3600, "s"),
        "time at or over OUTPUT_SOFT_LIMIT before a client that does not read is disconnected",
        Setter::Global(|g, v| g.output_soft_timeout = v.secs())),
    row("FILES_ROOT", None, Kind::Path(PathUse::ClientFiles),
        "folder of the PC files clients read and write (names beginning with .); \
         default: files in $STATE_DIRECTORY under systemd, else the configuration's folder",
        Setter::Global(|g, v| g.files_root = Some(v.text().into()))),
    row("FILES_QUOTA", None, number(0, u64::MAX, "bytes"),
        "bytes the files root may hold for WRITEFILE to add to it; \
         default: the smaller of 1 GiB and a tenth of the free space",
        Setter::Global(|g, v| g.files_quota = Some(v.number()))),
    // The built-in web page, /metrics and the JSON API (src/web).
    row("HTTP_PORT", None, number(1, 65535, ""), "TCP port of the web page and API (unset = off)",
        Setter::Global(|g, v| g.http_port = Some(v.number() as u16))),
    row("HTTP_BIND", Some("127.0.0.1"), Kind::IpAddr, "address the web page listens on",
        Setter::Global(|g, v| g.http_bind = v.ip_addr())),
    row("HTTP_TOKEN", None, Kind::Text,
        "token for writes, and for everything when HTTP_BIND is not a loopback address",
        Setter::Global(|g, v| g.http_token = Some(v.text()))),
    row("HTTP_HOSTS", None, Kind::Text,
        "host names (name or name:port, comma-separated) the web page answers to besides \
         its address and, on loopback, localhost; * for any",
        Setter::Global(|g, v| {
            g.http_hosts = v.text().split(',').map(|h| h.trim().to_ascii_lowercase())
                .filter(|h| !h.is_empty()).collect()
        })),
    row("HTTP_CERT", None, Kind::Path(PathUse::Input), "TLS certificate chain (PEM) of the web page",
        Setter::Global(|g, v| g.http_cert = Some(v.text()))),
    row("HTTP_KEY", None, Kind::Path(PathUse::Secret), "TLS private key (PEM) of the web page",
        Setter::Global(|g, v| g.http_key = Some(v.text()))),
    // The historian (issue 13).
    row("HISTORY_DIR", None, Kind::Path(PathUse::State),
        "folder of the history files, relative to $STATE_DIRECTORY under systemd, else to the configuration's folder (default: history)",
        Setter::Global(|g, v| g.history_dir = Some(v.text()))),
    row("HISTORY_RETENTION", None, Kind::Form(Form::Retention),
        "history kept: days and/or a size; older day files are deleted (default: all)",
        Setter::Global(|g, v| g.history_retention = history::parse_retention(&v.text()).unwrap_or_default())),
    row("HISTORY_SYNC", Some("1"), number(1, 3600, "s"),
        "seconds between durable commits of the history (at most this much is lost on a crash)",
        Setter::Global(|g, v| g.history_sync = v.secs())),
    row("HISTORY_COMPACT", Some("3600"), number(0, 86_400, "s"),
        "seconds after which samples are packed into compressed blocks (a few bytes each instead of ~20); 0 = never",
        Setter::Global(|g, v| g.history_compact = v.secs())),
    row("HISTORY_QUERY_TIMEOUT", Some("300"), number(1, 86_400, "s"),
        "seconds an /api/history answer may take, a slow or stalled reader included; then it ends with an error line",
        Setter::Global(|g, v| g.history_query_timeout = v.secs())),
    // MQTT (apps/mqtt/src/): the broker, the client, the spool.
    row("MQTT_URL", None, Kind::Text,
        "broker: mqtt://host[:port] (1883) or mqtts://host[:port] (8883, TLS); several (a cluster's nodes, a standby) separated by commas or blanks are tried round robin, moving on when one is lost; unset = MQTT off",
        Setter::Global(|g, v| g.mqtt.url = BrokerUrl::parse_list(&v.text()).ok())),
    row("MQTT_VERSION", Some("5"), choice("MQTT version", &["5", "3.1.1"]),
        "MQTT protocol version: 5, or 3.1.1 for brokers without 5 (NATS, RabbitMQ before 3.13); with 3.1.1 a retained /set is refused only when it comes at subscription",
        Setter::Global(|g, v| g.mqtt.v311 = v.text() == "3.1.1")),
    row("MQTT_USER", None, Kind::Text, "user name at the broker",
        Setter::Global(|g, v| g.mqtt.user = Some(v.text()))),
    row("MQTT_PASSWORD", None, Kind::Text, "password at the broker",
        Setter::Global(|g, v| g.mqtt.password = Some(v.text()))),
    row("MQTT_PASSWORD_FILE", None, Kind::Path(PathUse::Secret), "file holding the password (instead of MQTT_PASSWORD)",
        Setter::Global(|g, v| g.mqtt.password_file = Some(v.text()))),
    row("MQTT_CLIENT_ID", None, Kind::Text,
        "client id base (default plccoms-<host name>-<hash of the configuration path>)",
        Setter::Global(|g, v| g.mqtt.client_id = Some(v.text()))),
    row("MQTT_PREFIX", Some("plccoms"), Kind::Text, "first topic level(s)",
        Setter::Global(|g, v| g.mqtt.prefix = v.text())),
    row("MQTT_CA", None, Kind::Path(PathUse::Input), "PEM file of the CA(s) the broker's certificate is checked against",
        Setter::Global(|g, v| g.mqtt.ca = Some(v.text()))),
    row("MQTT_CERT", None, Kind::Path(PathUse::Input), "PEM file of a client certificate (with MQTT_KEY)",
        Setter::Global(|g, v| g.mqtt.cert = Some(v.text()))),
    row("MQTT_KEY", None, Kind::Path(PathUse::Secret), "PEM file of the client certificate's private key",
        Setter::Global(|g, v| g.mqtt.key = Some(v.text()))),
    row("MQTT_BUFFER", Some("67108864"), number(65536, 1 << 40, "bytes"),
        "unsent messages kept on disk per section; over it the oldest are dropped",
        Setter::Global(|g, v| g.mqtt.buffer = v.number())),
    row("MQTT_SPOOL", Some("mqtt-spool"), Kind::Path(PathUse::State),
        "folder of the on-disk queues, relative to $STATE_DIRECTORY under systemd, else to the configuration's folder",
        Setter::Global(|g, v| g.mqtt.spool = v.text())),
    row("SPARKPLUG_GROUP", Some("plccoms"), Kind::Text, "Sparkplug B group id of the edge node",
        Setter::Global(|g, v| g.mqtt.sparkplug_group = v.text())),
    row("SPARKPLUG_NODE", None, Kind::Text, "Sparkplug B edge node id (default: the host name)",
        Setter::Global(|g, v| g.mqtt.sparkplug_node = Some(v.text()))),
    row("SPARKPLUG_HOST", None, Kind::Text,
        "Sparkplug B primary host id: publish only while its STATE says online (default: none, always publish)",
        Setter::Global(|g, v| g.mqtt.sparkplug_host = Some(v.text()))),
    // OPC UA (apps/opcua/src/): the server, its security and its limits.
    row("OPCUA_PORT", None, number(1, 65535, ""), "TCP port of the OPC UA server (4840 is the standard; unset = off)",
        Setter::Global(|g, v| g.opcua.port = Some(v.number() as u16))),
    row("OPCUA_HOST", Some("127.0.0.1"), Kind::Text, "address the OPC UA server binds and names in its endpoint URLs",
        Setter::Global(|g, v| g.opcua.host = v.text())),
    row("OPCUA_SECURITY", Some("None, Basic256Sha256 Sign, Basic256Sha256 SignAndEncrypt"),
        Kind::Choices { what: "security policy and mode", choices: &OPCUA_SECURITY_CHOICES },
        "endpoints offered; None only on a loopback OPCUA_HOST unless OPCUA_ANONYMOUS",
        Setter::Global(|g, v| g.opcua.security = v.choices())),
    row("OPCUA_USERS", None, Kind::Path(PathUse::Secret),
        "file of users: name, role (read or write) and PBKDF2-SHA256 password hash per line",
        Setter::Global(|g, v| g.opcua.users = Some(v.text()))),
    row("OPCUA_ANONYMOUS", Some("No"), Kind::Bool,
        "anonymous sessions and the None policy also when OPCUA_HOST is not a loopback address",
        Setter::Global(|g, v| g.opcua.anonymous = v.bool())),
    row("OPCUA_PKI", Some("opcua-pki"), Kind::Path(PathUse::State),
        "folder of the server's certificate and key (made on first start), trusted/ and rejected/ client certificates",
        Setter::Global(|g, v| g.opcua.pki = v.text())),
    row("OPCUA_MAX_SESSIONS", Some("100"), number(1, 100_000, ""), "OPC UA sessions at once",
        Setter::Global(|g, v| g.opcua.max_sessions = v.number() as usize)),
    row("OPCUA_MAX_SUBSCRIPTIONS", Some("100"), number(1, 100_000, ""), "subscriptions per OPC UA session",
        Setter::Global(|g, v| g.opcua.max_subscriptions = v.number() as usize)),
    row("OPCUA_MAX_MONITORED_ITEMS", Some("100000"), number(1, 10_000_000, ""), "monitored items per OPC UA subscription",
        Setter::Global(|g, v| g.opcua.max_monitored_items = v.number() as usize)),
    row("OPCUA_MAX_NODES_PER_CALL", Some("100000"), number(100, 10_000_000, ""),
        "nodes (or monitored items) one OPC UA Read, Write, Browse or CreateMonitoredItems may name",
        Setter::Global(|g, v| g.opcua.max_nodes_per_call = v.number() as usize)),

    // A PLC section.
    row("IPADDR", None, Kind::Ipv4, "IP address of the PLC (0.0.0.0 = none yet)",
        Setter::Section(|s, v| s.ipaddr = Some(v.ipv4())))
        .setconf("ipaddr", SetConfScope::Section),
    row("IPADDR_LOCAL", None, Kind::Ipv4, "local address for the PLC link and the client port",
        Setter::Section(|s, v| s.ipaddr_local = Some(v.ipv4()))),
    row("EPSADDR", None, number(1, 126, ""),
        "EPSNET source address; chosen automatically if not set",
        Setter::Section(|s, v| s.epsaddr = Some(v.number() as u8)))
        .setconf("epsaddr", SetConfScope::Section),
    row("EPSTOUT", Some("1000"), number(1, 15000, "ms"), "EPSNET timeout",
        Setter::Section(|s, v| s.epstout = v.millis())),
    row("EPSTOUT_STEP", Some("500"), number(0, 5000, "ms"), "EPSNET timeout step per retry",
        Setter::Section(|s, v| s.epstout_step = v.millis())),
    row("EPSPORT", Some("61682"), number(1, 65535, ""), "EPSNET UDP port",
        Setter::Section(|s, v| s.epsport = v.number() as u16))
        .setconf("epsport", SetConfScope::Section),
    row("SERVER_PORT", None, number(1, 65535, ""), "TCP port clients connect to (required)",
        Setter::Section(|s, v| s.server_port = v.number() as u16)),
    row("SERIAL_DEVICE", None, Kind::Path(PathUse::Input), "serial device of the PLC link",
        Setter::Section(|s, v| s.serial_device = Some(v.text())))
        .setconf("serial_device", SetConfScope::Section),
    row("SERIAL_SPEED", None, number(1, U32_MAX, "baud"), "serial line speed",
        Setter::Section(|s, v| s.serial_speed = Some(v.number() as u32)))
        .setconf("serial_speed", SetConfScope::Section),
    row("SERIAL_RTS", None, number(0, U32_MAX, ""), "serial RTS control",
        Setter::Section(|s, v| s.serial_rts = Some(v.number() as u32))),
    row("SERIAL_PARITY", None, choice("parity", &serial::PARITIES),
        "serial parity of PROTOCOL = MODBUS_RTU (default EVEN)",
        Setter::Section(|s, v| s.serial_parity = serial::Parity::parse(&v.text()))),
    row("SERIAL_DATA_BITS", None, number(7, 8, ""), "serial data bits of PROTOCOL = MODBUS_RTU (default 8)",
        Setter::Section(|s, v| s.serial_data_bits = Some(v.number() as u8))),
    row("SERIAL_STOP_BITS", None, number(1, 2, ""), "serial stop bits of PROTOCOL = MODBUS_RTU (default 1)",
        Setter::Section(|s, v| s.serial_stop_bits = Some(v.number() as u8))),
    row("SHM_NAME", None, Kind::Path(PathUse::Input), "shared-memory module of a SoftPLC",
        Setter::Section(|s, v| s.shm_name = Some(v.text()))),
    row("SHM_SOCKET", None, number(0, U32_MAX, ""), "shared-memory socket of a SoftPLC",
        Setter::Section(|s, v| s.shm_socket = Some(v.number() as u32))),
    row("SHM_PORT", None, number(0, U32_MAX, ""), "shared-memory port of a SoftPLC",
        Setter::Section(|s, v| s.shm_port = Some(v.number() as u32))),
    row("PUBFILE_CRC", Some("No"), Kind::Bool, "check the public file's CRC against __PF_CRC",
        Setter::Section(|s, v| s.pubfile_crc = v.bool())),
    row("PUBFILE_WRITE", Some("No"), Kind::Bool,
        "store public files fetched from the PLC in a folder named after the section",
        Setter::Section(|s, v| s.pubfile_write = v.bool())),
    row("PUBFILE", None, Kind::Path(PathUse::Input),
        "user public file: //name = root folder; local first, else fetched from the PLC",
        Setter::Section(|s, v| s.pubfile = Some(v.text())))
        .setconf("pubfile", SetConfScope::Section),
    row("PUBFILE_FIXED", None, Kind::Path(PathUse::Input), "fixed public file; built in when not set",
        Setter::Section(|s, v| s.pubfile_fixed = Some(v.text()))),
    // This server's own keys.
    row("PROTOCOL", Some(Protocol::Epsnet.name()), choice("protocol", PROTOCOLS),
        "backend: EPSNET (default), MODBUS_TCP, MODBUS_RTU, MODBUS_RTU_TCP, S7, ADS or OPCUA",
        Setter::Section(|s, v| s.protocol = v.protocol())),
    row("SIMULATOR", Some("No"), Kind::Bool,
        "Yes runs a simulated PLC (EPSNET, or Modbus TCP) inside the server on a loopback port",
        Setter::Section(|s, v| {
            s.simulator = v.bool().then(|| Simulator { program: String::new(), pubfile: None });
        })),
    row("SIMULATOR_PROGRAM", Some("demo"), choice("simulator program", &SIMULATOR_PROGRAMS),
        "program of the simulated PLC",
        Setter::Section(|s, v| {
            if let Some(sim) = &mut s.simulator { sim.program = v.text() }
        })),
    row("SIMULATOR_PUB", None, Kind::Path(PathUse::Input),
        "public file of the simulated PLC (default: the built-in conf/demo.pub)",
        Setter::Section(|s, v| {
            if let Some(sim) = &mut s.simulator { sim.pubfile = Some(v.text()) }
        })),
    row("ALLOW", None, Kind::Networks, "client addresses and networks admitted (default: all)",
        Setter::Section(|s, v| s.allow = Some(v.networks()))),
    row("READ_ONLY", Some("No"), Kind::Bool,
        "Yes: requests that would change the PLC or the section answer ERROR:30",
        Setter::Section(|s, v| s.read_only = v.bool())),
    row("TRACE", Some("No"), Kind::Bool,
        "Yes: the section's PLC requests and answers and its clients' lines go to the log (trace level, target plccoms_frames); SETCONF:trace switches it at run time",
        Setter::Section(|s, v| s.trace = v.bool()))
        .setconf("trace", SetConfScope::Section),
    row("SETCONF_KEYS", None, Kind::Choices { what: "SETCONF name", choices: &SETCONF_NAMES },
        "the SETCONF names clients may use (default: all); others answer ERROR:30",
        Setter::Section(|s, v| s.setconf_keys = Some(v.choices()))),
    // The historian (issue 13).
    row("HISTORY", None, Kind::Form(Form::Masks), "variables recorded in the history (masks)",
        Setter::Section(|s, v| s.history.masks = history::parse_masks(&v.text()).unwrap_or_default())),
    row("HISTORY_DELTA", Some("0"), Kind::Form(Form::Deadband),
        "deadband: a change must exceed it to be recorded (0 = every change)",
        Setter::Section(|s, v| s.history.delta = history::parse_deadband(&v.text()).unwrap_or_default())),
    row("HISTORY_HEARTBEAT", Some("0"), number(0, 86400, "s"),
        "an unchanged value is recorded again this often (0 = off)",
        Setter::Section(|s, v| s.history.heartbeat = v.secs())),
    row("HISTORY_TRIGGER", None, Kind::Text,
        "BOOL variable whose rising edge records every cycle from HISTORY_PRE before to HISTORY_POST after",
        Setter::Section(|s, v| s.history.trigger = Some(v.text()))),
    row("HISTORY_PRE", Some("10"), number(0, 10000, "cycles"), "cycles recorded before a trigger",
        Setter::Section(|s, v| s.history.pre = v.number() as u32)),
    row("HISTORY_POST", Some("10"), number(0, 10000, "cycles"), "cycles recorded after a trigger",
        Setter::Section(|s, v| s.history.post = v.number() as u32)),
    row("HISTORY_STAMP", None, Kind::Form(Form::Stamps),
        "VALUE_VAR:STAMP_VAR pairs: samples carry the PLC's time from a DT or LINT/ULINT/LWORD (ms) variable",
        Setter::Section(|s, v| s.history.stamps = history::parse_stamps(&v.text()).unwrap_or_default())),
    // MQTT (apps/mqtt/src/): what the section publishes and what may be written.
    row("MQTT_PUBLISH", None, Kind::Text, "masks of the variables published (default none); __ and % names only by masks beginning so",
        Setter::Section(|s, v| s.mqtt.publish = split_masks(&v.text()))),
    row("MQTT_WRITE", None, Kind::Text, "masks of the variables <var>/set may write (default none); __ and % names only by masks beginning so",
        Setter::Section(|s, v| s.mqtt.write = split_masks(&v.text()))),
    row("MQTT_QOS", Some("1"), number(0, 1, ""), "QoS of value messages; 1 = kept on disk while the broker is away",
        Setter::Section(|s, v| s.mqtt.qos = v.number() as u8)),
    row("MQTT_RETAIN", Some("Yes"), Kind::Bool, "value messages are retained",
        Setter::Section(|s, v| s.mqtt.retain = v.bool())),
    row("MQTT_FORMAT", Some("plain"), choice("MQTT format", &MQTT_FORMATS),
        "plain (the value as GET prints it), json (value, time of the poll, quality) or sparkplug (as SPARKPLUG = Yes)",
        Setter::Section(|s, v| {
            let text = v.text();
            s.mqtt.format = if text == "json" { MqttFormat::Json } else { MqttFormat::Plain };
            s.mqtt.sparkplug |= text == "sparkplug";
        })),
    row("MQTT_DELTA", None, Kind::Text, "deadband: a value is published when it moved more than this",
        Setter::Section(|s, v| s.mqtt.delta = Some(v.text()))),
    row("MQTT_HA_DISCOVERY", Some("No"), Kind::Bool, "Home Assistant MQTT discovery",
        Setter::Section(|s, v| s.mqtt.ha_discovery = v.bool())),
    row("SPARKPLUG", Some("No"), Kind::Bool,
        "publish as a device of the Sparkplug B edge node (SPARKPLUG_GROUP, SPARKPLUG_NODE): MQTT_PUBLISH its metrics, MQTT_WRITE those DCMD may write",
        Setter::Section(|s, v| s.mqtt.sparkplug |= v.bool())),
    // OPC UA, with OPCUA_PORT in [*] (apps/opcua/src/).
    row("OPCUA_PUBLISH", None, Kind::Text, "masks of the variables in the OPC UA address space (default: every variable of the project)",
        Setter::Section(|s, v| s.opcua.publish = Some(split_masks(&v.text())))),
    row("OPCUA_WRITE", None, Kind::Text, "masks of the variables OPC UA users of role write may write (default none)",
        Setter::Section(|s, v| s.opcua.write = split_masks(&v.text()))),
    // Modbus (PROTOCOL = MODBUS_TCP, MODBUS_RTU, MODBUS_RTU_TCP).
    row("MODBUS_PORT", Some("502"), number(1, 65535, ""), "Modbus TCP port of the device",
        Setter::Section(|s, v| s.modbus.port = v.number() as u16)),
    row("MODBUS_UNIT", Some("1"), number(0, 255, ""), "Modbus unit id (slave address)",
        Setter::Section(|s, v| s.modbus.unit = v.number() as u8)),
    row("MODBUS_TAGS", None, Kind::Path(PathUse::Input),
        "Modbus tag file (CSV): //name = root folder, as PUBFILE",
        Setter::Section(|s, v| s.modbus.tags = Some(v.text()))),
    row("MODBUS_TIMEOUT", Some("1000"), number(1, 60000, "ms"), "Modbus transaction timeout",
        Setter::Section(|s, v| s.modbus.timeout = v.millis())),
    row("MODBUS_MAX_REGS", Some("125"), number(1, 125, "registers"),
        "registers one Modbus read may ask for",
        Setter::Section(|s, v| s.modbus.max_regs = v.number() as u16)),
    row("MODBUS_MAX_BITS", Some("2000"), number(1, 2000, "bits"),
        "coils or discrete inputs one Modbus read may ask for",
        Setter::Section(|s, v| s.modbus.max_bits = v.number() as u16)),
    row("MODBUS_GAP", Some("125"), number(0, 125, "registers"),
        "unwanted registers a Modbus read may span to join two blocks",
        Setter::Section(|s, v| s.modbus.gap = v.number() as u16)),
    row("MODBUS_INFLIGHT", Some("1"), number(1, 16, ""),
        "Modbus transactions in flight at once (devices that allow more)",
        Setter::Section(|s, v| s.modbus.inflight = v.number() as u8)),
    // Siemens S7 (PROTOCOL = S7).
    row("S7_PORT", Some("102"), number(1, 65535, ""), "ISO-on-TCP port of the S7 CPU",
        Setter::Section(|s, v| s.s7.port = v.number() as u16)),
    row("S7_RACK", Some("0"), number(0, 7, ""), "rack of the S7 CPU",
        Setter::Section(|s, v| s.s7.rack = v.number() as u8)),
    row("S7_SLOT", Some("1"), number(0, 31, ""), "slot of the S7 CPU: 1 for S7-1200/1500, 2 for S7-300",
        Setter::Section(|s, v| s.s7.slot = v.number() as u8)),
    row("S7_TSAP", None, Kind::Text, "local/remote TSAP in hex (e.g. 0100/0200 for a LOGO!); replaces S7_RACK/S7_SLOT",
        Setter::Section(|s, v| s.s7.tsap = super::S7::parse_tsap(&v.text()))),
    row("S7_PDU", Some("960"), number(240, 960, "bytes"), "PDU size asked for; the CPU's answer is used (GETINFO VERSION_PLC)",
        Setter::Section(|s, v| s.s7.pdu = v.number() as u16)),
    row("S7_TAGS", None, Kind::Path(PathUse::Input),
        "S7 tag file (CSV): //name = root folder, as PUBFILE",
        Setter::Section(|s, v| s.s7.tags = Some(v.text()))),
    row("S7_TIMEOUT", Some("1000"), number(1, 60000, "ms"), "how long the S7 CPU has to answer one request",
        Setter::Section(|s, v| s.s7.timeout = v.millis())),
    // Beckhoff ADS (PROTOCOL = ADS).
    row("ADS_NET_ID", None, Kind::Text, "AMS Net ID of the PLC (e.g. 5.12.34.56.1.1); default IPADDR.1.1",
        Setter::Section(|s, v| s.ads.net_id = Some(v.text()))),
    row("ADS_PORT", Some("851"), number(1, 65535, ""), "ADS port of the PLC runtime: 851 TwinCAT 3, 801 TwinCAT 2",
        Setter::Section(|s, v| s.ads.port = v.number() as u16)),
    row("ADS_SOURCE_NET_ID", None, Kind::Text,
        "our AMS Net ID, as the PLC's route names it; default this machine's address.1.1",
        Setter::Section(|s, v| s.ads.source_net_id = Some(v.text()))),
    row("ADS_TCP_PORT", Some("48898"), number(1, 65535, ""), "AMS/TCP port of the PLC",
        Setter::Section(|s, v| s.ads.tcp_port = v.number() as u16)),
    row("ADS_TIMEOUT", Some("1000"), number(1, 60000, "ms"), "ADS request timeout",
        Setter::Section(|s, v| s.ads.timeout = v.millis())),
    row("ADS_NOTIFY", None, Kind::Text,
        "masks of the variables sent by the PLC as device notifications (on change, PLC time stamps)",
        Setter::Section(|s, v| s.ads.notify = split_masks(&v.text()))),
    row("ADS_TAGS", None, Kind::Path(PathUse::Input),
        "ADS tag file (CSV: name,address,type,unit,description) for a PLC without a symbol table; //name = root folder",
        Setter::Section(|s, v| s.ads.tags = Some(v.text()))),
    row("ADS_CYCLE", Some("10"), number(1, 60000, "ms"), "the PLC's check cycle for ADS_NOTIFY",
        Setter::Section(|s, v| s.ads.cycle = v.millis())),
    // OPC UA client (PROTOCOL = OPCUA). OPCUA_SECURITY in [*] is the OPC
    // UA server app's; in a PLC section, this client's.
    row("OPCUA_URL", None, Kind::Text, "endpoint of the PLC's OPC UA server (opc.tcp://host:4840/path)",
        Setter::Section(|s, v| s.opcua_client.url = Some(v.text()))),
    row("OPCUA_SECURITY", Some("None"), Kind::Text,
        "None, or mode:policy (Sign or SignAndEncrypt : Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss)",
        Setter::Section(|s, v| s.opcua_client.security = v.text())),
    row("OPCUA_USER", None, Kind::Text, "user name at the server (default: anonymous)",
        Setter::Section(|s, v| s.opcua_client.user = Some(v.text()))),
    row("OPCUA_PASSWORD", None, Kind::Text, "password of OPCUA_USER",
        Setter::Section(|s, v| s.opcua_client.password = Some(v.text()))),
    row("OPCUA_PKI", None, Kind::Path(PathUse::State),
        "folder of the client certificate and of trusted/rejected server certificates (default: opcua-client-pki in the state directory)",
        Setter::Section(|s, v| s.opcua_client.pki = Some(v.text()))),
    row("OPCUA_BROWSE", None, Kind::Text,
        "nodes browsed for variables, comma-separated node ids (default: the Objects folder, i=85)",
        Setter::Section(|s, v| s.opcua_client.browse = Some(v.text()))),
    row("OPCUA_TAGS", None, Kind::Path(PathUse::Input),
        "OPC UA tag file (CSV: name,node,type,access,unit,description) instead of browsing",
        Setter::Section(|s, v| s.opcua_client.tags = Some(v.text()))),
    row("OPCUA_MODE", Some("subscribe"), choice("OPC UA mode", &OPCUA_MODES),
        "subscribe (monitored items, sampled at COMM_LOOP_DELAY) or read (cyclic Read)",
        Setter::Section(|s, v| s.opcua_client.subscribe = v.text() == "subscribe")),
    row("OPCUA_TIMEOUT", Some("1000"), number(1, 60000, "ms"), "how long one OPC UA request may take",
        Setter::Section(|s, v| s.opcua_client.timeout = v.millis())),
    row("OPCUA_REBROWSE", Some("10"), number(0, 86400, "s"),
        "the variables are browsed (or the tag file's types read) again this often; a change reloads the table (0 = never)",
        Setter::Section(|s, v| s.opcua_client.rebrowse = v.secs())),
    row("OPCUA_WRITE_SESSION", Some("Yes"), Kind::Bool,
        "SETs on a second session, not queued behind the subscription's publishes (No: one session, for a server short of sessions)",
        Setter::Section(|s, v| s.opcua_client.write_session = v.bool())),
    row("OPCUA_SESSION_ITEMS", Some("10000"), number(0, 10_000_000, "items"),
        "monitored items one session holds; more are monitored on further sessions, as many as the server grants, a rest of a tenth on the last (0 = all on one)",
        Setter::Section(|s, v| s.opcua_client.session_items = v.number() as usize)),
    // Accepted in a PLC section for symmetry with [*]: no effect there.
    row("SERIAL_DEVICE_CFG", None, Kind::Text, "no effect in a PLC section (a [*] key)",
        Setter::Section(|_, _| {})),
];
