//! A running section as its sessions and consumers see it: the global
//! settings, the live state (settings as SETCONF left them, link status),
//! the link's handle, the change stream, and the connected clients.

pub mod run;
pub mod write;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use plccoms_protocol::value::FormatOptions;
use tokio::sync::{oneshot, watch};
use tokio_util::sync::CancellationToken;

use crate::changes::{ChangeStream, Snapshot, Snapshots, Subscription};
use crate::config::Global;
use crate::driver::ReadRequest;
use crate::link::files::{FileJob, FileReply};
use crate::link::state::SectionState;
use crate::link::{ConfChange, LinkHandle, LinkState, ReadReply, ReconfReply};
use crate::metrics::{Gauge, SectionMetrics};

/// A connected client, for GETINFO's NETWORK list and the web page.
#[derive(Debug, Clone)]
pub struct ClientInfo {
    pub id: u64,
    pub peer: SocketAddr,
    /// Local wall-clock time of connection, `yyyy-mm-dd hh:mm:ss`.
    pub connected: String,
    /// UTC milliseconds of the connection.
    pub connected_ms: i64,
    pub stats: Arc<ClientStats>,
}

/// What a session reports of itself as it runs.
#[derive(Debug, Default)]
pub struct ClientStats {
    /// Variables enabled, the fixed ones included.
    pub enabled: Gauge,
    /// Output queued for the client, in bytes.
    pub queued: Gauge,
}

/// A running section, as every app sees it: its settings and live state,
/// its change stream (subscribe), reads and file jobs through its link,
/// the one write path (`write`, in write.rs), its clients and its GETINFO
/// lines. Apps never reach the link or the backend behind it.
pub struct Section {
    name: String,
    global: Arc<Global>,
    format: FormatOptions,
    link: LinkHandle,
    changes: ChangeStream,
    state: watch::Receiver<Arc<SectionState>>,
    metrics: Arc<SectionMetrics>,
    /// Cancelled when the server stops: sessions answer what they have and
    /// close.
    shutdown: CancellationToken,
    /// The folder local files (names beginning with `.`) live in: FILES_ROOT
    /// or the configuration file's folder, or its `<section name>` subfolder
    /// with PUBFILE_WRITE = Yes.
    root: PathBuf,
    /// The configuration file's folder (public files are found from it).
    config_dir: PathBuf,
    clients: Mutex<Clients>,
    /// An app's figures for GETINFO (the historian's, when it records this
    /// section).
    info_lines: OnceLock<Arc<dyn InfoLines>>,
}

/// An app's own GETINFO lines for a section (the historian's figures): the
/// app fills the section's slot, so the section needs no app's types.
pub trait InfoLines: Send + Sync {
    /// `KEY,value` lines, shown after the vendor's keys.
    fn getinfo(&self) -> Vec<(&'static str, String)>;
}

#[derive(Default)]
struct Clients {
    next_id: u64,
    list: Vec<ClientInfo>,
}

impl Section {
    pub fn new(
        global: Arc<Global>,
        link: LinkHandle,
        changes: ChangeStream,
        state: watch::Receiver<Arc<SectionState>>,
        metrics: Arc<SectionMetrics>,
        config_dir: PathBuf,
    ) -> Section {
        let format = format_options(&global);
        let config = state.borrow().config.clone();
        let files = match &global.files_root {
            Some(root) => config_dir.join(root),
            None => config_dir.clone(),
        };
        let root = if config.pubfile_write {
            files.join(&config.name)
        } else {
            files
        };
        Section {
            name: config.name,
            global,
            format,
            link,
            changes,
            state,
            metrics,
            shutdown: CancellationToken::new(),
            root,
            config_dir,
            clients: Mutex::new(Clients::default()),
            info_lines: OnceLock::new(),
        }
    }

    /// The section's name, as in its `[section]` header.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The global settings (`[*]`).
    pub fn global(&self) -> &Arc<Global> {
        &self.global
    }

    /// How values print (the global settings' number and date forms).
    pub fn format(&self) -> &FormatOptions {
        &self.format
    }

    pub fn metrics(&self) -> &Arc<SectionMetrics> {
        &self.metrics
    }

    /// The folder clients' local files (names beginning with `.`) live in.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Cancelled when the server stops: sessions answer what they have and
    /// close.
    pub fn shutdown(&self) -> &CancellationToken {
        &self.shutdown
    }

    /// The latest snapshot of the change stream.
    pub fn latest(&self) -> Arc<Snapshot> {
        self.changes.latest()
    }

    /// Every snapshot from now on (a session's view of the change stream).
    pub fn snapshots(&self) -> Snapshots {
        self.changes.receiver()
    }

