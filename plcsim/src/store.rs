//! The PLC's file system, backed by a host directory.
//!
//! Paths arrive as cp1250 bytes with `/` or `\` separators and are confined
//! to the root: `..`, drive letters and NUL are refused, and so is any path
//! that passes through a symbolic link (so no link can lead out). Writes are
//! staged in a hidden temporary file next to the target and renamed into
//! place only with the block flagged last, so readers never see half a file.
//!
//! The running program's public file is served too, read-only, at the root
//! under its own name ([`FileStore::set_program_file`]): a PLC keeps it with
//! the program, so a server told `PUBFILE = //VARLIST.PUB` finds it there.
//!
//! Every refusal is the PLC error byte 0x0C (wrong parameters): which byte a
//! real PLC answers for a missing file is unverified.

use std::collections::HashMap;
use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::path::{Component, Path, PathBuf};
use std::time::{Duration, Instant, UNIX_EPOCH};

use plccoms_plc::files::host::{info_of, list_dir};
use plccoms_plc::files::{DirEntry, FileInfo, FILE_ATTRIBUTE_ARCHIVE, FILE_ATTRIBUTE_READONLY};
use plccoms_plc::{time, Exception};
use plccoms_protocol::cp1250;

/// Name prefix of staging files; hidden from listings and unreachable by path.
pub const STAGING_PREFIX: &str = ".plcsim-staging-";
/// Files being written at once; the oldest is dropped beyond this.
pub const MAX_STAGED: usize = 16;
/// Largest file accepted.
pub const MAX_FILE_SIZE: u64 = 64 * 1024 * 1024;
/// Largest block read at once.
pub const MAX_BLOCK: u32 = 64 * 1024;
/// Most entries listed for one directory.
pub const MAX_ENTRIES: usize = 65_535;

#[derive(Debug, Clone)]
struct Staged {
    temp: PathBuf,
    len: u64,
    started: Instant,
}

#[derive(Debug, Clone)]
pub struct FileStore {
    root: PathBuf,
    staged: HashMap<PathBuf, Staged>,
    /// The last file committed and its length, so a repeated last block (a
    /// retry whose answer was lost) is acknowledged again.
    committed: Option<(PathBuf, u64)>,
    program_file: Option<ProgramFile>,
}

/// The program's public file as the PLC holds it: the bytes it was loaded
/// from, whatever happens to the host file later.
#[derive(Debug, Clone)]
struct ProgramFile {
    name: String,
    bytes: Vec<u8>,
    info: FileInfo,
}

const BAD: Exception = Exception::BadParameters;

fn bad<E>(_: E) -> Exception {
    BAD
}

