//! The on-disk queue of one section's messages (store-and-forward): every
//! QoS 1 message is appended here before it is sent, and leaves when the
//! broker acknowledged it. While the broker is away the queue grows on disk,
//! bounded by MQTT_BUFFER: past it the oldest messages are dropped (whole
//! segments) and counted. When the broker returns, sending starts again at
//! the oldest unacknowledged message, in order.
//!
//! Layout of the folder (one per section's client id):
//!
//! ```text
//! lock                    flock()ed while a process uses the folder
//! 00000000000000000042.seg  records from sequence number 42 on
//! head                    the first unacknowledged sequence number
//! ```
//!
//! A record is `sync | len: u32 LE | crc32c(len, body): u32 LE | body`,
//! the body `seq: u64 LE | flags: u8 (bits 0-1 QoS, bit 2 retain) | topic
//! length: u16 LE | topic (UTF-8) | payload`. The sync marker ([`SYNC`])
//! lets the records after a damaged one be found again. Segments written
//! before it (records `len | crc32c(body) | body`, no marker) are still
//! read; damage in them still ends their segment.
//!
//! What survives what:
//! - the server stopping (SIGTERM) or crashing, kill -9 included: every
//!   record written (records are written to the file as each batch of
//!   changes is taken, before they are sent); `head` is saved at most a
//!   second late, so up to a second of acknowledged messages may be sent
//!   again after a crash (QoS 1 is at least once);
//! - power loss: what was written up to the last sync; the queue is synced
//!   each second while the broker is away (or behind), not while every
//!   message is acknowledged at once;
//! - a record torn by a crash in the middle of a write, or damaged on disk:
//!   found by its length and checksum when the folder is opened (logged);
//!   reading goes on at the next sync marker that starts a whole record
//!   with a later sequence number (the segment is rewritten without the
//!   damaged bytes), else the segment is cut there. The other records of
//!   the segment and the other segments stay; the sequence numbers lost are
//!   passed by when reading meets them, not waited for.
//!
//! Segments that are wholly acknowledged are deleted; when everything is
//! acknowledged the current one is deleted too once it holds 64 KiB, so
//! while the broker keeps up the files stay small and short-lived.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use nix::fcntl::{Flock, FlockArg};
use tracing::warn;

/// A message as it is published.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Message {
    pub topic: String,
    pub payload: Vec<u8>,
    /// 0 or 1.
    pub qos: u8,
    pub retain: bool,
}

/// Starts every record. As a length (the first field of a record written
/// before it) it is out of range, so the two formats never mix up.
const SYNC: [u8; 4] = [0xf1, 0x5a, 0x51, 0xa7];
/// `sync | len | crc`.
const HEADER: usize = 12;
/// `len | crc` (records without the sync marker).
const OLD_HEADER: usize = 8;
/// Body bytes before the topic: seq, flags, topic length.
const BODY_HEAD: usize = 11;
/// The largest body a record may have (far beyond any message here).
pub const MAX_BODY: usize = 16 << 20;
/// The current segment is deleted when everything is acknowledged and it
/// holds at least this much.
const ROTATE_EMPTY: u64 = 64 << 10;

const CRC32C: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);

/// Appends the record of message `seq` to `out`.
pub fn encode_record(seq: u64, message: &Message, out: &mut Vec<u8>) {
    let topic = message.topic.as_bytes();
    let topic_len = u16::try_from(topic.len()).unwrap_or(u16::MAX);
    let topic = &topic[..usize::from(topic_len)];
    let body_len = BODY_HEAD + topic.len() + message.payload.len();
    let start = out.len();
    out.extend_from_slice(&SYNC);
    out.extend_from_slice(&(body_len as u32).to_le_bytes());
    out.extend_from_slice(&[0; 4]);
    out.extend_from_slice(&seq.to_le_bytes());
    out.push((message.qos & 3) | (u8::from(message.retain) << 2));
    out.extend_from_slice(&topic_len.to_le_bytes());
    out.extend_from_slice(topic);
    out.extend_from_slice(&message.payload);
    let crc = record_crc(&out[start + 4..start + 8], &out[start + HEADER..]);
    out[start + 8..start + 12].copy_from_slice(&crc.to_le_bytes());
}

/// The checksum of a record with the sync marker: its length and body.
fn record_crc(len: &[u8], body: &[u8]) -> u32 {
    let mut digest = CRC32C.digest();
    digest.update(len);
    digest.update(body);
    digest.finalize()
}

/// Why bytes are not a record.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RecordError {
    #[error("record length {0} is out of range ({BODY_HEAD}-{MAX_BODY})")]
    Length(u32),
    #[error("record checksum does not match")]
    Checksum,
    #[error("record flags {0:#04x} are not a QoS 0/1 message")]
    Flags(u8),
    #[error("record topic length {0} runs past the record")]
    TopicLength(u16),
    #[error("record topic is not UTF-8")]
    Topic,
}

