//! `WRITEFILE:<name>[<n>]=<n raw bytes>` blocks, ended by
//! `WRITEFILE:<name>[0]=`, answered `WRITEFILE:<name> OK` once the file is
//! written; and `WRITEFILEINFO:<name>[<n>]=<size> <attr> <created>
//! <modified>`, answered `WRITEFILEINFO:<name> OK`.
//!
//! As the manual says, the content first comes to the server, and the file
//! is written after the zero block; it appears whole or not at all. A local
//! file (`./name`) is streamed into a hidden staging file in the target's
//! folder and renamed into place; a PLC file is spooled to an unnamed
//! temporary file (at most [`MAX_PLC_FILE`], so many uploads at once hold
//! disk, not memory) and handed to the link whole, which writes it in the
//! backend's blocks with only the last one committing it. Blocks get no
//! answer of their own: failures are answered at the zero block (ERROR 42),
//! a local file's block past the files root's quota included
//! ([`plccoms_core::files_quota`], FILES_QUOTA).
//!
//! A block for another name while a transfer is open ends the open one with
//! ERROR 44 (unterminated). A gap longer than FFILE_TIMEOUT_WR between blocks
//! is ERROR 45 and the data is discarded; further blocks of that name are
//! ignored and its zero block is answered ERROR 45 again, so a file is never
//! made from the tail of a transfer. Block data that stops arriving short of
//! its count for FFILE_TIMEOUT_WR is ERROR 44 (see the session). A client
//! that disconnects mid-transfer leaves nothing behind.
//!
//! WRITEFILEINFO takes effect with its one data block; a `[0]=` block after
//! it is accepted without an answer, so both the manual's single-block form
//! and the WRITEFILE-like form work.

use plccoms_protocol::answer::ErrorCode;
use plccoms_protocol::request::{classify, parse_block, Command, Line};
use tokio::time::Instant;

use super::{error, is_local, local_path, log_file_refusal, ok_line, Cx, FileThen, Reply};
use plccoms_core::files_quota;
use plccoms_core::link::files::{FileJob, Spool};
use plccoms_core::localfs::{self, Access, Staging};
use plccoms_core::ratelimit::RateLimited;

/// Largest PLC file taken by WRITEFILE.
pub const MAX_PLC_FILE: usize = 16 * 1024 * 1024;
/// Largest WRITEFILEINFO data.
const MAX_INFO: usize = 256;

/// A WRITEFILE transfer in progress.
pub struct Upload {
    pub name: Vec<u8>,
    target: Target,
    /// The next block must arrive before this.
    pub deadline: Instant,
}

enum Target {
    Local(Staging),
    Plc(Spool),
    /// Writing failed; the zero block answers ERROR 42.
    Failed,
    /// Timed out (ERROR 45 sent): blocks are ignored, the zero block
    /// answers ERROR 45 again.
    TimedOut,
}

/// One `<command>:<name>[<n>]=<data>` block of WRITEFILE or WRITEFILEINFO.
pub fn block(cx: &mut Cx<'_>, header: &[u8], data: Vec<u8>, out: &mut Vec<u8>) -> Reply {
    let Line::Command { command, args } = classify(header) else {
        return error(cx, ErrorCode::BadRequest, header, out);
    };
    let name = match parse_block(args) {
        Ok((name, _, _)) => name.to_vec(),
        Err(_) => return error(cx, ErrorCode::BadRequest, header, out),
    };
    if cx.section.read_only() {
        // Blocks are dropped; the one that would be answered (WRITEFILE's
        // zero block, WRITEFILEINFO's data block) answers ERROR:30.
        let answered = match command {
            Command::WriteFileInfo => !data.is_empty(),
            _ => data.is_empty(),
        };
        if answered {
            let mut context = command.name().as_bytes().to_vec();
            context.push(b':');
            context.extend_from_slice(&name);
            return super::read_only(cx, &context, out);
        }
        return Reply::Done;
    }
    match command {
        Command::WriteFileInfo => write_info(cx, name, &data, out),
        _ => write_block(cx, name, data, out),
    }
}

