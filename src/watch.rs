//! `-t`: notice when the configuration file changes, so the server can exit
//! and its supervisor restart it with the new file.

use std::path::{Path, PathBuf};

use notify::{Event, RecursiveMode, Watcher};
use tokio::sync::mpsc;

/// Watches `path`; the returned receiver yields once per change. Keep the
/// watcher alive as long as the receiver is used.
pub fn watch_file(path: &Path) -> notify::Result<(notify::RecommendedWatcher, mpsc::Receiver<()>)> {
    let path = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let dir: PathBuf = path
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    let name = path.file_name().map(|n| n.to_os_string());
    let (tx, rx) = mpsc::channel(1);
    // Editors often replace the file, so watch its folder and filter by name.
    let mut watcher = notify::recommended_watcher(move |event: notify::Result<Event>| {
        let Ok(event) = event else { return };
        if event.kind.is_access() {
            return;
        }
        if event
            .paths
            .iter()
            .any(|p| p.file_name().map(|n| n.to_os_string()) == name)
        {
            let _ = tx.try_send(());
        }
    })?;
    watcher.watch(&dir, RecursiveMode::NonRecursive)?;
    Ok((watcher, rx))
}
