//! The PLC backend: the one interface through which the server touches a PLC.
//!
//! Errors come in two levels, as in tokio-modbus: the outer `Result` is the
//! link (`PlcError`: timeout, unreachable, garbage on the wire), the inner one
//! is what the device itself answered for one request (`Refusal`: an EPSNET
//! error byte, a Modbus exception). A caller cannot mistake a lost PLC for "address out of range".

use async_trait::async_trait;
use plccoms_protocol::Area;
use std::sync::Arc;

pub use plccoms_plc::files::{
    DirEntry, FileInfo, FILE_ATTRIBUTE_ARCHIVE, FILE_ATTRIBUTE_DIRECTORY, FILE_ATTRIBUTE_HIDDEN,
    FILE_ATTRIBUTE_READONLY, FILE_ATTRIBUTE_SYSTEM,
};
pub use plccoms_plc::memory::WriteData;
pub use plccoms_plc::Refusal;

/// Pause after the first failed probe; doubles up to [`PROBE_MAX`]. The
/// defaults of [`PlcBackend::probe_backoff`], which the link's health uses.
/// Pauses run from the start of one probe to the start of the next.
pub const PROBE_MIN: std::time::Duration = std::time::Duration::from_millis(100);
/// Longest pause between probes, start to start: with a probe being one
/// request without retry ([`PlcBackend::probe`], at most EPSTOUT), a PLC
/// that returns is found again within about a second, whatever the length
/// of the outage.
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

/// A value the device sent of its own accord between polls (an ADS device
/// notification), stamped with the device's own clock: the link publishes
/// it with that time, so the change stream, the historian, DIFFs and MQTT
/// carry the device's time rather than the poll's.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pushed {
    /// The variable.
    pub var: PushedVar,
    /// Its bytes, as a read of it answers them.
    pub bytes: PushedBytes,
    /// The device's time stamp: UTC milliseconds since 1970.
    pub unix_ms: i64,
    /// The device marked the value uncertain (OPC UA's Uncertain status):
    /// served as stale; `false` is good.
    pub uncertain: bool,
}

/// A pushed value's bytes: inline up to 16 (every type but STRING), so
/// that 100,000 values a second take no allocation each.
pub type PushedBytes = smallvec::SmallVec<[u8; 16]>;

/// Which variable a [`Pushed`] value is of.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PushedVar {
    /// Its place in the backend's variable list, numbered by
    /// [`next_list_version`]: the link asks its name
    /// ([`PlcBackend::pushed_name`]) and looks it up once per list, not
    /// once per value (at 100,000 values a second the lookups were a fifth
    /// of the CPU, and sharing each value's name a tenth).
    Listed { list: u32, index: u32 },
    /// Its name, as the backend's variable file has it: looked up each time.
    Named(Arc<[u8]>),
}

/// A number for a backend's new variable list, unique in the process (a
/// new backend's lists too): the `list` of [`PushedVar::Listed`].
pub fn next_list_version() -> u32 {
    static VERSION: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    VERSION.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

/// PLC run state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlcStatus {
    pub run: bool,
}

/// One PLC, reached some way. The server owns one per PLC section, driven by
/// one task (the section's link), so methods take `&mut self`. The link
/// wraps every backend in `link::traced::Traced`: a method added here must
/// be forwarded there too, or its default hides the backend's own.
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

    /// What may explain `refusal` of a read or write at `area`/`offset`, for
    /// the log line that reports it (a Modbus tag naming the 1-based
    /// reference 40001 where the device has holding 0).
    fn refusal_hint(&self, _area: Area, _offset: u32, _refusal: &Refusal) -> Option<String> {
        None
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

    /// Whether this is the link's trace wrapper already
    /// ([`crate::link::traced::Traced`]); no backend of a driver is.
    fn is_traced(&self) -> bool {
        false
    }

    /// (Re)initialise the link and return the PLC's identification string.
    async fn connect(&mut self) -> Result<String, PlcError>;

    /// One connection attempt while the device is not known to be there (at
    /// start-up, after a loss): as [`PlcBackend::connect`], but cheap for a
    /// device that is away, since the link makes one about every second
    /// ([`PROBE_MAX`]) until it answers: its first request is sent once,
    /// without retry, and waits at most the answer timeout. The default is
    /// `connect`, for backends whose connection attempt is already that.
    async fn probe(&mut self) -> Result<String, PlcError> {
        self.connect().await
    }

    /// Read every block; answers come back in request order. The backend packs
    /// and splits requests as its transport allows.
    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError>;

    /// Write every block, in order; answers in request order.
    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError>;

    async fn status(&mut self) -> Result<PlcStatus, PlcError>;

    /// Values the device pushed since the last call, oldest first (none
    /// for a device that is only polled). The link takes them before each
    /// poll and whenever [`PlcBackend::wait_pushed`] returns; a backend
    /// answers a pushed variable's reads with the value last taken, so a
    /// poll never publishes a pushed change before its own stamp does.
    fn take_pushed(&mut self) -> Vec<Pushed> {
        Vec::new()
    }

    /// The name of the variable at `index` of the backend's list `list`
    /// ([`PushedVar::Listed`]); `None` for a list it no longer serves.
    fn pushed_name(&self, _list: u32, _index: u32) -> Option<Arc<[u8]>> {
        None
    }

    /// The variables (named as in [`Pushed`]) whose values the reads
    /// since the last call answered as uncertain, once each; `None` for a
    /// device without a per-value quality (the default). The link takes
    /// them before and after each poll: with `Some`, every value the poll
    /// read is marked uncertain if named here, good if not.
    fn take_uncertain(&mut self) -> Option<Vec<Box<[u8]>>> {
        None
    }

    /// Returns when the device may have pushed something (never, by
    /// default). Cancel-safe: the link drops it whenever a poll or a request
    /// is due. An error is the link's failure, as from a read.
    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        std::future::pending().await
    }

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
pub fn add_dir_page(
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

/// A south driver, as the binary registers it: asked whether it serves a
/// section, and if so, the section's backend.
#[derive(Clone, Copy)]
pub struct Driver {
    /// For the log (`-v`): `epsnet`, `modbus`, `plugin`.
    pub name: &'static str,
    /// The backend of `section` when this driver serves it (`None`: not
    /// this driver's section). `dir` is the configuration's folder, where
    /// relative file names start. Nothing is opened here: the link opens its
    /// socket or device when it connects, and again after each loss.
    pub open: fn(&crate::config::Section, &std::path::Path) -> Option<Opened>,
}

/// The drivers of this build, in the binary's list. Each serves sections
/// no other serves (by `PROTOCOL` and the keys that pick a transport), so
/// their order does not matter.
#[derive(Clone, Copy)]
pub struct Drivers(pub &'static [Driver]);

impl Drivers {
    /// The backend of `section`: the one driver's that serves it, or why
    /// none can (a driver left out of this build).
    pub fn open(&self, section: &crate::config::Section, dir: &std::path::Path) -> Opened {
        for driver in self.0 {
            if let Some(opened) = (driver.open)(section, dir) {
                tracing::debug!(section = %section.name, driver = driver.name, "driver chosen");
                return opened;
            }
        }
        Err(format!(
            "PROTOCOL = {}: this build has no driver for it (built without its cargo feature)",
            section.protocol
        ))
    }
}