fn write_block(cx: &mut Cx<'_>, name: Vec<u8>, data: Vec<u8>, out: &mut Vec<u8>) -> Reply {
    if cx.client.upload.as_ref().is_some_and(|u| u.name != name) {
        if let Some(open) = cx.client.upload.take() {
            if !matches!(open.target, Target::TimedOut) {
                error(cx, ErrorCode::Unterminated, &open.name, out);
            }
        }
    }
    if data.is_empty() {
        return finish(cx, name, out);
    }
    let deadline = Instant::now() + cx.section.global().ffile_timeout_wr;
    let upload = match cx.client.upload.take() {
        Some(upload) => upload,
        None => Upload {
            target: start(cx, &name),
            name,
            deadline,
        },
    };
    let mut upload = Upload { deadline, ..upload };
    match &mut upload.target {
        Target::Local(staging) => {
            if !within_quota(cx, &upload.name, data.len()) || staging.write(&data).is_err() {
                upload.target = Target::Failed;
            }
        }
        Target::Plc(spool) => {
            if spool.len() + data.len() as u64 > MAX_PLC_FILE as u64 || spool.append(&data).is_err()
            {
                upload.target = Target::Failed;
            }
        }
        Target::Failed | Target::TimedOut => {}
    }
    cx.client.upload = Some(upload);
    Reply::Done
}

/// Whether `len` more bytes fit in the files root's quota; a refusal is
/// logged, rate-limited (a client can cause it at will).
fn within_quota(cx: &Cx<'_>, name: &[u8], len: usize) -> bool {
    static REFUSED: RateLimited = RateLimited::new(std::time::Duration::from_secs(1));
    let quota = cx.section.global().files_quota;
    match files_quota::admit(cx.section.root(), quota, len as u64) {
        Ok(()) => true,
        Err(over) => {
            log_file_refusal(
                &REFUSED,
                cx,
                name,
                format_args!("WRITEFILE refused: {over}"),
            );
            false
        }
    }
}

fn start(cx: &Cx<'_>, name: &[u8]) -> Target {
    if !is_local(name) {
        return Spool::new().map_or(Target::Failed, Target::Plc);
    }
    match local_path(cx, name, Access::Write) {
        Some(path) => Staging::create(path).map_or(Target::Failed, Target::Local),
        None => Target::Failed,
    }
}

fn finish(cx: &mut Cx<'_>, name: Vec<u8>, out: &mut Vec<u8>) -> Reply {
    let target = match cx.client.upload.take() {
        Some(upload) => upload.target,
        // Only the zero block: an empty file.
        None => start(cx, &name),
    };
    match target {
        Target::Local(staging) => match staging.commit() {
            Ok(()) => {
                ok_line(out, b"WRITEFILE:", &name, cx.client.eol);
                Reply::Done
            }
            Err(_) => error(cx, ErrorCode::WriteFile, &name, out),
        },
        Target::Plc(data) => {
            let job = FileJob::Write {
                path: name.clone(),
                data,
            };
            Reply::file(cx.section.file(job), FileThen::Write { name })
        }
        Target::Failed => error(cx, ErrorCode::WriteFile, &name, out),
        Target::TimedOut => error(cx, ErrorCode::WriteTimeout, &name, out),
    }
}

/// FFILE_TIMEOUT_WR passed since the last block: ERROR 45, data discarded.
pub fn timed_out(cx: &mut Cx<'_>, out: &mut Vec<u8>) {
    let Some(mut upload) = cx.client.upload.take() else {
        return;
    };
    if matches!(upload.target, Target::TimedOut) {
        // The remembered timeout expired: the name is free again.
        return;
    }
    error(cx, ErrorCode::WriteTimeout, &upload.name, out);
    // Dropping a staging file removes it.
    upload.target = Target::TimedOut;
    upload.deadline = Instant::now() + cx.section.global().ffile_timeout_wr * 12;
    // Stray blocks of the abandoned transfer are ignored for a while, then
    // the name is free again.
    cx.client.upload = Some(upload);
}

fn write_info(cx: &mut Cx<'_>, name: Vec<u8>, data: &[u8], out: &mut Vec<u8>) -> Reply {
    if data.is_empty() {
        return Reply::Done;
    }
    let info = match (data.len() <= MAX_INFO).then(|| localfs::parse_info(data)) {
        Some(Some(info)) => info,
        _ => return error(cx, ErrorCode::WriteFileInfo, &name, out),
    };
    if is_local(&name) {
        let done = local_path(cx, &name, Access::Write)
            .is_some_and(|path| localfs::write_info(&path, &info).is_ok());
        if !done {
            return error(cx, ErrorCode::WriteFileInfo, &name, out);
        }
        ok_line(out, b"WRITEFILEINFO:", &name, cx.client.eol);
        return Reply::Done;
    }
    let job = FileJob::WriteInfo {
        path: name.clone(),
        info,
    };
    Reply::file(cx.section.file(job), FileThen::WriteInfo { name })
}
