//! PLC file services, run by the link (the backend's one owner): file
//! information, directory listings, reads in blocks and whole-file writes,
//! plus the cache of recently read files (FFILE_MAXRECS, FFILE_TIMEOUT) and
//! SYNC_VAR_ENABLED (whether polling goes on during a transfer).
//!
//! The cache keeps whole files only, filled while a client reads one from
//! offset 0 to its end. It is bounded in entries (FFILE_MAXRECS; 0 turns it
//! off), in age (FFILE_TIMEOUT), and in bytes: files over
//! [`CACHE_MAX_FILE`] are never kept and the total stays under
//! [`CACHE_MAX_BYTES`], oldest entries going first. A write or an info
//! change of a file drops its entry.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use tokio::time::Instant;

use super::cycle::Cycle;
use crate::changes::Publisher;
use crate::driver::{Answer, DirEntry, FileInfo, PlcBackend, PlcError};

/// Largest file the cache keeps.
pub const CACHE_MAX_FILE: usize = 1024 * 1024;
/// Most bytes the cache holds in all.
pub const CACHE_MAX_BYTES: usize = 16 * 1024 * 1024;

/// A file request from a session.
#[derive(Debug)]
pub enum FileJob {
    Info {
        path: Vec<u8>,
    },
    List {
        path: Vec<u8>,
    },
    /// Up to `len` bytes from `offset` (the poller cuts the backend's
    /// requests to its file block size); fewer at the end of the file.
    Read {
        path: Vec<u8>,
        offset: u64,
        len: u32,
    },
    /// The whole file; the PLC commits it with the last block.
    Write {
        path: Vec<u8>,
        data: Spool,
    },
    WriteInfo {
        path: Vec<u8>,
        info: FileInfo,
    },
}

impl FileJob {
    pub fn path(&self) -> &[u8] {
        match self {
            FileJob::Info { path }
            | FileJob::List { path }
            | FileJob::Read { path, .. }
            | FileJob::Write { path, .. }
            | FileJob::WriteInfo { path, .. } => path,
        }
    }
}

#[derive(Debug)]
pub enum FileOutput {
    Info(FileInfo),
    List(Vec<DirEntry>),
    Data(Vec<u8>),
    Done,
}

pub type FileReply = Result<Answer<FileOutput>, super::LinkError>;

/// An upload's bytes on their way to the PLC, in an unnamed temporary file:
/// many clients uploading at once hold disk, not memory, and a crash leaves
/// nothing behind (the file has no name).
#[derive(Debug)]
pub struct Spool {
    file: std::fs::File,
    len: u64,
}

impl Spool {
    pub fn new() -> std::io::Result<Spool> {
        Ok(Spool {
            file: tempfile::tempfile()?,
            len: 0,
        })
    }

    pub fn len(&self) -> u64 {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn append(&mut self, data: &[u8]) -> std::io::Result<()> {
        use std::io::Write;
        self.file.write_all(data)?;
        self.len += data.len() as u64;
        Ok(())
    }

    /// The `len` bytes at `offset` (within what was appended).
    pub fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
        use std::os::unix::fs::FileExt;
        let mut buf = vec![0; len];
        self.file.read_exact_at(&mut buf, offset)?;
        Ok(buf)
    }
}

/// File transfer settings (FFILE_MAXRECS, FFILE_TIMEOUT, SYNC_VAR_ENABLED).
#[derive(Debug, Clone, Copy)]
pub struct FileSettings {
    pub cache_recs: usize,
    pub cache_timeout: Duration,
    /// Whether polling goes on while a file transfer is in progress.
    pub sync_var_enabled: bool,
}

impl Default for FileSettings {
    fn default() -> Self {
        FileSettings {
            cache_recs: 0,
            cache_timeout: Duration::ZERO,
            sync_var_enabled: true,
        }
    }
}

/// How long after its last file request a transfer counts as in progress
/// (for SYNC_VAR_ENABLED = No): a client reading a file asks for the next
/// block well within this.
const TRANSFER_IDLE: Duration = Duration::from_millis(500);

/// The link's file side: settings, cache, and whether a transfer is on.
pub struct Files {
    settings: FileSettings,
    cache: FileCache,
    /// A file transfer counts as in progress until then.
    transfer_until: Instant,
    /// COMM_LOOP_DELAY: how often a long upload polls.
    loop_delay: Duration,
}