/// The record at the start of `bytes`: `Ok(None)` when `bytes` ends before
/// it does, else the sequence number, the message and the bytes it took.
pub fn decode_record(bytes: &[u8]) -> Result<Option<(u64, Message, usize)>, RecordError> {
    let synced = bytes.starts_with(&SYNC);
    if !synced && SYNC.starts_with(&bytes[..bytes.len().min(4)]) {
        // The start of a marker, or nothing.
        return Ok(None);
    }
    let (at, header_len) = if synced { (4, HEADER) } else { (0, OLD_HEADER) };
    let Some(header) = bytes.get(at..header_len) else {
        return Ok(None);
    };
    let len = u32::from_le_bytes(header[..4].try_into().unwrap_or_default());
    let body_len = len as usize;
    if !(BODY_HEAD..=MAX_BODY).contains(&body_len) {
        return Err(RecordError::Length(len));
    }
    let Some(body) = bytes.get(header_len..header_len + body_len) else {
        return Ok(None);
    };
    let crc = u32::from_le_bytes(header[4..8].try_into().unwrap_or_default());
    let computed = if synced {
        record_crc(&header[..4], body)
    } else {
        CRC32C.checksum(body)
    };
    if computed != crc {
        return Err(RecordError::Checksum);
    }
    let seq = u64::from_le_bytes(body[..8].try_into().unwrap_or_default());
    let flags = body[8];
    if flags & !7 != 0 || flags & 3 > 1 {
        return Err(RecordError::Flags(flags));
    }
    let topic_len = u16::from_le_bytes([body[9], body[10]]);
    let topic_end = BODY_HEAD + usize::from(topic_len);
    let topic = body
        .get(BODY_HEAD..topic_end)
        .ok_or(RecordError::TopicLength(topic_len))?;
    let topic = std::str::from_utf8(topic).map_err(|_| RecordError::Topic)?;
    let message = Message {
        topic: topic.to_string(),
        payload: body[topic_end..].to_vec(),
        qos: flags & 3,
        retain: flags & 4 != 0,
    };
    Ok(Some((seq, message, header_len + body_len)))
}

/// Where the next record after the damaged one at `from` starts: a sync
/// marker opening a whole record numbered `next` or later. Each candidate's
/// checksum costs its claimed length, so a segment of markers claiming long
/// bodies would cost its size squared: candidates whose number cannot be
/// next are passed by before the checksum, and the checksums of one
/// segment draw on `budget` bytes; spent, the segment is cut there.
fn resync(bytes: &[u8], from: usize, next: u64, budget: &mut usize) -> Option<usize> {
    let mut at = from + 1;
    while let Some(found) = bytes.get(at..)?.windows(SYNC.len()).position(|w| w == SYNC) {
        at += found;
        let claimed = bytes
            .get(at + 4..at + 8)
            .map_or(0, |l| u32::from_le_bytes([l[0], l[1], l[2], l[3]]) as usize);
        // A record takes at least OLD_HEADER + BODY_HEAD bytes, so no
        // number of this segment lies further ahead than its size could
        // hold: one that does is damage too.
        let seq = bytes
            .get(at + HEADER..at + HEADER + 8)
            .map(|b| u64::from_le_bytes(b.try_into().unwrap_or_default()));
        let most_ahead = (bytes.len() / (OLD_HEADER + BODY_HEAD)) as u64;
        let plausible = seq.is_some_and(|seq| seq >= next && seq - next <= most_ahead);
        if plausible && claimed <= MAX_BODY {
            *budget = budget.checked_sub(claimed)?;
            if let Ok(Some((seq, _, _))) = decode_record(&bytes[at..]) {
                if seq >= next {
                    return Some(at);
                }
            }
        }
        at += 1;
    }
    None
}

/// Bytes of checksums [`resync`] may compute for one segment: eight times
/// the largest segment, far beyond what real damage needs.
const RESYNC_BUDGET: usize = 32 << 20;
/// Problems of one segment listed in the log; the rest are counted.
const LISTED_PROBLEMS: usize = 8;

/// What opening a folder found.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Recovered {
    /// Unacknowledged messages queued from before.
    pub messages: u64,
    pub bytes: u64,
    /// Damaged or torn records cut off, with where and why.
    pub cut: Vec<String>,
}

#[derive(Debug)]
struct Segment {
    first: u64,
    /// One past the last record's sequence number.
    next: u64,
    bytes: u64,
    path: PathBuf,
}

struct Reader {
    file: BufReader<File>,
    /// Sequence number of the record the next read returns.
    next: u64,
    /// Index-free identity of the segment: its first sequence number.
    segment: u64,
    /// A record read while seeking the cursor, returned next.
    pending: Option<(u64, Message)>,
}

