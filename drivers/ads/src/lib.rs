//! Beckhoff ADS (AMS/TCP): the backend for TwinCAT 2 and 3 PLCs, behind
//! the same line protocol as a Tecomat PLC.
//!
//! At each connection the backend reads the device's name, its ADS state
//! and its symbol version; when the version is new (or unknown) it uploads
//! the symbol table and data types and lays the symbols out in R
//! (`plccoms_plc::ads::symbols::Layout`), structures expanded to their
//! fields and arrays to their elements. The public file that names them is
//! served by the backend's file service as `ADS_SYMBOLS.pub`, which the
//! link fetches like a Tecomat PLC's public file; its CRC is `__PF_CRC`
//! (S70), so a new PLC program (a new symbol version, checked at every
//! poll) reloads the table live with every client's settings carried over.
//! `__PLC_RUN` (S2.2) is the ADS state RUN.
//!
//! Reads go by handle, many symbols in one ADS sum read (index group
//! 0xF080, at most 500 a request); handles are asked for in sum
//! read-writes (0xF082) the first time a symbol is read and released when
//! the symbols change. A device that refuses sum commands (0x701) is read
//! one symbol a request from then on. Writes go by handle, one a request;
//! the link reads the value back. ADS error codes travel as
//! `Refusal::Ads`, named, and logged with what to check.
//!
//! Reconnection attempts (a TCP connection and one ReadState sent once)
//! start 100 ms doubling to 1 s apart, as for every backend.

pub mod client;

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use async_trait::async_trait;
use bytes::{BufMut, Bytes, BytesMut};
use plccoms_protocol::{Area, Mask};
use tracing::{info, warn};

use client::Connection;
use plccoms_core::config::{Protocol, ADS_SYMBOLS};
use plccoms_core::driver::{
    Answer, Driver, FileInfo, Opened, PlcBackend, PlcError, PlcStatus, Pushed, PushedBytes,
    PushedVar, ReadRequest, Refusal, WriteData, WriteRequest, FILE_ATTRIBUTE_READONLY,
};
use plccoms_core::metrics::BackendCounters;
use plccoms_plc::ads::command::{
    decode_sum_read, decode_sum_read_write, BodyError, Request, Response, SumResult, TransMode,
};
use plccoms_plc::ads::symbols::{parse_data_types, parse_symbols, Layout, Leaf};
use plccoms_plc::ads::tags::{self, Address};
use plccoms_plc::ads::{filetime_to_unix_ms, group, AdsError, AmsAddr, NetId, MAX_SUM};
use plccoms_plc::memory::{PF_CRC_OFFSET, PLC_RUN_BIT, PLC_RUN_BYTE};

/// Settings of one ADS link (the section's keys).
#[derive(Debug, Clone)]
pub struct AdsConfig {
    /// IPADDR, ADS_TCP_PORT.
    pub device: SocketAddr,
    /// ADS_NET_ID, ADS_PORT.
    pub target: AmsAddr,
    /// ADS_SOURCE_NET_ID.
    pub source: Option<NetId>,
    /// ADS_TIMEOUT.
    pub timeout: Duration,
    /// ADS_NOTIFY: masks of the variables that come by notification.
    pub notify: Vec<String>,
    /// ADS_CYCLE: the PLC's check cycle for them.
    pub cycle: Duration,
    /// ADS_TAGS: the variables from this file instead of the symbol table.
    pub tags: Option<PathBuf>,
}

/// The symbols as last uploaded, and what is served of them.
#[derive(Default)]
struct Symbols {
    layout: Layout,
    /// The public file naming them, and its CRC (`__PF_CRC`).
    file: Vec<u8>,
    crc: u32,
    /// The symbol version they were uploaded at (`None`: the device has
    /// none, or none was read yet).
    version: Option<u8>,
    /// Per leaf: its handle on the present connection.
    handles: Vec<Option<u32>>,
}

pub struct AdsBackend {
    config: AdsConfig,
    connection: Option<Connection>,
    counters: Arc<BackendCounters>,
    symbols: Symbols,
    device_name: String,
    run: bool,
    /// The device takes sum commands (until it says otherwise).
    sum: bool,
    notes: Notes,
    /// Modification time and length of the tag file when it was loaded.
    tags_seen: Option<(SystemTime, u64)>,
}

/// The device notifications registered on the present connection.
#[derive(Default)]
struct Notes {
    /// Notification handle -> leaf.
    by_handle: HashMap<u32, usize>,
    /// Per notified leaf: the value last handed to the link (`None` until
    /// the first), which its polls answer.
    last: HashMap<usize, Option<Bytes>>,
}

fn not_connected() -> PlcError {
    PlcError::Io(std::io::Error::new(
        std::io::ErrorKind::NotConnected,
        "no connection to the device",
    ))
}

fn refused(error: AdsError) -> Refusal {
    Refusal::Ads(error)
}

