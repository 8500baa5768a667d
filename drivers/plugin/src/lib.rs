//! The plugin backend: a section with `SHM_NAME = <shared library>` reaches
//! its PLC through that library's C ABI (`plugin/include/plccoms_plugin.h`,
//! version 1; its Rust mirror is the `plccoms-plugin-abi` crate).
//!
//! Our side of the ABI trusts nothing the plugin hands back:
//! - the entry's table is checked (not NULL, aligned, ABI version, size,
//!   the required functions present) and copied once;
//! - every status is mapped (0, an EPSNET error byte 1..=255, the four
//!   `ERR_*` link errors); any other is a plugin error;
//! - every length is checked against the buffer we gave (a read must fill
//!   it exactly, an identification, a file block or a directory page must
//!   fit); a message is read within its 256 bytes, terminated or not;
//! - out-buffers carry guard bytes after the length we announce: a plugin
//!   that writes past it is reported, not believed.
//!
//! Calls run on a thread of the section's own (never the link's), one call
//! at a time; the link waits for each at most EPSTOUT + (EPSTOUT +
//! EPSTOUT_STEP), the time in which an EPSNET PLC is declared lost, and
//! counts a call that takes longer as a timeout: the PLC is lost, and the
//! next connection starts a fresh thread and handle. The late call's thread
//! ends when (if) the call returns; while [`MAX_THREADS`] threads are still
//! inside calls, no new one is started.
//!
//! Libraries are loaded for good (never unloaded, see [`Loaded`]).
//!
//! What is not isolated: the plugin runs in the server's process, so a
//! plugin that crashes (or corrupts memory, or never returns from a call
//! and holds a lock the process needs) takes the server down; [`crash`]
//! makes sure such a crash is logged, naming the plugin and the call.

pub mod crash;

use std::ffi::{c_char, CString};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc};
use std::time::Duration;

use async_trait::async_trait;
use plccoms_plc::epsnet::Exception;
use plccoms_plugin_abi as abi;
use tokio::sync::oneshot;
use tokio::time::Instant;

use plccoms_core::config::Protocol;
use plccoms_core::driver::{
    Answer, DirEntry, FileInfo, PlcBackend, PlcError, PlcStatus, ReadRequest, Refusal, WriteData,
    WriteRequest,
};
use plccoms_core::driver::{Driver, Opened};
use plccoms_core::metrics::BackendCounters;

/// Threads of one section that may be inside plugin calls at once.
pub const MAX_THREADS: usize = 4;
/// Read block when the plugin does not say (EPSNET's).
const DEFAULT_READ: u32 = 1230;
/// File block when the plugin does not say (EPSNET's).
const DEFAULT_FILE: u32 = 1150;
/// Directory entries asked of one call.
const DIR_PAGE: u32 = 64;
/// Guard bytes after every out-buffer.
const GUARD: usize = 16;
const GUARD_BYTE: u8 = 0xA5;

/// Settings of a plugin section.
#[derive(Debug, Clone)]
pub struct PluginConfig {
    /// SHM_NAME: a path, or a bare name the dynamic loader searches for.
    pub library: String,
    /// The section's keys, passed to `open`.
    pub keys: Vec<(String, String)>,
    /// EPSTOUT: the freshness of polled values builds on it.
    pub answer_timeout: Duration,
    /// The longest one call may take.
    pub call_timeout: Duration,
}

impl PluginConfig {
    /// From a section's keys.
    pub fn from_section(section: &plccoms_core::config::Section, library: &str) -> PluginConfig {
        let mut keys = vec![
            ("SECTION".to_string(), section.name.clone()),
            ("SHM_NAME".to_string(), library.to_string()),
            (
                "EPSTOUT".to_string(),
                section.epstout.as_millis().to_string(),
            ),
            (
                "EPSTOUT_STEP".to_string(),
                section.epstout_step.as_millis().to_string(),
            ),
        ];
        let mut add = |key: &str, value: Option<String>| {
            if let Some(value) = value {
                keys.push((key.to_string(), value));
            }
        };
        add("SHM_SOCKET", section.shm_socket.map(|v| v.to_string()));
        add("SHM_PORT", section.shm_port.map(|v| v.to_string()));
        add("IPADDR", section.ipaddr.map(|v| v.to_string()));
        add("EPSADDR", section.epsaddr.map(|v| v.to_string()));
        add("EPSPORT", Some(section.epsport.to_string()));
        add("SERIAL_DEVICE", section.serial_device.clone());
        add("SERIAL_SPEED", section.serial_speed.map(|v| v.to_string()));
        PluginConfig {
            library: library.to_string(),
            keys,
            answer_timeout: section.epstout,
            call_timeout: section.epstout * 2 + section.epstout_step,
        }
    }
}