    /// The changes of the variables matching `masks` (`*` wildcards, case
    /// insensitive), each with its quality, for as long as the
    /// subscription lives.
    pub fn subscribe<M: AsRef<[u8]>>(&self, masks: &[M]) -> Subscription {
        self.changes.subscribe(masks)
    }

    /// As [`Section::subscribe`], with masks that mean the project's
    /// variables: the system (`__`) variables only for masks beginning with
    /// `__`.
    pub fn subscribe_names<M: AsRef<[u8]>>(&self, masks: &[M]) -> Subscription {
        self.changes.subscribe_names(masks)
    }

    /// Reads blocks of PLC memory through the link (batched with whatever
    /// else waits); refused at once while the link is lost.
    pub fn read(&self, requests: Vec<ReadRequest>) -> oneshot::Receiver<ReadReply> {
        self.link.read(requests)
    }

    /// A file job (read, write, list, information) through the link.
    pub fn file(&self, job: FileJob) -> oneshot::Receiver<FileReply> {
        self.link.file(job)
    }

    /// SETCONF: applied by the link, undone when it fails.
    pub fn reconfigure(&self, change: ConfChange) -> oneshot::Receiver<ReconfReply> {
        self.link.reconfigure(change)
    }

    /// The link's state now.
    pub fn link_state(&self) -> LinkState {
        self.link.state()
    }

    /// Sets the app's GETINFO lines for this section (once; a second app's
    /// are refused: `false`).
    pub fn set_info_lines(&self, lines: Arc<dyn InfoLines>) -> bool {
        self.info_lines.set(lines).is_ok()
    }

    /// The app's GETINFO lines, if an app set them.
    pub fn info_lines(&self) -> Option<Vec<(&'static str, String)>> {
        self.info_lines.get().map(|lines| lines.getinfo())
    }

    /// The section's frame trace (see [`crate::trace`]).
    pub fn trace(&self) -> &crate::trace::FrameTrace {
        self.link.trace()
    }

    /// The live state: settings as SETCONF left them, and the link.
    pub fn state(&self) -> Arc<SectionState> {
        self.state.borrow().clone()
    }

    /// Follows the live state (settings, the link's status and the PLC's
    /// identification): `changed()` resolves at each change.
    pub fn watch_state(&self) -> watch::Receiver<Arc<SectionState>> {
        self.state.clone()
    }

    /// Waits until a new session may start serving (see
    /// [`SectionState::ready`]).
    pub async fn ready(&self) {
        let mut state = self.state.clone();
        let _ = state.wait_for(|s| s.ready()).await;
    }

    /// Where the section's public files in use are on this machine: never
    /// written by clients.
    pub fn public_files(&self) -> Vec<PathBuf> {
        let config = self.state.borrow().config.clone();
        [&config.pubfile, &config.pubfile_fixed]
            .into_iter()
            .flatten()
            .map(|name| config.path_of(&self.config_dir, name))
            .collect()
    }

    /// READ_ONLY = Yes.
    pub fn read_only(&self) -> bool {
        self.state.borrow().config.read_only
    }

    /// Registers a client unless NET_CONNECT_MAX are connected already.
    pub fn admit(&self, peer: SocketAddr) -> Option<ClientInfo> {
        let mut clients = self.clients.lock().unwrap_or_else(|p| p.into_inner());
        if clients.list.len() >= self.global.net_connect_max {
            return None;
        }
        clients.next_id += 1;
        let now = chrono::Local::now();
        let client = ClientInfo {
            id: clients.next_id,
            peer,
            connected: now.format("%Y-%m-%d %H:%M:%S").to_string(),
            connected_ms: now.timestamp_millis(),
            stats: Arc::default(),
        };
        clients.list.push(client.clone());
        self.metrics.clients.set(clients.list.len() as u64);
        Some(client)
    }

    pub fn leave(&self, id: u64) {
        let mut clients = self.clients.lock().unwrap_or_else(|p| p.into_inner());
        clients.list.retain(|c| c.id != id);
        self.metrics.clients.set(clients.list.len() as u64);
    }

    pub fn clients(&self) -> Vec<ClientInfo> {
        self.clients
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .list
            .clone()
    }
}

impl crate::metrics::SectionProbe for Section {
    fn max_output_queue(&self) -> u64 {
        let clients = self.clients.lock().unwrap_or_else(|p| p.into_inner());
        clients
            .list
            .iter()
            .map(|c| c.stats.queued.get())
            .max()
            .unwrap_or(0)
    }
}

/// How values print, from the global settings.
pub fn format_options(global: &Global) -> FormatOptions {
    FormatOptions {
        num_of_decimals: global.num_of_decimals,
        scient_notation: global.scient_notation,
        date_time_decimal: global.date_time_decimal,
        lim_of_decimals: global.lim_of_decimals,
    }
}
