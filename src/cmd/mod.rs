//! One module per protocol command. Each takes the session and the request's
//! arguments, applies the command and queues its answer.

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

use plccoms_protocol::answer::{write_error, write_warning, ErrorCode, WarningCode};
use plccoms_protocol::mask::Mask;
use plccoms_protocol::request::Command;

use crate::poller::files::{FileOutput, FileReply};
use crate::poller::LinkError;
use crate::session::Session;
use crate::vars::{VarId, VarTable};

/// Runs one request. `context` is the request as the client wrote it, for
/// error texts.
pub async fn dispatch(session: &mut Session, command: Command, args: &[u8], context: &[u8]) {
    if session.shared.config.read_only && matches!(command, Command::Set) {
        return read_only(session, context);
    }
    match command {
        Command::List => list::apply(session, args),
        Command::Get => get::apply(session, args, context).await,
        Command::Set => set::apply(session, args, context).await,
        Command::En => en::apply(session, args, context, true),
        Command::Di => en::apply(session, args, context, false),
        Command::Hide => hide::apply(session, args, context, true),
        Command::Unhide => hide::apply(session, args, context, false),
        Command::GetInfo => getinfo::apply(session, args, context),
        Command::SetConf => setconf::apply(session, args, context).await,
        Command::Help => help::apply(session),
        Command::GetMem => getmem::apply(session, args, context).await,
        Command::GetFile => getfile::apply(session, args, context).await,
        Command::GetFileInfo => getfileinfo::apply(session, args, context).await,
        Command::WriteFile | Command::WriteFileInfo => {
            // Data blocks come as `Frame::Block`s (see `writefile::block`);
            // a line here has no `[n]=`.
            error(session, ErrorCode::Incomplete, context);
        }
    }
}

/// READ_ONLY = Yes: a request that would change the PLC or the section
/// answers ERROR:30 with the request, and nothing is changed.
pub fn read_only(session: &mut Session, context: &[u8]) {
    error(session, ErrorCode::BadRequest, context);
}

/// Queues `ERROR:<code> <text> '<context>'`.
pub fn error(session: &mut Session, code: ErrorCode, context: &[u8]) {
    let mut out = Vec::new();
    write_error(&mut out, code, context);
    session.answer_line(out);
}

pub fn warning(session: &mut Session, code: WarningCode, context: &[u8]) {
    let mut out = Vec::new();
    write_warning(&mut out, code, context);
    session.answer_line(out);
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
    let mask = Mask::new(pattern);
    if mask.is_all() {
        return Selection::All(
            (0..table.len() as VarId)
                .filter(|&id| !hidden(id))
                .collect(),
        );
    }
    if !mask.has_wildcard() {
        return table
            .lookup(pattern)
            .map_or(Selection::Unknown, Selection::One);
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

/// What to answer when a PLC file service finishes.
pub enum FileThen {
    Info { name: Vec<u8> },
    List { name: Vec<u8> },
    Write { name: Vec<u8> },
    WriteInfo { name: Vec<u8> },
}

/// Writes the answer to a PLC file service.
pub fn complete_file(session: &mut Session, then: FileThen, reply: FileReply, out: &mut Vec<u8>) {
    let eol = session.conn.eol;
    let (name, code) = match &then {
        FileThen::Info { name } => (name, ErrorCode::FileInfo),
        FileThen::List { name } => (name, ErrorCode::GetFile),
        FileThen::Write { name } => (name, ErrorCode::WriteFile),
        FileThen::WriteInfo { name } => (name, ErrorCode::WriteFileInfo),
    };
    let output = match reply {
        Ok(Ok(output)) => output,
        Ok(Err(_)) | Err(LinkError::Plc(_)) => {
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
            let listing = crate::localfs::format_listing(&entries, eol);
            let blksize = session.shared.global.ffile_blksize;
            write_blocks(out, b"GETFILE", &name, &listing, blksize, eol);
        }
        (FileThen::Write { name }, FileOutput::Done) => {
            out.extend_from_slice(b"WRITEFILE:");
            out.extend_from_slice(&name);
            out.extend_from_slice(b" OK");
            out.extend_from_slice(eol);
        }
        (FileThen::WriteInfo { name }, FileOutput::Done) => {
            out.extend_from_slice(b"WRITEFILEINFO:");
            out.extend_from_slice(&name);
            out.extend_from_slice(b" OK");
            out.extend_from_slice(eol);
        }
        (_, _) => {
            // The poller answers each job with its own kind of output.
            write_error(out, ErrorCode::Unknown, b"");
            out.extend_from_slice(eol);
        }
    }
}
