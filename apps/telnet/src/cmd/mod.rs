//! The protocol's commands, one module each, all of one shape:
//!
//! ```text
//! run(&mut Cx, args, context, &mut out) -> Reply
//! ```
//!
//! A command reads and changes the client's state ([`ClientState`]) and the
//! section ([`Cx::section`]), and either writes its whole answer into `out`
//! at once ([`Reply::Done`]) or hands back a [`Waiting`]: a job the link is
//! doing, whose completion renders the answer. GETFILE hands back a
//! [`getfile::Stream`] that makes its blocks as the client reads them.
//!
//! Commands never write to the connection and know nothing of ordering: the
//! session owns the ordered answer queue and every "wait behind" rule.

pub mod en;
pub mod get;
pub mod getfile;
pub mod getfileinfo;
pub mod getinfo;
pub mod getmem;
pub mod help;
pub mod hide;
pub mod list;
pub mod set;
pub mod setconf;
pub mod writefile;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use plccoms_protocol::answer::{write_error, write_warning, ErrorCode, WarningCode};
use plccoms_protocol::mask::Mask;
use plccoms_protocol::request::Command;
use tokio::sync::oneshot;
use tracing::warn;

use crate::client::ClientTable;
use plccoms_core::changes::{Notice, Snapshot};
use plccoms_core::link::files::{FileOutput, FileReply};
use plccoms_core::link::{LinkError, ReadReply, ReconfError, ReconfReply, SetReply};
use plccoms_core::localfs::{self, Access, LocalError};
use plccoms_core::ratelimit::{more, RateLimited};
use plccoms_core::section::Section;
use plccoms_core::vars::{VarId, VarTable};

/// One client's state that commands read and change.
pub struct ClientState {
    pub vars: ClientTable,
    /// DIFF lines on for this client (`SETCONF:diff`).
    pub diff: bool,
    /// This client's line end (`SETCONF:crlf`).
    pub eol: &'static [u8],
    pub peer: SocketAddr,
    /// A WRITEFILE transfer in progress.
    pub upload: Option<writefile::Upload>,
}

/// What a command runs with.
pub struct Cx<'a> {
    pub section: &'a Section,
    pub client: &'a mut ClientState,
    /// The newest snapshot, for answers from the poll.
    pub newest: &'a Arc<Snapshot>,
    /// A SET of this client is unanswered: a GET must read through the PLC,
    /// behind it, to see its effect.
    pub behind_set: bool,
    /// The time the requests of this turn are handled at (read once per
    /// turn: a burst of GETs does not ask the clock for each).
    pub now: tokio::time::Instant,
}

/// A command's answer.
pub enum Reply {
    /// Written into `out` (possibly nothing).
    Done,
    /// Rendered when the link's job completes.
    Wait(Waiting),
    /// A GETFILE answer, made block by block.
    Stream(Box<getfile::Stream>),
}

/// Which rule of the session an answer waits under.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WaitKind {
    /// A read through the PLC.
    Read,
    /// A SET: DIFF lines wait until it is answered (its answer carries the
    /// new value).
    Set,
    /// A SETCONF of the section: later requests and public-file notices wait.
    Conf,
    /// A PLC file service.
    File,
}

/// What to do with the PLC's answer.
pub enum ReadThen {
    Vars {
        table: Arc<VarTable>,
        ids: Vec<VarId>,
        /// Per id: the value from the latest poll, or `None` when it is in
        /// the PLC's answer (in order).
        cached: Vec<Option<Arc<[u8]>>>,
        single: bool,
    },
    Direct {
        name: Vec<u8>,
        address: plccoms_protocol::address::DirectAddress,
    },
    /// A GETMEM block of `size` bytes.
    Mem { name: Vec<u8>, size: u32 },
}

impl ReadThen {
    /// About how many bytes the answer takes (the session bounds what it
    /// has waiting by it).
    pub fn estimate(&self) -> usize {
        match self {
            ReadThen::Vars { table, ids, .. } => ids.len() * (table.max_name_len() + 24),
            ReadThen::Direct { .. } => 64,
            ReadThen::Mem { size, .. } => *size as usize + 64,
        }
    }
}

/// An answer the link is working on.
pub struct Waiting(Job);

enum Job {
    Read {
        rx: oneshot::Receiver<ReadReply>,
        then: ReadThen,
    },
    Set {
        rx: oneshot::Receiver<SetReply>,
        then: plccoms_core::section::write::WriteTarget,
    },
    Conf {
        rx: oneshot::Receiver<ReconfReply>,
        then: setconf::ConfThen,
    },
    File {
        rx: oneshot::Receiver<FileReply>,
        then: FileThen,
    },
}