impl AdsBackend {
    pub fn new(config: AdsConfig) -> AdsBackend {
        AdsBackend {
            config,
            connection: None,
            counters: Arc::default(),
            symbols: Symbols::default(),
            device_name: String::new(),
            run: false,
            sum: true,
            notes: Notes::default(),
            tags_seen: None,
        }
    }

    /// Notifications registered on the device now.
    pub fn notifications(&self) -> usize {
        self.notes.by_handle.len()
    }

    /// Registers a notification for every leaf ADS_NOTIFY names (on change,
    /// checked every ADS_CYCLE). A refused one (0x716: the PLC has no
    /// handles left) is logged, and its variable polled.
    async fn register_notifications(&mut self) -> Result<(), PlcError> {
        if self.config.notify.is_empty() {
            return Ok(());
        }
        let masks: Vec<Mask> = self
            .config
            .notify
            .iter()
            .map(|m| Mask::new(m.as_bytes()))
            .collect();
        let wanted: Vec<usize> = (0..self.symbols.layout.leaves.len())
            .filter(|&i| {
                let upper = self.symbols.layout.leaves[i].name.to_ascii_uppercase();
                masks.iter().any(|m| m.matches(upper.as_bytes()))
            })
            .collect();
        let errors = self.ensure_handles(&wanted).await?;
        let cycle = u32::try_from(self.config.cycle.as_nanos() / 100).unwrap_or(u32::MAX);
        let mut refused = 0;
        for (&i, error) in wanted.iter().zip(errors) {
            let leaf = &self.symbols.layout.leaves[i];
            let (name, size) = (leaf.name.clone(), leaf.size());
            let outcome = match (error, self.place(i)) {
                (None, Some((group, offset))) => {
                    let request = Request::AddNotification {
                        group,
                        offset,
                        len: size,
                        mode: TransMode::ON_CHANGE,
                        max_delay: 0,
                        cycle,
                    };
                    self.request(&request).await?
                }
                (error, _) => Err(error.unwrap_or(AdsError::SYMBOL_NOT_FOUND)),
            };
            match outcome {
                Ok(Response::Handle(handle)) => {
                    self.notes.by_handle.insert(handle, i);
                    self.notes.last.insert(i, None);
                }
                Ok(_) => refused += 1,
                Err(e) => {
                    refused += 1;
                    if refused <= 5 {
                        self.log_refusal("notification", &name, e);
                    }
                }
            }
        }
        info!(device = %self.config.device, "{} device notifications registered ({refused} refused: polled)", self.notes.by_handle.len());
        Ok(())
    }

    /// Deletes every notification registered (best effort: the device
    /// forgets them with the connection anyway).
    async fn delete_notifications(&mut self) -> Result<(), PlcError> {
        let handles: Vec<u32> = self.notes.by_handle.keys().copied().collect();
        self.notes = Notes::default();
        for handle in handles {
            let _ = self
                .request(&Request::DeleteNotification { handle })
                .await?;
        }
        Ok(())
    }

    /// The variables as laid out now (for tests and tools).
    pub fn leaves(&self) -> &[Leaf] {
        &self.symbols.layout.leaves
    }

    /// One request; a failed exchange gives the connection up.
    async fn request(&mut self, request: &Request) -> Result<Result<Response, AdsError>, PlcError> {
        let connection = self.connection.as_mut().ok_or_else(not_connected)?;
        match connection.request(request, &self.counters).await {
            Ok(outcome) => Ok(outcome),
            Err(err) => {
                self.connection = None;
                Err(err)
            }
        }
    }

    async fn read_data(
        &mut self,
        group: u32,
        offset: u32,
        len: u32,
    ) -> Result<Result<Bytes, AdsError>, PlcError> {
        Ok(self
            .request(&Request::Read { group, offset, len })
            .await?
            .map(data))
    }

    async fn read_write(
        &mut self,
        group: u32,
        offset: u32,
        read_len: u32,
        write: Bytes,
    ) -> Result<Result<Bytes, AdsError>, PlcError> {
        let request = Request::ReadWrite {
            group,
            offset,
            read_len,
            data: write,
        };
        Ok(self.request(&request).await?.map(data))
    }

    /// A new connection: the device's state sent once while probing, its
    /// name, and the symbols when their version is new.
    async fn connect_with(&mut self, probing: bool) -> Result<String, PlcError> {
        if self.connection.is_some() && !self.notes.by_handle.is_empty() {
            // A new link to a device that answers (HALT -> RUN): its
            // notifications go first, within one timeout.
            let timeout = self.config.timeout;
            let _ = tokio::time::timeout(timeout, self.delete_notifications()).await;
        }
        self.notes = Notes::default();
        self.connection = None;
        let mut connection = Connection::open(
            self.config.device,
            self.config.target,
            self.config.source,
            self.config.timeout,
        )
        .await?;
        connection.probing(probing);
        self.connection = Some(connection);
        // Handles belong to the connection that asked for them.
        self.symbols.handles.iter_mut().for_each(|h| *h = None);
        self.read_state().await?;
        if let Some(connection) = self.connection.as_mut() {
            connection.probing(false);
        }
        if let Ok(Response::DeviceInfo { version, name }) =
            self.request(&Request::ReadDeviceInfo).await?
        {
            self.device_name = format!("{name} {}.{}.{}", version.0, version.1, version.2);
        }
        self.check_symbols(true).await?;
        if self.notes.by_handle.is_empty() {
            self.register_notifications().await?;
        }
        Ok(format!(
            "ADS {} ({} symbols)",
            self.device_name,
            self.symbols.layout.leaves.len()
        ))
    }

