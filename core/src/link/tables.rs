//! Where a section's variable files come from, and building its variable
//! table from them: at start-up (a local file at once; one that must be
//! fetched from the PLC when the link first connects), when the PLC's
//! program changes (`__PF_CRC`), and on `SETCONF:pubfile` or a new PLC
//! address. The user's file is a choice ([`UserKind`]): a public file
//! (PUBFILE), or a Modbus tag file (MODBUS_TAGS, on this machine only),
//! both under the same path rules.

use std::path::{Path, PathBuf};

use tracing::{info, warn};

use crate::config::{Protocol, Section};
use crate::driver::{PlcBackend, Refusal};
use crate::vars::{VarFile, VarTable, STANDARD_FIXED};
use plccoms_plc::modbus::tags;
use plccoms_plc::pubfile::{self, PubFile};
use plccoms_plc::MemoryMap;

/// Largest public file read, from this machine or fetched from a PLC.
pub const MAX_PUBFILE: u64 = 64 * 1024 * 1024;

/// A user public file as loaded: its name (as GETINFO and warnings show it)
/// and its bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UserFile {
    pub name: String,
    pub bytes: Vec<u8>,
}

/// What the link keeps of a loaded user file: its name, what tells a
/// reload whether the content changed, and the CRC to check against
/// `__PF_CRC`. Not the bytes: a 100,000-variable public file's text is
/// 38 bytes a variable (`tests/memory_per_var.rs`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Loaded {
    pub name: String,
    len: usize,
    /// Two SipHash-1-3 digests of the bytes (128 bits): a different file
    /// read as unchanged is a 2^-128 chance. Compared within this process
    /// only, so std's unspecified but fixed hasher is enough.
    digest: (u64, u64),
    /// [`expected_crc`] of the bytes.
    pub crc: Option<u32>,
}

impl Loaded {
    pub fn of(kind: UserKind, user: &UserFile) -> Loaded {
        use std::hash::{Hash, Hasher};
        let digest = |salt: u8| {
            let mut hasher = std::collections::hash_map::DefaultHasher::new();
            salt.hash(&mut hasher);
            user.bytes.hash(&mut hasher);
            hasher.finish()
        };
        Loaded {
            name: user.name.clone(),
            len: user.bytes.len(),
            digest: (digest(0), digest(1)),
            crc: expected_crc(kind, user),
        }
    }
}

/// What describes the user's variables.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UserKind {
    /// A public file (PUBFILE): local first, else fetched from the PLC.
    PubFile,
    /// A Modbus tag file (MODBUS_TAGS), on this machine only.
    ModbusTags,
    /// An S7 tag file (S7_TAGS), on this machine only.
    S7Tags,
    /// The device's own symbol table (ADS), always asked of the backend's
    /// file service under the name PUBFILE holds; reloaded when its
    /// `__PF_CRC` (the symbol version's file) changes.
    DeviceSymbols,
    /// The variables an OPC UA backend found (OPCUA_BROWSE, or OPCUA_TAGS
    /// with the server's types), always fetched from the backend as a tag
    /// file ([`plccoms_plc::opcua::VARS_FILE`]).
    Opcua,
}

impl UserKind {
    /// The kind a section's backend reads.
    pub fn of(section: &Section) -> UserKind {
        match section.protocol {
            protocol if protocol.is_modbus() => UserKind::ModbusTags,
            Protocol::S7 => UserKind::S7Tags,
            Protocol::Ads => UserKind::DeviceSymbols,
            Protocol::Opcua => UserKind::Opcua,
            _ => UserKind::PubFile,
        }
    }

    /// The section's setting that names the user file.
    pub fn name(self, section: &Section) -> Option<&String> {
        match self {
            UserKind::PubFile | UserKind::DeviceSymbols => section.pubfile.as_ref(),
            UserKind::ModbusTags => section.modbus.tags.as_ref(),
            UserKind::S7Tags => section.s7.tags.as_ref(),
            UserKind::Opcua => None,
        }
    }

