//! Input framing of a client connection, without I/O: bytes in, [`Frame`]s
//! out. The server wraps [`Decoder`] in a tokio-util codec.
//!
//! - Lines end in `\n`, `\r\n` or telnet's `\r\0`. Every `\r` and NUL is
//!   dropped from a line, so neither leaks into a name or an error text.
//! - Telnet IAC sequences are skipped, also when split across reads; `IAC IAC`
//!   is a literal 0xFF.
//! - Ctrl+D (0x04) on an empty line closes the session; elsewhere it is dropped.
//! - `WRITEFILE:name[n]=` and `WRITEFILEINFO:name[n]=` switch to raw mode for
//!   exactly `n` bytes of binary data, then an optional line end.
//! - A line over `max_line` bytes or a block over `max_block` bytes gives one
//!   [`Frame::TooLong`] and is skipped. The decoder holds at most
//!   `max_line + max_block` bytes plus a constant, whatever the client sends.

use bytes::{Buf, BytesMut};

use crate::request::{block_len_value, classify, Command, Line};

/// How many bytes of an over-long line [`Frame::TooLong`] carries.
pub const TOO_LONG_PREFIX: usize = 64;
/// Longest telnet subnegotiation skipped; past it the bytes count as data
/// again, so a stray `IAC SB` cannot swallow the session.
const MAX_SUBNEGOTIATION: usize = 512;

const IAC: u8 = 0xFF;
const SB: u8 = 250;
const SE: u8 = 240;
const WILL: u8 = 251;
const DONT: u8 = 254;
const CTRL_D: u8 = 0x04;

