//! A client session: reads requests, answers them in order, and sends DIFF
//! lines between answers.
//!
//! Requests are taken as fast as they arrive (clients pipeline hundreds at
//! once); answers that need the PLC wait in an ordered queue while later
//! requests are already parsed and sent on to the poller, so a burst of SETs
//! or GETs shares PLC round trips. Output is bounded: when the client does not
//! read, the session stops taking requests (at `OUTPUT_HIGH_WATER`) and defers
//! DIFFs (at OUTPUT_SOFT_LIMIT; it can always recompute them from the latest
//! snapshot, so they coalesce) instead of buffering.
//!
//! A client that does not read its output is disconnected: at once when its
//! queued output (written-out buffer plus finished answers waiting behind a
//! PLC request) passes OUTPUT_HARD_LIMIT, and when it stays at or above
//! OUTPUT_SOFT_LIMIT for OUTPUT_SOFT_TIMEOUT. Nothing a session does waits for
//! another session or holds up the poller: snapshots reach it on a `watch`
//! channel.

pub mod connection;
pub mod table;

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::Arc;

use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::decoder::Frame;
use plccoms_protocol::request::{classify, Command, Line};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tokio::sync::{oneshot, watch};
use tracing::{debug, info, warn};

use crate::cmd;
use crate::fanout::Snapshot;
use crate::poller::files::FileReply;
use crate::poller::{ReadReply, ReconfReply, SetReply};
use crate::section::SectionShared;
use connection::{Connection, OUTPUT_HIGH_WATER};
use table::ClientTable;

/// Answers waiting for the PLC at most, before the session stops reading.
const MAX_PENDING: usize = 1024;
/// Received bytes not yet handed to the decoder (requests waiting behind a
/// SETCONF): past this, the session stops reading until they are handled.
const MAX_UNPARSED_INPUT: usize = 64 * 1024;

/// An answer in the ordered queue.
pub enum Pending {
    Ready(Vec<u8>),
    Read {
        rx: oneshot::Receiver<ReadReply>,
        then: cmd::get::ReadThen,
    },
    Set {
        rx: oneshot::Receiver<SetReply>,
        then: cmd::set::SetThen,
    },
    Conf {
        rx: oneshot::Receiver<ReconfReply>,
        then: cmd::setconf::ConfThen,
    },
    /// A PLC file service (GETFILEINFO, a directory listing, WRITEFILE,
    /// WRITEFILEINFO).
    File {
        rx: oneshot::Receiver<FileReply>,
        then: cmd::FileThen,
    },
    /// A GETFILE answer, sent block by block. While it is at the head of the
    /// queue it is being written, so DIFF lines wait until it ends.
    Stream(Box<cmd::getfile::Stream>),
}

enum Completion {
    Read(ReadReply),
    Set(SetReply),
    Conf(ReconfReply),
    File(FileReply),
}

pub struct Session {
    pub shared: Arc<SectionShared>,
    pub conn: Connection,
    pub vars: ClientTable,
    pub snapshot: Arc<Snapshot>,
    snapshots: watch::Receiver<Arc<Snapshot>>,
    /// The newest published snapshot, for answers from the poll; may be
    /// ahead of `snapshot` while DIFF lines wait. See [`Session::refresh_newest`].
    pub newest: Arc<Snapshot>,
    newest_rx: watch::Receiver<Arc<Snapshot>>,
    pub pending: VecDeque<Pending>,
    /// The variable command a bare continuation line repeats.
    continuation: Option<Command>,
    /// DIFF lines on for this client (`SETCONF:diff`).
    pub diff: bool,
    pub peer: SocketAddr,
    close: bool,
    /// The server is stopping: no more input is read; what was received is
    /// answered, then the session closes.
    stopping: bool,
    /// A snapshot arrived while a SET was unanswered; its DIFFs wait so the
    /// SET's own answer is not doubled by a DIFF for the same change.
    diffs_deferred: bool,
    /// Sequence of the last public-file notice this client was told of.
    pub notice_seen: u64,
    /// A WRITEFILE transfer in progress.
    pub upload: Option<cmd::writefile::Upload>,
    /// Bytes of the finished answers (`Pending::Ready`) in `pending`.
    ready_bytes: usize,
    /// Since when queued output has been at or above OUTPUT_SOFT_LIMIT.
    over_soft_since: Option<tokio::time::Instant>,
    /// Why the session was cut off (output limits); nothing more is written.
    dropped: Option<String>,
}

