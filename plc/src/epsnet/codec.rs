//! Bytes <-> [`Packet`]: the only place that touches raw EPSNET bytes.
//!
//! Decoding never panics: every malformed input is a [`DecodeError`] naming
//! what was wrong and at which byte offset of the datagram.

use bytes::{Buf, BufMut, BytesMut};

use super::frame::{
    DataFrame, Frame, Header, Packet, ACK, END, HEADER_LEN, MAX_DPLEN, MAX_PACKET, PN,
    SHORT_MAX_LE, START,
};

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("truncated header: {len} bytes, need {HEADER_LEN}")]
    TruncatedHeader { len: usize },
    #[error("DPLEN {dplen} larger than the {available} bytes after the header")]
    DplenTooLarge { dplen: usize, available: usize },
    #[error("packet carries no frame (DPLEN 0)")]
    Empty,
    #[error("bad start byte 0x{byte:02X} at offset {offset}")]
    BadStart { offset: usize, byte: u8 },
    #[error("bad second start byte 0x{byte:02X} at offset {offset}")]
    BadSecondStart { offset: usize, byte: u8 },
    #[error("length bytes differ at offset {offset}: 0x{first:02X} vs 0x{second:02X}")]
    LengthMismatch {
        offset: usize,
        first: u8,
        second: u8,
    },
    #[error("frame length {len} at offset {offset} too short for DA SA FC")]
    LengthTooShort { offset: usize, len: usize },
    #[error("frame at offset {offset} needs {needed} bytes, only {available} left in DPLEN")]
    Truncated {
        offset: usize,
        needed: usize,
        available: usize,
    },
    #[error(
        "FCS mismatch at offset {offset}: computed 0x{computed:02X}, frame says 0x{found:02X}"
    )]
    FcsMismatch {
        offset: usize,
        computed: u8,
        found: u8,
    },
    #[error("missing end byte at offset {offset}: 0x{byte:02X} instead of 0x16")]
    MissingEnd { offset: usize, byte: u8 },
    #[error("datagram of {len} bytes exceeds the {MAX_PACKET}-byte limit")]
    TooLong { len: usize },
    #[error("frame at offset {offset} claims {len} bytes, more than the {MAX_DPLEN}-byte limit")]
    FrameTooLong { offset: usize, len: usize },
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    #[error("frame data of {0} bytes does not fit a frame")]
    FrameTooLong(usize),
    #[error("packet of {0} bytes exceeds the {MAX_PACKET}-byte limit")]
    PacketTooLong(usize),
}

/// FCS: sum of the bytes mod 256.
pub fn fcs(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |sum, b| sum.wrapping_add(*b))
}

/// Appends one frame's wire bytes.
pub fn encode_frame(frame: &Frame, out: &mut Vec<u8>) -> Result<(), EncodeError> {
    let f = match frame {
        Frame::Ack => {
            out.push(ACK);
            return Ok(());
        }
        Frame::Data(f) => f,
    };
    let le = f.data.len() + 3;
    if le > usize::from(u16::MAX) {
        return Err(EncodeError::FrameTooLong(f.data.len()));
    }
    if le <= SHORT_MAX_LE {
        out.extend_from_slice(&[START, le as u8, le as u8, START]);
    } else {
        out.extend_from_slice(&[START, 0, 0, START]);
        out.extend_from_slice(&(le as u16).to_be_bytes());
    }
    let body_start = out.len();
    out.extend_from_slice(&[f.da, f.sa, f.fc]);
    out.extend_from_slice(&f.data);
    let sum = fcs(&out[body_start..]);
    out.extend_from_slice(&[sum, END]);
    Ok(())
}

/// The whole datagram: header, frames, padding.
pub fn encode_packet(packet: &Packet) -> Result<Vec<u8>, EncodeError> {
    let mut out = Vec::with_capacity(packet.encoded_len());
    out.extend_from_slice(&[0; HEADER_LEN]);
    for frame in &packet.frames {
        encode_frame(frame, &mut out)?;
    }
    let dplen = out.len() - HEADER_LEN;
    if out.len() > MAX_PACKET {
        return Err(EncodeError::PacketTooLong(out.len()));
    }
    out[0..2].copy_from_slice(&packet.mesi.to_be_bytes());
    out[2] = PN;
    out[3] = 0;
    out[4..6].copy_from_slice(&(dplen as u16).to_be_bytes());
    if out.len() % 2 == 1 {
        out.push(0);
    }
    Ok(out)
}

pub fn decode_header(buf: &[u8]) -> Result<Header, DecodeError> {
    if buf.len() < HEADER_LEN {
        return Err(DecodeError::TruncatedHeader { len: buf.len() });
    }
    Ok(Header {
        mesi: u16::from_be_bytes([buf[0], buf[1]]),
        pn: buf[2],
        res: buf[3],
        dplen: u16::from_be_bytes([buf[4], buf[5]]),
    })
}