/// Bytes that end the plain fast path of [`Decoder::decode`].
const SPECIAL: [bool; 256] = {
    let mut table = [false; 256];
    let mut i = 0;
    let special = [b'\n', b'\r', 0, CTRL_D, IAC, b'='];
    while i < special.len() {
        table[special[i] as usize] = true;
        i += 1;
    }
    table
};

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Frame {
    /// One line without its line end, `\r` and NUL removed. May be empty.
    Line(Vec<u8>),
    /// A `WRITEFILE:`/`WRITEFILEINFO:` block: the header up to and including
    /// `]=` in the client's case, and exactly the `n` raw bytes.
    Block { header: Vec<u8>, data: Vec<u8> },
    /// A line or block over the limit: its first bytes, for the error text.
    /// The rest of it is discarded.
    TooLong(Vec<u8>),
    /// Ctrl+D on an empty line: the client ends the session.
    Close,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Telnet {
    Data,
    /// After IAC.
    Iac,
    /// After IAC WILL/WONT/DO/DONT: the option byte follows.
    Option,
    /// Inside IAC SB ... IAC SE; bytes skipped so far.
    Sub(usize),
    /// IAC inside a subnegotiation.
    SubIac(usize),
}

#[derive(Debug)]
enum Mode {
    /// Collecting a line.
    Line,
    /// Skipping the rest of an over-long line, up to its line end.
    Discard,
    /// Raw block data: `remaining` bytes still to come.
    Block {
        header: Vec<u8>,
        data: Vec<u8>,
        remaining: usize,
    },
    /// Skipping the raw data of an over-long block.
    SkipBlock { remaining: usize },
    /// After block data: an optional `\n` or `\r\n` follows.
    BlockEnd,
    /// After block data and a `\r`.
    BlockEndCr,
}

/// Incremental input framing for one client connection.
#[derive(Debug)]
pub struct Decoder {
    max_line: usize,
    max_block: usize,
    line: Vec<u8>,
    mode: Mode,
    telnet: Telnet,
    /// The previous data byte was `\r` (which may start `\r\n` or `\r\0`).
    after_cr: bool,
}

/// What one data byte (telnet removed) did to the line.
enum Step {
    Continue,
    Frame(Frame),
}

impl Decoder {
    pub fn new(max_line: usize, max_block: usize) -> Decoder {
        Decoder {
            max_line,
            max_block,
            line: Vec::new(),
            mode: Mode::Line,
            telnet: Telnet::Data,
            after_cr: false,
        }
    }

    /// The header of a `WRITEFILE`/`WRITEFILEINFO` block whose data is still
    /// arriving, if any (for the unterminated-data timeout).
    pub fn pending_block(&self) -> Option<&[u8]> {
        match &self.mode {
            Mode::Block { header, .. } => Some(header),
            _ => None,
        }
    }

    /// Drops a block whose data is still arriving and goes back to line
    /// mode: what the client sends next is read as requests again.
    pub fn abandon_block(&mut self) {
        if matches!(self.mode, Mode::Block { .. } | Mode::SkipBlock { .. }) {
            self.mode = Mode::Line;
            self.after_cr = false;
        }
    }

    /// The next frame, consuming from `src` what it scanned; `None` when
    /// `src` holds no complete frame (all of it is then consumed and kept
    /// in the decoder's bounded state).
    pub fn decode(&mut self, src: &mut BytesMut) -> Option<Frame> {
        if let Some(frame) = self.plain_line(src) {
            return Some(frame);
        }
        loop {
            match &mut self.mode {
                Mode::Block {
                    data, remaining, ..
                } => {
                    let take = (*remaining).min(src.len());
                    data.extend_from_slice(&src[..take]);
                    src.advance(take);
                    *remaining -= take;
                    if *remaining > 0 {
                        return None;
                    }
                    let Mode::Block { header, data, .. } =
                        std::mem::replace(&mut self.mode, Mode::BlockEnd)
                    else {
                        unreachable!("matched Mode::Block above")
                    };
                    return Some(Frame::Block { header, data });
                }
                Mode::SkipBlock { remaining } => {
                    let take = (*remaining).min(src.len());
                    src.advance(take);
                    *remaining -= take;
                    if *remaining > 0 {
                        return None;
                    }
                    self.mode = Mode::BlockEnd;
                }
                Mode::BlockEnd => match src.first() {
                    None => return None,
                    Some(b'\n') => {
                        src.advance(1);
                        self.mode = Mode::Line;
                    }
                    Some(b'\r') => {
                        src.advance(1);
                        self.mode = Mode::BlockEndCr;
                    }
                    Some(_) => self.mode = Mode::Line,
                },
                Mode::BlockEndCr => match src.first() {
                    None => return None,
                    Some(b'\n' | 0) => {
                        src.advance(1);
                        self.mode = Mode::Line;
                    }
                    // A lone `\r` is dropped, as in any line.
                    Some(_) => self.mode = Mode::Line,
                },
                Mode::Line | Mode::Discard => {
                    let mut used = 0;
                    let mut frame = None;
                    for &byte in src.iter() {
                        used += 1;
                        let Some(data) = self.telnet(byte) else {
                            continue;
                        };
                        if let Step::Frame(f) = self.data_byte(data) {
                            frame = Some(f);
                            break;
                        }
                        if matches!(self.mode, Mode::Block { .. } | Mode::SkipBlock { .. }) {
                            break;
                        }
                    }
                    src.advance(used);
                    if frame.is_some() {
                        return frame;
                    }
                    if matches!(self.mode, Mode::Line | Mode::Discard) {
                        return None;
                    }
                }
            }
        }
    }

    /// The common case at a fraction of the cost: a whole line of plain bytes
    /// (no telnet, NUL, Ctrl+D, `=` or lone `\r`) ending in `\n` or
    /// `\r\n`, at the start of a line. Anything else goes byte by byte.
    fn plain_line(&mut self, src: &mut BytesMut) -> Option<Frame> {
        if !matches!(self.mode, Mode::Line)
            || self.telnet != Telnet::Data
            || self.after_cr
            || !self.line.is_empty()
        {
            return None;
        }
        let end = src.iter().position(|&b| SPECIAL[b as usize])?;
        let skip = match (src[end], src.get(end + 1)) {
            (b'\n', _) => 1,
            (b'\r', Some(b'\n')) => 2,
            _ => return None,
        };
        if end > self.max_line {
            return None;
        }
        let line = src[..end].to_vec();
        src.advance(end + skip);
        Some(Frame::Line(line))
    }

    /// Runs one byte through the telnet filter: the data byte, if any.
    fn telnet(&mut self, byte: u8) -> Option<u8> {
        let (next, data) = match (self.telnet, byte) {
            (Telnet::Data, IAC) => (Telnet::Iac, None),
            (Telnet::Data, b) => (Telnet::Data, Some(b)),
            (Telnet::Iac, IAC) => (Telnet::Data, Some(IAC)),
            (Telnet::Iac, WILL..=DONT) => (Telnet::Option, None),
            (Telnet::Iac, SB) => (Telnet::Sub(0), None),
            (Telnet::Iac, _) => (Telnet::Data, None),
            (Telnet::Option, _) => (Telnet::Data, None),
            (Telnet::Sub(n), _) if n >= MAX_SUBNEGOTIATION => (Telnet::Data, Some(byte)),
            (Telnet::Sub(n), IAC) => (Telnet::SubIac(n + 1), None),
            (Telnet::Sub(n), _) => (Telnet::Sub(n + 1), None),
            (Telnet::SubIac(_), SE) => (Telnet::Data, None),
            (Telnet::SubIac(n), _) => (Telnet::Sub(n + 1), None),
        };
        self.telnet = next;
        data
    }

    /// Handles one data byte in line or discard mode.
    fn data_byte(&mut self, byte: u8) -> Step {
        if std::mem::take(&mut self.after_cr) && byte == 0 {
            return self.end_of_line();
        }
        match byte {
            b'\n' => self.end_of_line(),
            b'\r' => {
                self.after_cr = true;
                Step::Continue
            }
            0 => Step::Continue,
            CTRL_D => {
                if matches!(self.mode, Mode::Line) && self.line.is_empty() {
                    Step::Frame(Frame::Close)
                } else {
                    Step::Continue
                }
            }
            _ if matches!(self.mode, Mode::Discard) => Step::Continue,
            _ if self.line.len() >= self.max_line => {
                let prefix = self.line[..self.line.len().min(TOO_LONG_PREFIX)].to_vec();
                self.line = Vec::new();
                self.mode = Mode::Discard;
                Step::Frame(Frame::TooLong(prefix))
            }
            _ => {
                self.line.push(byte);
                if byte == b'=' {
                    return self.check_block_start();
                }
                Step::Continue
            }
        }
    }

    fn end_of_line(&mut self) -> Step {
        self.after_cr = false;
        match self.mode {
            Mode::Discard => {
                self.mode = Mode::Line;
                Step::Continue
            }
            _ => {
                // One exact-size allocation per line; the buffer is reused
                // unless a long line grew it.
                let line = self.line.clone();
                if self.line.capacity() > 1024 {
                    self.line = Vec::new();
                } else {
                    self.line.clear();
                }
                Step::Frame(Frame::Line(line))
            }
        }
    }

    /// After an `=`: if the line is `WRITEFILE:...[<digits>]=` (or
    /// WRITEFILEINFO), switch to raw block data.
    fn check_block_start(&mut self) -> Step {
        let line = &self.line;
        let Some(before) = line.strip_suffix(b"]=") else {
            return Step::Continue;
        };
        let digits_start = before
            .iter()
            .rposition(|b| !b.is_ascii_digit())
            .map_or(0, |p| p + 1);
        let digits = &before[digits_start..];
        if digits.is_empty() || digits_start == 0 || before[digits_start - 1] != b'[' {
            return Step::Continue;
        }
        if !matches!(
            classify(line),
            Line::Command {
                command: Command::WriteFile | Command::WriteFileInfo,
                ..
            }
        ) {
            return Step::Continue;
        }
        match block_len_value(digits) {
            Some(n) if n <= self.max_block => {
                self.mode = Mode::Block {
                    header: std::mem::take(&mut self.line),
                    data: Vec::with_capacity(n),
                    remaining: n,
                };
                Step::Continue
            }
            too_long => {
                let prefix = line[..line.len().min(TOO_LONG_PREFIX)].to_vec();
                self.line = Vec::new();
                // A length we can count is skipped as data, so the binary
                // block is not taken for commands; an absurd one (beyond
                // usize) cannot be, so skip to the line end instead.
                self.mode = match too_long {
                    Some(remaining) => Mode::SkipBlock { remaining },
                    None => Mode::Discard,
                };
                Step::Frame(Frame::TooLong(prefix))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frames(decoder: &mut Decoder, src: &mut BytesMut) -> Vec<Frame> {
        let mut out = Vec::new();
        while let Some(frame) = decoder.decode(src) {
            out.push(frame);
        }
        out
    }

    fn decode_all(input: &[u8]) -> Vec<Frame> {
        let mut d = Decoder::new(1024, 4096);
        let mut src = BytesMut::from(input);
        let out = frames(&mut d, &mut src);
        assert!(src.is_empty());
        out
    }

    /// Feeds `input` in chunks of `chunk` bytes.
    fn decode_chunked(input: &[u8], chunk: usize) -> Vec<Frame> {
        let mut d = Decoder::new(1024, 4096);
        let mut src = BytesMut::new();
        let mut out = Vec::new();
        for part in input.chunks(chunk) {
            src.extend_from_slice(part);
            out.extend(frames(&mut d, &mut src));
        }
        out
    }

    fn line(text: &[u8]) -> Frame {
        Frame::Line(text.to_vec())
    }

    #[test]
    fn line_ends() {
        assert_eq!(
            decode_all(b"GET:a\nGET:b\r\nGET:c\r\0GET:d"),
            vec![line(b"GET:a"), line(b"GET:b"), line(b"GET:c")]
        );
        assert_eq!(decode_all(b"\n\r\n"), vec![line(b""), line(b"")]);
        assert_eq!(decode_all(b"GE\rT:\0x\n"), vec![line(b"GET:x")]);
        for chunk in 1..4 {
            assert_eq!(
                decode_chunked(b"GET:a\r\nb\r\0c\n", chunk),
                vec![line(b"GET:a"), line(b"b"), line(b"c")]
            );
        }
    }

    #[test]
    fn leaves_the_rest_in_src() {
        let mut d = Decoder::new(1024, 4096);
        let mut src = BytesMut::from(&b"GET:a\nGET:b\nGET"[..]);
        assert_eq!(d.decode(&mut src), Some(line(b"GET:a")));
        assert_eq!(&src[..], b"GET:b\nGET");
        assert_eq!(d.decode(&mut src), Some(line(b"GET:b")));
        assert_eq!(d.decode(&mut src), None);
        assert!(src.is_empty());
        src.extend_from_slice(b":c\n");
        assert_eq!(d.decode(&mut src), Some(line(b"GET:c")));
    }

    #[test]
    fn real_telnet_negotiation_split_across_reads() {
        // What a Linux telnet client sends on connect, then a command.
        let mut input = vec![
            0xff, 0xfd, 0x03, 0xff, 0xfb, 0x18, 0xff, 0xfb, 0x1f, 0xff, 0xfb, 0x20, 0xff, 0xfb,
            0x21, 0xff, 0xfb, 0x22, 0xff, 0xfb, 0x27, 0xff, 0xfd, 0x05,
        ];
        // Subnegotiation: terminal type, NAWS.
        input.extend_from_slice(&[
            0xff, 0xfa, 0x18, 0x00, b'X', b'T', b'E', b'R', b'M', 0xff, 0xf0,
        ]);
        input.extend_from_slice(&[0xff, 0xfa, 0x1f, 0x00, 0x50, 0x00, 0xff, 0xff, 0xff, 0xf0]);
        input.extend_from_slice(b"GET:x\r\n");
        // IAC IP (interrupt), IAC NOP, then an escaped 0xFF in data.
        input.extend_from_slice(&[0xff, 0xf4, 0xff, 0xf1]);
        input.extend_from_slice(b"SET:s,\"a");
        input.extend_from_slice(&[0xff, 0xff]);
        input.extend_from_slice(b"\"\r\0");
        let expected = vec![line(b"GET:x"), line(b"SET:s,\"a\xff\"")];
        for chunk in 1..=input.len() {
            assert_eq!(decode_chunked(&input, chunk), expected, "chunk {chunk}");
        }
    }

    #[test]
    fn unterminated_subnegotiation_is_bounded() {
        let mut input = vec![0xff, 0xfa];
        input.extend_from_slice(&[b'z'; MAX_SUBNEGOTIATION]);
        input.extend_from_slice(b"GET:x\n");
        assert_eq!(decode_all(&input), vec![line(b"GET:x")]);
    }

    #[test]
    fn ctrl_d() {
        assert_eq!(decode_all(b"\x04"), vec![Frame::Close]);
        assert_eq!(
            decode_all(b"GET:a\n\x04"),
            vec![line(b"GET:a"), Frame::Close]
        );
        assert_eq!(decode_all(b"GE\x04T:a\n"), vec![line(b"GET:a")]);
        // Telnet negotiation before it does not count as line content.
        assert_eq!(decode_all(&[0xff, 0xfb, 0x18, 0x04]), vec![Frame::Close]);
    }

    #[test]
    fn too_long_line_then_recovery() {
        let mut d = Decoder::new(10, 100);
        let mut src = BytesMut::from(&b"0123456789ABCDEF\nGET:x\n"[..]);
        assert_eq!(
            d.decode(&mut src),
            Some(Frame::TooLong(b"0123456789".to_vec()))
        );
        assert_eq!(d.decode(&mut src), Some(line(b"GET:x")));
        assert_eq!(d.decode(&mut src), None);
        // Exactly max_line is fine.
        let mut src = BytesMut::from(&b"0123456789\n"[..]);
        assert_eq!(d.decode(&mut src), Some(line(b"0123456789")));
    }

    #[test]
    fn one_megabyte_without_newline_stays_bounded() {
        let mut d = Decoder::new(1024, 4096);
        let mut src = BytesMut::new();
        let mut out = Vec::new();
        for _ in 0..256 {
            src.extend_from_slice(&[b'a'; 4096]);
            out.extend(frames(&mut d, &mut src));
            assert!(src.is_empty());
            assert!(d.line.capacity() <= 2048);
        }
        assert_eq!(out, vec![Frame::TooLong(vec![b'a'; TOO_LONG_PREFIX])]);
        src.extend_from_slice(b"\nGET:x\n");
        assert_eq!(frames(&mut d, &mut src), vec![line(b"GET:x")]);
    }

    #[test]
    fn write_file_blocks_are_raw() {
        let mut input = b"WRITEFILE:test.txt[7]=a\r\n\0\xff\x04b".to_vec();
        input.extend_from_slice(b"\r\nwriteFile:test.txt[0]=\nGET:x\n");
        let expected = vec![
            Frame::Block {
                header: b"WRITEFILE:test.txt[7]=".to_vec(),
                data: b"a\r\n\0\xff\x04b".to_vec(),
            },
            Frame::Block {
                header: b"writeFile:test.txt[0]=".to_vec(),
                data: Vec::new(),
            },
            line(b"GET:x"),
        ];
        for chunk in 1..=input.len() {
            assert_eq!(decode_chunked(&input, chunk), expected, "chunk {chunk}");
        }
    }

    #[test]
    fn write_file_info_block_and_missing_line_end() {
        let input = b"WRITEFILEINFO:test.txt[34]=44 0 41854524393844 41854674928753GET:x\n";
        assert_eq!(
            decode_all(input),
            vec![
                Frame::Block {
                    header: b"WRITEFILEINFO:test.txt[34]=".to_vec(),
                    data: b"44 0 41854524393844 41854674928753".to_vec(),
                },
                line(b"GET:x"),
            ]
        );
    }

    #[test]
    fn only_write_commands_switch_to_raw() {
        assert_eq!(
            decode_all(b"SET:s,\"[3]=\"\nGETFILE:a[3]=x\n"),
            vec![line(b"SET:s,\"[3]=\""), line(b"GETFILE:a[3]=x")]
        );
        assert_eq!(
            decode_all(b"WRITEFILE:a[x]=\n"),
            vec![line(b"WRITEFILE:a[x]=")]
        );
    }

    #[test]
    fn block_over_the_limit_is_skipped() {
        let mut d = Decoder::new(1024, 4);
        let mut src = BytesMut::from(&b"WRITEFILE:big[6]=\n\nGET:x\nGET:y\n"[..]);
        assert_eq!(
            d.decode(&mut src),
            Some(Frame::TooLong(b"WRITEFILE:big[6]=".to_vec()))
        );
        // The 6 raw bytes `\n\nGET:` are skipped, then `x\n` is a line.
        assert_eq!(d.decode(&mut src), Some(line(b"x")));
        assert_eq!(d.decode(&mut src), Some(line(b"GET:y")));
        let mut src = BytesMut::from(&b"WRITEFILE:a[99999999999999999999999]=zz\nGET:y\n"[..]);
        assert!(matches!(d.decode(&mut src), Some(Frame::TooLong(_))));
        assert_eq!(d.decode(&mut src), Some(line(b"GET:y")));
    }
}