impl Session {
    pub fn new(shared: Arc<SectionShared>, stream: TcpStream, peer: SocketAddr) -> Session {
        let mut snapshots = shared.snapshots.clone();
        let snapshot = snapshots.borrow_and_update().clone();
        let mut newest_rx = shared.snapshots.clone();
        let newest = newest_rx.borrow_and_update().clone();
        let vars = ClientTable::new(&snapshot, !shared.global.pf_var_disabled);
        let notice_seen = snapshot.notice_seq();
        let crlf = shared.global.end_line_crlf;
        let diff = shared.global.diff_var_enabled;
        Session {
            conn: Connection::new(stream, crlf),
            vars,
            snapshot,
            snapshots,
            newest,
            newest_rx,
            pending: VecDeque::new(),
            continuation: None,
            diff,
            peer,
            close: false,
            stopping: false,
            diffs_deferred: false,
            notice_seen,
            upload: None,
            ready_bytes: 0,
            over_soft_since: None,
            dropped: None,
            shared,
        }
    }

    /// Serves the client until it leaves.
    pub async fn run(mut self) {
        let section = self.shared.name.clone();
        let peer = self.peer;
        debug!(section = %section, client = %peer, "client connected");
        if let Err(err) = self.serve().await {
            debug!(section = %section, client = %peer, "connection error: {err}");
        }
        if let Some(why) = &self.dropped {
            // Dropping the socket closes it (with a reset if input is
            // unread): nothing more is owed to this client.
            warn!(section = %section, client = %peer, "client disconnected: {why}");
            return;
        }
        // A client that asked to close but does not read what it is owed
        // gets as long as a soft-limit stall.
        let grace = self.shared.global.output_soft_timeout;
        let _ = tokio::time::timeout(grace, self.conn.flush()).await;
        let _ = self.conn.writer.shutdown().await;
        debug!(section = %section, client = %peer, "client disconnected");
    }

    /// Output queued for the client: the unwritten buffer and the finished
    /// answers waiting behind a PLC request.
    pub fn queued_output(&self) -> usize {
        self.conn.backlog() + self.ready_bytes
    }

    /// Applies OUTPUT_HARD_LIMIT and OUTPUT_SOFT_LIMIT; `Some(why)` when the
    /// client must go.
    fn check_output_limits(&mut self) -> Option<String> {
        let global = &self.shared.global;
        let queued = self.queued_output();
        if queued > global.output_hard_limit {
            return Some(format!(
                "{queued} bytes of output queued, over OUTPUT_HARD_LIMIT ({} bytes)",
                global.output_hard_limit
            ));
        }
        if queued < global.output_soft_limit {
            self.over_soft_since = None;
            return None;
        }
        let since = *self
            .over_soft_since
            .get_or_insert_with(tokio::time::Instant::now);
        let held = since.elapsed();
        (held >= global.output_soft_timeout).then(|| {
            format!(
                "not reading: {queued} bytes of output queued, at or over OUTPUT_SOFT_LIMIT ({} bytes) for {} s (OUTPUT_SOFT_TIMEOUT)",
                global.output_soft_limit,
                held.as_secs()
            )
        })
    }

