//! AMS/TCP framing, for both ends: a 6-byte AMS/TCP header (2 reserved
//! zero bytes, the length of what follows), the 32-byte AMS header, then the
//! command's data. All fields little-endian. [`AmsCodec`] is a tokio-util
//! `Decoder`/`Encoder`; it never panics on what the wire brings, and refuses
//! a length past [`MAX_FRAME`] before buffering it.

use bytes::{Buf, BufMut, Bytes, BytesMut};
use tokio_util::codec::{Decoder, Encoder};

use super::{AdsError, AmsAddr, NetId};

pub const TCP_HEADER_LEN: usize = 6;
pub const AMS_HEADER_LEN: usize = 32;
/// Largest AMS packet taken (header and data): a symbol table of 100,000
/// symbols is about 10 MB.
pub const MAX_FRAME: usize = 64 * 1024 * 1024;

/// State flag: the packet is a response.
pub const STATE_RESPONSE: u16 = 0x0001;
/// State flag: an ADS command (always set).
pub const STATE_ADS: u16 = 0x0004;

/// ADS command ids.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CommandId(pub u16);

impl CommandId {
    pub const READ_DEVICE_INFO: CommandId = CommandId(1);
    pub const READ: CommandId = CommandId(2);
    pub const WRITE: CommandId = CommandId(3);
    pub const READ_STATE: CommandId = CommandId(4);
    pub const WRITE_CONTROL: CommandId = CommandId(5);
    pub const ADD_NOTIFICATION: CommandId = CommandId(6);
    pub const DELETE_NOTIFICATION: CommandId = CommandId(7);
    pub const NOTIFICATION: CommandId = CommandId(8);
    pub const READ_WRITE: CommandId = CommandId(9);
}

/// The AMS header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AmsHeader {
    pub target: AmsAddr,
    pub source: AmsAddr,
    pub command: CommandId,
    pub state: u16,
    /// The AMS-level error (0: none); a command's own result is in its data.
    pub error: u32,
    pub invoke_id: u32,
}

impl AmsHeader {
    pub fn is_response(&self) -> bool {
        self.state & STATE_RESPONSE != 0
    }

    /// The header of the answer to this request.
    pub fn response(&self, error: u32) -> AmsHeader {
        AmsHeader {
            target: self.source,
            source: self.target,
            command: self.command,
            state: self.state | STATE_RESPONSE,
            error,
            invoke_id: self.invoke_id,
        }
    }
}

/// One AMS packet as read from or written to the stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AmsPacket {
    pub header: AmsHeader,
    pub data: Bytes,
}

/// The stream cannot be framed any more (the connection must be closed).
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    #[error("AMS/TCP reserved field is 0x{0:04X}, not 0 (not an ADS stream?)")]
    Reserved(u16),
    #[error("AMS/TCP length {0} is less than the 32-byte AMS header")]
    Short(u32),
    #[error("AMS/TCP length {0} is more than the {MAX_FRAME} bytes accepted")]
    TooLong(u32),
    #[error("AMS header says {said} data bytes, the packet holds {held}")]
    DataLength { said: u32, held: usize },
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// AMS/TCP bytes <-> [`AmsPacket`].
#[derive(Debug, Default, Clone, Copy)]
pub struct AmsCodec;

fn addr(buf: &mut &[u8]) -> AmsAddr {
    let mut id = [0u8; 6];
    buf.copy_to_slice(&mut id);
    AmsAddr {
        net_id: NetId(id),
        port: buf.get_u16_le(),
    }
}

