//! `GETFILEINFO:<name>`: `GETFILEINFO:<name>[<len>]=<size> <attr> <created>
//! <modified>`, `len` being the length of the text after `=`. Attribute bits
//! and the `ttida` times as in `backend::FileInfo`. A missing file, or a local
//! name leading outside the root folder, is ERROR 40.

use plccoms_protocol::answer::ErrorCode;
use tracing::warn;

use super::{error, is_local, FileThen};
use crate::backend::FileInfo;
use crate::localfs::{self, LocalError};
use crate::poller::files::FileJob;
use crate::session::{trim, Pending, Session};

pub async fn apply(session: &mut Session, args: &[u8], context: &[u8]) {
    let name = trim(args);
    if name.is_empty() {
        return error(session, ErrorCode::Incomplete, context);
    }
    if is_local(name) {
        let info = match localfs::resolve(&session.shared.root, name) {
            Ok(path) => localfs::info(&path).ok(),
            Err(err) => {
                refused(session, name, &err);
                None
            }
        };
        return match info {
            Some(info) => {
                let mut out = Vec::new();
                write_info(&mut out, name, &info, session.conn.eol);
                session.answer(out);
            }
            None => error(session, ErrorCode::FileInfo, name),
        };
    }
    let rx = session
        .shared
        .poller
        .file(FileJob::Info {
            path: name.to_vec(),
        })
        .await;
    let then = FileThen::Info {
        name: name.to_vec(),
    };
    session.pending.push_back(Pending::File { rx, then });
}

pub fn write_info(out: &mut Vec<u8>, name: &[u8], info: &FileInfo, eol: &[u8]) {
    let text = format!(
        "{} {} {} {}",
        info.size, info.attributes, info.created, info.modified
    );
    super::write_block(out, b"GETFILEINFO", name, text.as_bytes(), eol);
}

/// Logs a local name refused for leading outside the root folder.
pub fn refused(session: &Session, name: &[u8], err: &LocalError) {
    if let LocalError::Outside = err {
        warn!(
            section = %session.shared.name,
            client = %session.peer,
            name = %String::from_utf8_lossy(name),
            "refused local file access outside the root folder"
        );
    }
}