pub struct Spool {
    dir: PathBuf,
    _lock: Flock<File>,
    limit: u64,
    segment_limit: u64,
    segments: VecDeque<Segment>,
    writer: Option<BufWriter<File>>,
    next_seq: u64,
    /// The first unacknowledged sequence number.
    head: u64,
    /// Acknowledged sequence numbers above `head`.
    acked: BTreeSet<u64>,
    /// Sequence numbers found missing while reading (damage skipped,
    /// segments cut), start -> end (exclusive), at or above `head`: nothing
    /// will acknowledge them, so `head` passes them by.
    gaps: BTreeMap<u64, u64>,
    /// The next sequence number to send.
    cursor: u64,
    reader: Option<Reader>,
    bytes: u64,
    saved_head: u64,
    /// Written (or a segment created) since the last sync.
    unsynced: bool,
    scratch: Vec<u8>,
}

impl Spool {
    /// Opens (creating) the queue in `dir`, at most `limit` bytes, and
    /// recovers what it holds. Fails when another process holds the folder.
    pub fn open(dir: &Path, limit: u64) -> io::Result<(Spool, Recovered)> {
        fs::create_dir_all(dir)?;
        let lock_file = OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(dir.join("lock"))?;
        let lock = Flock::lock(lock_file, FlockArg::LockExclusiveNonblock).map_err(|(_, e)| {
            io::Error::new(
                io::ErrorKind::WouldBlock,
                format!(
                    "{} is in use by another process ({e}): two servers with the same MQTT client id?",
                    dir.display()
                ),
            )
        })?;
        let mut recovered = Recovered::default();
        let mut names: Vec<(u64, PathBuf)> = Vec::new();
        for entry in fs::read_dir(dir)? {
            let path = entry?.path();
            let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
                continue;
            };
            if let Some(first) = name.strip_suffix(".seg").and_then(|n| n.parse().ok()) {
                names.push((first, path));
            } else if name
                .strip_suffix(".tmp")
                .is_some_and(|n| n.parse::<u64>().is_ok())
            {
                // A segment's rewrite that a crash interrupted: the segment
                // itself is still there, whole.
                let _ = fs::remove_file(&path);
            }
        }
        names.sort();
        let mut segments = VecDeque::new();
        for (first, path) in names {
            // One segment that cannot be read (a folder of that name, say)
            // is left alone; the others are the queue.
            let segment = match recover_segment(first, path.clone(), &mut recovered) {
                Ok(segment) => segment,
                Err(e) => {
                    recovered.cut.push(format!(
                        "{} cannot be read ({e}): left as it is, its messages not sent",
                        path.display()
                    ));
                    continue;
                }
            };
            if segment.next > segment.first {
                segments.push_back(segment);
            } else {
                let _ = fs::remove_file(&segment.path);
            }
        }
        let saved = read_head(&dir.join("head"));
        let next_seq = segments
            .back()
            .map_or(saved.unwrap_or(1).max(1), |s| s.next);
        let first = segments.front().map_or(next_seq, |s| s.first);
        let head = saved.unwrap_or(first).clamp(first, next_seq);
        let bytes = segments.iter().map(|s| s.bytes).sum();
        recovered.messages = next_seq - head;
        recovered.bytes = bytes;
        let mut spool = Spool {
            dir: dir.to_path_buf(),
            _lock: lock,
            limit,
            segment_limit: (limit / 16).clamp(4 << 10, 4 << 20),
            segments,
            writer: None,
            next_seq,
            head,
            acked: BTreeSet::new(),
            gaps: BTreeMap::new(),
            cursor: head,
            reader: None,
            bytes,
            saved_head: saved.unwrap_or(0),
            unsynced: false,
            scratch: Vec::new(),
        };
        spool.release();
        Ok((spool, recovered))
    }

    /// Unacknowledged messages.
    pub fn len(&self) -> u64 {
        let missing: u64 = self.gaps.iter().map(|(start, end)| end - start).sum();
        (self.next_seq - self.head - self.acked.len() as u64).saturating_sub(missing)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes on disk.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Whether messages are waiting to be sent.
    pub fn has_unsent(&self) -> bool {
        self.cursor < self.next_seq
    }

    /// Appends `messages`; returns how many unacknowledged messages were
    /// dropped (the oldest) to stay within the limit.
    pub fn push(&mut self, messages: &[Message]) -> io::Result<u64> {
        if messages.is_empty() {
            return Ok(0);
        }
        for message in messages {
            let full = self
                .segments
                .back()
                .is_none_or(|s| s.bytes >= self.segment_limit);
            if self.writer.is_none() || full {
                self.start_segment()?;
            }
            self.scratch.clear();
            encode_record(self.next_seq, message, &mut self.scratch);
            let n = self.scratch.len() as u64;
            if let Some(writer) = self.writer.as_mut() {
                writer.write_all(&self.scratch)?;
            }
            if let Some(segment) = self.segments.back_mut() {
                segment.bytes += n;
                segment.next = self.next_seq + 1;
            }
            self.bytes += n;
            self.next_seq += 1;
        }
        if let Some(writer) = self.writer.as_mut() {
            writer.flush()?;
        }
        self.unsynced = true;
        Ok(self.enforce_limit())
    }

    fn start_segment(&mut self) -> io::Result<()> {
        if let Some(mut writer) = self.writer.take() {
            writer.flush()?;
        }
        let path = self.dir.join(format!("{:020}.seg", self.next_seq));
        let file = OpenOptions::new()
            .create(true)
            .truncate(true)
            .write(true)
            .open(&path)?;
        self.segments.push_back(Segment {
            first: self.next_seq,
            next: self.next_seq,
            bytes: 0,
            path,
        });
        self.writer = Some(BufWriter::with_capacity(64 << 10, file));
        Ok(())
    }

    /// Drops the oldest segments while over the limit; returns the
    /// unacknowledged messages they held.
    fn enforce_limit(&mut self) -> u64 {
        let mut dropped = 0;
        while self.bytes > self.limit && self.segments.len() > 1 {
            let Some(segment) = self.segments.pop_front() else {
                break;
            };
            let _ = fs::remove_file(&segment.path);
            self.bytes -= segment.bytes;
            let from = self.head.max(segment.first);
            if segment.next > from {
                let acked = self.acked.range(from..segment.next).count() as u64;
                dropped += segment.next - from - acked;
            }
            self.set_head(self.segments.front().map_or(self.next_seq, |s| s.first));
        }
        dropped
    }

    fn set_head(&mut self, head: u64) {
        if head > self.head {
            self.head = head;
            self.acked = self.acked.split_off(&head);
        }
        loop {
            if self.acked.remove(&self.head) {
                self.head += 1;
            } else if let Some(&end) = self.gaps.get(&self.head) {
                self.head = end;
            } else {
                break;
            }
        }
        if self
            .gaps
            .keys()
            .next()
            .is_some_and(|&start| start < self.head)
        {
            self.gaps = self.gaps.split_off(&self.head);
        }
        if self.cursor < self.head {
            self.cursor = self.head;
            self.reader = None;
        }
    }

    /// The next message to send, if any, with its sequence number.
    pub fn next_unsent(&mut self) -> io::Result<Option<(u64, Message)>> {
        while self.cursor < self.next_seq {
            let reader = match self.reader.take() {
                Some(reader) if reader.next == self.cursor => reader,
                _ => match self.open_reader()? {
                    Some(reader) => reader,
                    None => return Ok(None),
                },
            };
            match self.read_record(reader)? {
                Step::Found(seq, message) => return Ok(Some((seq, message))),
                Step::Wait => return Ok(None),
                Step::Next => continue,
            }
        }
        Ok(None)
    }

    /// A reader positioned at the cursor (moved past a gap if need be).
    fn open_reader(&mut self) -> io::Result<Option<Reader>> {
        let Some(segment) = self
            .segments
            .iter()
            .rev()
            .find(|s| s.first <= self.cursor)
            .or_else(|| self.segments.front())
            .map(|s| (s.first, s.path.clone()))
        else {
            return Ok(None);
        };
        let (first, path) = segment;
        if self.cursor < first {
            self.missing(self.cursor, first);
            self.cursor = first;
        }
        let mut reader = Reader {
            file: BufReader::with_capacity(64 << 10, File::open(&path)?),
            next: first,
            segment: first,
            pending: None,
        };
        // By sequence number: a segment may have gaps (damage skipped).
        let target = self.cursor;
        let mut raw = Vec::new();
        while reader.next < target {
            if read_raw(&mut reader.file, &mut raw)?.is_none() {
                break;
            }
            match decode_record(&raw) {
                Ok(Some((seq, message, _))) if seq >= target => {
                    reader.pending = Some((seq, message));
                    break;
                }
                Ok(Some((seq, _, _))) => reader.next = seq + 1,
                // Damage: reading at the cursor meets what follows it.
                _ => break,
            }
        }
        Ok(Some(reader))
    }

    /// Reads the record at the reader.
    fn read_record(&mut self, mut reader: Reader) -> io::Result<Step> {
        let mut raw = Vec::new();
        let decoded = match reader.pending.take() {
            Some((seq, message)) => Ok(Some((seq, message, 0))),
            None => match read_raw(&mut reader.file, &mut raw)? {
                Some(()) => decode_record(&raw),
                None => Ok(None),
            },
        };
        let later = self
            .segments
            .iter()
            .find(|s| s.first > reader.segment)
            .map(|s| s.first);
        match decoded {
            Ok(Some((seq, message, _))) if seq >= self.cursor => {
                self.missing(self.cursor, seq);
                self.cursor = seq + 1;
                reader.next = seq + 1;
                self.reader = Some(reader);
                Ok(Step::Found(seq, message))
            }
            // The end of what was written: wait for more, or go on to the
            // next segment.
            Ok(None) => match later {
                Some(first) => {
                    self.missing(self.cursor, first);
                    self.cursor = self.cursor.max(first);
                    Ok(Step::Next)
                }
                None => {
                    self.reader = Some(reader);
                    Ok(Step::Wait)
                }
            },
            damaged => {
                let problem = match damaged {
                    Err(e) => e.to_string(),
                    _ => "a sequence number out of order".to_string(),
                };
                warn!(spool = %self.dir.display(), "damaged record at {}: {problem}; skipping the rest of its segment", self.cursor);
                let resume = later.unwrap_or(self.next_seq).max(self.cursor);
                self.missing(self.cursor, resume);
                self.cursor = resume;
                Ok(Step::Next)
            }
        }
    }

    /// Notes `from..to` as missing (read past) and moves `head` past them
    /// if it reached them.
    fn missing(&mut self, from: u64, to: u64) {
        let from = from.max(self.head);
        if from < to {
            let end = self.gaps.entry(from).or_insert(to);
            *end = (*end).max(to);
            // Counted once, as missing.
            let inside: Vec<u64> = self.acked.range(from..to).copied().collect();
            for seq in inside {
                self.acked.remove(&seq);
            }
            self.set_head(self.head);
        }
    }

    /// Marks `seq` acknowledged by the broker.
    pub fn ack(&mut self, seq: u64) {
        if seq < self.head || seq >= self.next_seq {
            return;
        }
        self.acked.insert(seq);
        self.set_head(self.head);
        self.release();
    }

    /// Deletes wholly acknowledged segments.
    fn release(&mut self) {
        while self.segments.len() > 1 && self.segments[0].next <= self.head {
            if let Some(segment) = self.segments.pop_front() {
                let _ = fs::remove_file(&segment.path);
                self.bytes -= segment.bytes;
            }
        }
        let drained = self.head == self.next_seq;
        if drained && self.segments.len() == 1 && self.segments[0].bytes >= ROTATE_EMPTY {
            if let Some(segment) = self.segments.pop_front() {
                self.writer = None;
                self.reader = None;
                let _ = fs::remove_file(&segment.path);
                self.bytes -= segment.bytes;
            }
        }
    }

    /// Sending starts again at the oldest unacknowledged message (a new
    /// connection).
    pub fn rewind(&mut self) {
        self.cursor = self.head;
        self.reader = None;
    }

    /// Saves `head` if it moved, and syncs what was written if `durable`.
    pub fn checkpoint(&mut self, durable: bool) -> io::Result<()> {
        if durable && self.unsynced {
            if let Some(writer) = self.writer.as_mut() {
                writer.flush()?;
                writer.get_ref().sync_data()?;
            }
            File::open(&self.dir)?.sync_all()?;
            self.unsynced = false;
        }
        if self.head != self.saved_head {
            let tmp = self.dir.join("head.tmp");
            let mut bytes = self.head.to_le_bytes().to_vec();
            bytes.extend_from_slice(&CRC32C.checksum(&bytes).to_le_bytes());
            fs::write(&tmp, &bytes)?;
            fs::rename(&tmp, self.dir.join("head"))?;
            self.saved_head = self.head;
        }
        Ok(())
    }
}

