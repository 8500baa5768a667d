//! A client session: reads requests, runs them (`cmd`), answers them in
//! order, and sends DIFF lines between answers.
//!
//! Requests are taken as fast as they arrive (clients pipeline hundreds at
//! once); answers that need the PLC wait in the ordered queue ([`queue`],
//! which also holds every "wait behind" rule) while later requests are
//! already parsed and sent on to the link, so a burst of SETs or GETs shares
//! PLC round trips. Output is bounded: when the client does not read, the
//! session stops taking requests (at `OUTPUT_HIGH_WATER`) and defers DIFFs
//! (at OUTPUT_SOFT_LIMIT; it can always recompute them from the latest
//! snapshot, so they coalesce) instead of buffering.
//!
//! A client that does not read its output is disconnected: at once when its
//! queued output (written-out buffer plus finished answers waiting behind a
//! PLC request) passes OUTPUT_HARD_LIMIT, and when it stays at or above
//! OUTPUT_SOFT_LIMIT for OUTPUT_SOFT_TIMEOUT. Nothing a session does waits for
//! another session or holds up the link: snapshots reach it on a `watch`
//! channel.

pub mod connection;
pub mod queue;
// The fan-out latency of this server's client writes (a measuring build only).
#[cfg(feature = "fanout-trace")]
pub mod trace;

use std::net::SocketAddr;
use std::sync::Arc;

use plccoms_protocol::answer::ErrorCode;
use plccoms_protocol::decoder::Frame;
use plccoms_protocol::request::{classify, Command, Line};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tracing::{debug, info, warn};

use crate::client::ClientTable;
use crate::cmd::{self, trim, ClientState, Cx, Effect, Reply};
use connection::{Connection, OUTPUT_HIGH_WATER};
use plccoms_core::changes::{Notice, Snapshot, Snapshots};
use plccoms_core::section::{ClientInfo, ClientStats, Section};
use queue::{AnswerQueue, Entry, HeadDone};

/// Sleeps until `deadline`; built without reading the clock or arming a
/// timer, so the `select!` branches that are off cost nothing.
async fn sleep_until(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(deadline) => tokio::time::sleep_until(deadline).await,
        None => std::future::pending().await,
    }
}

/// Asks the allocator to give freed memory back to the system, at most once
/// a second. glibc keeps what a flood of large answers freed in its
/// per-thread arenas: without this, a client that pipelined hundreds of
/// megabytes' worth of requests left that much resident after it left.
fn trim_memory() {
    use std::sync::atomic::{AtomicBool, Ordering};
    static LAST: plccoms_core::ratelimit::RateLimited =
        plccoms_core::ratelimit::RateLimited::new(std::time::Duration::from_secs(1));
    static LATER: AtomicBool = AtomicBool::new(false);
    if LAST.admit().is_some() {
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        // SAFETY: malloc_trim only walks the allocator's own free lists.
        unsafe {
            libc::malloc_trim(0);
        }
    } else if !LATER.swap(true, Ordering::Relaxed) {
        // Sessions that leave together: one more trim after them all.
        tokio::spawn(async {
            tokio::time::sleep(std::time::Duration::from_millis(1100)).await;
            LATER.store(false, Ordering::Relaxed);
            trim_memory();
        });
    }
}

/// Answers waiting for the PLC at most, before the session stops reading.
const MAX_PENDING: usize = 1024;
/// Received bytes not yet handed to the decoder (requests waiting behind a
/// SETCONF): past this, the session stops reading until they are handled.
const MAX_UNPARSED_INPUT: usize = 64 * 1024;
/// Requests handled in one go before the session yields to other tasks.
const REQUESTS_PER_TURN: usize = 256;
/// Beyond the time a silent PLC takes to be declared lost, how long a
/// burst's answers may wait for each other.
const HOLD_MARGIN: std::time::Duration = std::time::Duration::from_millis(200);

