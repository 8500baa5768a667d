//! EPSNET frame types: plain data, no I/O and no parsing (see `codec`).
//!
//! A UDP datagram carries a 6-byte header and one or more frames:
//!
//! ```text
//! MESI u16 | PN u8 (0x02) | RES u8 (0) | DPLEN u16 BE | frames... | [0x00 pad to even length]
//! variable frame:  68 LE LE 68 DA SA FC <data> FCS 16
//! long frame:      68 00 00 68 LH LL DA SA FC <data> FCS 16      (project choice, see below)
//! short ack:       E5
//! ```
//!
//! Public: the header fields, DPLEN big-endian, the padding, the variable
//! frame with LE = bytes from DA through the last data byte and FCS = their
//! sum mod 256, and `E5`.
//!
//! Decided by this project, unverified against a real PLC:
//! - MESI is sent big-endian, like DPLEN.
//! - LE is one byte, so a frame carrying more than 255 bytes (a 1230-byte
//!   read answer) uses the long form: LE = LE = 0x00 (never valid for a normal
//!   frame, which holds at least DA SA FC), followed by the real length as a
//!   big-endian u16. FCS and the end byte are as in the normal form.
//! - A datagram's total size is capped at [`MAX_PACKET`] (1472 bytes: an
//!   Ethernet MTU of 1500 less IP and UDP headers), in both directions.
//!
//! On a serial line (public: the same frames, a frame ends at its end byte
//! 0x16) this project decides, unverified against a real PLC:
//! - frames follow each other with nothing between them: no header, no MESI,
//!   no padding; the long form is the same;
//! - the server sends one request frame and waits for its one answer frame
//!   before the next (half-duplex, as on RS-485), so answers are matched by
//!   order; the timeouts and retries are those of UDP (EPSTOUT,
//!   EPSTOUT_STEP);
//! - a frame is at most [`MAX_DPLEN`] bytes, as any frame a datagram carries;
//! - the line settings are 8 data bits, no parity, 1 stop bit at
//!   SERIAL_SPEED.

/// The UDP port PLCs listen on (0xF0F2).
pub const DEFAULT_PORT: u16 = 61682;

pub const HEADER_LEN: usize = 6;
/// PN as seen on the wire.
pub const PN: u8 = 0x02;
/// Largest UDP payload sent or accepted, header and padding included.
pub const MAX_PACKET: usize = 1472;
/// Largest EPSNET part of a packet (DPLEN).
pub const MAX_DPLEN: usize = MAX_PACKET - HEADER_LEN;

pub const START: u8 = 0x68;
pub const END: u8 = 0x16;
pub const ACK: u8 = 0xE5;

/// Bytes a variable frame adds around its data: `68 LE LE 68 DA SA FC .. FCS 16`.
pub const SHORT_OVERHEAD: usize = 9;
/// Same for the long form, which carries two more length bytes.
pub const LONG_OVERHEAD: usize = 11;
/// Largest DA..data length the short form can carry.
pub const SHORT_MAX_LE: usize = 255;

/// The 6-byte datagram header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    pub mesi: u16,
    pub pn: u8,
    pub res: u8,
    pub dplen: u16,
}

/// A variable-length frame: destination, source, function code and data.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DataFrame {
    pub da: u8,
    pub sa: u8,
    pub fc: u8,
    pub data: Vec<u8>,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Frame {
    Data(DataFrame),
    /// Short acknowledge `E5`.
    Ack,
}

impl Frame {
    /// Bytes this frame takes on the wire.
    pub fn encoded_len(&self) -> usize {
        match self {
            Frame::Ack => 1,
            Frame::Data(f) => data_frame_len(f.data.len()),
        }
    }
}

/// Wire length of a variable frame carrying `data_len` data bytes.
pub fn data_frame_len(data_len: usize) -> usize {
    if data_len + 3 <= SHORT_MAX_LE {
        data_len + SHORT_OVERHEAD
    } else {
        data_len + LONG_OVERHEAD
    }
}

/// Wire length of a datagram with `frames_len` bytes of frames.
pub fn packet_len(frames_len: usize) -> usize {
    let len = HEADER_LEN + frames_len;
    len + len % 2
}

/// One UDP datagram: a message id and the frames it carries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Packet {
    pub mesi: u16,
    pub frames: Vec<Frame>,
}

impl Packet {
    pub fn encoded_len(&self) -> usize {
        packet_len(self.frames.iter().map(Frame::encoded_len).sum())
    }
}