/// What reading at the cursor found.
enum Step {
    Found(u64, Message),
    /// Nothing more written yet.
    Wait,
    /// The segment is done: read on at the (moved) cursor.
    Next,
}

/// Reads one record's bytes (header and body) into `out`; `None` at the end
/// of the file or of what was written whole.
fn read_raw(file: &mut impl Read, out: &mut Vec<u8>) -> io::Result<Option<()>> {
    out.clear();
    out.resize(OLD_HEADER, 0);
    if !read_full(file, &mut out[..])? {
        return Ok(None);
    }
    let header_len = if out.starts_with(&SYNC) {
        out.resize(HEADER, 0);
        if !read_full(file, &mut out[OLD_HEADER..])? {
            return Ok(None);
        }
        HEADER
    } else {
        OLD_HEADER
    };
    let at = header_len - OLD_HEADER;
    let len = u32::from_le_bytes([out[at], out[at + 1], out[at + 2], out[at + 3]]) as usize;
    if !(BODY_HEAD..=MAX_BODY).contains(&len) {
        // Let the decoder name the problem.
        return Ok(Some(()));
    }
    out.resize(header_len + len, 0);
    if !read_full(file, &mut out[header_len..])? {
        return Ok(None);
    }
    Ok(Some(()))
}

/// `read_exact` that says `false` at end of file instead of failing.
fn read_full(file: &mut impl Read, buf: &mut [u8]) -> io::Result<bool> {
    let mut done = 0;
    while done < buf.len() {
        match file.read(&mut buf[done..]) {
            Ok(0) => return Ok(false),
            Ok(n) => done += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(true)
}

/// Checks a segment's records. Damaged bytes are skipped up to the next
/// record found again ([`resync`]), the segment rewritten without them;
/// with no record after them, it is cut there.
fn recover_segment(first: u64, path: PathBuf, recovered: &mut Recovered) -> io::Result<Segment> {
    let bytes = fs::read(&path)?;
    let mut kept: Vec<std::ops::Range<usize>> = Vec::new();
    let mut at = 0;
    let mut next = first;
    let mut problems = Vec::new();
    let mut budget = RESYNC_BUDGET;
    while at < bytes.len() {
        let problem = match decode_record(&bytes[at..]) {
            // Past a skip, or in a segment with gaps, numbers may jump.
            Ok(Some((seq, _, used)))
                if seq == next || (seq > next && bytes[at..].starts_with(&SYNC)) =>
            {
                kept.push(at..at + used);
                at += used;
                next = seq + 1;
                continue;
            }
            Ok(Some((seq, _, _))) => format!("sequence {seq} where {next} was due"),
            Ok(None) => "a record torn at the end".to_string(),
            Err(e) => e.to_string(),
        };
        match resync(&bytes, at, next, &mut budget) {
            Some(found) => {
                problems.push(format!("bytes {at}-{found} skipped ({problem})"));
                at = found;
            }
            None => {
                problems.push(format!("cut at byte {at} ({problem})"));
                break;
            }
        }
    }
    let size: usize = kept.iter().map(|r| r.len()).sum();
    if !problems.is_empty() {
        let unlisted = problems.len().saturating_sub(LISTED_PROBLEMS);
        problems.truncate(LISTED_PROBLEMS);
        if unlisted > 0 {
            problems.push(format!("{unlisted} more"));
        }
        recovered.cut.push(format!(
            "{} ({} bytes): {}; {size} bytes of whole records kept",
            path.display(),
            bytes.len(),
            problems.join(", ")
        ));
        let contiguous = kept.last().is_none_or(|r| r.end == size);
        if contiguous {
            let file = OpenOptions::new().write(true).open(&path)?;
            file.set_len(size as u64)?;
            file.sync_all()?;
        } else {
            // Written whole under another name, then renamed over it: a
            // crash leaves either the old segment or the new one.
            let tmp = path.with_extension("tmp");
            let mut out = Vec::with_capacity(size);
            for range in &kept {
                out.extend_from_slice(&bytes[range.clone()]);
            }
            let mut file = File::create(&tmp)?;
            file.write_all(&out)?;
            file.sync_all()?;
            fs::rename(&tmp, &path)?;
        }
    }
    Ok(Segment {
        first,
        next,
        bytes: size as u64,
        path,
    })
}

fn read_head(path: &Path) -> Option<u64> {
    let bytes = fs::read(path).ok()?;
    let (seq, crc) = (bytes.get(..8)?, bytes.get(8..12)?);
    let seq: [u8; 8] = seq.try_into().ok()?;
    (CRC32C.checksum(&seq).to_le_bytes() == crc).then(|| u64::from_le_bytes(seq))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(i: u64) -> Message {
        Message {
            topic: format!("p/S/V{}", i % 7),
            payload: i.to_string().into_bytes(),
            qos: 1,
            retain: i & 1 == 0,
        }
    }

    fn drain(spool: &mut Spool) -> Vec<u64> {
        let mut seen = Vec::new();
        while let Some((seq, m)) = spool.next_unsent().unwrap() {
            assert_eq!(m, message(seq));
            seen.push(seq);
        }
        seen
    }

    #[test]
    fn records_round_trip_and_reject_damage() {
        let mut out = Vec::new();
        encode_record(7, &message(7), &mut out);
        let (seq, m, used) = decode_record(&out).unwrap().unwrap();
        assert_eq!((seq, m, used), (7, message(7), out.len()));
        assert_eq!(decode_record(&out[..out.len() - 1]), Ok(None));
        assert_eq!(decode_record(&out[..3]), Ok(None));
        let mut bad = out.clone();
        *bad.last_mut().unwrap() ^= 1;
        assert_eq!(decode_record(&bad), Err(RecordError::Checksum));
        assert_eq!(
            decode_record(&[0xff, 0xff, 0xff, 0xff, 0, 0, 0, 0]),
            Err(RecordError::Length(u32::MAX))
        );
    }

    #[test]
    fn sends_in_order_acks_and_reopens_with_what_is_unacknowledged() {
        let dir = tempfile::tempdir().unwrap();
        let messages: Vec<Message> = (1..=100).map(message).collect();
        {
            let (mut spool, recovered) = Spool::open(dir.path(), 1 << 20).unwrap();
            assert_eq!(recovered, Recovered::default());
            assert_eq!(spool.push(&messages).unwrap(), 0);
            assert_eq!(drain(&mut spool), (1..=100).collect::<Vec<_>>());
            for seq in 1..=40 {
                spool.ack(seq);
            }
            // Out of order: 42 before 41.
            spool.ack(42);
            assert_eq!(spool.len(), 59);
            spool.ack(41);
            assert_eq!(spool.len(), 58);
            // A new connection sends again from the first unacknowledged.
            spool.rewind();
            assert_eq!(drain(&mut spool), (43..=100).collect::<Vec<_>>());
            spool.checkpoint(true).unwrap();
            // Another process cannot take the folder.
            assert!(Spool::open(dir.path(), 1 << 20).is_err());
        }
        let (mut spool, recovered) = Spool::open(dir.path(), 1 << 20).unwrap();
        assert_eq!(recovered.messages, 58);
        assert_eq!(drain(&mut spool), (43..=100).collect::<Vec<_>>());
        spool.push(&[message(101)]).unwrap();
        assert_eq!(drain(&mut spool), [101]);
        for seq in 43..=101 {
            spool.ack(seq);
        }
        assert!(spool.is_empty());
    }

    #[test]
    fn a_torn_tail_is_cut_and_the_rest_kept() {
        let dir = tempfile::tempdir().unwrap();
        {
            let (mut spool, _) = Spool::open(dir.path(), 1 << 20).unwrap();
            spool
                .push(&(1..=10).map(message).collect::<Vec<_>>())
                .unwrap();
        }
        let seg = dir.path().join(format!("{:020}.seg", 1));
        let len = fs::metadata(&seg).unwrap().len();
        OpenOptions::new()
            .write(true)
            .open(&seg)
            .unwrap()
            .set_len(len - 3)
            .unwrap();
        let (mut spool, recovered) = Spool::open(dir.path(), 1 << 20).unwrap();
        assert_eq!(recovered.messages, 9);
        assert_eq!(recovered.cut.len(), 1, "{:?}", recovered.cut);
        assert!(recovered.cut[0].contains("torn"), "{:?}", recovered.cut);
        assert_eq!(drain(&mut spool), (1..=9).collect::<Vec<_>>());
        spool.push(&[message(10)]).unwrap();
        assert_eq!(drain(&mut spool), [10]);
    }

    #[test]
    fn over_the_limit_the_oldest_are_dropped_and_counted() {
        let dir = tempfile::tempdir().unwrap();
        // 64 KiB: segments of 4 KiB.
        let (mut spool, _) = Spool::open(dir.path(), 64 << 10).unwrap();
        let mut dropped = 0;
        for chunk in (1..=5000).collect::<Vec<u64>>().chunks(100) {
            let batch: Vec<Message> = chunk.iter().map(|&i| message(i)).collect();
            dropped += spool.push(&batch).unwrap();
        }
        assert!(spool.bytes() <= 64 << 10, "{}", spool.bytes());
        assert!(dropped > 0);
        assert_eq!(spool.len() + dropped, 5000);
        let seen = drain(&mut spool);
        assert_eq!(seen.len() as u64, spool.len());
        assert_eq!(*seen.last().unwrap(), 5000);
        assert!(seen.windows(2).all(|w| w[1] == w[0] + 1));
    }

    #[test]
    fn acknowledged_segments_are_deleted() {
        let dir = tempfile::tempdir().unwrap();
        let (mut spool, _) = Spool::open(dir.path(), 1 << 20).unwrap();
        for round in 0..50u64 {
            let batch: Vec<Message> = (round * 100 + 1..=round * 100 + 100).map(message).collect();
            spool.push(&batch).unwrap();
            while let Some((seq, _)) = spool.next_unsent().unwrap() {
                spool.ack(seq);
            }
        }
        assert!(spool.is_empty());
        let files = fs::read_dir(dir.path()).unwrap().count();
        assert!(files <= 3, "{files} files left");
        assert!(spool.bytes() < ROTATE_EMPTY + (64 << 10));
    }

    /// Fills a queue of several segments (4 KiB each) with messages
    /// 1..=300, none acknowledged, and closes it.
    fn three_hundred(dir: &Path) -> Vec<PathBuf> {
        let (mut spool, _) = Spool::open(dir, 64 << 10).unwrap();
        for chunk in (1..=300).collect::<Vec<u64>>().chunks(10) {
            let batch: Vec<Message> = chunk.iter().map(|&i| message(i)).collect();
            spool.push(&batch).unwrap();
        }
        spool.checkpoint(true).unwrap();
        drop(spool);
        let mut segments: Vec<PathBuf> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "seg"))
            .collect();
        segments.sort();
        segments
    }

    #[test]
    fn a_flipped_bit_loses_one_record_not_the_rest_of_its_segment() {
        let dir = tempfile::tempdir().unwrap();
        let segments = three_hundred(dir.path());
        assert!(segments.len() >= 3, "{segments:?}");
        // One bit in the first segment's third record, and one in the
        // length of the second segment's first record.
        for (segment, at) in [(&segments[0], 2 * 30 + 20), (&segments[1], 1)] {
            let mut bytes = fs::read(segment).unwrap();
            bytes[at] ^= 0x10;
            fs::write(segment, bytes).unwrap();
        }
        let (mut spool, recovered) = Spool::open(dir.path(), 64 << 10).unwrap();
        assert_eq!(recovered.cut.len(), 2, "{:?}", recovered.cut);
        let seen = drain(&mut spool);
        assert!(seen.len() >= 296, "{} of 300 left", seen.len());
        assert!(seen.windows(2).all(|w| w[1] > w[0]));
        assert_eq!(seen.last(), Some(&300));
        // And once more: what was rewritten reads back the same.
        drop(spool);
        let (mut spool, recovered) = Spool::open(dir.path(), 64 << 10).unwrap();
        assert!(recovered.cut.is_empty(), "{:?}", recovered.cut);
        assert_eq!(drain(&mut spool), seen);
        // The lost ones are not waited for: acknowledging what was sent
        // empties the queue, and its files go.
        assert_eq!(spool.len(), seen.len() as u64);
        for &seq in &seen {
            spool.ack(seq);
        }
        assert!(spool.is_empty(), "{} left", spool.len());
        spool.push(&[message(301)]).unwrap();
        spool.rewind();
        assert_eq!(drain(&mut spool), [301]);
    }

    /// A segment of sync markers each claiming a body to its end would cost
    /// its size squared in checksums: the work is bounded and the segment
    /// cut, the records before the damage kept, the log line short.
    #[test]
    fn a_segment_of_false_markers_is_cut_with_bounded_work() {
        let dir = tempfile::tempdir().unwrap();
        let mut bytes = Vec::new();
        encode_record(0, &message(0), &mut bytes);
        let whole = bytes.len();
        bytes.extend_from_slice(b"junk");
        let false_markers = 200_000;
        let total = bytes.len() + false_markers * 24;
        while bytes.len() < total {
            let at = bytes.len();
            bytes.extend_from_slice(&SYNC);
            let claimed = (total - at - HEADER) as u32;
            bytes.extend_from_slice(&claimed.to_le_bytes());
            bytes.extend_from_slice(&[0; 4]);
            // A plausible number: the cheap checks pass, the checksum fails.
            bytes.extend_from_slice(&1u64.to_le_bytes());
            bytes.extend_from_slice(&[0; 4]);
        }
        let path = dir.path().join("00000000000000000000.seg");
        fs::write(&path, &bytes).unwrap();
        let mut recovered = Recovered::default();
        let segment = recover_segment(0, path, &mut recovered).unwrap();
        assert_eq!((segment.next, segment.bytes), (1, whole as u64));
        assert_eq!(recovered.cut.len(), 1);
        assert!(recovered.cut[0].len() < 1024, "{}", recovered.cut[0]);
    }

    #[test]
    fn empty_truncated_or_foreign_segments_leave_the_others() {
        for case in [
            "empty",
            "truncated",
            "foreign",
            "empty-last",
            "foreign-last",
            "folder",
        ] {
            let dir = tempfile::tempdir().unwrap();
            let segments = three_hundred(dir.path());
            let middle = &segments[1];
            let last = dir.path().join(format!("{:020}.seg", 1_000_000));
            match case {
                "empty" => fs::write(middle, b"").unwrap(),
                "truncated" => {
                    let len = fs::metadata(middle).unwrap().len();
                    OpenOptions::new()
                        .write(true)
                        .open(middle)
                        .unwrap()
                        .set_len(len / 2)
                        .unwrap()
                }
                "foreign" => fs::write(middle, vec![0x5a; 3000]).unwrap(),
                "empty-last" => fs::write(&last, b"").unwrap(),
                "folder" => fs::create_dir(&last).unwrap(),
                _ => fs::write(&last, vec![0x5a; 3000]).unwrap(),
            }
            let (mut spool, _) = Spool::open(dir.path(), 64 << 10).unwrap();
            let seen = drain(&mut spool);
            let first_of_third: u64 = segments[2]
                .file_stem()
                .unwrap()
                .to_str()
                .unwrap()
                .parse()
                .unwrap();
            assert!(seen.contains(&1), "{case}: {seen:?}");
            assert!(seen.contains(&first_of_third), "{case}: {seen:?}");
            assert_eq!(seen.last(), Some(&300), "{case}");
            // New messages follow the old ones.
            spool.push(&[message(1_000_001)]).unwrap_or_default();
        }
    }

    #[test]
    fn segments_written_before_the_sync_marker_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let mut old = Vec::new();
        for seq in 1..=5 {
            let mut record = Vec::new();
            encode_record(seq, &message(seq), &mut record);
            // The same record without the marker, its checksum over the body.
            let body = &record[HEADER..];
            old.extend_from_slice(&record[4..8]);
            old.extend_from_slice(&CRC32C.checksum(body).to_le_bytes());
            old.extend_from_slice(body);
        }
        fs::write(dir.path().join(format!("{:020}.seg", 1)), &old).unwrap();
        let (mut spool, recovered) = Spool::open(dir.path(), 1 << 20).unwrap();
        assert_eq!((recovered.messages, recovered.cut.len()), (5, 0));
        spool.push(&[message(6)]).unwrap();
        assert_eq!(drain(&mut spool), (1..=6).collect::<Vec<_>>());
    }
}