pub struct Session {
    section: Arc<Section>,
    conn: Connection,
    client: ClientState,
    /// The snapshot DIFF lines were last taken from.
    snapshot: Arc<Snapshot>,
    snapshots: Snapshots,
    /// The newest published snapshot, for answers from the poll; may be
    /// ahead of `snapshot` while DIFF lines wait. See [`Session::refresh_newest`].
    newest: Arc<Snapshot>,
    newest_rx: Snapshots,
    queue: AnswerQueue,
    /// The variable command a bare continuation line repeats.
    continuation: Option<Command>,
    close: bool,
    /// The server is stopping: no more input is read; what was received is
    /// answered, then the session closes.
    stopping: bool,
    /// A snapshot arrived while a SET was unanswered or a file streamed; its
    /// DIFFs wait until then.
    diffs_deferred: bool,
    /// Sequence of the last public-file notice this client was told of.
    notice_seen: u64,
    /// Since when queued output has been at or above OUTPUT_SOFT_LIMIT.
    over_soft_since: Option<tokio::time::Instant>,
    /// Why the session was cut off (output limits); nothing more is written.
    dropped: Option<String>,
    /// What the session reports of itself (GETINFO, the web page).
    stats: Arc<ClientStats>,
    /// Resolves when the server stops. Kept across wake-ups: registered
    /// once, not on every turn of the loop.
    stop: std::pin::Pin<Box<tokio_util::sync::WaitForCancellationFutureOwned>>,
    /// The last turn took [`REQUESTS_PER_TURN`] requests: yield first.
    turn_used: bool,
    /// Output waits until then for the rest of a burst's answers.
    holding: Option<tokio::time::Instant>,
    /// While requests are taken: the time they are handled at.
    turn_now: Option<tokio::time::Instant>,
    /// The most output it had queued or coming.
    peak: usize,
    /// Snapshots whose DIFF lines are queued and not written yet.
    #[cfg(feature = "fanout-trace")]
    traced: Vec<(u64, tokio::time::Instant)>,
}

impl Session {
    pub fn new(section: Arc<Section>, stream: TcpStream, peer: SocketAddr) -> Session {
        let mut snapshots = section.snapshots();
        let snapshot = snapshots.borrow_and_update().clone();
        let mut newest_rx = section.snapshots();
        let newest = newest_rx.borrow_and_update().clone();
        let global = section.global();
        let client = ClientState {
            vars: ClientTable::new(&snapshot, !global.pf_var_disabled),
            diff: global.diff_var_enabled,
            eol: if global.end_line_crlf { b"\r\n" } else { b"\n" },
            peer,
            upload: None,
        };
        Session {
            conn: Connection::new(stream),
            client,
            notice_seen: snapshot.notice_seq(),
            snapshot,
            snapshots,
            newest,
            newest_rx,
            queue: AnswerQueue::default(),
            continuation: None,
            close: false,
            stopping: false,
            diffs_deferred: false,
            over_soft_since: None,
            dropped: None,
            stats: Arc::default(),
            stop: Box::pin(section.shutdown().clone().cancelled_owned()),
            turn_used: false,
            holding: None,
            turn_now: None,
            peak: 0,
            #[cfg(feature = "fanout-trace")]
            traced: Vec::new(),
            section,
        }
    }

    /// Serves a client until it leaves, once the section is ready for it.
    pub async fn serve_client(section: Arc<Section>, stream: TcpStream, client: ClientInfo) {
        tokio::select! {
            _ = section.ready() => {}
            _ = section.shutdown().cancelled() => return,
        }
        let mut session = Session::new(section, stream, client.peer);
        session.stats = client.stats;
        if session.run().await {
            trim_memory();
        }
    }