    /// What logs call the file: each backend's own term.
    pub fn what(self) -> &'static str {
        match self {
            UserKind::PubFile => "public file",
            UserKind::ModbusTags | UserKind::S7Tags => "tag file",
            UserKind::DeviceSymbols => "symbol table",
            UserKind::Opcua => "OPC UA variable list",
        }
    }

    /// The log line of a changed `__PF_CRC`: a Tecomat PLC runs another
    /// program (the vendor's wording); a Modbus section's tag file was
    /// edited (its `__PF_CRC` is the file's CRC).
    pub fn changed(self, last: u64, now: u64) -> String {
        match self {
            UserKind::PubFile => format!(
                "__PF_CRC changed ({last:08X} -> {now:08X}): the PLC's program changed, reloading the public file"
            ),
            UserKind::ModbusTags | UserKind::S7Tags => {
                format!("tag file changed, reloading (__PF_CRC {last:08X} -> {now:08X})")
            }
            UserKind::DeviceSymbols => format!(
                "the PLC's symbols changed (__PF_CRC {last:08X} -> {now:08X}): a new program, reloading them"
            ),
            UserKind::Opcua => format!(
                "the OPC UA server's variables changed, reloading (__PF_CRC {last:08X} -> {now:08X})"
            ),
        }
    }
}

/// Where a section's variable files are: everything but the section's own
/// settings (PUBFILE or MODBUS_TAGS, PUBFILE_WRITE), which come from its
/// live state.
#[derive(Debug, Clone)]
pub struct PubSource {
    /// The configuration file's folder.
    pub dir: PathBuf,
    pub fixed_name: String,
    pub fixed: PubFile,
    pub kind: UserKind,
}

/// Why the user public file is not loaded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LoadError {
    /// It is not on this machine and must be fetched from the PLC, which
    /// cannot be asked now: the link fetches it when it connects.
    FromPlc,
    Failed(String),
}

impl PubSource {
    /// Reads the fixed file (PUBFILE_FIXED beside the configuration, or the
    /// standard one when the key is not set).
    pub fn new(section: &Section, dir: &Path) -> Result<PubSource, String> {
        let kind = UserKind::of(section);
        let (fixed_name, fixed) = match &section.pubfile_fixed {
            // A Modbus backend answers the system variables where the
            // standard file places them.
            Some(name) if kind == UserKind::PubFile => {
                let path = dir.join(name);
                let file = pubfile::load(&path)
                    .map_err(|e| format!("fixed public file {}: {e}", path.display()))?;
                (name.clone(), file)
            }
            _ => ("FIXED.pub".to_string(), pubfile::parse(STANDARD_FIXED)),
        };
        Ok(PubSource {
            dir: dir.to_path_buf(),
            fixed_name,
            fixed,
            kind,
        })
    }

    /// Where a PUBFILE value lives on this machine ([`Section::path_of`]).
    pub fn local_path(&self, section: &Section, name: &str) -> PathBuf {
        section.path_of(&self.dir, name)
    }

    /// The user public file if it is on this machine (`Ok(None)` when the
    /// section names none); [`LoadError::FromPlc`] when it must be fetched.
    /// At most [`MAX_PUBFILE`] bytes are read. A client's name must stay in
    /// the configuration's folder and name none of the server's own files;
    /// every refusal reads the same, so a client cannot probe for files.
    pub fn load_local(
        &self,
        section: &Section,
        by: NamedBy,
    ) -> Result<Option<UserFile>, LoadError> {
        if self.kind == UserKind::Opcua {
            return Err(LoadError::FromPlc);
        }
        let Some(name) = self.kind.name(section) else {
            return Ok(None);
        };
        let local = self.local_path(section, name);
        let what = self.kind.what();
        if self.kind == UserKind::DeviceSymbols {
            return Err(LoadError::FromPlc);
        }
        if by == NamedBy::Client {
            let refused = || LoadError::Failed(format!("{what} {name} refused"));
            check_client_name(name).map_err(|_| refused())?;
            if let Ok(real) = std::fs::canonicalize(&local) {
                let dir = std::fs::canonicalize(&self.dir).map_err(|_| refused())?;
                if !real.starts_with(&dir)
                    || crate::localfs::is_own(&real, crate::localfs::Access::Write, &[])
                {
                    return Err(refused());
                }
            }
        }
        if local.is_file() {
            return read_bounded(&local)
                .map(|bytes| {
                    Some(UserFile {
                        name: file_name(name),
                        bytes,
                    })
                })
                .map_err(|e| LoadError::Failed(format!("{what} {}: {e}", local.display())));
        }
        if self.kind != UserKind::PubFile {
            return Err(LoadError::Failed(format!(
                "tag file {} not found",
                local.display()
            )));
        }
        if name.starts_with("../") {
            return Err(LoadError::Failed(format!(
                "public file {} not found (paths starting with ../ are local only)",
                local.display()
            )));
        }
        Err(LoadError::FromPlc)
    }

