//! A host folder seen as a PLC's file system: the simulated PLC's store and
//! the server's local files (FILES_ROOT) show host files alike. The one
//! place in this crate that touches the host's file system, and only to read
//! names and metadata: both consumers need exactly the same view, and the
//! server's core may not import the simulator.

use std::fs;
use std::io;
use std::path::Path;

use plccoms_protocol::cp1250;

use super::{
    DirEntry, FileInfo, FILE_ATTRIBUTE_ARCHIVE, FILE_ATTRIBUTE_DIRECTORY, FILE_ATTRIBUTE_HIDDEN,
    FILE_ATTRIBUTE_READONLY,
};
use crate::time;

/// A host directory's entries by cp1250 name, sorted: names that cp1250
/// cannot hold and names starting with `hidden_prefix` (staging files) are
/// left out, at most `max` entries.
pub fn list_dir(host: &Path, hidden_prefix: &str, max: usize) -> io::Result<Vec<DirEntry>> {
    let mut entries = Vec::new();
    for entry in fs::read_dir(host)? {
        let Ok(entry) = entry else { continue };
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        if name.starts_with(hidden_prefix) {
            continue;
        }
        let Some(bytes) = cp1250::try_encode(name) else {
            continue;
        };
        let Ok(meta) = fs::metadata(entry.path()) else {
            continue;
        };
        entries.push(DirEntry {
            name: bytes,
            info: info_of(&entry.path(), &meta),
        });
        if entries.len() >= max {
            break;
        }
    }
    entries.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(entries)
}

/// GETFILEINFO's view of a host file: size, attributes (directory or
/// archive, read-only, hidden for dot names) and ttida times.
pub fn info_of(path: &Path, meta: &fs::Metadata) -> FileInfo {
    let mut attributes = if meta.is_dir() {
        FILE_ATTRIBUTE_DIRECTORY
    } else {
        FILE_ATTRIBUTE_ARCHIVE
    };
    if meta.permissions().readonly() {
        attributes |= FILE_ATTRIBUTE_READONLY;
    }
    if path
        .file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.starts_with('.'))
    {
        attributes |= FILE_ATTRIBUTE_HIDDEN;
    }
    let modified = meta.modified().map(time::ttida_from_system).unwrap_or(0);
    let created = meta
        .created()
        .map(time::ttida_from_system)
        .unwrap_or(modified);
    FileInfo {
        size: if meta.is_dir() { 0 } else { meta.len() },
        attributes,
        created,
        modified,
    }
}