    /// Serves the client until it leaves. Returns whether it held a lot of
    /// memory (freed by now).
    pub async fn run(mut self) -> bool {
        let section = self.section.name().to_string();
        let peer = self.client.peer;
        debug!(section = %section, client = %peer, "client connected");
        if let Err(err) = self.serve().await {
            debug!(section = %section, client = %peer, "connection error: {err}");
        }
        let held_much = self.peak >= OUTPUT_HIGH_WATER;
        if let Some(why) = &self.dropped {
            // Dropping the socket closes it (with a reset if input is
            // unread): nothing more is owed to this client.
            warn!(section = %section, client = %peer, "client disconnected: {why}");
            return held_much;
        }
        // A client that asked to close but does not read what it is owed
        // gets as long as a soft-limit stall.
        let grace = self.section.global().output_soft_timeout;
        let _ = tokio::time::timeout(grace, self.conn.flush()).await;
        let _ = self.conn.writer.shutdown().await;
        debug!(section = %section, client = %peer, "client disconnected");
        held_much
    }

    /// Output queued for the client: the unwritten buffer and the finished
    /// answers waiting behind a PLC request.
    fn queued_output(&self) -> usize {
        self.conn.backlog() + self.queue.ready_bytes()
    }

    /// Publishes the session's figures: a few relaxed stores per wake-up.
    fn report(&mut self) {
        self.peak = self.peak.max(self.ahead());
        let queued = self.queued_output() as u64;
        self.stats.queued.set(queued);
        self.stats
            .enabled
            .set(self.client.vars.enabled_total() as u64);
    }