    async fn read_state(&mut self) -> Result<(), PlcError> {
        match self.request(&Request::ReadState).await? {
            Ok(Response::State { ads, .. }) => self.run = ads.is_run(),
            Ok(_) => {}
            Err(error) => {
                return Err(PlcError::Refused(refused(error)));
            }
        }
        Ok(())
    }

    /// Reads the symbol version; uploads the symbols again when it changed
    /// (or `always` and none are loaded).
    async fn check_symbols(&mut self, at_connect: bool) -> Result<(), PlcError> {
        let version = match self.read_data(group::SYM_VERSION, 0, 1).await? {
            Ok(bytes) => bytes.first().copied(),
            Err(_) => None,
        };
        let loaded = !self.symbols.file.is_empty();
        if let Some(path) = self.config.tags.clone() {
            return self.check_tags(&path, version, loaded).await;
        }
        if loaded && version.is_some() && version == self.symbols.version {
            return Ok(());
        }
        if loaded && version.is_none() && !at_connect {
            return Ok(());
        }
        let notified = !self.notes.by_handle.is_empty();
        if loaded {
            info!(device = %self.config.device, "symbol version {:?} -> {version:?}: uploading the symbols again", self.symbols.version);
            self.delete_notifications().await?;
            self.release_handles().await?;
        }
        self.upload().await?;
        self.symbols.version = version;
        if notified {
            self.register_notifications().await?;
        }
        Ok(())
    }

    /// With a tag file: the file loaded again when it changed; handles and
    /// notifications made again when the PLC's program changed.
    async fn check_tags(
        &mut self,
        path: &Path,
        version: Option<u8>,
        loaded: bool,
    ) -> Result<(), PlcError> {
        let stamp = std::fs::metadata(path)
            .ok()
            .map(|m| (m.modified().unwrap_or(SystemTime::UNIX_EPOCH), m.len()));
        let new_file = !loaded || (stamp.is_some() && stamp != self.tags_seen);
        let new_program = loaded && version.is_some() && version != self.symbols.version;
        self.symbols.version = version;
        if !new_file && !new_program {
            return Ok(());
        }
        let notified = !self.notes.by_handle.is_empty();
        if loaded {
            self.delete_notifications().await?;
            self.release_handles().await?;
        }
        if new_file {
            // A file being rewritten may be unreadable for a moment: the
            // last one stays, and it is looked at again at the next poll.
            match load_tags(path, &self.config.device) {
                Ok(layout) => {
                    self.tags_seen = stamp;
                    self.serve(layout);
                }
                Err(e) if loaded => warn!(device = %self.config.device, "{e}"),
                Err(e) => return Err(PlcError::Protocol(e)),
            }
        }
        if notified {
            self.register_notifications().await?;
        }
        Ok(())
    }

    /// Serves `layout` from now on: its public file and `__PF_CRC`.
    fn serve(&mut self, layout: Layout) {
        let file = layout.public_file(&format!(
            "{} at {}",
            self.device_name, self.config.target.net_id
        ));
        self.symbols.crc = plccoms_plc::pubfile::crc_of(plccoms_plc::pubfile::crc_content(&file));
        self.symbols.handles = vec![None; layout.leaves.len()];
        self.symbols.layout = layout;
        self.symbols.file = file;
    }