/// Refuses a library file that someone other than its installer could
/// replace, as ssh refuses loose key files: writable by group or others, in
/// a folder writable by group or others (without the sticky bit), or
/// writable by the server's own user (a process running as the server, or a
/// client of a path the server forgot to guard, could then put its code in
/// the server). Root can write every file, so for a server running as root
/// only the group and others bits count.
fn check_library_file(path: &Path) -> Result<(), String> {
    use std::os::unix::fs::MetadataExt;
    // SAFETY: geteuid cannot fail and touches no memory.
    let euid = unsafe { libc::geteuid() };
    let file = std::fs::metadata(path).map_err(|e| format!("{e}"))?;
    if let Some(why) = loose_library(file.mode(), file.uid(), euid) {
        return Err(format!(
            "the library is {why} (mode {:04o}, owner uid {}); make it read-only for all but its owner (chmod go-w,u-w) or owned by another user than the server's",
            file.mode() & 0o7777,
            file.uid()
        ));
    }
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let folder_meta =
        std::fs::metadata(folder).map_err(|e| format!("{}: {e}", folder.display()))?;
    let mode = folder_meta.mode();
    if mode & 0o022 != 0 && mode & 0o1000 == 0 {
        return Err(format!(
            "its folder {} is writable by group or others (mode {:04o}): anyone in them could replace the library",
            folder.display(),
            mode & 0o7777
        ));
    }
    Ok(())
}

/// Why a library file of `mode` owned by `owner` is loose for a server
/// running as `euid`, if it is.
fn loose_library(mode: u32, owner: u32, euid: u32) -> Option<&'static str> {
    if mode & 0o022 != 0 {
        Some("writable by group or others")
    } else if euid != 0 && owner == euid && mode & 0o200 != 0 {
        Some("writable by the server's own user")
    } else {
        None
    }
}

/// A loaded plugin and its handle, owned by the worker thread.
struct Loaded {
    api: abi::PluginApi,
    handle: Option<abi::Handle>,
    /// What a crash note says before the call's name.
    note: String,
    /// Never unloaded: a plugin (a Rust or C++ one at least) may have left
    /// thread-exit handlers in the threads that called it, which run after
    /// the handle is closed. dlopen counts: loading it again costs nothing.
    _library: std::mem::ManuallyDrop<libloading::Library>,
}

impl Loaded {
    /// Loads the library and checks its table.
    fn load(library: &str, note: String) -> Result<Loaded, PlcError> {
        let bad = |what: String| PlcError::Protocol(format!("plugin {library}: {what}"));
        let path = Path::new(library);
        if path.components().count() > 1 {
            check_library_file(path).map_err(|why| {
                PlcError::Io(std::io::Error::other(format!("refused {library}: {why}")))
            })?;
        }
        // SAFETY: loading runs the library's initialisers, which we must
        // trust as we trust its calls (see the module doc).
        let lib = crash::inside(format!("{note}: load").as_bytes(), || unsafe {
            libloading::Library::new(path)
        })
        .map_err(|e| PlcError::Io(std::io::Error::other(format!("cannot load {library}: {e}"))))?;
        // SAFETY: the symbol's type is the ABI's entry.
        let entry: abi::EntryFn = unsafe {
            *lib.get::<abi::EntryFn>(abi::ENTRY)
                .map_err(|e| bad(format!("no {} export: {e}", "plccoms_plugin_entry")))?
        };
        let table = crash::inside(format!("{note}: entry").as_bytes(), || unsafe {
            entry(abi::ABI_VERSION)
        });
        let api = check_table(table).map_err(bad)?;
        Ok(Loaded {
            api,
            handle: None,
            note,
            _library: std::mem::ManuallyDrop::new(lib),
        })
    }

    fn note(&self, call: &str) -> Vec<u8> {
        format!("{}: {call}", self.note).into_bytes()
    }
}

impl Drop for Loaded {
    fn drop(&mut self) {
        if let (Some(handle), Some(close)) = (self.handle.take(), self.api.close) {
            let note = self.note("close");
            // SAFETY: a handle `open` gave, closed once.
            crash::inside(&note, || unsafe { close(handle) });
        }
    }
}

