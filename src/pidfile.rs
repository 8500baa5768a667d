//! `--pid-file`: the server's process id, for init scripts and monitors.
//! The file stays locked (flock) for the server's life, so a second server
//! given the same file is refused with the first one's pid, while a file a
//! crashed server left behind (nobody holds its lock) is simply taken over:
//! a stale pid file never blocks a start, and a recycled pid cannot fool it.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, Write};
use std::os::fd::AsRawFd;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

/// The pid file, held for as long as the value lives; removed on drop.
pub struct PidFile {
    path: PathBuf,
    _file: File,
}

impl PidFile {
    /// Writes this process's pid to `path`, or says why not (another
    /// server holds it, the folder is not writable).
    pub fn create(path: &Path) -> Result<PidFile, String> {
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(0o644)
            .open(path)
            .map_err(|e| format!("pid file {}: {e}", path.display()))?;
        // SAFETY: flock on a descriptor this function owns.
        if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            return Err(format!(
                "pid file {}: another plccoms (pid {}) is running with it; stop it or give -d another --pid-file",
                path.display(),
                holder.trim()
            ));
        }
        let pid = std::process::id();
        file.set_len(0)
            .and_then(|()| file.rewind())
            .and_then(|()| writeln!(file, "{pid}"))
            .and_then(|()| file.sync_all())
            .map_err(|e| format!("pid file {}: {e}", path.display()))?;
        Ok(PidFile {
            path: path.to_path_buf(),
            _file: file,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for PidFile {
    fn drop(&mut self) {
        // Still locked by us: nobody else can have written it meanwhile.
        let _ = std::fs::remove_file(&self.path);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_held_file_is_refused_and_a_stale_one_taken_over() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plccoms.pid");
        std::fs::write(&path, "999999\n").unwrap();
        let held = PidFile::create(&path).expect("a stale file is taken over");
        let pid = std::process::id().to_string();
        assert_eq!(std::fs::read_to_string(&path).unwrap().trim(), pid);
        let refused = PidFile::create(&path).err().expect("held");
        assert!(
            refused.contains(&format!("another plccoms (pid {pid}) is running with it")),
            "{refused}"
        );
        drop(held);
        assert!(!path.exists(), "removed at the end");
    }
}