/// What the link answered for a [`Waiting`].
pub struct Completion(Completed);

enum Completed {
    Read(ReadReply),
    Set(SetReply),
    Conf(ReconfReply),
    File(FileReply),
}

/// What an answer did besides its bytes, for the session to act on.
pub enum Effect {
    None,
    /// SETCONF loaded a public file: the client switches to the new table
    /// and is told of every notice up to this one, this one by the answer.
    Reconfigured(Arc<Notice>),
}

impl Waiting {
    pub fn kind(&self) -> WaitKind {
        match self.0 {
            Job::Read { .. } => WaitKind::Read,
            Job::Set { .. } => WaitKind::Set,
            Job::Conf { .. } => WaitKind::Conf,
            Job::File { .. } => WaitKind::File,
        }
    }

    /// About how many bytes the answer will take.
    pub fn estimate(&self) -> usize {
        match &self.0 {
            Job::Read { then, .. } => then.estimate(),
            Job::File {
                then: FileThen::List { .. },
                ..
            } => 4096,
            Job::Set { .. } | Job::Conf { .. } | Job::File { .. } => 128,
        }
    }

    /// Waits for the link's answer (a link gone at shutdown is offline).
    pub async fn ready(&mut self) -> Completion {
        Completion(match &mut self.0 {
            Job::Read { rx, .. } => Completed::Read(rx.await.unwrap_or(Err(LinkError::Offline))),
            Job::Set { rx, .. } => Completed::Set(rx.await.unwrap_or(Err(LinkError::Offline))),
            Job::Conf { rx, .. } => Completed::Conf(rx.await.unwrap_or(Err(
                ReconfError::Unreachable("the server is stopping".to_string()),
            ))),
            Job::File { rx, .. } => Completed::File(rx.await.unwrap_or(Err(LinkError::Offline))),
        })
    }

    /// Renders the answer into `out`.
    pub fn finish(self, done: Completion, cx: &mut Cx<'_>, out: &mut Vec<u8>) -> Effect {
        match (self.0, done.0) {
            (Job::Read { then, .. }, Completed::Read(reply)) => match then {
                ReadThen::Mem { name, .. } => getmem::complete(cx, &name, reply, out),
                then => get::complete(cx, then, reply, out),
            },
            (Job::Set { then, .. }, Completed::Set(reply)) => set::complete(cx, then, reply, out),
            (Job::Conf { then, .. }, Completed::Conf(reply)) => {
                return setconf::complete(cx, then, reply, out)
            }
            (Job::File { then, .. }, Completed::File(reply)) => complete_file(cx, then, reply, out),
            _ => unreachable!("a completion comes from its own job"),
        }
        Effect::None
    }
}

impl Reply {
    fn read(rx: oneshot::Receiver<ReadReply>, then: ReadThen) -> Reply {
        Reply::Wait(Waiting(Job::Read { rx, then }))
    }

    fn set(
        rx: oneshot::Receiver<SetReply>,
        then: plccoms_core::section::write::WriteTarget,
    ) -> Reply {
        Reply::Wait(Waiting(Job::Set { rx, then }))
    }

    fn conf(rx: oneshot::Receiver<ReconfReply>, then: setconf::ConfThen) -> Reply {
        Reply::Wait(Waiting(Job::Conf { rx, then }))
    }

    fn file(rx: oneshot::Receiver<FileReply>, then: FileThen) -> Reply {
        Reply::Wait(Waiting(Job::File { rx, then }))
    }
}

/// Runs one request. `context` is the request as the client wrote it, for
/// error texts.
pub fn run(
    cx: &mut Cx<'_>,
    command: Command,
    args: &[u8],
    context: &[u8],
    out: &mut Vec<u8>,
) -> Reply {
    if matches!(command, Command::Set) && cx.section.read_only() {
        return read_only(cx, context, out);
    }
    match command {
        Command::List => list::run(cx, args, out),
        Command::Get => get::run(cx, args, context, out),
        Command::Set => set::run(cx, args, context, out),
        Command::En => en::run(cx, args, context, true, out),
        Command::Di => en::run(cx, args, context, false, out),
        Command::Hide => hide::run(cx, args, context, true, out),
        Command::Unhide => hide::run(cx, args, context, false, out),
        Command::GetInfo => getinfo::run(cx, args, context, out),
        Command::SetConf => setconf::run(cx, args, context, out),
        Command::Help => help::run(cx, out),
        Command::GetMem => getmem::run(cx, args, context, out),
        Command::GetFile => getfile::run(cx, args, context, out),
        Command::GetFileInfo => getfileinfo::run(cx, args, context, out),
        Command::WriteFile | Command::WriteFileInfo => {
            // Data blocks come as blocks (see `writefile::block`); a line
            // here has no `[n]=`.
            error(cx, ErrorCode::Incomplete, context, out)
        }
    }
}