impl Files {
    pub fn new(settings: FileSettings, loop_delay: Duration) -> Files {
        Files {
            cache: FileCache::new(settings.cache_recs, settings.cache_timeout),
            settings,
            transfer_until: Instant::now(),
            loop_delay,
        }
    }

    /// SYNC_VAR_ENABLED = No and a transfer is in progress: no polling.
    pub fn polling_paused(&self) -> bool {
        !self.settings.sync_var_enabled && Instant::now() < self.transfer_until
    }

    /// Runs one file job. A long upload polls between its blocks (unless
    /// SYNC_VAR_ENABLED = No), so it does not stop the values.
    pub async fn run(
        &mut self,
        job: FileJob,
        backend: &mut dyn PlcBackend,
        cycle: &mut Cycle,
        publisher: &mut Publisher,
    ) -> Result<Answer<FileOutput>, PlcError> {
        self.transfer_until = Instant::now() + TRANSFER_IDLE;
        let result = self.run_job(job, backend, cycle, publisher).await;
        self.transfer_until = Instant::now() + TRANSFER_IDLE;
        result
    }

    async fn run_job(
        &mut self,
        job: FileJob,
        backend: &mut dyn PlcBackend,
        cycle: &mut Cycle,
        publisher: &mut Publisher,
    ) -> Result<Answer<FileOutput>, PlcError> {
        let block = backend.max_file_block().max(1);
        Ok(match job {
            FileJob::Info { path } => backend.file_info(&path).await?.map(FileOutput::Info),
            FileJob::List { path } => backend.list_dir(&path).await?.map(FileOutput::List),
            FileJob::Read { path, offset, len } => {
                if let Some(data) = self.cache.get(&path, offset, len) {
                    return Ok(Ok(FileOutput::Data(data)));
                }
                let data = match read_file(backend, &path, offset, len).await? {
                    Ok(data) => data,
                    Err(e) => return Ok(Err(e)),
                };
                self.cache.note_read(&path, offset, len, &data);
                Ok(FileOutput::Data(data))
            }
            FileJob::Write { path, data } => {
                self.cache.invalidate(&path);
                let block = u64::from(block);
                let pieces = data.len().div_ceil(block).max(1);
                let mut last_poll = Instant::now();
                for index in 0..pieces {
                    let start = index * block;
                    let end = (start + block).min(data.len());
                    let last = index + 1 == pieces;
                    let piece = data
                        .read(start, (end - start) as usize)
                        .map_err(|e| PlcError::Protocol(format!("upload spool: {e}")))?;
                    if let Err(e) = backend.write_file(&path, start, &piece, last).await? {
                        return Ok(Err(e));
                    }
                    self.transfer_until = Instant::now() + TRANSFER_IDLE;
                    if self.settings.sync_var_enabled && last_poll.elapsed() >= self.loop_delay {
                        // What the poll finds (HALT -> RUN, a new program)
                        // the link handles after the upload.
                        cycle.poll(backend, publisher).await?;
                        last_poll = Instant::now();
                    }
                }
                Ok(FileOutput::Done)
            }
            FileJob::WriteInfo { path, info } => {
                self.cache.invalidate(&path);
                backend
                    .write_file_info(&path, &info)
                    .await?
                    .map(|()| FileOutput::Done)
            }
        })
    }
}

/// `len` bytes of the PLC's file `path` from `offset`, asked for in the
/// backend's blocks; fewer where the file ends first (a short block). The
/// one place a file is read, for clients' reads and the server's own.
pub async fn read_file(
    backend: &mut dyn PlcBackend,
    path: &[u8],
    offset: u64,
    len: u32,
) -> Result<Answer<Vec<u8>>, PlcError> {
    let block = backend.max_file_block().max(1);
    let mut data = Vec::with_capacity(len as usize);
    while data.len() < len as usize {
        let want = (len - data.len() as u32).min(block);
        let at = offset + data.len() as u64;
        match backend.read_file(path, at, want).await? {
            Ok(piece) => {
                let short = piece.len() < want as usize;
                data.extend_from_slice(&piece);
                if short {
                    break;
                }
            }
            Err(e) => return Ok(Err(e)),
        }
    }
    Ok(Ok(data))
}

