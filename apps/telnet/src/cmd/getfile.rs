//! `GETFILE:<name>`: the file as `GETFILE:<name>[N]=<N raw bytes>` blocks of
//! at most FFILE_BLKSIZE, then `GETFILE:<name>[0]=`. A name ending in `/`
//! lists the directory: one entry a line (the client's line end), folders
//! with a trailing `/`, in the same blocks.
//!
//! Files stream: the answer is a [`Stream`] at the head of the session's
//! queue that makes its next block only when the client has drained output
//! below the high-water mark (local files are read a block at a time; PLC
//! files are fetched by the poller one FFILE_BLKSIZE block per request, so
//! polling and other clients' requests go on between blocks). The session
//! holds DIFF lines back while a stream is at the head, so they never land
//! inside its block sequence.
//!
//! Errors: a missing or unreadable file, or a local name leading outside the
//! root folder, is ERROR 41 when no block was sent yet. A read that fails
//! after blocks went out ends the answer with `ERROR:46 Aborted get file:
//! '<name>'` in place of the `[0]=` terminator.

use std::fs::File;
use std::io::Read;

use plccoms_protocol::answer::{write_error, ErrorCode};
use tokio::sync::oneshot;

use super::{error, is_local, local_path, trim, write_block, Cx, FileThen, Reply};
use plccoms_core::link::files::{FileJob, FileOutput, FileReply};
use plccoms_core::link::LinkError;
use plccoms_core::localfs::{self, Access};

/// A GETFILE answer being sent.
pub struct Stream {
    name: Vec<u8>,
    source: Source,
    /// Bytes sent so far.
    offset: u64,
}

enum Source {
    Local(File),
    /// A PLC file; the block requested from the poller, if one is.
    Plc {
        path: Vec<u8>,
        rx: Option<oneshot::Receiver<FileReply>>,
    },
}

impl Stream {
    /// The reply being waited for, if the stream waits on the PLC.
    pub fn waiting(&mut self) -> Option<&mut oneshot::Receiver<FileReply>> {
        match &mut self.source {
            Source::Plc { rx, .. } => rx.as_mut(),
            Source::Local(_) => None,
        }
    }

    /// Moves the answer on: local blocks until `room` more bytes are
    /// written, or a request for the PLC's next block. Returns whether the
    /// answer is complete.
    pub fn advance(&mut self, cx: &Cx<'_>, out: &mut Vec<u8>, room: usize) -> bool {
        match self.source {
            Source::Local(_) => pump_local(cx, self, out, room),
            Source::Plc { .. } => {
                request_next(cx, self);
                false
            }
        }
    }

    /// Takes the PLC's answer for the block waited for; returns whether the
    /// answer is complete.
    pub fn on_reply(&mut self, cx: &Cx<'_>, reply: FileReply, out: &mut Vec<u8>) -> bool {
        plc_block(cx, self, reply, out)
    }
}

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let name = trim(args);
    if name.is_empty() {
        return error(cx, ErrorCode::Incomplete, context, out);
    }
    let listing = name.last() == Some(&b'/');
    if is_local(name) {
        let Some(path) = local_path(cx, name, Access::Read) else {
            return error(cx, ErrorCode::GetFile, name, out);
        };
        if listing {
            return match localfs::list(&path) {
                Ok(entries) => {
                    let eol = cx.client.eol;
                    let data = localfs::format_listing(&entries, eol);
                    let blksize = cx.section.global().ffile_blksize;
                    super::write_blocks(out, b"GETFILE", name, &data, blksize, eol);
                    Reply::Done
                }
                Err(_) => error(cx, ErrorCode::GetFile, name, out),
            };
        }
        let file = match File::open(&path) {
            Ok(file) if file.metadata().is_ok_and(|m| m.is_file()) => file,
            _ => return error(cx, ErrorCode::GetFile, name, out),
        };
        return Reply::Stream(Box::new(Stream {
            name: name.to_vec(),
            source: Source::Local(file),
            offset: 0,
        }));
    }
    if listing {
        let rx = cx.section.file(FileJob::List {
            path: name.to_vec(),
        });
        let then = FileThen::List {
            name: name.to_vec(),
        };
        return Reply::file(rx, then);
    }
    let mut stream = Stream {
        name: name.to_vec(),
        source: Source::Plc {
            path: name.to_vec(),
            rx: None,
        },
        offset: 0,
    };
    request_next(cx, &mut stream);
    Reply::Stream(Box::new(stream))
}

fn blksize(cx: &Cx<'_>) -> usize {
    cx.section.global().ffile_blksize.clamp(1, 65536)
}

/// Asks the link for the next block of a PLC file, unless a request is out.
fn request_next(cx: &Cx<'_>, stream: &mut Stream) {
    let len = blksize(cx) as u32;
    if let Source::Plc { path, rx } = &mut stream.source {
        if rx.is_none() {
            let job = FileJob::Read {
                path: path.clone(),
                offset: stream.offset,
                len,
            };
            *rx = Some(cx.section.file(job));
        }
    }
}

/// Makes the stream's next local blocks until `room` more bytes are in
/// `out`. Returns whether the answer is complete.
fn pump_local(cx: &Cx<'_>, stream: &mut Stream, out: &mut Vec<u8>, room: usize) -> bool {
    let blksize = blksize(cx);
    let eol = cx.client.eol;
    let Source::Local(file) = &mut stream.source else {
        return false;
    };
    let mut buf = vec![0; blksize];
    let limit = out.len() + room;
    while out.len() < limit {
        // Blocking reads of one block: a page-cache read of at most 64 KiB
        // costs microseconds, less than a trip to a blocking thread.
        let mut filled = 0;
        let failed = loop {
            match file.read(&mut buf[filled..]) {
                Ok(0) => break false,
                Ok(n) => {
                    filled += n;
                    if filled == blksize {
                        break false;
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(_) => break true,
            }
        };
        if failed {
            abort(out, &stream.name, stream.offset, eol);
            return true;
        }
        if filled > 0 {
            write_block(out, b"GETFILE", &stream.name, &buf[..filled], eol);
            stream.offset += filled as u64;
        }
        if filled < blksize {
            write_block(out, b"GETFILE", &stream.name, b"", eol);
            return true;
        }
    }
    false
}

/// Handles a PLC block; returns whether the answer is complete.
fn plc_block(cx: &Cx<'_>, stream: &mut Stream, reply: FileReply, out: &mut Vec<u8>) -> bool {
    let eol = cx.client.eol;
    let requested = blksize(cx);
    if let Source::Plc { rx, .. } = &mut stream.source {
        *rx = None;
    }
    let data = match reply {
        Ok(Ok(FileOutput::Data(data))) => data,
        Err(LinkError::Offline) if stream.offset == 0 => {
            write_error(out, ErrorCode::ConnectPlc, b"");
            out.extend_from_slice(eol);
            return true;
        }
        _ => {
            abort(out, &stream.name, stream.offset, eol);
            return true;
        }
    };
    if !data.is_empty() {
        write_block(out, b"GETFILE", &stream.name, &data, eol);
        stream.offset += data.len() as u64;
    }
    if data.len() < requested {
        write_block(out, b"GETFILE", &stream.name, b"", eol);
        return true;
    }
    false
}

/// ERROR 41 before any block, ERROR 46 after some.
fn abort(out: &mut Vec<u8>, name: &[u8], sent: u64, eol: &[u8]) {
    let code = if sent == 0 {
        ErrorCode::GetFile
    } else {
        ErrorCode::AbortedGet
    };
    write_error(out, code, name);
    out.extend_from_slice(eol);
}
