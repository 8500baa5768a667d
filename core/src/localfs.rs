//! Files on the server's machine (names beginning with `.` in GETFILE,
//! GETFILEINFO, WRITEFILE and WRITEFILEINFO), confined to the section's root
//! folder (FILES_ROOT, or the configuration's folder).
//!
//! A name is split on `/` and `\`; `..`, drive letters (`:`) and NUL are
//! refused outright, `.` and empty parts are skipped (so `./a`, `.//a` and
//! `a` are the same file). What exists of the path is then resolved with
//! symbolic links followed and must still lie inside the root: a link that
//! stays inside is fine, one that leads out is refused. Uploads are written
//! to a hidden temporary name in the target's folder and renamed into place.
//!
//! The server's own files are out of clients' reach ([`Access`]): nothing
//! under a hidden name (a part beginning with `.`) is read or written, the
//! root folder itself is never written, and the files the server registers
//! as its own ([`protect`]: the configuration, the log, state folders, the
//! public files in use) are never written or have their information
//! changed; those registered as secret (the configuration, key and
//! password files) are not read either.

use std::fs::{self, File};
use std::io;
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{OnceLock, RwLock};
use std::time::{Duration, UNIX_EPOCH};

use crate::driver::{DirEntry, FileInfo, FILE_ATTRIBUTE_DIRECTORY, FILE_ATTRIBUTE_READONLY};
use plccoms_plc::files::host::info_of;
use plccoms_plc::time;
use plccoms_protocol::cp1250;

/// Name prefix of upload staging files; hidden from listings and refused as
/// a path part.
pub const STAGING_PREFIX: &str = ".plccoms-upload-";
/// Most entries listed for one directory.
pub const MAX_ENTRIES: usize = 65_535;

#[derive(Debug, thiserror::Error)]
pub enum LocalError {
    /// The name leads outside the root (traversal, absolute, or a link).
    #[error("outside the root folder")]
    Outside,
    /// One of the server's own files, a hidden name or the root itself.
    #[error("one of the server's own files")]
    Protected,
    #[error(transparent)]
    Io(#[from] io::Error),
}

/// What a client wants to do with a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// GETFILE, GETFILEINFO.
    Read,
    /// WRITEFILE, WRITEFILEINFO.
    Write,
}

/// A file or folder of the server's own.
#[derive(Debug, Clone)]
struct Own {
    path: PathBuf,
    /// Not even read by clients (it holds passwords or keys).
    secret: bool,
}

fn own_files() -> &'static RwLock<Vec<Own>> {
    static OWN: OnceLock<RwLock<Vec<Own>>> = OnceLock::new();
    OWN.get_or_init(RwLock::default)
}

/// Registers `path` (a file or a folder, existing or not yet) as the
/// server's own: clients never write it or anything under it; with `secret`
/// they do not read it either. For the whole process: every section's
/// clients are kept away from it.
pub fn protect(path: &Path, secret: bool) {
    let path = absolute(path);
    let mut own = own_files().write().unwrap_or_else(|p| p.into_inner());
    if let Some(known) = own.iter_mut().find(|o| o.path == path) {
        known.secret |= secret;
    } else {
        own.push(Own { path, secret });
    }
}

/// `path` made absolute and, as far as it exists, with links resolved.
fn absolute(path: &Path) -> PathBuf {
    if let Ok(real) = fs::canonicalize(path) {
        return real;
    }
    let path = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    match (path.parent(), path.file_name()) {
        (Some(parent), Some(name)) => absolute(parent).join(name),
        _ => path,
    }
}

/// Whether `real` (resolved) is, or lies under, one of the server's own
/// files that `access` may not touch (`extra`: more own files, such as a
/// section's public files in use).
pub fn is_own(real: &Path, access: Access, extra: &[PathBuf]) -> bool {
    let own = own_files().read().unwrap_or_else(|p| p.into_inner());
    let hit = |path: &Path| real == path || real.starts_with(path);
    match access {
        Access::Write => {
            own.iter().any(|o| hit(&o.path)) || extra.iter().any(|p| hit(&absolute(p)))
        }
        Access::Read => own.iter().any(|o| o.secret && hit(&o.path)),
    }
}

/// The host path of a local file name for `access`, checked to lie inside
/// `root` and to be none of the server's own files (`extra`: more of them).
/// The target itself may be missing (for uploads); its folder must exist.
pub fn resolve_for(
    root: &Path,
    name: &[u8],
    access: Access,
    extra: &[PathBuf],
) -> Result<PathBuf, LocalError> {
    let real = resolve(root, name)?;
    let root = fs::canonicalize(root)?;
    let relative = real.strip_prefix(&root).map_err(|_| LocalError::Outside)?;
    let hidden = relative
        .components()
        .any(|c| c.as_os_str().to_string_lossy().starts_with('.'));
    let root_itself = relative.as_os_str().is_empty();
    if hidden || (access == Access::Write && root_itself) || is_own(&real, access, extra) {
        return Err(LocalError::Protected);
    }
    Ok(real)
}