struct Entry {
    path: Vec<u8>,
    stored: Instant,
    data: Arc<Vec<u8>>,
}

/// Recently read PLC files.
pub struct FileCache {
    max_recs: usize,
    ttl: Duration,
    entries: VecDeque<Entry>,
    bytes: usize,
    /// A read from offset 0 in progress: path and the bytes so far.
    filling: Option<(Vec<u8>, Vec<u8>)>,
}

impl FileCache {
    pub fn new(max_recs: usize, ttl: Duration) -> FileCache {
        FileCache {
            max_recs,
            ttl,
            entries: VecDeque::new(),
            bytes: 0,
            filling: None,
        }
    }

    fn enabled(&self) -> bool {
        self.max_recs > 0 && !self.ttl.is_zero()
    }

    /// `len` bytes from `offset` of a cached file (fewer at its end).
    pub fn get(&mut self, path: &[u8], offset: u64, len: u32) -> Option<Vec<u8>> {
        self.expire();
        let entry = self.entries.iter().find(|e| e.path == path)?;
        let start = usize::try_from(offset).ok()?.min(entry.data.len());
        let end = start.saturating_add(len as usize).min(entry.data.len());
        Some(entry.data[start..end].to_vec())
    }

    /// Notes a block read from the PLC; a file read whole from its start is
    /// stored when its end (a short block) arrives.
    pub fn note_read(&mut self, path: &[u8], offset: u64, len: u32, data: &[u8]) {
        if !self.enabled() {
            return;
        }
        if offset == 0 {
            self.filling = Some((path.to_vec(), Vec::new()));
        }
        let Some((fill_path, buf)) = self.filling.as_mut() else {
            return;
        };
        if fill_path != path || buf.len() as u64 != offset {
            self.filling = None;
            return;
        }
        buf.extend_from_slice(data);
        if buf.len() > CACHE_MAX_FILE {
            self.filling = None;
            return;
        }
        if data.len() < len as usize {
            let (path, data) = self.filling.take().expect("checked above");
            self.insert(path, data);
        }
    }

    fn insert(&mut self, path: Vec<u8>, data: Vec<u8>) {
        self.invalidate(&path);
        self.bytes += data.len();
        self.entries.push_back(Entry {
            path,
            stored: Instant::now(),
            data: Arc::new(data),
        });
        while self.entries.len() > self.max_recs || self.bytes > CACHE_MAX_BYTES {
            match self.entries.pop_front() {
                Some(old) => self.bytes -= old.data.len(),
                None => break,
            }
        }
    }

    pub fn invalidate(&mut self, path: &[u8]) {
        if self.filling.as_ref().is_some_and(|(p, _)| p == path) {
            self.filling = None;
        }
        let bytes = &mut self.bytes;
        self.entries.retain(|e| {
            let keep = e.path != path;
            if !keep {
                *bytes -= e.data.len();
            }
            keep
        });
    }

    fn expire(&mut self) {
        while let Some(front) = self.entries.front() {
            if front.stored.elapsed() < self.ttl {
                break;
            }
            if let Some(old) = self.entries.pop_front() {
                self.bytes -= old.data.len();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cache_keeps_whole_files_within_bounds() {
        let mut cache = FileCache::new(2, Duration::from_secs(60));
        cache.note_read(b"a", 0, 4, b"abcd");
        assert!(cache.get(b"a", 0, 4).is_none(), "not complete yet");
        cache.note_read(b"a", 4, 4, b"ef");
        assert_eq!(cache.get(b"a", 2, 10).unwrap(), b"cdef");
        assert_eq!(cache.get(b"a", 9, 10).unwrap(), b"");
        cache.note_read(b"b", 0, 4, b"b");
        cache.note_read(b"c", 0, 4, b"c");
        assert!(cache.get(b"a", 0, 1).is_none(), "oldest evicted");
        cache.invalidate(b"c");
        assert!(cache.get(b"c", 0, 1).is_none());
        // A read that skips ahead is not stored.
        cache.note_read(b"d", 0, 2, b"xy");
        cache.note_read(b"d", 4, 2, b"z");
        assert!(cache.get(b"d", 0, 1).is_none());
        let mut off = FileCache::new(0, Duration::from_secs(60));
        off.note_read(b"a", 0, 4, b"ab");
        assert!(off.get(b"a", 0, 4).is_none());
    }
}