    /// Applies OUTPUT_HARD_LIMIT and OUTPUT_SOFT_LIMIT; `Some(why)` when the
    /// client must go.
    fn check_output_limits(&mut self) -> Option<String> {
        let global = self.section.global();
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
            if std::mem::take(&mut self.turn_used) {
                // Many requests in: let other clients' tasks run first.
                tokio::task::yield_now().await;
            }
            let drained = self.take_requests();
            if self.stopping && drained {
                self.close = true;
            }
            self.release_ready();
            self.pump_stream();
            self.report();
            if let Some(why) = self.check_output_limits() {
                self.dropped = Some(why);
                return Ok(());
            }
            if (self.close || self.conn.eof) && self.queue.is_empty() {
                return Ok(());
            }
            if self.turn_used {
                // More requests wait in the input: take them after the yield.
                continue;
            }
            let head_waiting = self.queue.head_waiting();
            let held = self.held();
            let hold_deadline = self.holding;
            let streaming = self.queue.streaming();
            let write_deadline = self.write_deadline();
            let backlog = self.conn.backlog();
            let can_read = !self.conn.eof
                && !self.close
                && !self.stopping
                && self.queue.len() < MAX_PENDING
                && self.conn.input.len() < MAX_UNPARSED_INPUT
                && self.ahead() < OUTPUT_HIGH_WATER;
            // Snapshots also carry public-file changes, so every client takes
            // them, DIFF lines on or off; never inside a streamed answer.
            let want_diffs = backlog < self.section.global().output_soft_limit && !streaming;
            let closing = self.close || self.stopping;
            let soft_deadline = self
                .over_soft_since
                .map(|since| since + self.section.global().output_soft_timeout);
            let Session {
                conn,
                queue,
                snapshots,
                stop,
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
                done = queue.head_done(), if head_waiting => {
                    self.complete_head(done);
                }
                result = writer.write(&out[*written..]), if backlog > 0 && !held => {
                    let n = result?;
                    if n == 0 {
                        return Ok(());
                    }
                    if self.section.trace().on() {
                        let at = self.conn.written;
                        for line in self.conn.out[at..at + n].split_inclusive(|b| *b == b'\n') {
                            self.section.trace().client(&self.client.peer, "<-", line);
                        }
                    }
                    self.conn.advance_written(n);
                    #[cfg(feature = "fanout-trace")]
                    if self.conn.backlog() == 0 && !self.traced.is_empty() {
                        trace::written(&mut self.traced);
                    }
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
                        // The link is gone: the server is shutting down.
                        self.close = true;
                    } else {
                        self.take_snapshot();
                    }
                }
                _ = stop.as_mut(), if !closing => {
                    self.stopping = true;
                }
                _ = sleep_until(write_deadline), if write_deadline.is_some() => {
                    self.write_timeout();
                }
                // A burst held too long goes out as it is.
                _ = sleep_until(hold_deadline), if held => {}
                // Wakes the limit check when the client stays stalled.
                _ = sleep_until(soft_deadline), if soft_deadline.is_some() => {}
                else => return Ok(()),
            }
        }
    }

    /// Output this session holds or will produce for requests it took:
    /// past [`OUTPUT_HIGH_WATER`] it takes no more until the client reads,
    /// so a client that pipelines without reading holds bounded memory.
    fn ahead(&self) -> usize {
        self.conn.backlog() + self.queue.ahead()
    }

    /// Handles the complete requests already received, while the queue and
    /// output have room, at most [`REQUESTS_PER_TURN`] before other clients
    /// get a turn. Returns whether no complete request is left.
    fn take_requests(&mut self) -> bool {
        self.turn_now = Some(tokio::time::Instant::now());
        let drained = self.take_requests_now();
        self.turn_now = None;
        drained
    }

    fn take_requests_now(&mut self) -> bool {
        // Requests after a SETCONF wait for it: they may name variables of
        // the public file it loads.
        let mut budget = REQUESTS_PER_TURN;
        let mut taken = 0;
        while !self.close
            && self.queue.len() < MAX_PENDING
            && self.ahead() < OUTPUT_HIGH_WATER
            && !self.queue.conf_outstanding()
        {
            if budget == 0 {
                self.turn_used = true;
                return false;
            }
            budget -= 1;
            let Some(frame) = self.conn.next_frame() else {
                self.hold_burst(taken);
                return true;
            };
            taken += 1;
            match frame {
                Frame::Line(line) => self.handle_line(&line),
                Frame::Block { header, data } => {
                    self.section
                        .trace()
                        .client(&self.client.peer, "->", &header);
                    self.continuation = None;
                    self.dispatch(|cx, out| cmd::writefile::block(cx, &header, data, out));
                }
                Frame::TooLong(prefix) => {
                    let mut context = prefix;
                    context.extend_from_slice(b"...");
                    self.answer_error(ErrorCode::BadRequest, &context);
                }
                Frame::Close => {
                    info!(section = %self.section.name(), client = %self.client.peer, "client closed the session (Ctrl+D)");
                    self.close = true;
                }
            }
        }
        self.hold_burst(taken);
        false
    }

    /// Requests that arrived together are answered in one write once all
    /// their answers are ready: clients that read a burst's answers with a
    /// single `recv()` find them all (and the server makes one write
    /// instead of several). Bounded: until the PLC would be declared lost,
    /// or the output reaches the high-water mark. A request alone is
    /// answered as soon as it can be.
    fn hold_burst(&mut self, taken: usize) {
        if taken >= 2 && self.queue.waiting() && self.holding.is_none() {
            let config = &self.section.state().config;
            let bound = config.epstout * 2 + config.epstout_step + HOLD_MARGIN;
            self.holding = Some(tokio::time::Instant::now() + bound);
        }
    }

    /// Whether written output must wait for the rest of a burst's answers.
    fn held(&mut self) -> bool {
        if let Some(until) = self.holding {
            if !self.queue.waiting()
                || self.conn.backlog() >= OUTPUT_HIGH_WATER
                || tokio::time::Instant::now() >= until
            {
                self.holding = None;
            }
        }
        self.holding.is_some()
    }

    fn handle_line(&mut self, line: &[u8]) {
        self.section.trace().client(&self.client.peer, "->", line);
        match classify(line) {
            Line::Empty => {}
            Line::Command { command, args } => {
                self.continuation = command.accepts_continuation().then_some(command);
                self.dispatch(|cx, out| cmd::run(cx, command, args, trim(line), out));
            }
            Line::UnknownCommand => {
                self.continuation = None;
                self.answer_error(ErrorCode::UnknownCommand, trim(line));
            }
            Line::Continuation(args) => match self.continuation {
                Some(command) => {
                    let mut context = command.name().as_bytes().to_vec();
                    context.push(b':');
                    context.extend_from_slice(args);
                    self.dispatch(|cx, out| cmd::run(cx, command, args, &context, out));
                }
                None => self.answer_error(ErrorCode::UnknownCommand, trim(line)),
            },
        }
    }

    /// Runs a command and queues its answer in order: written straight to
    /// the connection when nothing waits ahead of it.
    fn dispatch(&mut self, command: impl FnOnce(&mut Cx<'_>, &mut Vec<u8>) -> Reply) {
        self.refresh_newest();
        let direct = self.queue.is_empty();
        let mut behind = Vec::new();
        let out = if direct {
            &mut self.conn.out
        } else {
            &mut behind
        };
        let mut cx = Cx {
            section: &self.section,
            client: &mut self.client,
            newest: &self.newest,
            behind_set: self.queue.set_outstanding(),
            now: self.turn_now.unwrap_or_else(tokio::time::Instant::now),
        };
        let reply = command(&mut cx, out);
        self.queue.push_ready(behind);
        match reply {
            Reply::Done => {}
            Reply::Wait(waiting) => self.queue.push_wait(waiting),
            Reply::Stream(stream) => self.queue.push_stream(stream),
        }
    }

    fn answer_error(&mut self, code: ErrorCode, context: &[u8]) {
        self.dispatch(|cx, out| cmd::error(cx, code, context, out));
    }

    /// Keeps the GETFILE answer at the head of the queue going: local blocks
    /// while output is below the high-water mark, or the next PLC request.
    fn pump_stream(&mut self) {
        loop {
            let backlog = self.conn.backlog();
            let Some(stream) = self.queue.head_stream() else {
                return;
            };
            if stream.waiting().is_some() || backlog >= OUTPUT_HIGH_WATER {
                return;
            }
            let cx = Cx {
                section: &self.section,
                client: &mut self.client,
                newest: &self.newest,
                behind_set: false,
                now: tokio::time::Instant::now(),
            };
            if !stream.advance(&cx, &mut self.conn.out, OUTPUT_HIGH_WATER - backlog) {
                return;
            }
            self.queue.pop_head();
            self.stream_done();
        }
    }

    /// A GETFILE answer ended: what waited behind it may go out.
    fn stream_done(&mut self) {
        self.release_ready();
        if self.diffs_deferred && !self.queue.set_outstanding() {
            self.diffs_deferred = false;
            self.take_snapshot();
        }
    }

    /// When the WRITEFILE transfer times out: data of a block stopped
    /// arriving, or no next block came.
    fn write_deadline(&self) -> Option<tokio::time::Instant> {
        let wait = self.section.global().ffile_timeout_wr;
        if self.conn.pending_block().is_some() {
            return Some(self.conn.last_input + wait);
        }
        self.client.upload.as_ref().map(|u| u.deadline)
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
            if self.client.upload.as_ref().is_some_and(|u| u.name == name) {
                self.client.upload = None;
            }
            return self.answer_error(ErrorCode::Unterminated, &name);
        }
        self.dispatch(|cx, out| {
            cmd::writefile::timed_out(cx, out);
            Reply::Done
        });
    }

    /// Moves answers that are complete at the head of the queue to output.
    fn release_ready(&mut self) {
        while let Some(bytes) = self.queue.pop_ready() {
            self.conn.extend(&bytes);
        }
    }

    fn complete_head(&mut self, done: HeadDone) {
        let mut out = Vec::new();
        let mut cx = Cx {
            section: &self.section,
            client: &mut self.client,
            newest: &self.newest,
            behind_set: false,
            now: tokio::time::Instant::now(),
        };
        match (self.queue.pop_head(), done) {
            (Some(Entry::Stream(mut stream)), HeadDone::Stream(reply)) => {
                if stream.on_reply(&cx, reply, &mut self.conn.out) {
                    self.stream_done();
                } else {
                    self.queue.push_front_stream(stream);
                }
                return;
            }
            (Some(Entry::Wait(waiting)), HeadDone::Wait(done)) => {
                if let Effect::Reconfigured(notice) = waiting.finish(done, &mut cx, &mut out) {
                    self.reconfigured(&notice, &mut out);
                }
            }
            _ => unreachable!("the head's completion comes from the head"),
        }
        self.conn.extend(&out);
        self.release_ready();
        if self.diffs_deferred && !self.queue.set_outstanding() && !self.queue.streaming() {
            self.diffs_deferred = false;
            self.take_snapshot();
        } else {
            self.sync_table();
        }
    }

    /// This client's SETCONF loaded a public file: from the next request on
    /// it uses the new table (the link published it before answering), and
    /// hears of every reload before this one, then this one, in the answer.
    fn reconfigured(&mut self, notice: &Notice, out: &mut Vec<u8>) {
        self.snapshot = self.snapshots.borrow().clone();
        self.sync_vars();
        self.notices_up_to(notice.seq - 1, out);
        self.notice_seen = self.notice_seen.max(notice.seq);
        cmd::setconf::write_notice(notice, out);
        out.extend_from_slice(self.client.eol);
    }

    fn take_snapshot(&mut self) {
        let snapshot = self.snapshots.borrow_and_update().clone();
        self.snapshot = snapshot;
        // An idle client must not keep an old snapshot (and the value
        // chunks changed since) alive through `newest`.
        self.refresh_newest();
        self.sync_table();
        if !self.client.diff {
            return;
        }
        if self.queue.set_outstanding() || self.queue.streaming() {
            self.diffs_deferred = true;
            return;
        }
        let Session {
            client,
            conn,
            section,
            snapshot,
            ..
        } = self;
        let before = conn.out.len();
        let lines =
            client
                .vars
                .collect_diffs(snapshot, section.format(), client.eol, &mut conn.out);
        if lines > 0 {
            #[cfg(feature = "fanout-trace")]
            if let Some(polled) = snapshot.polled {
                self.traced.push((snapshot.seq, polled.at));
            }
            section.metrics().diff_lines.add(lines as u64);
            section
                .metrics()
                .diff_bytes
                .add((conn.out.len() - before) as u64);
        }
    }

    /// Carries this client's settings over to a new table (a new public
    /// file).
    fn sync_vars(&mut self) {
        if !Arc::ptr_eq(&self.snapshot.table, self.client.vars.table()) {
            let all_enabled = !self.section.global().pf_var_disabled;
            self.client.vars = self.client.vars.remap(&self.snapshot, all_enabled);
        }
    }

    /// Follows a new public file: carries this client's settings over and
    /// tells it WARNING:250 (or 251 when only reloaded). While its own
    /// SETCONF is unanswered the SETCONF's answer does the telling.
    fn sync_table(&mut self) {
        self.sync_vars();
        if self.queue.conf_outstanding() {
            return;
        }
        let mut lines = Vec::new();
        self.notices_up_to(u64::MAX, &mut lines);
        // Between answers, like a DIFF line.
        self.conn.extend(&lines);
    }

    /// Writes the WARNING lines of the notices this client has not heard of,
    /// up to sequence `last`, oldest first.
    fn notices_up_to(&mut self, last: u64, out: &mut Vec<u8>) {
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
            out.extend_from_slice(self.client.eol);
        }
    }

    /// Brings `newest` up to date: one atomic load when nothing was
    /// published since, so a burst of GETs does not contend on the channel.
    fn refresh_newest(&mut self) {
        if self.newest_rx.has_changed() {
            self.newest = self.newest_rx.borrow_and_update().clone();
        }
    }
}