    async fn upload(&mut self) -> Result<(), PlcError> {
        let info = self
            .read_data(group::SYM_UPLOADINFO2, 0, 24)
            .await?
            .map_err(|e| upload_refused("symbol table size", e))?;
        let word = |i: usize| {
            info.get(4 * i..4 * i + 4)
                .map_or(0, |w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
        };
        let (symbols_len, types_len) = (word(1), word(3));
        let max = plccoms_plc::ads::frame::MAX_FRAME as u32 - 64;
        if symbols_len > max || types_len > max {
            return Err(PlcError::Protocol(format!(
                "symbol table of {symbols_len} bytes and data types of {types_len}: more than {max} accepted"
            )));
        }
        let table = self
            .read_data(group::SYM_UPLOAD, 0, symbols_len)
            .await?
            .map_err(|e| upload_refused("symbol table", e))?;
        let symbols = parse_symbols(&table).map_err(|e| PlcError::Protocol(e.to_string()))?;
        let types = if types_len > 0 {
            let bytes = self
                .read_data(group::SYM_DT_UPLOAD, 0, types_len)
                .await?
                .map_err(|e| upload_refused("data types", e))?;
            parse_data_types(&bytes).map_err(|e| PlcError::Protocol(e.to_string()))?
        } else {
            Vec::new()
        };
        let layout = Layout::expand(&symbols, &types);
        for skipped in &layout.skipped.first {
            warn!(device = %self.config.device, "symbol not served: {skipped}");
        }
        if layout.skipped.count > layout.skipped.first.len() {
            warn!(device = %self.config.device, "{} more symbols not served", layout.skipped.count - layout.skipped.first.len());
        }
        info!(device = %self.config.device, symbols = symbols.len(), variables = layout.leaves.len(), "symbols uploaded");
        self.serve(layout);
        Ok(())
    }

    /// Releases every handle held (best effort: a device that lost them
    /// answers an error, which changes nothing).
    async fn release_handles(&mut self) -> Result<(), PlcError> {
        let held: Vec<u32> = self.symbols.handles.iter().flatten().copied().collect();
        for handle in held {
            let request = Request::Write {
                group: group::SYM_RELEASEHND,
                offset: 0,
                data: Bytes::copy_from_slice(&handle.to_le_bytes()),
            };
            let _ = self.request(&request).await?;
        }
        self.symbols.handles.iter_mut().for_each(|h| *h = None);
        Ok(())
    }

    /// Handles for `leaves` (indices) that have none yet; a leaf the device
    /// refuses keeps none, and its refusal is returned.
    async fn ensure_handles(
        &mut self,
        leaves: &[usize],
    ) -> Result<Vec<Option<AdsError>>, PlcError> {
        let mut errors = vec![None; leaves.len()];
        let missing: Vec<(usize, usize)> = leaves
            .iter()
            .enumerate()
            .filter(|(_, &i)| {
                self.symbols.handles[i].is_none()
                    && !self.symbols.layout.leaves[i].ads_name.is_empty()
            })
            .map(|(k, &i)| (k, i))
            .collect();
        for chunk in missing.chunks(MAX_SUM) {
            let names: Vec<Bytes> = chunk
                .iter()
                .map(|&(_, i)| {
                    Bytes::from(self.symbols.layout.leaves[i].ads_name.clone().into_bytes())
                })
                .collect();
            let results = if self.sum && chunk.len() > 1 {
                let mut write = BytesMut::new();
                for name in &names {
                    write.put_u32_le(group::SYM_HNDBYNAME);
                    write.put_u32_le(0);
                    write.put_u32_le(4);
                    write.put_u32_le(name.len() as u32);
                }
                for name in &names {
                    write.put_slice(name);
                }
                let read_len = (chunk.len() * 12) as u32;
                let count = chunk.len();
                self.sum(group::SUMUP_READWRITE, count, read_len, write, |answer| {
                    decode_sum_read_write(answer, count)
                })
                .await?
            } else {
                None
            };
            let results = match results {
                Some(results) => results,
                None => {
                    let mut one_by_one = Vec::with_capacity(names.len());
                    for name in names {
                        one_by_one.push(self.read_write(group::SYM_HNDBYNAME, 0, 4, name).await?);
                    }
                    one_by_one
                }
            };
            for (&(k, i), result) in chunk.iter().zip(results) {
                match result {
                    Ok(bytes) if bytes.len() >= 4 => {
                        self.symbols.handles[i] =
                            Some(u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]))
                    }
                    Ok(_) => errors[k] = Some(AdsError::INVALID_SIZE),
                    Err(e) => errors[k] = Some(e),
                }
            }
        }
        Ok(errors)
    }

    /// Where leaf `i` is read and written: by its handle, or at its index
    /// group/offset (a tag file's `group:offset`); `None` without a handle.
    fn place(&self, i: usize) -> Option<(u32, u32)> {
        let leaf = &self.symbols.layout.leaves[i];
        if leaf.ads_name.is_empty() {
            return Some((leaf.group, leaf.offset));
        }
        self.symbols.handles[i].map(|handle| (group::SYM_VALBYHND, handle))
    }

    /// One sum command of `count` sub-requests, its answer split by
    /// `decode`; `None` when the device has no sum commands (from now on,
    /// one request a symbol), every sub-request the refusal when it refuses
    /// the whole.
    async fn sum(
        &mut self,
        group: u32,
        count: usize,
        read_len: u32,
        write: BytesMut,
        decode: impl FnOnce(&Bytes) -> Result<Vec<SumResult>, BodyError>,
    ) -> Result<Option<Vec<SumResult>>, PlcError> {
        match self
            .read_write(group, count as u32, read_len, write.freeze())
            .await?
        {
            Ok(answer) => decode(&answer)
                .map(Some)
                .map_err(|e| PlcError::Protocol(e.to_string())),
            Err(e) if is_unsupported(e) => {
                self.no_sum(e);
                Ok(None)
            }
            Err(e) => Ok(Some(vec![Err(e); count])),
        }
    }

    fn no_sum(&mut self, error: AdsError) {
        info!(device = %self.config.device, "the device refuses ADS sum commands ({error}): one symbol a request from now on");
        self.sum = false;
    }

    /// The values of `leaves` (indices), each the device's data or refusal.
    async fn read_leaves(
        &mut self,
        leaves: &[usize],
    ) -> Result<Vec<Result<Bytes, AdsError>>, PlcError> {
        // A notified leaf answers the value last handed to the link.
        let (known, asked): (Vec<_>, Vec<_>) = leaves
            .iter()
            .copied()
            .enumerate()
            .partition(|(_, i)| matches!(self.notes.last.get(i), Some(Some(_))));
        if known.is_empty() {
            return self.read_from_device(leaves).await;
        }
        let asked_leaves: Vec<usize> = asked.iter().map(|&(_, i)| i).collect();
        let mut from_device = self.read_from_device(&asked_leaves).await?.into_iter();
        let mut results = vec![Err(AdsError::SYMBOL_NOT_FOUND); leaves.len()];
        for (k, i) in known {
            if let Some(Some(bytes)) = self.notes.last.get(&i) {
                results[k] = Ok(bytes.clone());
            }
        }
        for (k, _) in asked {
            if let Some(result) = from_device.next() {
                results[k] = result;
            }
        }
        Ok(results)
    }

    async fn read_from_device(
        &mut self,
        leaves: &[usize],
    ) -> Result<Vec<Result<Bytes, AdsError>>, PlcError> {
        let handle_errors = self.ensure_handles(leaves).await?;
        let mut results: Vec<Option<Result<Bytes, AdsError>>> =
            handle_errors.into_iter().map(|e| e.map(Err)).collect();
        let wanted: Vec<(usize, (u32, u32), u32)> = leaves
            .iter()
            .enumerate()
            .filter(|(k, _)| results[*k].is_none())
            .filter_map(|(k, &i)| {
                let size = self.symbols.layout.leaves[i].size();
                self.place(i).map(|place| (k, place, size))
            })
            .collect();
        for chunk in wanted.chunks(MAX_SUM) {
            let answers = if self.sum && chunk.len() > 1 {
                let mut write = BytesMut::with_capacity(chunk.len() * 12);
                for &(_, (group, offset), size) in chunk {
                    write.put_u32_le(group);
                    write.put_u32_le(offset);
                    write.put_u32_le(size);
                }
                let sizes: Vec<u32> = chunk.iter().map(|c| c.2).collect();
                let read_len = 4 * chunk.len() as u32 + sizes.iter().sum::<u32>();
                self.sum(group::SUMUP_READ, chunk.len(), read_len, write, |answer| {
                    decode_sum_read(answer, &sizes)
                })
                .await?
            } else {
                None
            };
            let answers = match answers {
                Some(answers) => answers,
                None => {
                    let mut one_by_one = Vec::with_capacity(chunk.len());
                    for &(_, (group, offset), size) in chunk {
                        one_by_one.push(self.read_data(group, offset, size).await?);
                    }
                    one_by_one
                }
            };
            for (&(k, _, size), answer) in chunk.iter().zip(answers) {
                results[k] = Some(match answer {
                    Ok(bytes) if bytes.len() as u32 == size => Ok(bytes),
                    Ok(_) => Err(AdsError::INVALID_SIZE),
                    Err(e) => Err(e),
                });
            }
        }
        // A refused handle is asked for again at the next read: the symbol
        // may come back with the program.
        for (k, &i) in leaves.iter().enumerate() {
            if matches!(results[k], Some(Err(e)) if forgets_handle(e)) {
                self.symbols.handles[i] = None;
            }
        }
        Ok(results
            .into_iter()
            .map(|r| r.unwrap_or(Err(AdsError::SYMBOL_NOT_FOUND)))
            .collect())
    }

    /// The system area: `__PLC_RUN` and `__PF_CRC`.
    fn system(&self, offset: u32, len: u32) -> Answer<Vec<u8>> {
        let mut image = [0u8; 4096];
        if self.run {
            image[PLC_RUN_BYTE as usize] |= 1 << PLC_RUN_BIT;
        }
        let crc = PF_CRC_OFFSET as usize;
        image[crc..crc + 4].copy_from_slice(&self.symbols.crc.to_le_bytes());
        let end = offset as usize + len as usize;
        image
            .get(offset as usize..end)
            .map(<[u8]>::to_vec)
            .ok_or(refused(AdsError::INVALID_OFFSET))
    }

    fn log_refusal(&self, what: &str, name: &str, error: AdsError) {
        let hint = error.hint().map(|h| format!("; {h}")).unwrap_or_default();
        warn!(device = %self.config.device, "{what} of {name} refused: {error}{hint}");
    }

    async fn write_one(&mut self, write: &WriteRequest) -> Result<Answer<()>, PlcError> {
        let leaves = &self.symbols.layout.leaves;
        let index = leaves.partition_point(|l| l.at + l.size() <= write.offset);
        let Some(leaf) = leaves
            .get(index)
            .filter(|l| l.at <= write.offset && write.area == Area::R)
        else {
            return Ok(Err(refused(AdsError::INVALID_OFFSET)));
        };
        let (at, size, name) = (leaf.at, leaf.size(), leaf.name.clone());
        let within = (write.offset - at) as usize;
        let whole = match &write.data {
            WriteData::Bytes(bytes) if within == 0 && bytes.len() as u32 == size => {
                Bytes::copy_from_slice(bytes)
            }
            data => {
                // Part of a symbol: what is around it first.
                let mut current = match self.read_from_device(&[index]).await?.remove(0) {
                    Ok(bytes) => bytes.to_vec(),
                    Err(e) => return Ok(Err(refused(e))),
                };
                match data {
                    WriteData::Bytes(bytes) if within + bytes.len() <= current.len() => {
                        current[within..within + bytes.len()].copy_from_slice(bytes)
                    }
                    WriteData::Bit { bit, value } if *bit < 8 => {
                        let mask = 1u8 << bit;
                        if *value {
                            current[within] |= mask;
                        } else {
                            current[within] &= !mask;
                        }
                    }
                    _ => return Ok(Err(refused(AdsError::INVALID_SIZE))),
                }
                Bytes::from(current)
            }
        };
        if let Some(e) = self.ensure_handles(&[index]).await?.remove(0) {
            self.log_refusal("write", &name, e);
            return Ok(Err(refused(e)));
        }
        let (group, offset) = self
            .place(index)
            .ok_or_else(|| PlcError::Protocol("no handle".into()))?;
        let request = Request::Write {
            group,
            offset,
            data: whole,
        };
        match self.request(&request).await? {
            Ok(_) => {
                // The link reads a write back: from the PLC, not the value
                // last notified, until the next notification comes.
                if let Some(last) = self.notes.last.get_mut(&index) {
                    *last = None;
                }
                Ok(Ok(()))
            }
            Err(e) => {
                self.log_refusal("write", &name, e);
                if forgets_handle(e) {
                    self.symbols.handles[index] = None;
                }
                Ok(Err(refused(e)))
            }
        }
    }
}