    async fn serve(&mut self) -> std::io::Result<()> {
        loop {
            let drained = self.take_requests().await;
            if self.stopping && drained {
                self.close = true;
            }
            self.release_ready();
            self.pump_stream().await;
            if let Some(why) = self.check_output_limits() {
                self.dropped = Some(why);
                return Ok(());
            }
            if (self.close || self.conn.eof) && self.pending.is_empty() {
                return Ok(());
            }
            let head_waiting = match self.pending.front_mut() {
                Some(
                    Pending::Read { .. }
                    | Pending::Set { .. }
                    | Pending::Conf { .. }
                    | Pending::File { .. },
                ) => true,
                Some(Pending::Stream(stream)) => stream.waiting().is_some(),
                _ => false,
            };
            let streaming = matches!(self.pending.front(), Some(Pending::Stream(_)));
            let write_deadline = self.write_deadline();
            let backlog = self.conn.backlog();
            let can_read = !self.conn.eof
                && !self.close
                && !self.stopping
                && self.pending.len() < MAX_PENDING
                && self.conn.input.len() < MAX_UNPARSED_INPUT
                && backlog < OUTPUT_HIGH_WATER;
            // Snapshots also carry public-file changes, so every client takes
            // them, DIFF lines on or off; never inside a streamed answer.
            let want_diffs = backlog < self.shared.global.output_soft_limit && !streaming;
            let closing = self.close || self.stopping;
            let soft_deadline = self
                .over_soft_since
                .map(|since| since + self.shared.global.output_soft_timeout);
            let Session {
                conn,
                pending,
                snapshots,
                shared,
                ..
            } = self;
            let Connection {
                reader,
                writer,
                input,
                out,
                written,
                ..
            } = conn;
            tokio::select! {
                biased;
                completion = head_reply(pending), if head_waiting => {
                    self.complete_head(completion);
                }
                result = writer.write(&out[*written..]), if backlog > 0 => {
                    let n = result?;
                    if n == 0 {
                        return Ok(());
                    }
                    self.conn.advance_written(n);
                }
                result = Connection::read_more(reader, input), if can_read => {
                    self.conn.last_input = tokio::time::Instant::now();
                    if result? == 0 {
                        self.conn.eof = true;
                        // Let a last line without its line end count.
                        self.conn.input.extend_from_slice(b"\n");
                    }
                }
                changed = snapshots.changed(), if want_diffs => {
                    if changed.is_err() {
                        // The poller is gone: the server is shutting down.
                        self.close = true;
                    } else {
                        self.take_snapshot();
                    }
                }
                _ = shared.shutdown.cancelled(), if !closing => {
                    self.stopping = true;
                }
                _ = tokio::time::sleep_until(write_deadline.unwrap_or_else(tokio::time::Instant::now)), if write_deadline.is_some() => {
                    self.write_timeout();
                }
                // Wakes the limit check when the client stays stalled.
                _ = tokio::time::sleep_until(soft_deadline.unwrap_or_else(tokio::time::Instant::now)), if soft_deadline.is_some() => {}
                else => return Ok(()),
            }
        }
    }

    /// Handles every complete request already received, while the queue and
    /// output have room. Returns whether no complete request is left.
    async fn take_requests(&mut self) -> bool {
        // Requests after a SETCONF wait for it: they may name variables of
        // the public file it loads.
        while !self.close
            && self.pending.len() < MAX_PENDING
            && self.conn.backlog() < OUTPUT_HIGH_WATER
            && !self.conf_outstanding()
        {
            let Some(frame) = self.conn.next_frame() else {
                return true;
            };
            match frame {
                Frame::Line(line) => self.handle_line(&line).await,
                Frame::Block { header, data } => {
                    self.continuation = None;
                    cmd::writefile::block(self, &header, data).await;
                }
                Frame::TooLong(prefix) => {
                    let mut context = prefix;
                    context.extend_from_slice(b"...");
                    let mut out = Vec::new();
                    write_error(&mut out, ErrorCode::BadRequest, &context);
                    self.answer_line(out);
                }
                Frame::Close => {
                    info!(section = %self.shared.name, client = %self.peer, "client closed the session (Ctrl+D)");
                    self.close = true;
                }
            }
        }
        false
    }

    async fn handle_line(&mut self, line: &[u8]) {
        match classify(line) {
            Line::Empty => {}
            Line::Command { command, args } => {
                self.continuation = command.accepts_continuation().then_some(command);
                cmd::dispatch(self, command, args, trim(line)).await;
            }
            Line::UnknownCommand => {
                self.continuation = None;
                let mut out = Vec::new();
                write_error(&mut out, ErrorCode::UnknownCommand, trim(line));
                self.answer_line(out);
            }
            Line::Continuation(args) => match self.continuation {
                Some(command) => {
                    let mut context = command.name().as_bytes().to_vec();
                    context.push(b':');
                    context.extend_from_slice(args);
                    cmd::dispatch(self, command, args, &context).await;
                }
                None => {
                    let mut out = Vec::new();
                    write_error(&mut out, ErrorCode::UnknownCommand, trim(line));
                    self.answer_line(out);
                }
            },
        }
    }