/// READ_ONLY = Yes: a request that would change the PLC or the section
/// answers ERROR:30 with the request, and nothing is changed.
pub fn read_only(cx: &Cx<'_>, context: &[u8], out: &mut Vec<u8>) -> Reply {
    error(cx, ErrorCode::BadRequest, context, out)
}

/// Writes `ERROR:<code> <text> '<context>'` and the line end.
pub fn error(cx: &Cx<'_>, code: ErrorCode, context: &[u8], out: &mut Vec<u8>) -> Reply {
    write_error(out, code, context);
    out.extend_from_slice(cx.client.eol);
    Reply::Done
}

pub fn warning(cx: &Cx<'_>, code: WarningCode, context: &[u8], out: &mut Vec<u8>) -> Reply {
    write_warning(out, code, context);
    out.extend_from_slice(cx.client.eol);
    Reply::Done
}

/// Which variables a mask names.
pub enum Selection {
    /// The "all" form (empty or only `*`): every variable not hidden.
    All(Vec<VarId>),
    /// A mask with wildcards, hidden variables included.
    Matching(Vec<VarId>),
    /// An exact name.
    One(VarId),
    /// An exact name that does not exist.
    Unknown,
}

impl Selection {
    pub fn ids(self) -> Vec<VarId> {
        match self {
            Selection::All(ids) | Selection::Matching(ids) => ids,
            Selection::One(id) => vec![id],
            Selection::Unknown => Vec::new(),
        }
    }
}

/// Resolves `pattern` against `table`; `hidden` tells which variables the
/// all-form skips.
pub fn select(table: &VarTable, pattern: &[u8], hidden: impl Fn(VarId) -> bool) -> Selection {
    // One name (most requests): no mask to build.
    if !pattern.is_empty() && !pattern.contains(&b'*') {
        return table
            .lookup(pattern)
            .map_or(Selection::Unknown, Selection::One);
    }
    let mask = Mask::new(pattern);
    if mask.is_all() {
        return Selection::All(
            (0..table.len() as VarId)
                .filter(|&id| !hidden(id))
                .collect(),
        );
    }
    if mask.min_len() > table.max_name_len() {
        // Longer than every name: nothing to try (a client cannot make the
        // server compare megabytes of stars against every name).
        return Selection::Matching(Vec::new());
    }
    Selection::Matching(
        table
            .vars()
            .iter()
            .enumerate()
            .filter(|(_, var)| mask.matches(&var.name))
            .map(|(id, _)| id as VarId)
            .collect(),
    )
}

/// One block of a transfer answer: `<command>:<name>[<n>]=<n raw bytes>`
/// and the line end (`[0]=` with no data ends the transfer).
pub fn write_block(out: &mut Vec<u8>, command: &[u8], name: &[u8], data: &[u8], eol: &[u8]) {
    out.extend_from_slice(command);
    out.push(b':');
    out.extend_from_slice(name);
    out.push(b'[');
    out.extend_from_slice(data.len().to_string().as_bytes());
    out.extend_from_slice(b"]=");
    out.extend_from_slice(data);
    out.extend_from_slice(eol);
}

/// `data` in blocks of at most `blksize` bytes, then the `[0]=` terminator.
pub fn write_blocks(
    out: &mut Vec<u8>,
    command: &[u8],
    name: &[u8],
    data: &[u8],
    blksize: usize,
    eol: &[u8],
) {
    for chunk in data.chunks(blksize.max(1)) {
        write_block(out, command, name, chunk, eol);
    }
    write_block(out, command, name, b"", eol);
}

/// Names beginning with `.` are files on the server's machine.
pub fn is_local(name: &[u8]) -> bool {
    name.first() == Some(&b'.')
}