/// The host path of a local file name, checked to lie inside `root`. The
/// target itself may be missing (for uploads); its folder must exist.
pub fn resolve(root: &Path, name: &[u8]) -> Result<PathBuf, LocalError> {
    let root = fs::canonicalize(root)?;
    let text = cp1250::decode(name);
    let mut path = root.clone();
    for part in text.split(['/', '\\']) {
        if part.is_empty() || part == "." {
            continue;
        }
        if part == ".." || part.contains(['\0', ':']) || part.starts_with(STAGING_PREFIX) {
            return Err(LocalError::Outside);
        }
        let mut components = Path::new(part).components();
        if !matches!(
            (components.next(), components.next()),
            (Some(Component::Normal(_)), None)
        ) {
            return Err(LocalError::Outside);
        }
        path.push(part);
    }
    // Follow links in what exists: the real place must be under the root.
    let real = match fs::canonicalize(&path) {
        Ok(real) => real,
        Err(_) => {
            if fs::symlink_metadata(&path).is_ok() {
                // A dangling link: where it points cannot be checked.
                return Err(LocalError::Outside);
            }
            let parent = path.parent().ok_or(LocalError::Outside)?;
            let real_parent = fs::canonicalize(parent)?;
            real_parent.join(path.file_name().ok_or(LocalError::Outside)?)
        }
    };
    if !real.starts_with(&root) {
        return Err(LocalError::Outside);
    }
    Ok(real)
}

pub fn info(path: &Path) -> io::Result<FileInfo> {
    Ok(info_of(path, &fs::metadata(path)?))
}

/// A directory's entries by name; names not representable in cp1250 and
/// staging files are left out.
pub fn list(path: &Path) -> io::Result<Vec<DirEntry>> {
    plccoms_plc::files::host::list_dir(path, STAGING_PREFIX, MAX_ENTRIES)
}

/// A GETFILE directory listing: one entry a line, directories with a
/// trailing `/`.
pub fn format_listing(entries: &[DirEntry], eol: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    for entry in entries {
        out.extend_from_slice(&entry.name);
        if entry.info.attributes & FILE_ATTRIBUTE_DIRECTORY != 0 {
            out.push(b'/');
        }
        out.extend_from_slice(eol);
    }
    out
}

/// An upload in progress: a staging file next to the target, removed unless
/// committed.
pub struct Staging {
    temp: PathBuf,
    target: PathBuf,
    file: Option<File>,
}

impl Staging {
    pub fn create(target: PathBuf) -> io::Result<Staging> {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let parent = target
            .parent()
            .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "no folder"))?;
        if fs::metadata(&target).is_ok_and(|m| m.is_dir()) {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "target is a directory",
            ));
        }
        let temp = parent.join(format!(
            "{STAGING_PREFIX}{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        let file = File::options().write(true).create_new(true).open(&temp)?;
        Ok(Staging {
            temp,
            target,
            file: Some(file),
        })
    }

    pub fn write(&mut self, data: &[u8]) -> io::Result<()> {
        use std::io::Write;
        match self.file.as_mut() {
            Some(file) => file.write_all(data),
            None => Err(io::Error::other("already committed")),
        }
    }

    /// Moves the finished file into place.
    pub fn commit(mut self) -> io::Result<()> {
        if let Some(file) = self.file.take() {
            file.sync_all()?;
        }
        fs::rename(&self.temp, &self.target)
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        // Not committed (or the rename failed): the data is discarded.
        let _ = fs::remove_file(&self.temp);
    }
}

/// WRITEFILEINFO on a local file: the read-only attribute and the
/// modification time (0 leaves it); the creation time cannot be set.
pub fn write_info(path: &Path, info: &FileInfo) -> io::Result<()> {
    let meta = fs::metadata(path)?;
    if info.modified != 0 {
        let secs = time::unix_from_ttida(info.modified)
            .filter(|&s| s >= 0)
            .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "bad time"))?;
        File::options()
            .write(!meta.is_dir())
            .read(meta.is_dir())
            .open(path)
            .and_then(|f| f.set_modified(UNIX_EPOCH + Duration::from_secs(secs as u64)))?;
    }
    let mut perms = meta.permissions();
    let readonly = info.attributes & FILE_ATTRIBUTE_READONLY != 0;
    if perms.readonly() != readonly {
        #[allow(clippy::permissions_set_readonly_false)]
        perms.set_readonly(readonly);
        fs::set_permissions(path, perms)?;
    }
    Ok(())
}

/// Parses `<size> <attr> <created> <modified>` (WRITEFILEINFO data).
pub fn parse_info(text: &[u8]) -> Option<FileInfo> {
    let text = std::str::from_utf8(text).ok()?;
    let mut fields = text.split_ascii_whitespace();
    let info = FileInfo {
        size: fields.next()?.parse().ok()?,
        attributes: fields.next()?.parse().ok()?,
        created: fields.next()?.parse().ok()?,
        modified: fields.next()?.parse().ok()?,
    };
    fields.next().is_none().then_some(info)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_stay_inside_the_root() {
        let dir = tempfile::tempdir().unwrap();
        let root = fs::canonicalize(dir.path()).unwrap();
        fs::create_dir(root.join("sub")).unwrap();
        assert_eq!(resolve(&root, b"./a.txt").unwrap(), root.join("a.txt"));
        assert_eq!(resolve(&root, b".\\sub\\b").unwrap(), root.join("sub/b"));
        assert_eq!(resolve(&root, b".//etc/x").ok(), None); // folder missing
        for bad in [&b"../x"[..], b"./sub/../../x", b"./C:/x", b"./a\0b"] {
            assert!(matches!(resolve(&root, bad), Err(LocalError::Outside)));
        }
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink("/etc", root.join("out")).unwrap();
            std::os::unix::fs::symlink(root.join("sub"), root.join("in")).unwrap();
            assert!(matches!(
                resolve(&root, b"./out/passwd"),
                Err(LocalError::Outside)
            ));
            assert_eq!(resolve(&root, b"./in/c").unwrap(), root.join("sub/c"));
        }
    }

    #[test]
    fn info_text_parses() {
        let info = parse_info(b"44 0 41854524393844 41854674928753").unwrap();
        assert_eq!(info.size, 44);
        assert_eq!(info.modified, 41_854_674_928_753);
        assert!(parse_info(b"1 2 3").is_none());
        assert!(parse_info(b"1 2 3 4 5").is_none());
    }
}
