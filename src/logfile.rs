//! The log file (`-l`, or `PLCComS.log` with `-d`): appended, never
//! truncated, and opened anew on SIGHUP, so that logrotate can move it away
//! and signal (`conf/plccoms.logrotate`): the lines after the signal go to a
//! new file at the old path, none is lost or split between the two.

use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::os::fd::{AsRawFd, RawFd};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use tracing::{error, info};

/// The log file; `Arc<LogFile>` is tracing-subscriber's writer (each line
/// is written whole under the lock, so a reopen falls between lines).
pub struct LogFile {
    path: PathBuf,
    file: Mutex<File>,
}

fn open(path: &Path) -> io::Result<File> {
    OpenOptions::new().create(true).append(true).open(path)
}

impl LogFile {
    pub fn open(path: &Path) -> io::Result<Arc<LogFile>> {
        Ok(Arc::new(LogFile {
            path: path.to_path_buf(),
            file: Mutex::new(open(path)?),
        }))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Opens the path again (creating the file if it was moved away) and
    /// writes there from now on. On failure the old file stays in use.
    pub fn reopen(&self) -> io::Result<()> {
        let file = open(&self.path)?;
        *self.lock() = file;
        // The line a crashing plugin leaves goes to the new file too.
        #[cfg(feature = "plugin")]
        plccoms_driver_plugin::crash::set_log_fd(self.as_raw_fd());
        Ok(())
    }

    fn lock(&self) -> MutexGuard<'_, File> {
        // A File stays usable after a panic elsewhere.
        self.file.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl AsRawFd for LogFile {
    /// The file written now (another after [`LogFile::reopen`]).
    fn as_raw_fd(&self) -> RawFd {
        self.lock().as_raw_fd()
    }
}

impl Write for &LogFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.lock().write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> io::Result<()> {
        self.lock().write_all(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.lock().flush()
    }
}

/// From now on SIGHUP reopens `log` (logging that it did) instead of ending
/// the process, and then yields on the returned receiver (the server
/// re-reads its configuration). Call inside the runtime, as early as
/// possible: until then SIGHUP ends the process.
pub fn reopen_on_hangup(
    log: Option<Arc<LogFile>>,
) -> io::Result<tokio::sync::mpsc::UnboundedReceiver<()>> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut hangups = signal(SignalKind::hangup())?;
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        while hangups.recv().await.is_some() {
            // The log first: what the reload says goes to the new file.
            if let Some(log) = &log {
                reopen(log);
            }
            let _ = tx.send(());
        }
    });
    Ok(rx)
}

fn reopen(log: &LogFile) {
    info!("SIGHUP: reopening the log file {}", log.path().display());
    match log.reopen() {
        Ok(()) => info!("SIGHUP: log file {} reopened", log.path().display()),
        Err(e) => error!(
            "SIGHUP: cannot reopen the log file {}: {e}; still writing to the old one",
            log.path().display()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reopen_follows_a_moved_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.log");
        std::fs::write(&path, "before\n").unwrap();
        let log = LogFile::open(&path).unwrap();
        (&*log).write_all(b"one\n").unwrap();
        let moved = dir.path().join("a.log.1");
        std::fs::rename(&path, &moved).unwrap();
        (&*log).write_all(b"two\n").unwrap();
        log.reopen().unwrap();
        (&*log).write_all(b"three\n").unwrap();
        assert_eq!(
            std::fs::read_to_string(&moved).unwrap(),
            "before\none\ntwo\n"
        );
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "three\n");
        // Its folder gone: the old file stays in use.
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).unwrap();
        let log = LogFile::open(&sub.join("b.log")).unwrap();
        std::fs::remove_dir_all(&sub).unwrap();
        assert!(log.reopen().is_err());
        (&*log).write_all(b"still\n").unwrap();
    }
}