    /// The user public file: the local file if there is one, else fetched
    /// from the PLC (and stored locally with PUBFILE_WRITE). `None` when the
    /// section names none.
    pub async fn load_user(
        &self,
        section: &Section,
        by: NamedBy,
        backend: Option<&mut (dyn PlcBackend + 'static)>,
    ) -> Result<Option<UserFile>, String> {
        match self.load_local(section, by) {
            Ok(user) => return Ok(user),
            Err(LoadError::Failed(message)) => return Err(message),
            Err(LoadError::FromPlc) => {}
        }
        let name = match self.kind {
            UserKind::Opcua => plccoms_plc::opcua::VARS_FILE,
            _ => section.pubfile.as_deref().unwrap_or_default(),
        };
        let local = self.local_path(section, name);
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
                    "public file {name}: not at {} on this machine, and {e}",
                    local.display()
                )
            })?;
        let display = file_name(name);
        info!(section = %section.name, "{} {name} fetched from the PLC ({} bytes)", self.kind.what(), bytes.len());
        if section.pubfile_write && self.kind == UserKind::PubFile {
            if let Some(parent) = local.parent() {
                let _ = std::fs::create_dir_all(parent);
            }
            if let Err(e) = std::fs::write(&local, &bytes) {
                warn!(section = %section.name, "cannot store {}: {e}", local.display());
            }
        }
        Ok(Some(UserFile {
            name: display,
            bytes,
        }))
    }

    /// The variable table of the fixed file and `user`; bad lines are logged.
    pub fn build(&self, section: &str, user: Option<&UserFile>) -> Result<VarTable, String> {
        let (parsed, map) = match self.kind {
            UserKind::PubFile => (
                user.map(|u| (u.name.as_str(), VarFile::from(&pubfile::parse(&u.bytes)))),
                MemoryMap::FOXTROT,
            ),
            UserKind::DeviceSymbols => (
                user.map(|u| (u.name.as_str(), VarFile::from(&pubfile::parse(&u.bytes)))),
                plccoms_plc::ads::MAP,
            ),
            UserKind::ModbusTags => (
                user.map(|u| (u.name.as_str(), VarFile::from(&tags::parse(&u.bytes)))),
                plccoms_plc::modbus::MAP,
            ),
            UserKind::S7Tags => (
                user.map(|u| {
                    let file = plccoms_plc::s7::tags::parse(&u.bytes);
                    (u.name.as_str(), VarFile::from(&file))
                }),
                plccoms_plc::s7::MAP,
            ),
            UserKind::Opcua => (
                user.map(|u| {
                    let file = plccoms_plc::opcua::tags::parse(&u.bytes);
                    (u.name.as_str(), VarFile::from(&file))
                }),
                plccoms_plc::opcua::MAP,
            ),
        };
        let mut warnings = Vec::new();
        let table = VarTable::build_from(
            &self.fixed_name,
            &VarFile::from(&self.fixed),
            parsed.as_ref().map(|(name, file)| (*name, file)),
            &map,
            &mut warnings,
        )
        .map_err(|e| e.to_string())?;
        // A file of garbage is a few lines of log, not megabytes.
        let what = self.kind.what();
        for warning in warnings.iter().take(LOGGED_WARNINGS) {
            warn!(section = %section, "{what} {warning}");
        }
        let more = warnings.len().saturating_sub(LOGGED_WARNINGS)
            + parsed.as_ref().map_or(0, |(_, file)| file.more_warnings);
        if more > 0 {
            warn!(section = %section, "{what}: {more} more problems not shown");
        }
        Ok(table)
    }
}