/// Largest tag file read.
const MAX_TAG_FILE: u64 = 64 * 1024 * 1024;

/// The variables of a tag file, laid out; its problems logged.
fn load_tags(path: &Path, device: &SocketAddr) -> Result<Layout, String> {
    let size = std::fs::metadata(path)
        .map_err(|e| format!("tag file {}: {e}", path.display()))?
        .len();
    if size > MAX_TAG_FILE {
        return Err(format!(
            "tag file {}: {size} bytes, more than the {MAX_TAG_FILE} accepted",
            path.display()
        ));
    }
    let bytes = std::fs::read(path).map_err(|e| format!("tag file {}: {e}", path.display()))?;
    let file = tags::parse(&bytes);
    for warning in file.warnings.iter().take(5) {
        warn!(device = %device, "tag file {}: {warning}", path.display());
    }
    let more = file.warnings.len().saturating_sub(5) + file.more_warnings;
    if more > 0 {
        warn!(device = %device, "tag file {}: {more} more problems not shown", path.display());
    }
    let mut layout = Layout::default();
    for tag in file.tags {
        match tag.address {
            Address::Symbol(symbol) => layout.push(tag.name, symbol, 0, 0, tag.ty),
            Address::Group { group, offset } => {
                layout.push(tag.name, String::new(), group, offset, tag.ty)
            }
        }
    }
    info!(device = %device, variables = layout.leaves.len(), "tag file {} loaded", path.display());
    Ok(layout)
}

