//! The quota of the local files root: what clients write there with
//! WRITEFILE, added to everything already in it (any subfolder, staging
//! files of uploads in progress included), stays under FILES_QUOTA, or by
//! default under the smaller of [`DEFAULT_QUOTA`] and a tenth of the free
//! space of the root's file system. A block over it fails its upload
//! (WRITEFILE's ERROR 42 at the zero block): a client cannot fill the disk
//! the historian and the log write to.
//!
//! Walking the root for every block would let a client of 1-byte blocks
//! make the server walk a tree at will: the root is measured at most every
//! [`MEASURE_EVERY`], and the bytes admitted since are added to that figure.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The default quota's fixed part.
pub const DEFAULT_QUOTA: u64 = 1 << 30;
/// How often the root is measured again (files deleted free room then).
pub const MEASURE_EVERY: Duration = Duration::from_secs(1);
/// Entries a measurement looks at, at most; a root with more is full.
const MAX_ENTRIES: usize = 1_000_000;

/// What a root holds, as last measured, and what was admitted since.
struct Usage {
    measured: Instant,
    /// Bytes in the root, and the quota then in force.
    bytes: u64,
    quota: u64,
    admitted_since: u64,
}

/// Why a write is refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OverQuota {
    pub used: u64,
    pub quota: u64,
}

impl std::fmt::Display for OverQuota {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the files root holds {} bytes, its quota is {} (FILES_QUOTA)",
            self.used, self.quota
        )
    }
}

/// The default quota for a file system with `free` bytes available.
pub fn default_quota(free: u64) -> u64 {
    DEFAULT_QUOTA.min(free / 10)
}

/// Admits `len` more bytes written under `root`, or says why not.
/// `configured` is FILES_QUOTA (`None`: the default).
pub fn admit(root: &Path, configured: Option<u64>, len: u64) -> Result<(), OverQuota> {
    static ROOTS: Mutex<Option<HashMap<PathBuf, Usage>>> = Mutex::new(None);
    let mut roots = ROOTS.lock().unwrap_or_else(|e| e.into_inner());
    let roots = roots.get_or_insert_with(HashMap::new);
    let now = Instant::now();
    let stale = roots
        .get(root)
        .is_none_or(|usage| now.duration_since(usage.measured) >= MEASURE_EVERY);
    if stale {
        let quota = configured.unwrap_or_else(|| default_quota(free_space(root)));
        roots.insert(
            root.to_path_buf(),
            Usage {
                measured: now,
                bytes: blocking(|| measure(root)),
                quota,
                admitted_since: 0,
            },
        );
    }
    let usage = roots.get_mut(root).expect("measured above");
    let used = usage.bytes.saturating_add(usage.admitted_since);
    if used.saturating_add(len) > usage.quota {
        return Err(OverQuota {
            used,
            quota: usage.quota,
        });
    }
    usage.admitted_since = usage.admitted_since.saturating_add(len);
    Ok(())
}

/// Runs `walk` where it may block: a measurement of a large root takes a
/// second (100,000 files: 0.14 s warm, 0.8 s cold), which on a runtime
/// worker would stall every session scheduled there; on the multi-threaded
/// runtime the server runs, those sessions move to another worker.
fn blocking<T>(walk: impl FnOnce() -> T) -> T {
    use tokio::runtime::{Handle, RuntimeFlavor};
    match Handle::try_current().map(|h| h.runtime_flavor()) {
        Ok(RuntimeFlavor::MultiThread) => tokio::task::block_in_place(walk),
        _ => walk(),
    }
}

/// Bytes of the clients' files under `root` (links not followed); the
/// server's own files and folders there (the history, the MQTT queue, the
/// configuration when the root is its folder) are not the clients' and do
/// not count. `u64::MAX` past [`MAX_ENTRIES`] entries.
fn measure(root: &Path) -> u64 {
    let mut total = 0u64;
    let mut entries = 0usize;
    let root = std::fs::canonicalize(root).unwrap_or_else(|_| root.to_path_buf());
    let mut folders = vec![root];
    while let Some(folder) = folders.pop() {
        let Ok(list) = std::fs::read_dir(&folder) else {
            continue;
        };
        for entry in list.flatten() {
            entries += 1;
            if entries > MAX_ENTRIES {
                return u64::MAX;
            }
            let Ok(meta) = entry.metadata() else {
                continue;
            };
            if crate::localfs::is_own(&entry.path(), crate::localfs::Access::Write, &[]) {
                continue;
            }
            if meta.is_dir() {
                folders.push(entry.path());
            } else if meta.is_file() {
                total = total.saturating_add(meta.len());
            }
        }
    }
    total
}

/// Bytes free to an unprivileged writer on the file system of `path` (0
/// when it cannot be asked).
fn free_space(path: &Path) -> u64 {
    use std::os::unix::ffi::OsStrExt;
    let Ok(c_path) = std::ffi::CString::new(path.as_os_str().as_bytes()) else {
        return 0;
    };
    // SAFETY: statvfs is plain integers, valid all zero.
    let mut stat: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: a NUL-terminated path and an out-pointer to a local.
    if unsafe { libc::statvfs(c_path.as_ptr(), &mut stat) } != 0 {
        return 0;
    }
    // Narrower than u64 on some targets.
    #[allow(clippy::useless_conversion)]
    u64::from(stat.f_bavail).saturating_mul(u64::from(stat.f_frsize))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_is_the_smaller_of_a_gigabyte_and_a_tenth_of_the_free_space() {
        assert_eq!(default_quota(100 << 30), 1 << 30);
        assert_eq!(default_quota(5 << 30), 512 << 20);
        assert_eq!(default_quota(0), 0);
        assert!(free_space(Path::new("/")) > 0);
    }

    #[test]
    fn what_is_there_and_what_was_admitted_count() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        std::fs::write(dir.path().join("sub/x"), [0u8; 600]).unwrap();
        assert_eq!(measure(dir.path()), 600);
        assert!(admit(dir.path(), Some(1000), 300).is_ok());
        // Not measured again yet: the 300 admitted count.
        assert_eq!(
            admit(dir.path(), Some(1000), 200),
            Err(OverQuota {
                used: 900,
                quota: 1000
            })
        );
        assert!(admit(dir.path(), Some(1000), 100).is_ok());
    }
}