/// The entry's table, checked and copied.
fn check_table(table: *const abi::PluginApi) -> Result<abi::PluginApi, String> {
    if table.is_null() {
        return Err(format!(
            "the entry returned no table for ABI version {}",
            abi::ABI_VERSION
        ));
    }
    if !table.is_aligned() {
        return Err("the entry returned a misaligned table".into());
    }
    // SAFETY: non-NULL and aligned; the header's first two fields are read
    // before the whole, whose size the second one vouches for.
    let (version, size) = unsafe {
        (
            std::ptr::addr_of!((*table).abi_version).read(),
            std::ptr::addr_of!((*table).struct_size).read(),
        )
    };
    if version != abi::ABI_VERSION {
        return Err(format!(
            "ABI version {version}, this server speaks {}",
            abi::ABI_VERSION
        ));
    }
    let ours = std::mem::size_of::<abi::PluginApi>();
    if (size as usize) < ours {
        return Err(format!(
            "table of {size} bytes, version {version} has {ours}"
        ));
    }
    // SAFETY: as above.
    let api = unsafe { table.read() };
    let missing = [
        ("open", api.open.is_none()),
        ("close", api.close.is_none()),
        ("identify", api.identify.is_none()),
        ("status", api.status.is_none()),
        ("read", api.read.is_none()),
        ("write", api.write.is_none()),
        ("write_bits", api.write_bits.is_none()),
    ];
    if let Some((name, _)) = missing.iter().find(|(_, none)| *none) {
        return Err(format!("the table has no {name} function"));
    }
    for (name, block) in [
        ("max_read_block", api.max_read_block),
        ("max_file_block", api.max_file_block),
    ] {
        if block > 65535 {
            return Err(format!("{name} {block} is above 65535"));
        }
    }
    Ok(api)
}

/// A buffer for the plugin to write into, with guard bytes after it.
struct OutBuf {
    bytes: Vec<u8>,
    len: usize,
}

impl OutBuf {
    fn new(len: usize) -> OutBuf {
        let mut bytes = vec![0u8; len + GUARD];
        bytes[len..].fill(GUARD_BYTE);
        OutBuf { bytes, len }
    }

    fn ptr(&mut self) -> *mut u8 {
        self.bytes.as_mut_ptr()
    }

    /// The first `got` bytes, if the plugin kept within the buffer.
    fn take(mut self, got: usize, what: &str) -> Result<Vec<u8>, PlcError> {
        if self.bytes[self.len..].iter().any(|&b| b != GUARD_BYTE) {
            return Err(PlcError::Protocol(format!(
                "plugin {what} wrote past the {}-byte buffer it was given",
                self.len
            )));
        }
        if got > self.len {
            return Err(PlcError::Protocol(format!(
                "plugin {what} reported {got} bytes in a {}-byte buffer",
                self.len
            )));
        }
        self.bytes.truncate(got);
        Ok(self.bytes)
    }
}

/// The plugin's message, read within its buffer.
fn message(err: &abi::PluginError) -> String {
    let bytes: Vec<u8> = err.text.iter().map(|&c| c as u8).collect();
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    let text: String = String::from_utf8_lossy(&bytes[..end])
        .chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .collect();
    text.trim().to_string()
}

/// A call's status: done, the PLC's refusal, or a link failure.
fn status(what: &str, code: i32, err: &abi::PluginError) -> Result<Answer<()>, PlcError> {
    let text = message(err);
    let says = if text.is_empty() {
        String::new()
    } else {
        format!(": {text}")
    };
    match code {
        abi::OK => Ok(Ok(())),
        // The ABI's refusals are EPSNET error bytes.
        1..=255 => Ok(Err(Refusal::Epsnet(Exception::from_byte(code as u8)))),
        abi::ERR_UNSUPPORTED => Ok(Err(Refusal::UNKNOWN_SERVICE)),
        abi::ERR_TIMEOUT => Err(PlcError::Timeout(format!("plugin {what}{says}"))),
        abi::ERR_IO => Err(PlcError::Io(std::io::Error::other(format!(
            "plugin {what}{says}"
        )))),
        abi::ERR_PROTOCOL => Err(PlcError::Protocol(format!("plugin {what}{says}"))),
        other => Err(PlcError::Protocol(format!(
            "plugin {what} returned status {other}, which the ABI does not define{says}"
        ))),
    }
}

fn new_error() -> abi::PluginError {
    abi::PluginError {
        text: [0; abi::ERROR_LEN],
    }
}

type Job = Box<dyn FnOnce(&mut Loaded) + Send>;