fn data(response: Response) -> Bytes {
    match response {
        Response::Data(data) => data,
        _ => Bytes::new(),
    }
}

/// The symbol behind a handle is gone (or the handle with it).
fn forgets_handle(e: AdsError) -> bool {
    matches!(e.0, 0x70C | 0x710 | 0x711)
}

/// A device without sum commands answers one of these to them.
fn is_unsupported(e: AdsError) -> bool {
    matches!(e.0, 0x701 | 0x702 | 0x8)
}

fn upload_refused(what: &str, e: AdsError) -> PlcError {
    let hint = e.hint().map(|h| format!("; {h}")).unwrap_or_default();
    PlcError::Protocol(format!("the PLC refused its {what}: {e}{hint}"))
}

#[async_trait]
impl PlcBackend for AdsBackend {
    fn describe(&self) -> String {
        format!(
            "ADS {} {}:{}",
            self.config.device, self.config.target.net_id, self.config.target.port
        )
    }

    fn max_read_block(&self, area: Area) -> u32 {
        match area {
            Area::S => 4096,
            _ => 64 * 1024,
        }
    }

    /// Symbols lie back to back: a read joins only adjacent ones.
    fn read_gap(&self, _area: Area) -> Option<u32> {
        Some(0)
    }

    fn max_file_block(&self) -> u32 {
        64 * 1024
    }

