//! ISO-on-TCP (RFC 1006) bytes <-> COTP TPDUs, for both ends: a TPKT
//! header (version 3, reserved 0, a 16-bit big-endian length counting the
//! header) frames each TPDU on the TCP stream. Never panics on what the
//! wire brings: a malformed frame is a typed error and the connection is
//! closed.

use bytes::{Buf, BytesMut};

use super::frame::{FrameError, Tpdu};

/// TPKT's header.
pub const TPKT_HEADER: usize = 4;
/// Largest TPKT accepted: a 1024-byte TPDU (what both ends negotiate) with
/// its headers; S7 PDUs are at most 960 bytes.
pub const MAX_TPKT: usize = 1024 + TPKT_HEADER + 3;

/// Why the stream cannot be framed any more.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    #[error("TPKT version {0}, not 3")]
    Version(u8),
    #[error("TPKT length {0} is outside {min}..={MAX_TPKT}", min = TPKT_HEADER + 2)]
    Length(u16),
    #[error("COTP: {0}")]
    Frame(#[from] FrameError),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// Splits a TCP stream into TPDUs, and frames TPDUs onto it.
#[derive(Debug, Default, Clone, Copy)]
pub struct TpktCodec;

impl tokio_util::codec::Decoder for TpktCodec {
    type Item = Tpdu;
    type Error = CodecError;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<Tpdu>, CodecError> {
        if src.len() < TPKT_HEADER {
            return Ok(None);
        }
        if src[0] != 3 {
            return Err(CodecError::Version(src[0]));
        }
        let length = u16::from_be_bytes([src[2], src[3]]);
        if !(TPKT_HEADER + 2..=MAX_TPKT).contains(&usize::from(length)) {
            return Err(CodecError::Length(length));
        }
        let length = usize::from(length);
        if src.len() < length {
            src.reserve(length - src.len());
            return Ok(None);
        }
        let frame = src.split_to(length);
        Ok(Some(Tpdu::parse(&frame[TPKT_HEADER..])?))
    }
}

impl tokio_util::codec::Encoder<Tpdu> for TpktCodec {
    type Error = CodecError;

    fn encode(&mut self, tpdu: Tpdu, dst: &mut BytesMut) -> Result<(), CodecError> {
        let start = dst.len();
        dst.extend_from_slice(&[3, 0, 0, 0]);
        tpdu.encode(dst);
        let length = dst.len() - start;
        if length > MAX_TPKT {
            dst.truncate(start);
            return Err(CodecError::Length(length.min(usize::from(u16::MAX)) as u16));
        }
        dst[start + 2..start + 4].copy_from_slice(&(length as u16).to_be_bytes());
        Ok(())
    }
}

/// Decodes every whole frame of `bytes` (the fuzz target's and the
/// property test's entry point): the TPDUs, and any S7 PDU in them parsed
/// as an answer and as a job. Stops at the first framing error.
pub fn decode_all(bytes: &[u8]) -> Result<Vec<Tpdu>, CodecError> {
    use tokio_util::codec::Decoder;
    let mut codec = TpktCodec;
    let mut src = BytesMut::from(bytes);
    let mut out = Vec::new();
    while let Some(tpdu) = codec.decode(&mut src)? {
        if let Tpdu::Data(pdu) = &tpdu {
            let _ = super::frame::Answer::parse(pdu);
            let _ = super::frame::Job::parse(pdu);
        }
        out.push(tpdu);
    }
    src.advance(src.len());
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;
    use tokio_util::codec::{Decoder, Encoder};

    #[test]
    fn frames_round_trip_and_wait_for_more() {
        let mut codec = TpktCodec;
        let mut wire = BytesMut::new();
        let tpdu = Tpdu::Data(Bytes::from_static(&[0x32, 1, 0, 0, 0, 1, 0, 0, 0, 0]));
        codec.encode(tpdu.clone(), &mut wire).unwrap();
        assert_eq!(&wire[..7], [3, 0, 0, 17, 2, 0xF0, 0x80]);
        let mut part = BytesMut::from(&wire[..10]);
        assert_eq!(codec.decode(&mut part).unwrap(), None);
        part.extend_from_slice(&wire[10..]);
        assert_eq!(codec.decode(&mut part).unwrap(), Some(tpdu));
        assert!(part.is_empty());
    }

    #[test]
    fn bad_headers_are_errors() {
        let mut codec = TpktCodec;
        for (bytes, text) in [
            (&[4u8, 0, 0, 7, 2, 0xF0, 0x80][..], "version 4"),
            (&[3, 0, 0xFF, 0xFF][..], "length 65535"),
            (&[3, 0, 0, 5, 0][..], "length 5"),
            (&[3, 0, 0, 7, 9, 0xF0, 0x80][..], "length indicator 9"),
            (&[3, 0, 0, 7, 2, 0xF0, 0x00][..], "fragmented"),
        ] {
            let e = codec.decode(&mut BytesMut::from(bytes)).unwrap_err();
            assert!(e.to_string().contains(text), "{e} / {text}");
        }
    }
}