/// The host path of a local file name for `access`, or `None` when it is
/// not to be had: outside the root, one of the server's own files, or a
/// path that does not resolve. Refusals are logged, at most once a second.
pub fn local_path(cx: &Cx<'_>, name: &[u8], access: Access) -> Option<PathBuf> {
    static REFUSED: RateLimited = RateLimited::new(std::time::Duration::from_secs(1));
    let extra = match access {
        Access::Write => cx.section.public_files(),
        Access::Read => Vec::new(),
    };
    match localfs::resolve_for(cx.section.root(), name, access, &extra) {
        Ok(path) => Some(path),
        Err(err @ (LocalError::Outside | LocalError::Protected)) => {
            log_file_refusal(
                &REFUSED,
                cx,
                name,
                format_args!("refused local file access: {err}"),
            );
            None
        }
        Err(LocalError::Io(_)) => None,
    }
}

/// Logs a local file refused to a client, through `limiter`: a client can
/// cause it at will.
pub fn log_file_refusal(
    limiter: &RateLimited,
    cx: &Cx<'_>,
    name: &[u8],
    what: std::fmt::Arguments<'_>,
) {
    if let Some(quiet) = limiter.admit() {
        warn!(
            section = %cx.section.name(),
            client = %cx.client.peer,
            name = %String::from_utf8_lossy(name),
            "{what}{}",
            more(quiet)
        );
    }
}

/// ERROR:10 when there is no link, `code` when the PLC failed the request
/// or it could not be sent in time.
pub fn link_error(err: LinkError, code: ErrorCode, eol: &[u8], out: &mut Vec<u8>) {
    let code = match err {
        LinkError::Offline => ErrorCode::ConnectPlc,
        LinkError::Plc(_) | LinkError::Late => code,
    };
    write_error(out, code, b"");
    out.extend_from_slice(eol);
}

/// What to answer when a PLC file service finishes.
pub enum FileThen {
    Info { name: Vec<u8> },
    List { name: Vec<u8> },
    Write { name: Vec<u8> },
    WriteInfo { name: Vec<u8> },
}

/// Writes the answer to a PLC file service.
fn complete_file(cx: &mut Cx<'_>, then: FileThen, reply: FileReply, out: &mut Vec<u8>) {
    let eol = cx.client.eol;
    let (name, code) = match &then {
        FileThen::Info { name } => (name, ErrorCode::FileInfo),
        FileThen::List { name } => (name, ErrorCode::GetFile),
        FileThen::Write { name } => (name, ErrorCode::WriteFile),
        FileThen::WriteInfo { name } => (name, ErrorCode::WriteFileInfo),
    };
    let output = match reply {
        Ok(Ok(output)) => output,
        Ok(Err(_)) | Err(LinkError::Plc(_) | LinkError::Late) => {
            write_error(out, code, name);
            out.extend_from_slice(eol);
            return;
        }
        Err(LinkError::Offline) => {
            write_error(out, ErrorCode::ConnectPlc, b"");
            out.extend_from_slice(eol);
            return;
        }
    };
    match (then, output) {
        (FileThen::Info { name }, FileOutput::Info(info)) => {
            getfileinfo::write_info(out, &name, &info, eol)
        }
        (FileThen::List { name }, FileOutput::List(entries)) => {
            let listing = plccoms_core::localfs::format_listing(&entries, eol);
            let blksize = cx.section.global().ffile_blksize;
            write_blocks(out, b"GETFILE", &name, &listing, blksize, eol);
        }
        (FileThen::Write { name }, FileOutput::Done) => ok_line(out, b"WRITEFILE:", &name, eol),
        (FileThen::WriteInfo { name }, FileOutput::Done) => {
            ok_line(out, b"WRITEFILEINFO:", &name, eol)
        }
        (_, _) => {
            // The link answers each job with its own kind of output.
            write_error(out, ErrorCode::Unknown, b"");
            out.extend_from_slice(eol);
        }
    }
}

/// `<command><name> OK` and the line end.
pub fn ok_line(out: &mut Vec<u8>, command: &[u8], name: &[u8], eol: &[u8]) {
    out.extend_from_slice(command);
    out.extend_from_slice(name);
    out.extend_from_slice(b" OK");
    out.extend_from_slice(eol);
}

/// `bytes` without leading and trailing spaces and tabs.
pub fn trim(bytes: &[u8]) -> &[u8] {
    let start = bytes
        .iter()
        .position(|b| !matches!(b, b' ' | b'\t'))
        .unwrap_or(bytes.len());
    let end = bytes
        .iter()
        .rposition(|b| !matches!(b, b' ' | b'\t'))
        .map_or(start, |e| e + 1);
    &bytes[start..end]
}