    fn answer_timeout(&self) -> Duration {
        self.config.timeout
    }

    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters;
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        self.connect_with(false).await
    }

    /// A new connection (refused at once by a host whose router is off, or
    /// given up after ADS_TIMEOUT) and one ReadState sent once.
    async fn probe(&mut self) -> Result<String, PlcError> {
        self.connect_with(true).await
    }

    async fn read(&mut self, reads: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        if self.connection.is_none() {
            return Err(not_connected());
        }
        if reads.iter().any(|r| r.area == Area::S) {
            self.read_state().await?;
            self.check_symbols(false).await?;
        }
        // Every symbol of every read in one list, each once.
        let mut wanted: Vec<usize> = Vec::new();
        let mut spans = Vec::with_capacity(reads.len());
        for read in reads {
            if read.area != Area::R {
                spans.push(None);
                continue;
            }
            let covering = self.symbols.layout.covering(read.offset, read.len);
            let first = covering
                .first()
                .map(|l| self.symbols.layout.leaves.partition_point(|x| x.at < l.at));
            let end = u64::from(read.offset) + u64::from(read.len);
            let whole = covering.first().is_some_and(|l| l.at <= read.offset)
                && covering
                    .last()
                    .is_some_and(|l| u64::from(l.at + l.size()) >= end);
            match first {
                Some(first) if whole => {
                    let range = first..first + covering.len();
                    wanted.extend(range.clone());
                    spans.push(Some(range));
                }
                _ => spans.push(None),
            }
        }
        wanted.sort_unstable();
        wanted.dedup();
        let values = self.read_leaves(&wanted).await?;
        let mut answers = Vec::with_capacity(reads.len());
        for (read, span) in reads.iter().zip(spans) {
            if read.area == Area::S {
                answers.push(self.system(read.offset, read.len));
                continue;
            }
            let Some(range) = span else {
                answers.push(Err(refused(AdsError::INVALID_OFFSET)));
                continue;
            };
            let mut bytes = Vec::with_capacity(read.len as usize);
            let mut failure = None;
            for i in range {
                let leaf = &self.symbols.layout.leaves[i];
                let k = wanted.binary_search(&i).expect("listed above");
                match &values[k] {
                    Ok(data) => {
                        let from = read.offset.saturating_sub(leaf.at) as usize;
                        let to = ((read.offset + read.len).min(leaf.at + leaf.size()) - leaf.at)
                            as usize;
                        bytes.extend_from_slice(&data[from..to]);
                    }
                    Err(e) => {
                        failure.get_or_insert(refused(*e));
                    }
                }
            }
            answers.push(match failure {
                Some(e) => Err(e),
                None => Ok(bytes),
            });
        }
        Ok(answers)
    }

    async fn write(&mut self, writes: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let mut answers = Vec::with_capacity(writes.len());
        for write in writes {
            answers.push(self.write_one(write).await?);
        }
        Ok(answers)
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        if self.connection.is_none() {
            return Err(not_connected());
        }
        self.read_state().await?;
        Ok(PlcStatus { run: self.run })
    }

    /// The samples of the device notifications received so far, each with
    /// the PLC's time stamp; the last of each variable is what its polls
    /// answer from now on.
    fn take_pushed(&mut self) -> Vec<Pushed> {
        let Some(connection) = self.connection.as_mut() else {
            return Vec::new();
        };
        let mut pushed = Vec::new();
        for stamp in connection.take_notifications() {
            let unix_ms = filetime_to_unix_ms(stamp.filetime);
            for sample in stamp.samples {
                // A notification deleted meanwhile, or of another size.
                let Some(&i) = self.notes.by_handle.get(&sample.handle) else {
                    continue;
                };
                let leaf = &self.symbols.layout.leaves[i];
                if sample.data.len() as u32 != leaf.size() {
                    continue;
                }
                pushed.push(Pushed {
                    var: PushedVar::Named(leaf.name.as_bytes().into()),
                    bytes: PushedBytes::from_slice(&sample.data),
                    unix_ms,
                    // ADS has no per-value quality.
                    uncertain: false,
                });
                self.notes.last.insert(i, Some(sample.data));
            }
        }
        pushed
    }

    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        let Some(connection) = self
            .connection
            .as_mut()
            .filter(|_| !self.notes.by_handle.is_empty())
        else {
            return std::future::pending().await;
        };
        let result = connection.until_notified().await;
        if result.is_err() {
            self.connection = None;
        }
        result
    }

    /// The public file of the symbols, `ADS_SYMBOLS.pub`; nothing else.
    async fn file_info(&mut self, path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        if !is_symbol_file(path) || self.symbols.file.is_empty() {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        Ok(Ok(FileInfo {
            size: self.symbols.file.len() as u64,
            attributes: FILE_ATTRIBUTE_READONLY,
            created: 0,
            modified: 0,
        }))
    }

    async fn read_file(
        &mut self,
        path: &[u8],
        offset: u64,
        len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        if !is_symbol_file(path) {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        let file = &self.symbols.file;
        let from = (offset as usize).min(file.len());
        let to = from.saturating_add(len as usize).min(file.len());
        Ok(Ok(file[from..to].to_vec()))
    }
}

fn is_symbol_file(path: &[u8]) -> bool {
    let name = path.strip_prefix(b"/").unwrap_or(path);
    let name = name.strip_prefix(b"/").unwrap_or(name);
    name.eq_ignore_ascii_case(ADS_SYMBOLS.as_bytes())
}

/// This driver, for the binary's list: sections with `PROTOCOL = ADS`.
pub const DRIVER: Driver = Driver { name: "ads", open };

/// ADS to `IPADDR:ADS_TCP_PORT`, or `None` when the section has no device
/// yet (`IPADDR` unset or `0.0.0.0`).
fn open(section: &plccoms_core::config::Section, dir: &std::path::Path) -> Option<Opened> {
    if section.protocol != Protocol::Ads {
        return None;
    }
    if section.serial_device.is_some() || section.shm_name.is_some() || section.simulator.is_some()
    {
        return Some(Err(
            "PROTOCOL = ADS runs over TCP to a TwinCAT PLC: SERIAL_DEVICE, SHM_NAME and SIMULATOR do not apply (plcsim --ads plays a PLC)"
                .to_string(),
        ));
    }
    let Some(ip) = section.ipaddr.filter(|ip| !ip.is_unspecified()) else {
        return Some(Ok(None));
    };
    Some(
        config_of(section, ip, dir)
            .map(|config| Some(Box::new(AdsBackend::new(config)) as Box<dyn PlcBackend>)),
    )
}

/// ADS settings from a section's keys, for a device at `ip`.
pub fn config_of(
    section: &plccoms_core::config::Section,
    ip: std::net::Ipv4Addr,
    dir: &std::path::Path,
) -> Result<AdsConfig, String> {
    let ads = &section.ads;
    let net_id = match &ads.net_id {
        Some(text) => NetId::parse(text).map_err(|e| format!("ADS_NET_ID: {e}"))?,
        None => {
            let [a, b, c, d] = ip.octets();
            NetId([a, b, c, d, 1, 1])
        }
    };
    let source = match &ads.source_net_id {
        Some(text) => Some(NetId::parse(text).map_err(|e| format!("ADS_SOURCE_NET_ID: {e}"))?),
        None => None,
    };
    Ok(AdsConfig {
        device: SocketAddr::new(IpAddr::V4(ip), ads.tcp_port),
        target: AmsAddr {
            net_id,
            port: ads.port,
        },
        source,
        timeout: ads.timeout,
        notify: ads.notify.clone(),
        cycle: ads.cycle,
        tags: ads.tags.as_deref().map(|name| section.path_of(dir, name)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn section(ini: &str) -> plccoms_core::config::Section {
        let text = format!("[*]\n[A]\nSERVER_PORT = 1\nPROTOCOL = ADS\n{ini}\n");
        let loaded = plccoms_core::config::parse(Path::new("t.ini"), &text).unwrap();
        loaded.config.sections.into_iter().next().unwrap()
    }

    #[test]
    fn net_ids_default_to_the_address_and_ports_to_twincat_3() {
        let s = section("IPADDR = 10.1.2.3");
        let config = config_of(&s, s.ipaddr.unwrap(), Path::new("/etc")).unwrap();
        assert_eq!(config.target.net_id, NetId([10, 1, 2, 3, 1, 1]));
        assert_eq!(config.target.port, 851);
        assert_eq!(config.device, "10.1.2.3:48898".parse().unwrap());
        assert_eq!(config.source, None);
        let s = section(
            "IPADDR = 10.1.2.3\nADS_NET_ID = 5.9.8.7.1.1\nADS_PORT = 801\n\
             ADS_SOURCE_NET_ID = 10.0.0.9.1.1\nADS_TAGS = //t.csv",
        );
        let config = config_of(&s, s.ipaddr.unwrap(), Path::new("/etc")).unwrap();
        assert_eq!(config.target.net_id, NetId([5, 9, 8, 7, 1, 1]));
        assert_eq!(config.target.port, 801);
        assert_eq!(config.source, Some(NetId([10, 0, 0, 9, 1, 1])));
        assert_eq!(config.tags, Some(PathBuf::from("/etc/t.csv")));
    }

    #[test]
    fn only_ads_sections_over_tcp_are_this_drivers() {
        let dir = Path::new(".");
        assert!((DRIVER.open)(&section("IPADDR = 0.0.0.0"), dir)
            .unwrap()
            .unwrap()
            .is_none());
        assert!((DRIVER.open)(&section("SIMULATOR = Yes"), dir)
            .unwrap()
            .is_err());
        let mut epsnet = section("IPADDR = 10.1.2.3");
        epsnet.protocol = Protocol::Epsnet;
        assert!((DRIVER.open)(&epsnet, dir).is_none());
        assert!(is_symbol_file(b"//ADS_SYMBOLS.pub"));
        assert!(is_symbol_file(b"ads_symbols.pub"));
        assert!(!is_symbol_file(b"other.pub"));
    }
}