/// Decodes one frame from the start of `buf`; `base` is the offset of `buf`
/// in the datagram, for error messages. Returns the frame and its length.
pub fn decode_frame(buf: &[u8], base: usize) -> Result<(Frame, usize), DecodeError> {
    let truncated = |needed: usize| DecodeError::Truncated {
        offset: base,
        needed,
        available: buf.len(),
    };
    match buf.first() {
        None => return Err(truncated(1)),
        Some(&ACK) => return Ok((Frame::Ack, 1)),
        Some(&START) => {}
        Some(&byte) => return Err(DecodeError::BadStart { offset: base, byte }),
    }
    if buf.len() < 4 {
        return Err(truncated(4));
    }
    if buf[1] != buf[2] {
        return Err(DecodeError::LengthMismatch {
            offset: base + 1,
            first: buf[1],
            second: buf[2],
        });
    }
    if buf[3] != START {
        return Err(DecodeError::BadSecondStart {
            offset: base + 3,
            byte: buf[3],
        });
    }
    let (le, body_start) = if buf[1] == 0 {
        if buf.len() < 6 {
            return Err(truncated(6));
        }
        (usize::from(u16::from_be_bytes([buf[4], buf[5]])), 6)
    } else {
        (usize::from(buf[1]), 4)
    };
    if le < 3 {
        return Err(DecodeError::LengthTooShort {
            offset: base + 1,
            len: le,
        });
    }
    let total = body_start + le + 2;
    if buf.len() < total {
        return Err(truncated(total));
    }
    let body = &buf[body_start..body_start + le];
    let computed = fcs(body);
    let found = buf[body_start + le];
    if computed != found {
        return Err(DecodeError::FcsMismatch {
            offset: base + body_start + le,
            computed,
            found,
        });
    }
    let end = buf[body_start + le + 1];
    if end != END {
        return Err(DecodeError::MissingEnd {
            offset: base + body_start + le + 1,
            byte: end,
        });
    }
    let frame = DataFrame {
        da: body[0],
        sa: body[1],
        fc: body[2],
        data: body[3..].to_vec(),
    };
    Ok((Frame::Data(frame), total))
}

/// Decodes a whole datagram. Bytes after DPLEN (the padding) are ignored.
pub fn decode_packet(buf: &[u8]) -> Result<Packet, DecodeError> {
    if buf.len() > MAX_PACKET {
        return Err(DecodeError::TooLong { len: buf.len() });
    }
    let header = decode_header(buf)?;
    let dplen = usize::from(header.dplen);
    let available = buf.len() - HEADER_LEN;
    if dplen > available {
        return Err(DecodeError::DplenTooLarge { dplen, available });
    }
    if dplen == 0 {
        return Err(DecodeError::Empty);
    }
    let body = &buf[HEADER_LEN..HEADER_LEN + dplen];
    let mut frames = Vec::new();
    let mut pos = 0;
    while pos < body.len() {
        let (frame, len) = decode_frame(&body[pos..], HEADER_LEN + pos)?;
        frames.push(frame);
        pos += len;
    }
    Ok(Packet {
        mesi: header.mesi,
        frames,
    })
}

/// tokio-util codec for transports that hand over one datagram per buffer
/// (`UdpFramed`): each call consumes the whole buffer as one packet.
#[derive(Debug, Default, Clone, Copy)]
pub struct EpsnetCodec;

impl tokio_util::codec::Decoder for EpsnetCodec {
    type Item = Packet;
    type Error = std::io::Error;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<Packet>, std::io::Error> {
        if src.is_empty() {
            return Ok(None);
        }
        let result = decode_packet(src);
        src.advance(src.len());
        result
            .map(Some)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))
    }
}

impl tokio_util::codec::Encoder<Packet> for EpsnetCodec {
    type Error = std::io::Error;