impl PubSource {
    /// The start-up log line of what was loaded: `public files loaded:
    /// FIXED.pub, user.pub` (the user file maybe still to be read from the
    /// PLC), or `tag file loaded: tags.csv` (no fixed file: a Modbus
    /// backend answers the system variables itself).
    pub fn loaded_line(
        &self,
        section: &Section,
        user: Option<&UserFile>,
        from_plc: bool,
    ) -> String {
        if self.kind == UserKind::Opcua {
            return match user {
                Some(user) => format!("OPC UA variables loaded: {}", user.name),
                None => "OPC UA variables are looked for when the server answers".to_string(),
            };
        }
        if self.kind != UserKind::PubFile {
            return match user {
                Some(user) => format!("tag file loaded: {}", user.name),
                None => "no tag file: __PLC_RUN and __PF_CRC only".to_string(),
            };
        }
        let mut line = format!("public files loaded: {}", self.fixed_name);
        if let Some(user) = user {
            line.push_str(&format!(", {}", user.name));
        }
        if from_plc {
            line.push_str(&format!(
                "; {} is read from the PLC when it answers",
                self.kind.name(section).map_or("", String::as_str)
            ));
        }
        line
    }
}

/// Problems of one public file that are logged one by one.
const LOGGED_WARNINGS: usize = 5;

/// Who names a public file: the configuration (trusted: `../` allowed, as
/// the vendor's server allows it), or a client's SETCONF (only inside the
/// configuration's folder, never one of the server's own files).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NamedBy {
    Configuration,
    Client,
}

/// A SETCONF:pubfile value's form: `//name` or a relative name, no
/// absolute path, no `..`, no drive letter, no NUL.
pub fn check_client_name(name: &str) -> Result<(), String> {
    let rest = name.strip_prefix("//").unwrap_or(name);
    if rest.is_empty() || rest.starts_with(['/', '\\']) {
        return Err(format!(
            "'{name}' is not a root-relative name (//name or name)"
        ));
    }
    for part in rest.split(['/', '\\']) {
        if part == ".." || part.contains(['\0', ':']) {
            return Err(format!("'{name}' leads outside the root folder"));
        }
    }
    Ok(())
}

/// A local file's bytes, refused past [`MAX_PUBFILE`] without reading it all.
fn read_bounded(path: &Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let file = std::fs::File::open(path)?;
    let size = file.metadata()?.len();
    let too_large = || {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("more than the {MAX_PUBFILE} bytes accepted"),
        )
    };
    if size > MAX_PUBFILE {
        return Err(too_large());
    }
    let mut bytes = Vec::with_capacity(size as usize);
    file.take(MAX_PUBFILE + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > MAX_PUBFILE {
        return Err(too_large());
    }
    Ok(bytes)
}

/// The CRC that `__PF_CRC` must match for `user` (PUBFILE_CRC): a public
/// file's trailer; a tag file's content (the Modbus backend's `__PF_CRC`).
pub fn expected_crc(kind: UserKind, user: &UserFile) -> Option<u32> {
    match kind {
        UserKind::PubFile | UserKind::DeviceSymbols => pubfile::crc_trailer(&user.bytes),
        UserKind::ModbusTags | UserKind::S7Tags | UserKind::Opcua => {
            Some(pubfile::crc_of(&user.bytes))
        }
    }
}

/// The name a PUBFILE value has in the PLC's file system.
pub fn plc_path(name: &str) -> &str {
    name.trim_start_matches('/')
}

fn file_name(name: &str) -> String {
    name.rsplit(['/', '\\']).next().unwrap_or(name).to_string()
}

/// Reads a whole file from the PLC's file system.
pub async fn fetch_file(backend: &mut dyn PlcBackend, path: &[u8]) -> Result<Vec<u8>, String> {
    let info = backend
        .file_info(path)
        .await
        .map_err(|e| format!("the PLC cannot be asked for it: {e}"))?
        .map_err(|e| match e {
            // What EPSNET answers for a missing file (see plc::epsnet::service).
            Refusal::BAD_PARAMETERS => format!("file not found on the PLC (it answered {e})"),
            e => format!("the PLC refused it: {e}"),
        })?;
    if info.size > MAX_PUBFILE {
        return Err(format!(
            "{} bytes is more than the {MAX_PUBFILE} accepted",
            info.size
        ));
    }
    // Exactly the size the PLC gave: at most MAX_PUBFILE, however the file
    // changes meanwhile.
    super::files::read_file(backend, path, 0, info.size as u32)
        .await
        .map_err(|e| format!("reading it from the PLC failed: {e}"))?
        .map_err(|e| format!("the PLC refused to read it: {e}"))
}
