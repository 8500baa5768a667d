//! One client's socket: input framing (telnet bytes, line ends, limits, file
//! blocks, via the protocol crate's decoder) and the output buffer. Everything
//! above it sees frames and lines, never raw bytes.

use std::io;

use bytes::BytesMut;
use plccoms_protocol::decoder::{Decoder, Frame};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::TcpStream;

/// Longest request line accepted.
pub const MAX_LINE: usize = 16 * 1024;
/// Largest WRITEFILE block accepted (FFILE_BLKSIZE's maximum).
pub const MAX_BLOCK: usize = 65536;
/// Output held before the session stops producing more until the client
/// reads.
pub const OUTPUT_HIGH_WATER: usize = 256 * 1024;

/// Output buffer capacity kept once everything is written.
const RETAINED_OUTPUT: usize = 16 * 1024;

pub struct Connection {
    pub(crate) reader: OwnedReadHalf,
    pub(crate) writer: OwnedWriteHalf,
    pub(crate) input: BytesMut,
    decoder: Decoder,
    /// Bytes waiting to be written; `written` of them already are.
    pub(crate) out: Vec<u8>,
    pub(crate) written: usize,
    /// The client closed its side: answer what it sent, then close.
    pub eof: bool,
    /// When input last arrived.
    pub last_input: tokio::time::Instant,
}

impl Connection {
    pub fn new(stream: TcpStream) -> Connection {
        let _ = stream.set_nodelay(true);
        let (reader, writer) = stream.into_split();
        Connection {
            reader,
            writer,
            input: BytesMut::with_capacity(4096),
            decoder: Decoder::new(MAX_LINE, MAX_BLOCK),
            out: Vec::new(),
            written: 0,
            eof: false,
            last_input: tokio::time::Instant::now(),
        }
    }

    /// The next complete frame already received, if any.
    pub fn next_frame(&mut self) -> Option<Frame> {
        self.decoder.decode(&mut self.input)
    }

    /// The header of a WRITEFILE block whose data is still arriving.
    pub fn pending_block(&self) -> Option<&[u8]> {
        self.decoder.pending_block()
    }

    /// Drops a block whose data stopped arriving.
    pub fn abandon_block(&mut self) {
        self.decoder.abandon_block();
    }

    /// Bytes queued and not yet written.
    pub fn backlog(&self) -> usize {
        self.out.len() - self.written
    }

    /// Appends already terminated lines.
    pub fn extend(&mut self, bytes: &[u8]) {
        self.out.extend_from_slice(bytes);
    }

    /// Writes everything queued (used when closing).
    pub async fn flush(&mut self) -> io::Result<()> {
        if self.backlog() > 0 {
            self.writer.write_all(&self.out[self.written..]).await?;
        }
        self.out.clear();
        self.written = 0;
        self.writer.flush().await
    }

    pub(crate) fn advance_written(&mut self, n: usize) {
        self.written += n;
        if self.written == self.out.len() {
            self.written = 0;
            if self.out.capacity() > RETAINED_OUTPUT {
                // A big answer or DIFF burst is over: give its memory back,
                // so a thousand idle clients do not each keep their peak.
                self.out = Vec::new();
            } else {
                self.out.clear();
            }
        } else if self.written > 64 * 1024 {
            self.out.drain(..self.written);
            self.written = 0;
        }
    }

    pub(crate) async fn read_more(
        reader: &mut OwnedReadHalf,
        input: &mut BytesMut,
    ) -> io::Result<usize> {
        input.reserve(4096);
        reader.read_buf(input).await
    }
}