    /// Queues a complete answer (lines already terminated).
    pub fn answer(&mut self, bytes: Vec<u8>) {
        if bytes.is_empty() {
            return;
        }
        if self.pending.is_empty() {
            self.conn.extend(&bytes);
        } else {
            self.ready_bytes += bytes.len();
            self.pending.push_back(Pending::Ready(bytes));
        }
    }

    /// Queues a one-line answer given without its line end.
    pub fn answer_line(&mut self, mut line: Vec<u8>) {
        line.extend_from_slice(self.conn.eol);
        self.answer(line);
    }

    /// Keeps the GETFILE answer at the head of the queue going: local blocks
    /// while output is below the high-water mark, or the next PLC request.
    async fn pump_stream(&mut self) {
        loop {
            let Some(Pending::Stream(_)) = self.pending.front() else {
                return;
            };
            let Some(Pending::Stream(mut stream)) = self.pending.pop_front() else {
                return;
            };
            let done = if stream.waiting().is_some() || self.conn.backlog() >= OUTPUT_HIGH_WATER {
                false
            } else if stream.is_local() {
                cmd::getfile::pump_local(self, &mut stream, OUTPUT_HIGH_WATER)
            } else {
                cmd::getfile::request_next(self, &mut stream).await;
                false
            };
            if !done {
                self.pending.push_front(Pending::Stream(stream));
                return;
            }
            self.stream_done();
        }
    }

    /// A GETFILE answer ended: what waited behind it may go out.
    fn stream_done(&mut self) {
        self.release_ready();
        if self.diffs_deferred && !self.set_outstanding() {
            self.diffs_deferred = false;
            self.take_snapshot();
        }
    }

    /// When the WRITEFILE transfer times out: data of a block stopped
    /// arriving, or no next block came.
    fn write_deadline(&self) -> Option<tokio::time::Instant> {
        let wait = self.shared.global.ffile_timeout_wr;
        if self.conn.pending_block().is_some() {
            return Some(self.conn.last_input + wait);
        }
        self.upload.as_ref().map(|u| u.deadline)
    }

    fn write_timeout(&mut self) {
        if let Some(header) = self.conn.pending_block() {
            // The block's data never came whole: its count does not match.
            let name = match classify(header) {
                Line::Command { args, .. } => plccoms_protocol::request::parse_block(args)
                    .map(|(name, _, _)| name.to_vec())
                    .unwrap_or_default(),
                _ => Vec::new(),
            };
            self.conn.abandon_block();
            if self.upload.as_ref().is_some_and(|u| u.name == name) {
                self.upload = None;
            }
            let mut out = Vec::new();
            write_error(&mut out, ErrorCode::Unterminated, &name);
            self.answer_line(out);
            return;
        }
        cmd::writefile::timed_out(self);
    }

    /// Moves answers that are complete at the head of the queue to output.
    fn release_ready(&mut self) {
        while let Some(Pending::Ready(_)) = self.pending.front() {
            if let Some(Pending::Ready(bytes)) = self.pending.pop_front() {
                self.ready_bytes -= bytes.len();
                self.conn.extend(&bytes);
            }
        }
    }

    /// Whether a SET of this client has not been answered yet (a GET must
    /// then read through the PLC, behind it, to see its effect).
    pub fn set_outstanding(&self) -> bool {
        self.pending
            .iter()
            .any(|p| matches!(p, Pending::Set { .. }))
    }

    /// A SETCONF is unanswered. Nothing is queued behind one, so it can only
    /// be the last entry: checked in O(1) for every request parsed.
    fn conf_outstanding(&self) -> bool {
        matches!(self.pending.back(), Some(Pending::Conf { .. }))
    }

    fn complete_head(&mut self, completion: Completion) {
        let Some(head) = self.pending.pop_front() else {
            return;
        };
        let mut out = Vec::new();
        match (head, completion) {
            (Pending::Stream(mut stream), Completion::File(reply)) => {
                if cmd::getfile::plc_block(self, &mut stream, reply) {
                    self.stream_done();
                } else {
                    self.pending.push_front(Pending::Stream(stream));
                }
                return;
            }
            (Pending::File { then, .. }, Completion::File(reply)) => {
                cmd::complete_file(self, then, reply, &mut out)
            }
            (Pending::Read { then, .. }, Completion::Read(reply)) => {
                cmd::get::complete(self, then, reply, &mut out)
            }
            (Pending::Set { then, .. }, Completion::Set(reply)) => {
                cmd::set::complete(self, then, reply, &mut out)
            }
            (Pending::Conf { then, .. }, Completion::Conf(reply)) => {
                cmd::setconf::complete(self, then, reply, &mut out)
            }
            _ => unreachable!("completion matches the head it came from"),
        }
        self.conn.extend(&out);
        self.release_ready();
        if self.diffs_deferred && !self.set_outstanding() {
            self.diffs_deferred = false;
            self.take_snapshot();
        } else {
            self.sync_table();
        }
    }