/// The thread that makes the calls.
struct Worker {
    jobs: mpsc::SyncSender<Job>,
}

pub struct PluginBackend {
    config: PluginConfig,
    worker: Option<Worker>,
    max_read: u32,
    max_file: u32,
    files: bool,
    /// This section's worker threads still running.
    threads: Arc<AtomicUsize>,
    counters: Arc<BackendCounters>,
}

impl PluginBackend {
    pub fn new(config: PluginConfig) -> PluginBackend {
        PluginBackend {
            config,
            worker: None,
            max_read: DEFAULT_READ,
            max_file: DEFAULT_FILE,
            files: false,
            threads: Arc::default(),
            counters: Arc::default(),
        }
    }

    /// Runs `f` on the worker, bounded by the call timeout.
    async fn call<T: Send + 'static>(
        &self,
        what: &'static str,
        f: impl FnOnce(&mut Loaded) -> Result<T, PlcError> + Send + 'static,
    ) -> Result<T, PlcError> {
        let worker = self.worker.as_ref().ok_or(PlcError::NotConfigured)?;
        let (reply, answer) = oneshot::channel();
        let abandoned = Arc::new(AtomicBool::new(false));
        let skip = abandoned.clone();
        let job: Job = Box::new(move |loaded| {
            if !skip.load(Ordering::Relaxed) {
                let _ = reply.send(f(loaded));
            }
        });
        self.counters.requests.inc();
        let started = Instant::now();
        match worker.jobs.try_send(job) {
            Ok(()) => {}
            Err(mpsc::TrySendError::Full(_)) => {
                self.counters.timeouts.inc();
                return Err(PlcError::Timeout(format!(
                    "plugin {}: an earlier call has not returned",
                    self.config.library
                )));
            }
            Err(mpsc::TrySendError::Disconnected(_)) => {
                return Err(PlcError::Io(std::io::Error::other(
                    "the plugin's thread has ended",
                )))
            }
        }
        match tokio::time::timeout(self.config.call_timeout, answer).await {
            Ok(Ok(result)) => {
                self.counters.round_trip.observe(started.elapsed());
                if matches!(result, Err(PlcError::Protocol(_))) {
                    self.counters.errors.inc();
                }
                result
            }
            Ok(Err(_)) => Err(PlcError::Io(std::io::Error::other(format!(
                "the plugin's thread ended during {what}"
            )))),
            Err(_) => {
                abandoned.store(true, Ordering::Relaxed);
                self.counters.timeouts.inc();
                Err(PlcError::Timeout(format!(
                    "plugin {} {what} did not return within {} ms",
                    self.config.library,
                    self.config.call_timeout.as_millis()
                )))
            }
        }
    }

    /// A fresh thread with the library loaded (the old thread, if any, ends
    /// after its call).
    async fn start(&mut self) -> Result<(), PlcError> {
        self.worker = None;
        if self.threads.load(Ordering::Relaxed) >= MAX_THREADS {
            return Err(PlcError::Timeout(format!(
                "plugin {}: {MAX_THREADS} calls into it have not returned",
                self.config.library
            )));
        }
        let (jobs, queue) = mpsc::sync_channel::<Job>(1);
        let (ready, loaded) = oneshot::channel();
        let library = self.config.library.clone();
        let section = self
            .config
            .keys
            .first()
            .map(|(_, v)| v.clone())
            .unwrap_or_default();
        let note = format!("plugin {library} (section {section})");
        let threads = self.threads.clone();
        threads.fetch_add(1, Ordering::Relaxed);
        let spawned = std::thread::Builder::new()
            .name(format!("plugin {section}"))
            .spawn(move || {
                let loaded = Loaded::load(&library, note);
                let mut loaded = match loaded {
                    Ok(loaded) => {
                        let limits = (
                            loaded.api.max_read_block,
                            loaded.api.max_file_block,
                            loaded.api.file_info.is_some()
                                && loaded.api.file_read.is_some()
                                && loaded.api.file_write.is_some()
                                && loaded.api.file_write_info.is_some()
                                && loaded.api.dir_list.is_some(),
                        );
                        let _ = ready.send(Ok(limits));
                        loaded
                    }
                    Err(e) => {
                        let _ = ready.send(Err(e));
                        threads.fetch_sub(1, Ordering::Relaxed);
                        return;
                    }
                };
                while let Ok(job) = queue.recv() {
                    job(&mut loaded);
                }
                drop(loaded);
                threads.fetch_sub(1, Ordering::Relaxed);
            });
        if let Err(e) = spawned {
            self.threads.fetch_sub(1, Ordering::Relaxed);
            return Err(PlcError::Io(e));
        }
        let (read, file, files) = match tokio::time::timeout(self.config.call_timeout, loaded).await
        {
            Ok(Ok(limits)) => limits?,
            Ok(Err(_)) => {
                return Err(PlcError::Io(std::io::Error::other(
                    "the plugin's thread ended while loading",
                )))
            }
            Err(_) => {
                return Err(PlcError::Timeout(format!(
                    "plugin {} did not load within {} ms",
                    self.config.library,
                    self.config.call_timeout.as_millis()
                )))
            }
        };
        self.max_read = if read == 0 { DEFAULT_READ } else { read };
        self.max_file = if file == 0 { DEFAULT_FILE } else { file };
        self.files = files;
        self.worker = Some(Worker { jobs });
        Ok(())
    }

    async fn open(&mut self) -> Result<(), PlcError> {
        let keys = self.config.keys.clone();
        self.call("open", move |loaded| {
            let strings: Vec<(CString, CString)> = keys
                .iter()
                .map(|(k, v)| Ok((CString::new(k.as_str())?, CString::new(v.as_str())?)))
                .collect::<Result<_, std::ffi::NulError>>()
                .map_err(|e| PlcError::Protocol(format!("a key holds a NUL byte: {e}")))?;
            let table: Vec<abi::Key> = strings
                .iter()
                .map(|(k, v)| abi::Key {
                    key: k.as_ptr(),
                    value: v.as_ptr(),
                })
                .collect();
            let open = loaded.api.open.expect("checked at load");
            let mut handle: abi::Handle = std::ptr::null_mut();
            let mut err = new_error();
            let note = loaded.note("open");
            // SAFETY: the keys and the out-pointers live across the call.
            let code = crash::inside(&note, || unsafe {
                open(table.as_ptr(), table.len(), &mut handle, &mut err)
            });
            match status("open", code, &err)? {
                Ok(()) => {
                    loaded.handle = Some(handle);
                    Ok(())
                }
                Err(e) => Err(PlcError::Refused(e)),
            }
        })
        .await
    }

    /// Reads one block (at most `max_read`).
    async fn read_block(&self, r: ReadRequest) -> Result<Answer<Vec<u8>>, PlcError> {
        self.call("read", move |loaded| {
            let read = loaded.api.read.expect("checked at load");
            let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
            let mut buf = OutBuf::new(r.len as usize);
            let mut got = 0u32;
            let mut err = new_error();
            let note = loaded.note("read");
            // SAFETY: the buffer holds r.len bytes (and the guard).
            let code = crash::inside(&note, || unsafe {
                read(
                    handle,
                    r.area.letter() as u8 as c_char,
                    r.offset,
                    buf.ptr(),
                    r.len,
                    &mut got,
                    &mut err,
                )
            });
            if let Err(e) = status("read", code, &err)? {
                return Ok(Err(e));
            }
            if got != r.len {
                return Err(PlcError::Protocol(format!(
                    "plugin read returned {got} bytes for a read of {} at {}{}",
                    r.len,
                    r.area.letter(),
                    r.offset
                )));
            }
            buf.take(got as usize, "read").map(Ok)
        })
        .await
    }

    async fn write_block(&self, w: WriteRequest) -> Result<Answer<()>, PlcError> {
        self.call("write", move |loaded| {
            let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
            let area = w.area.letter() as u8 as c_char;
            let mut err = new_error();
            let (what, code) = match &w.data {
                WriteData::Bit { bit, value } => {
                    let Some(mask) = 1u8.checked_shl(u32::from(*bit)) else {
                        return Ok(Err(Refusal::BAD_PARAMETERS));
                    };
                    let f = loaded.api.write_bits.expect("checked at load");
                    let note = loaded.note("write_bits");
                    let value = if *value { mask } else { 0 };
                    // SAFETY: scalars and our error buffer.
                    let code = crash::inside(&note, || unsafe {
                        f(handle, area, w.offset, mask, value, &mut err)
                    });
                    ("write_bits", code)
                }
                WriteData::Bytes(bytes) => {
                    let Ok(len) = u32::try_from(bytes.len()) else {
                        return Ok(Err(Refusal::BAD_PARAMETERS));
                    };
                    let f = loaded.api.write.expect("checked at load");
                    let note = loaded.note("write");
                    // SAFETY: `bytes` holds `len` bytes across the call.
                    let code = crash::inside(&note, || unsafe {
                        f(handle, area, w.offset, bytes.as_ptr(), len, &mut err)
                    });
                    ("write", code)
                }
            };
            status(what, code, &err)
        })
        .await
    }

    /// File services: `None` when the plugin has none (answered as a PLC
    /// without them: not activated).
    fn no_files(&self) -> Option<Refusal> {
        (!self.files).then_some(Refusal::NOT_ACTIVATED)
    }
}