    fn encode(&mut self, packet: Packet, dst: &mut BytesMut) -> Result<(), std::io::Error> {
        let bytes = encode_packet(&packet)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
        dst.put_slice(&bytes);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn data(da: u8, sa: u8, fc: u8, data: &[u8]) -> Frame {
        Frame::Data(DataFrame {
            da,
            sa,
            fc,
            data: data.to_vec(),
        })
    }

    #[test]
    fn settid_golden_bytes() {
        // 2024-03-15 13:45:30, a Friday (5).
        let frame = data(0x00, 0x7D, 0x63, &[0x08, 24, 3, 15, 13, 45, 30, 5]);
        let mut out = Vec::new();
        encode_frame(&frame, &mut out).unwrap();
        let sum = [0x00u8, 0x7D, 0x63, 0x08, 24, 3, 15, 13, 45, 30, 5]
            .iter()
            .fold(0u32, |s, b| s + u32::from(*b)) as u8;
        assert_eq!(
            out,
            [0x68, 0x0B, 0x0B, 0x68, 0x00, 0x7D, 0x63, 0x08, 24, 3, 15, 13, 45, 30, 5, sum, 0x16]
        );
        assert_eq!(decode_frame(&out, 0).unwrap(), (frame, out.len()));
        assert_eq!(decode_frame(&[0xE5], 0).unwrap(), (Frame::Ack, 1));
    }

    #[test]
    fn packet_round_trip_with_padding_and_long_frame() {
        let packet = Packet {
            mesi: 0x1234,
            frames: vec![
                data(0, 5, 0x63, &[1, 2, 3]),
                Frame::Ack,
                data(5, 0, 0x08, &vec![0xAB; 1232]),
            ],
        };
        let bytes = encode_packet(&packet).unwrap();
        assert_eq!(bytes.len() % 2, 0);
        assert_eq!(&bytes[0..4], &[0x12, 0x34, 0x02, 0x00]);
        let dplen = usize::from(u16::from_be_bytes([bytes[4], bytes[5]]));
        assert_eq!(dplen, (3 + 9) + 1 + (1232 + 11));
        assert_eq!(bytes.len(), packet.encoded_len());
        assert_eq!(
            &bytes[HEADER_LEN + 13..HEADER_LEN + 19],
            &[0x68, 0, 0, 0x68, 0x04, 0xD3]
        );
        assert_eq!(decode_packet(&bytes).unwrap(), packet);
    }

    #[test]
    fn short_form_up_to_255() {
        let f = data(0, 1, 2, &vec![7; 252]);
        let mut out = Vec::new();
        encode_frame(&f, &mut out).unwrap();
        assert_eq!(&out[..4], &[0x68, 255, 255, 0x68]);
        let f = data(0, 1, 2, &vec![7; 253]);
        out.clear();
        encode_frame(&f, &mut out).unwrap();
        assert_eq!(&out[..6], &[0x68, 0, 0, 0x68, 1, 0]);
        assert_eq!(decode_frame(&out, 0).unwrap().0, f);
    }

    fn good() -> Vec<u8> {
        encode_packet(&Packet {
            mesi: 1,
            frames: vec![data(0, 5, 0x63, &[0x01])],
        })
        .unwrap()
    }

    #[test]
    fn every_malformed_class_is_named() {
        // Frame: header 0..6, 68@6 LE@7 LE@8 68@9 DA@10 SA@11 FC@12 data@13 FCS@14 16@15
        assert_eq!(
            decode_packet(&[0, 1, 2]),
            Err(DecodeError::TruncatedHeader { len: 3 })
        );
        let mut b = good();
        b[5] = 40;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::DplenTooLarge { dplen: 40, .. })
        ));
        let mut b = good();
        b[5] = 0;
        assert_eq!(decode_packet(&b), Err(DecodeError::Empty));
        let mut b = good();
        b[6] = 0x10;
        assert_eq!(
            decode_packet(&b),
            Err(DecodeError::BadStart {
                offset: 6,
                byte: 0x10
            })
        );
        let mut b = good();
        b[8] = 5;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::LengthMismatch { offset: 7, .. })
        ));
        let mut b = good();
        b[9] = 0x69;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::BadSecondStart { offset: 9, .. })
        ));
        let mut b = good();
        b[14] ^= 0xFF;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::FcsMismatch { offset: 14, .. })
        ));
        let mut b = good();
        b[15] = 0x17;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::MissingEnd {
                offset: 15,
                byte: 0x17
            })
        ));
        let mut b = good();
        b[7] = 2;
        b[8] = 2;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::LengthTooShort { offset: 7, len: 2 })
        ));
        let mut b = good();
        b[7] = 9;
        b[8] = 9;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::Truncated { offset: 6, .. })
        ));
        let mut b = good();
        b.truncate(15);
        b[5] = 9;
        assert!(matches!(
            decode_packet(&b),
            Err(DecodeError::Truncated { .. })
        ));
        assert!(matches!(
            decode_packet(&vec![0; 2000]),
            Err(DecodeError::TooLong { .. })
        ));
    }

    #[test]
    fn decode_never_panics_on_garbage() {
        let mut seed = 0x1234_5678_9abc_def0u64;
        let mut buf = Vec::new();
        for _ in 0..20_000 {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            let len = (seed % 40) as usize;
            buf.clear();
            let mut s = seed;
            for _ in 0..len {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
                let pick = (s >> 33) as u8;
                buf.push(match pick % 5 {
                    0 => 0x68,
                    1 => 0x16,
                    2 => 0xE5,
                    3 => 0,
                    _ => pick,
                });
            }
            let _ = decode_packet(&buf);
            let _ = decode_frame(&buf, 0);
        }
    }
}