    fn take_snapshot(&mut self) {
        let snapshot = self.snapshots.borrow_and_update().clone();
        self.snapshot = snapshot;
        // An idle client must not keep an old snapshot (and the value
        // chunks changed since) alive through `newest`.
        self.refresh_newest();
        self.sync_table();
        if !self.diff {
            return;
        }
        if self.set_outstanding() || matches!(self.pending.front(), Some(Pending::Stream(_))) {
            self.diffs_deferred = true;
            return;
        }
        let Session {
            vars,
            conn,
            shared,
            snapshot,
            ..
        } = self;
        vars.collect_diffs(snapshot, &shared.format, conn.eol, &mut conn.out);
    }

    /// Follows a new public file: carries this client's settings over to the
    /// new table and tells it WARNING:250 (or 251 when only reloaded). While
    /// its own SETCONF is unanswered the SETCONF's answer does the telling.
    pub fn sync_table(&mut self) {
        if !Arc::ptr_eq(&self.snapshot.table, self.vars.table()) {
            let all_enabled = !self.shared.global.pf_var_disabled;
            self.vars = self.vars.remap(&self.snapshot, all_enabled);
        }
        if self.conf_outstanding() {
            return;
        }
        let mut lines = Vec::new();
        self.notices_up_to(u64::MAX, &mut lines);
        // Between answers, like a DIFF line.
        self.conn.extend(&lines);
    }

    /// Writes the WARNING lines of the notices this client has not heard of,
    /// up to sequence `last`, oldest first.
    pub fn notices_up_to(&mut self, last: u64, out: &mut Vec<u8>) {
        if self.snapshot.notice_seq() <= self.notice_seen {
            // Nearly always: no Arc clone on every answer completed.
            return;
        }
        let snapshot = self.snapshot.clone();
        for notice in snapshot.notices_after(self.notice_seen) {
            if notice.seq > last {
                break;
            }
            self.notice_seen = notice.seq;
            cmd::setconf::write_notice(notice, out);
            out.extend_from_slice(self.conn.eol);
        }
    }

    /// Brings `newest` up to date: one atomic load when nothing was
    /// published since, so a burst of GETs does not contend on the channel.
    pub fn refresh_newest(&mut self) {
        if self.newest_rx.has_changed().unwrap_or(false) {
            self.newest = self.newest_rx.borrow_and_update().clone();
        }
    }

    /// The latest snapshot, without waiting for the next change.
    pub fn latest_snapshot(&mut self) -> Arc<Snapshot> {
        self.snapshot = self.snapshots.borrow().clone();
        self.snapshot.clone()
    }
}

async fn head_reply(pending: &mut VecDeque<Pending>) -> Completion {
    match pending.front_mut() {
        Some(Pending::Read { rx, .. }) => {
            Completion::Read(rx.await.unwrap_or(Err(crate::poller::LinkError::Offline)))
        }
        Some(Pending::Set { rx, .. }) => {
            Completion::Set(rx.await.unwrap_or(Err(crate::poller::LinkError::Offline)))
        }
        Some(Pending::Conf { rx, .. }) => Completion::Conf(rx.await.unwrap_or(Err(
            crate::poller::ReconfError::Unreachable("the server is stopping".to_string()),
        ))),
        Some(Pending::File { rx, .. }) => {
            Completion::File(rx.await.unwrap_or(Err(crate::poller::LinkError::Offline)))
        }
        Some(Pending::Stream(stream)) => match stream.waiting() {
            Some(rx) => {
                Completion::File(rx.await.unwrap_or(Err(crate::poller::LinkError::Offline)))
            }
            None => std::future::pending().await,
        },
        _ => std::future::pending().await,
    }
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