fn to_info(i: &abi::FileInfo) -> FileInfo {
    FileInfo {
        size: i.size,
        attributes: i.attributes,
        created: i.created,
        modified: i.modified,
    }
}

fn from_info(i: &FileInfo) -> abi::FileInfo {
    abi::FileInfo {
        size: i.size,
        attributes: i.attributes,
        reserved: 0,
        created: i.created,
        modified: i.modified,
    }
}

#[async_trait]
impl PlcBackend for PluginBackend {
    fn describe(&self) -> String {
        format!("plugin {}", self.config.library)
    }

    fn max_read_block(&self, _area: plccoms_protocol::Area) -> u32 {
        self.max_read
    }

    fn max_file_block(&self) -> u32 {
        self.max_file
    }

    fn answer_timeout(&self) -> Duration {
        self.config.answer_timeout
    }

    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters;
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        self.start().await?;
        self.open().await?;
        let ident = self
            .call("identify", |loaded| {
                let f = loaded.api.identify.expect("checked at load");
                let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
                let mut buf = OutBuf::new(abi::IDENT_LEN);
                let mut len = 0usize;
                let mut err = new_error();
                let note = loaded.note("identify");
                // SAFETY: the buffer holds IDENT_LEN bytes (and the guard).
                let code = crash::inside(&note, || unsafe {
                    f(
                        handle,
                        buf.ptr() as *mut c_char,
                        abi::IDENT_LEN,
                        &mut len,
                        &mut err,
                    )
                });
                match status("identify", code, &err)? {
                    Ok(()) => buf.take(len, "identify"),
                    Err(e) => Err(PlcError::Refused(e)),
                }
            })
            .await?;
        self.status().await?;
        Ok(plccoms_protocol::cp1250::decode(&ident)
            .trim_end_matches('\0')
            .to_string())
    }

    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let mut out = Vec::with_capacity(requests.len());
        for r in requests {
            if r.offset.checked_add(r.len).is_none() {
                out.push(Err(Refusal::BAD_PARAMETERS));
                continue;
            }
            let mut joined = Vec::with_capacity(r.len as usize);
            let mut answer = Ok(());
            let mut done = 0;
            while done < r.len || (r.len == 0 && done == 0) {
                let len = (r.len - done).min(self.max_read);
                let block = ReadRequest {
                    area: r.area,
                    offset: r.offset + done,
                    len,
                };
                match self.read_block(block).await? {
                    Ok(bytes) => joined.extend_from_slice(&bytes),
                    Err(e) => {
                        answer = Err(e);
                        break;
                    }
                }
                done += len;
                if len == 0 {
                    break;
                }
            }
            out.push(answer.map(|()| joined));
        }
        Ok(out)
    }

    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let mut out = Vec::with_capacity(requests.len());
        for w in requests {
            let blocks: Vec<WriteRequest> = match &w.data {
                WriteData::Bytes(bytes) if bytes.len() > self.max_read as usize => bytes
                    .chunks(self.max_read as usize)
                    .enumerate()
                    .map(|(i, chunk)| WriteRequest {
                        area: w.area,
                        offset: w.offset.saturating_add((i as u32) * self.max_read),
                        data: WriteData::Bytes(chunk.to_vec()),
                    })
                    .collect(),
                _ => vec![w.clone()],
            };
            let mut answer = Ok(());
            for block in blocks {
                answer = self.write_block(block).await?;
                if answer.is_err() {
                    break;
                }
            }
            out.push(answer);
        }
        Ok(out)
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        self.call("status", |loaded| {
            let f = loaded.api.status.expect("checked at load");
            let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
            let mut run = 0i32;
            let mut err = new_error();
            let note = loaded.note("status");
            // SAFETY: out-pointers to our locals.
            let code = crash::inside(&note, || unsafe { f(handle, &mut run, &mut err) });
            match status("status", code, &err)? {
                Ok(()) => Ok(PlcStatus { run: run != 0 }),
                Err(e) => Err(PlcError::Refused(e)),
            }
        })
        .await
    }

    async fn file_info(&mut self, path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        if let Some(e) = self.no_files() {
            return Ok(Err(e));
        }
        let path = path.to_vec();
        self.call("file_info", move |loaded| {
            let f = loaded.api.file_info.expect("files checked");
            let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
            let mut info = abi::FileInfo::default();
            let mut err = new_error();
            let note = loaded.note("file_info");
            // SAFETY: the path and the out-structure live across the call.
            let code = crash::inside(&note, || unsafe {
                f(handle, path.as_ptr(), path.len(), &mut info, &mut err)
            });
            Ok(status("file_info", code, &err)?.map(|()| to_info(&info)))
        })
        .await
    }

    async fn read_file(
        &mut self,
        path: &[u8],
        offset: u64,
        len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        if let Some(e) = self.no_files() {
            return Ok(Err(e));
        }
        if len > self.max_file {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        let path = path.to_vec();
        self.call("file_read", move |loaded| {
            let f = loaded.api.file_read.expect("files checked");
            let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
            let mut buf = OutBuf::new(len as usize);
            let mut got = 0u32;
            let mut err = new_error();
            let note = loaded.note("file_read");
            // SAFETY: the buffer holds `len` bytes (and the guard).
            let code = crash::inside(&note, || unsafe {
                f(
                    handle,
                    path.as_ptr(),
                    path.len(),
                    offset,
                    buf.ptr(),
                    len,
                    &mut got,
                    &mut err,
                )
            });
            if let Err(e) = status("file_read", code, &err)? {
                return Ok(Err(e));
            }
            buf.take(got as usize, "file_read").map(Ok)
        })
        .await
    }

    async fn write_file(
        &mut self,
        path: &[u8],
        offset: u64,
        data: &[u8],
        last: bool,
    ) -> Result<Answer<()>, PlcError> {
        if let Some(e) = self.no_files() {
            return Ok(Err(e));
        }
        // The link splits uploads into max_file_block pieces; a larger one
        // is refused, so the plugin never gets more than it announced.
        if data.len() > self.max_file as usize {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        let path = path.to_vec();
        let data = data.to_vec();
        let last = i32::from(last);
        self.call("file_write", move |loaded| {
            let f = loaded.api.file_write.expect("files checked");
            let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
            let mut err = new_error();
            let note = loaded.note("file_write");
            // SAFETY: the path and data live across the call.
            let code = crash::inside(&note, || unsafe {
                f(
                    handle,
                    path.as_ptr(),
                    path.len(),
                    offset,
                    data.as_ptr(),
                    data.len() as u32,
                    last,
                    &mut err,
                )
            });
            status("file_write", code, &err)
        })
        .await
    }

    async fn write_file_info(
        &mut self,
        path: &[u8],
        info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        if let Some(e) = self.no_files() {
            return Ok(Err(e));
        }
        let path = path.to_vec();
        let info = from_info(info);
        self.call("file_write_info", move |loaded| {
            let f = loaded.api.file_write_info.expect("files checked");
            let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
            let mut err = new_error();
            let note = loaded.note("file_write_info");
            // SAFETY: the path and the structure live across the call.
            let code = crash::inside(&note, || unsafe {
                f(handle, path.as_ptr(), path.len(), &info, &mut err)
            });
            status("file_write_info", code, &err)
        })
        .await
    }

    async fn list_dir(&mut self, path: &[u8]) -> Result<Answer<Vec<DirEntry>>, PlcError> {
        if let Some(e) = self.no_files() {
            return Ok(Err(e));
        }
        let mut all = Vec::new();
        loop {
            let Ok(start) = u32::try_from(all.len()) else {
                return Err(PlcError::Protocol("directory listing too long".into()));
            };
            let path = path.to_vec();
            let page = self
                .call("dir_list", move |loaded| {
                    let f = loaded.api.dir_list.expect("files checked");
                    let handle = loaded.handle.ok_or(PlcError::NotConfigured)?;
                    let mut entries = vec![abi::DirEntry::default(); DIR_PAGE as usize];
                    let (mut count, mut more) = (0u32, 0i32);
                    let mut err = new_error();
                    let note = loaded.note("dir_list");
                    // SAFETY: `entries` holds DIR_PAGE entries.
                    let code = crash::inside(&note, || unsafe {
                        f(
                            handle,
                            path.as_ptr(),
                            path.len(),
                            start,
                            entries.as_mut_ptr(),
                            DIR_PAGE,
                            &mut count,
                            &mut more,
                            &mut err,
                        )
                    });
                    if let Err(e) = status("dir_list", code, &err)? {
                        return Ok(Err(e));
                    }
                    if count > DIR_PAGE {
                        return Err(PlcError::Protocol(format!(
                            "plugin dir_list reported {count} entries in a page of {DIR_PAGE}"
                        )));
                    }
                    let mut page = Vec::with_capacity(count as usize);
                    for entry in &entries[..count as usize] {
                        let len = entry.name_len as usize;
                        if len > abi::NAME_LEN {
                            return Err(PlcError::Protocol(format!(
                                "plugin dir_list reported a name of {len} bytes"
                            )));
                        }
                        page.push(DirEntry {
                            name: entry.name[..len].to_vec(),
                            info: to_info(&entry.info),
                        });
                    }
                    Ok(Ok((page, more != 0)))
                })
                .await?;
            match page {
                Ok((entries, more)) => {
                    if plccoms_core::driver::add_dir_page(&mut all, entries, more)? {
                        return Ok(Ok(all));
                    }
                }
                Err(e) => return Ok(Err(e)),
            }
        }
    }
}

/// This driver, for the binary's list: sections with `PROTOCOL = EPSNET`
/// and a backend plugin, `SHM_NAME` (the vendor's shared module).
pub const DRIVER: Driver = Driver {
    name: "plugin",
    open,
};

/// The plugin `SHM_NAME` of an EPSNET section. Nothing is loaded here: the
/// link loads it when it connects, and again after each loss.
fn open(section: &plccoms_core::config::Section, dir: &Path) -> Option<Opened> {
    if section.protocol != Protocol::Epsnet {
        return None;
    }
    let library = section.shm_name.as_ref()?;
    // A path starts from the configuration's folder, as every path key;
    // a bare name is the dynamic loader's to find.
    let library = if library.contains('/') {
        section.path_of(dir, library).to_string_lossy().into_owned()
    } else {
        library.clone()
    };
    let config = PluginConfig::from_section(section, &library);
    Some(Ok(Some(Box::new(PluginBackend::new(config)))))
}

#[cfg(test)]
mod tests {
    #[test]
    fn loose_libraries_are_named() {
        use super::loose_library;
        assert_eq!(
            loose_library(0o100664, 0, 0),
            Some("writable by group or others")
        );
        assert_eq!(
            loose_library(0o100646, 1000, 1000),
            Some("writable by group or others")
        );
        assert_eq!(
            loose_library(0o100644, 1000, 1000),
            Some("writable by the server's own user")
        );
        assert_eq!(loose_library(0o100444, 1000, 1000), None);
        assert_eq!(loose_library(0o100644, 0, 1000), None);
        // Root writes everything: only group and others count.
        assert_eq!(loose_library(0o100755, 0, 0), None);
    }

    use super::*;

    #[test]
    fn statuses_map_to_the_two_levels() {
        let mut err = new_error();
        assert!(matches!(status("read", 0, &err), Ok(Ok(()))));
        assert!(matches!(
            status("read", 0x0C, &err),
            Ok(Err(Refusal::BAD_PARAMETERS))
        ));
        assert!(matches!(
            status("read", abi::ERR_UNSUPPORTED, &err),
            Ok(Err(Refusal::UNKNOWN_SERVICE))
        ));
        assert!(matches!(
            status("read", abi::ERR_TIMEOUT, &err),
            Err(PlcError::Timeout(_))
        ));
        assert!(matches!(
            status("read", abi::ERR_IO, &err),
            Err(PlcError::Io(_))
        ));
        // An unterminated message is read within its buffer.
        err.text.fill(b'x' as c_char);
        match status("read", 1000, &err) {
            Err(PlcError::Protocol(text)) => {
                assert!(text.starts_with(
                    "plugin read returned status 1000, which the ABI does not define: xxx"
                ));
                assert!(text.len() < 400);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn out_buffers_catch_overruns_and_lies() {
        let buf = OutBuf::new(4);
        assert_eq!(buf.take(4, "read").unwrap(), [0; 4]);
        let buf = OutBuf::new(4);
        assert!(buf.take(5, "read").is_err());
        let mut buf = OutBuf::new(4);
        // SAFETY: within the allocation (guard included).
        unsafe { *buf.ptr().add(4) = 0 };
        assert!(buf.take(4, "read").is_err());
    }

    #[test]
    fn tables_are_checked() {
        assert!(check_table(std::ptr::null()).is_err());
    }
}