impl Decoder for AmsCodec {
    type Item = AmsPacket;
    type Error = FrameError;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<AmsPacket>, FrameError> {
        if src.len() < TCP_HEADER_LEN {
            return Ok(None);
        }
        let reserved = u16::from_le_bytes([src[0], src[1]]);
        if reserved != 0 {
            return Err(FrameError::Reserved(reserved));
        }
        let length = u32::from_le_bytes([src[2], src[3], src[4], src[5]]);
        if (length as usize) < AMS_HEADER_LEN {
            return Err(FrameError::Short(length));
        }
        if length as usize > MAX_FRAME {
            return Err(FrameError::TooLong(length));
        }
        let total = TCP_HEADER_LEN + length as usize;
        if src.len() < total {
            // Room for this frame only as its bytes come in: a lying
            // length costs nothing until they do.
            return Ok(None);
        }
        let mut frame = src.split_to(total).freeze();
        frame.advance(TCP_HEADER_LEN);
        let mut head: &[u8] = &frame[..AMS_HEADER_LEN];
        let target = addr(&mut head);
        let source = addr(&mut head);
        let command = CommandId(head.get_u16_le());
        let state = head.get_u16_le();
        let said = head.get_u32_le();
        let error = head.get_u32_le();
        let invoke_id = head.get_u32_le();
        let data = frame.slice(AMS_HEADER_LEN..);
        if said as usize != data.len() {
            return Err(FrameError::DataLength {
                said,
                held: data.len(),
            });
        }
        Ok(Some(AmsPacket {
            header: AmsHeader {
                target,
                source,
                command,
                state,
                error,
                invoke_id,
            },
            data,
        }))
    }
}

impl Encoder<AmsPacket> for AmsCodec {
    type Error = FrameError;

    fn encode(&mut self, packet: AmsPacket, dst: &mut BytesMut) -> Result<(), FrameError> {
        let length = AMS_HEADER_LEN + packet.data.len();
        if length > MAX_FRAME {
            return Err(FrameError::TooLong(length.min(u32::MAX as usize) as u32));
        }
        let h = &packet.header;
        dst.reserve(TCP_HEADER_LEN + length);
        dst.put_u16_le(0);
        dst.put_u32_le(length as u32);
        for end in [h.target, h.source] {
            dst.put_slice(&end.net_id.0);
            dst.put_u16_le(end.port);
        }
        dst.put_u16_le(h.command.0);
        dst.put_u16_le(h.state);
        dst.put_u32_le(packet.data.len() as u32);
        dst.put_u32_le(h.error);
        dst.put_u32_le(h.invoke_id);
        dst.put_slice(&packet.data);
        Ok(())
    }
}

/// A packet's AMS-level error as a result.
pub fn check_header(header: &AmsHeader) -> Result<(), AdsError> {
    match header.error {
        0 => Ok(()),
        code => Err(AdsError(code)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn packet() -> AmsPacket {
        AmsPacket {
            header: AmsHeader {
                target: AmsAddr {
                    net_id: NetId([5, 1, 2, 3, 1, 1]),
                    port: 851,
                },
                source: AmsAddr {
                    net_id: NetId([10, 0, 0, 1, 1, 1]),
                    port: 32905,
                },
                command: CommandId::READ,
                state: STATE_ADS,
                error: 0,
                invoke_id: 7,
            },
            data: Bytes::from_static(&[1, 2, 3]),
        }
    }

    #[test]
    fn packets_round_trip_and_wait_for_their_bytes() {
        let mut buf = BytesMut::new();
        AmsCodec.encode(packet(), &mut buf).unwrap();
        assert_eq!(buf.len(), 6 + 32 + 3);
        assert_eq!(&buf[..6], &[0, 0, 35, 0, 0, 0]);
        let whole = buf.clone();
        let mut part = BytesMut::from(&whole[..20]);
        assert!(AmsCodec.decode(&mut part).unwrap().is_none());
        assert_eq!(AmsCodec.decode(&mut buf).unwrap(), Some(packet()));
        assert!(buf.is_empty());
    }

    #[test]
    fn bad_frames_are_named() {
        let mut buf = BytesMut::from(&[1u8, 0, 40, 0, 0, 0][..]);
        assert!(matches!(
            AmsCodec.decode(&mut buf),
            Err(FrameError::Reserved(1))
        ));
        let mut buf = BytesMut::from(&[0u8, 0, 4, 0, 0, 0][..]);
        assert!(matches!(
            AmsCodec.decode(&mut buf),
            Err(FrameError::Short(4))
        ));
        let mut buf = BytesMut::from(&[0u8, 0, 0xFF, 0xFF, 0xFF, 0xFF][..]);
        assert!(matches!(
            AmsCodec.decode(&mut buf),
            Err(FrameError::TooLong(_))
        ));
        let mut buf = BytesMut::new();
        AmsCodec.encode(packet(), &mut buf).unwrap();
        buf[6 + 20] = 9; // data length 9, 3 held
        assert!(matches!(
            AmsCodec.decode(&mut buf),
            Err(FrameError::DataLength { said: 9, held: 3 })
        ));
    }
}