impl FileStore {
    pub fn open(root: impl AsRef<Path>) -> io::Result<FileStore> {
        let root = fs::canonicalize(root)?;
        if !root.is_dir() {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("{} is not a directory", root.display()),
            ));
        }
        Ok(FileStore {
            root,
            staged: HashMap::new(),
            committed: None,
            program_file: None,
        })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Serves `bytes` read-only as `/<name>` (matched without regard to
    /// ASCII case: clients and ini files spell names as they like), hiding a
    /// host file of that name. `name` must be one file name that cp1250 can hold.
    pub fn set_program_file(&mut self, name: &str, bytes: Vec<u8>) -> Result<(), String> {
        if matches!(name, "" | "." | "..")
            || name.contains(['/', '\\', ':', '\0'])
            || name.starts_with(STAGING_PREFIX)
        {
            return Err(format!("'{name}' is not a plain file name"));
        }
        if cp1250::try_encode(name).is_none() {
            return Err(format!("'{name}' cannot be written in cp1250"));
        }
        let now = time::ttida_from_system(std::time::SystemTime::now());
        let info = FileInfo {
            size: bytes.len() as u64,
            attributes: FILE_ATTRIBUTE_ARCHIVE | FILE_ATTRIBUTE_READONLY,
            created: now,
            modified: now,
        };
        self.program_file = Some(ProgramFile {
            name: name.to_string(),
            bytes,
            info,
        });
        Ok(())
    }

    /// The name the program's public file is served under, if any.
    pub fn program_file_name(&self) -> Option<&str> {
        self.program_file.as_ref().map(|f| f.name.as_str())
    }

    /// The program's public file when `path` names it.
    fn program_file(&self, path: &[u8]) -> Option<&ProgramFile> {
        let file = self.program_file.as_ref()?;
        let text = cp1250::decode(path);
        let mut parts = text
            .split(['/', '\\'])
            .filter(|part| !part.is_empty() && *part != ".");
        match (parts.next(), parts.next()) {
            (Some(name), None) if name.eq_ignore_ascii_case(&file.name) => Some(file),
            _ => None,
        }
    }

    /// The host path of a PLC path, confined to the root.
    pub fn resolve(&self, path: &[u8]) -> Result<PathBuf, Exception> {
        let text = cp1250::decode(path);
        let mut out = self.root.clone();
        let mut checking = true;
        for part in text.split(['/', '\\']) {
            if part.is_empty() || part == "." {
                continue;
            }
            if part == ".."
                || part.contains(['\0', ':', '\u{FFFD}'])
                || part.starts_with(STAGING_PREFIX)
            {
                return Err(BAD);
            }
            // One normal component, nothing the OS would read otherwise.
            let mut components = Path::new(part).components();
            if !matches!(
                (components.next(), components.next()),
                (Some(Component::Normal(_)), None)
            ) {
                return Err(BAD);
            }
            out.push(part);
            if checking {
                match fs::symlink_metadata(&out) {
                    Ok(meta) if meta.file_type().is_symlink() => return Err(BAD),
                    Ok(_) => {}
                    Err(_) => checking = false,
                }
            }
        }
        Ok(out)
    }

    pub fn info(&self, path: &[u8]) -> Result<FileInfo, Exception> {
        if let Some(file) = self.program_file(path) {
            return Ok(file.info);
        }
        let host = self.resolve(path)?;
        let meta = fs::symlink_metadata(&host).map_err(bad)?;
        Ok(info_of(&host, &meta))
    }

    pub fn read(&self, path: &[u8], offset: u64, len: u32) -> Result<Vec<u8>, Exception> {
        if len > MAX_BLOCK {
            return Err(BAD);
        }
        if let Some(file) = self.program_file(path) {
            let start =
                usize::try_from(offset).map_or(file.bytes.len(), |o| o.min(file.bytes.len()));
            let end = start.saturating_add(len as usize).min(file.bytes.len());
            return Ok(file.bytes[start..end].to_vec());
        }
        let host = self.resolve(path)?;
        let mut file = File::open(&host).map_err(bad)?;
        if !file.metadata().map_err(bad)?.is_file() {
            return Err(BAD);
        }
        file.seek(SeekFrom::Start(offset)).map_err(bad)?;
        let mut data = Vec::with_capacity(len as usize);
        file.take(u64::from(len))
            .read_to_end(&mut data)
            .map_err(bad)?;
        Ok(data)
    }

    pub fn write(
        &mut self,
        path: &[u8],
        offset: u64,
        data: &[u8],
        last: bool,
    ) -> Result<(), Exception> {
        if self.program_file(path).is_some() {
            return Err(BAD);
        }
        let host = self.resolve(path)?;
        let end = offset.checked_add(data.len() as u64).ok_or(BAD)?;
        if end > MAX_FILE_SIZE {
            self.discard(&host);
            return Err(BAD);
        }
        if let Ok(meta) = fs::symlink_metadata(&host) {
            if !meta.is_file() || meta.permissions().readonly() {
                return Err(BAD);
            }
        }
        let parent = host.parent().ok_or(BAD)?;
        let name = host.file_name().ok_or(BAD)?;
        if host == self.root || !parent.is_dir() {
            return Err(BAD);
        }
        if offset == 0 {
            self.discard(&host);
            if self.staged.len() >= MAX_STAGED {
                let oldest = self
                    .staged
                    .iter()
                    .min_by_key(|(_, s)| s.started)
                    .map(|(p, _)| p.clone());
                if let Some(oldest) = oldest {
                    self.discard(&oldest);
                }
            }
            let mut temp_name = std::ffi::OsString::from(STAGING_PREFIX);
            temp_name.push(name);
            let temp = parent.join(temp_name);
            File::create(&temp).map_err(bad)?;
            self.staged.insert(
                host.clone(),
                Staged {
                    temp,
                    len: 0,
                    started: Instant::now(),
                },
            );
            if self.committed.as_ref().is_some_and(|(p, _)| *p == host) {
                self.committed = None;
            }
        }
        let Some(staged) = self.staged.get_mut(&host) else {
            // A repeated last block of a file already committed.
            return match &self.committed {
                Some((p, len)) if *p == host && *len == end && last => Ok(()),
                _ => Err(BAD),
            };
        };
        if offset == staged.len {
            let mut file = OpenOptions::new()
                .append(true)
                .open(&staged.temp)
                .map_err(bad)?;
            file.write_all(data).map_err(bad)?;
            staged.len = end;
        } else if end != staged.len {
            // Neither the next block nor a repeat of the previous one.
            return Err(BAD);
        }
        if last {
            let staged = self.staged.remove(&host).ok_or(BAD)?;
            if let Err(e) = fs::rename(&staged.temp, &host) {
                let _ = fs::remove_file(&staged.temp);
                return Err(bad(e));
            }
            self.committed = Some((host, staged.len));
        }
        Ok(())
    }

    fn discard(&mut self, host: &Path) {
        if let Some(staged) = self.staged.remove(host) {
            let _ = fs::remove_file(staged.temp);
        }
    }

    /// Sets the read-only attribute and the modification time (0 leaves it);
    /// creation time cannot be set on the host and is ignored.
    pub fn write_info(&mut self, path: &[u8], info: &FileInfo) -> Result<(), Exception> {
        if self.program_file(path).is_some() {
            return Err(BAD);
        }
        let host = self.resolve(path)?;
        if host == self.root {
            return Err(BAD);
        }
        let meta = fs::symlink_metadata(&host).map_err(bad)?;
        if info.modified != 0 {
            let secs = time::unix_from_ttida(info.modified).ok_or(BAD)?;
            let when = if secs >= 0 {
                UNIX_EPOCH + Duration::from_secs(secs as u64)
            } else {
                return Err(BAD);
            };
            File::open(&host)
                .and_then(|f| f.set_modified(when))
                .map_err(bad)?;
        }
        let mut perms = meta.permissions();
        let readonly = info.attributes & FILE_ATTRIBUTE_READONLY != 0;
        if perms.readonly() != readonly {
            #[allow(clippy::permissions_set_readonly_false)]
            perms.set_readonly(readonly);
            fs::set_permissions(&host, perms).map_err(bad)?;
        }
        Ok(())
    }

    /// Entries of a directory, by name; names not representable in cp1250
    /// are left out.
    pub fn list(&self, path: &[u8]) -> Result<Vec<DirEntry>, Exception> {
        let host = self.resolve(path)?;
        let mut entries = list_dir(&host, STAGING_PREFIX, MAX_ENTRIES).map_err(bad)?;
        if let Some(file) = self.program_file.as_ref().filter(|_| host == self.root) {
            let name = cp1250::try_encode(&file.name).ok_or(BAD)?;
            entries.retain(|e| !e.name.eq_ignore_ascii_case(&name));
            entries.push(DirEntry {
                name,
                info: file.info,
            });
            entries.sort_by(|a, b| a.name.cmp(&b.name));
        }
        Ok(entries)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_plc::files::FILE_ATTRIBUTE_DIRECTORY;

    #[test]
    fn paths_stay_inside_the_root() {
        let dir = tempfile::tempdir().unwrap();
        let store = FileStore::open(dir.path()).unwrap();
        let root = store.root().to_path_buf();
        assert_eq!(store.resolve(b"/a/b.txt").unwrap(), root.join("a/b.txt"));
        assert_eq!(store.resolve(b"\\a\\b").unwrap(), root.join("a/b"));
        assert_eq!(store.resolve(b"").unwrap(), root);
        assert_eq!(store.resolve(b"../x"), Err(BAD));
        assert_eq!(store.resolve(b"a/../../x"), Err(BAD));
        assert_eq!(store.resolve(b"C:/x"), Err(BAD));
        assert_eq!(store.resolve(b"a\0b"), Err(BAD));
        assert_eq!(store.resolve(b".plcsim-staging-x"), Err(BAD));
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink("/etc", dir.path().join("out")).unwrap();
            assert_eq!(store.resolve(b"out/passwd"), Err(BAD));
        }
    }

    #[test]
    fn staged_write_appears_on_last_block() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = FileStore::open(dir.path()).unwrap();
        store.write(b"f.txt", 0, b"hello ", false).unwrap();
        assert!(store.info(b"f.txt").is_err());
        assert_eq!(store.list(b"/").unwrap().len(), 0);
        // A repeated block is accepted; a gap is not.
        store.write(b"f.txt", 0, b"hello ", false).unwrap();
        assert_eq!(store.write(b"f.txt", 10, b"x", false), Err(BAD));
        store.write(b"f.txt", 6, b"world", true).unwrap();
        store.write(b"f.txt", 6, b"world", true).unwrap();
        assert_eq!(store.read(b"f.txt", 0, 100).unwrap(), b"hello world");
        assert_eq!(store.read(b"f.txt", 6, 3).unwrap(), b"wor");
        let info = store.info(b"f.txt").unwrap();
        assert_eq!(info.size, 11);
        assert_eq!(info.attributes & FILE_ATTRIBUTE_DIRECTORY, 0);
        fs::create_dir(dir.path().join("sub")).unwrap();
        let list = store.list(b"").unwrap();
        assert_eq!(list.len(), 2);
        assert_eq!(list[1].name, b"sub");
        assert_ne!(list[1].info.attributes & FILE_ATTRIBUTE_DIRECTORY, 0);
    }

    #[test]
    fn write_info_sets_time_and_readonly() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = FileStore::open(dir.path()).unwrap();
        store.write(b"f", 0, b"x", true).unwrap();
        let when = time::ttida_from_unix(1_710_510_330);
        store
            .write_info(
                b"f",
                &FileInfo {
                    size: 0,
                    attributes: FILE_ATTRIBUTE_READONLY,
                    created: 0,
                    modified: when,
                },
            )
            .unwrap();
        let info = store.info(b"f").unwrap();
        assert_eq!(info.modified, when);
        assert_ne!(info.attributes & FILE_ATTRIBUTE_READONLY, 0);
        assert_eq!(store.write(b"f", 0, b"y", true), Err(BAD));
        store
            .write_info(
                b"f",
                &FileInfo {
                    attributes: 0,
                    ..FileInfo::default()
                },
            )
            .unwrap();
        store.write(b"f", 0, b"y", true).unwrap();
    }

    #[test]
    fn the_program_file_is_served_read_only_at_the_root() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("VARLIST.PUB"), b"host copy").unwrap();
        fs::write(dir.path().join("other.txt"), b"x").unwrap();
        let mut store = FileStore::open(dir.path()).unwrap();
        store
            .set_program_file("VARLIST.PUB", b"program's".to_vec())
            .unwrap();
        for path in [&b"//VARLIST.PUB"[..], b"/varlist.pub", b"\\VarList.Pub"] {
            assert_eq!(store.read(path, 0, 100).unwrap(), b"program's", "{path:?}");
            let info = store.info(path).unwrap();
            assert_eq!(info.size, 9);
            assert_ne!(info.attributes & FILE_ATTRIBUTE_READONLY, 0);
            assert_eq!(store.write(path, 0, b"y", true), Err(BAD));
            assert_eq!(store.write_info(path, &FileInfo::default()), Err(BAD));
        }
        assert_eq!(store.read(b"VARLIST.PUB", 3, 100).unwrap(), b"gram's");
        assert_eq!(store.read(b"VARLIST.PUB", 100, 10).unwrap(), b"");
        // Elsewhere than the root, the name is an ordinary path.
        assert!(store.info(b"sub/VARLIST.PUB").is_err());
        let names: Vec<Vec<u8>> = store
            .list(b"/")
            .unwrap()
            .into_iter()
            .map(|e| e.name)
            .collect();
        assert_eq!(names, [b"VARLIST.PUB".to_vec(), b"other.txt".to_vec()]);
        assert_eq!(
            fs::read(dir.path().join("VARLIST.PUB")).unwrap(),
            b"host copy"
        );
        for bad in ["", "..", "a/b", "a\\b", "C:x", ".plcsim-staging-x"] {
            assert!(store.set_program_file(bad, Vec::new()).is_err(), "{bad:?}");
        }
    }
}
