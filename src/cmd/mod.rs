//! One module per protocol command. Each takes the session and the request's
//! arguments, applies the command and queues its answer.

pub mod en;
pub mod get;
pub mod getinfo;
pub mod help;
pub mod hide;
pub mod list;
pub mod set;
pub mod setconf;

use plccoms_protocol::answer::{write_error, write_warning, ErrorCode, WarningCode};
use plccoms_protocol::mask::Mask;
use plccoms_protocol::request::Command;

use crate::session::Session;
use crate::vars::{VarId, VarTable};

/// Runs one request. `context` is the request as the client wrote it, for
/// error texts.
pub async fn dispatch(session: &mut Session, command: Command, args: &[u8], context: &[u8]) {
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
        Command::GetMem
        | Command::GetFile
        | Command::GetFileInfo
        | Command::WriteFile
        | Command::WriteFileInfo => {
            // Memory and file transfers come with the files issue.
            error(session, ErrorCode::UnknownCommand, context);
        }
    }
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
