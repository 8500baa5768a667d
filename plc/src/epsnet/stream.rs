//! EPSNET frames on a byte stream (a serial line): bytes <-> [`Frame`]s.
//!
//! On a serial line there is no datagram header and no MESI: frames follow
//! each other, a variable frame ending at its end byte `0x16` (public), an
//! acknowledge being the single byte `E5`. The line may bring garbage (noise,
//! a device that was switched on mid-frame) and truncated frames, so the
//! decoder resynchronises instead of failing:
//!
//! - bytes before a plausible start (`68` or `E5`) are skipped as one run;
//! - a `68` whose header is implausible (length bytes differ, no second `68`,
//!   a length below 3 or above [`MAX_FRAME`]) is skipped, one byte, and the
//!   scan goes on from the next byte;
//! - a frame with a wrong FCS but its end byte in place is skipped whole (its
//!   boundaries were right, only its content is damaged); with the end byte
//!   missing too, only its first byte is skipped, since the length was
//!   probably what was damaged;
//! - a frame that never completes is the caller's to abandon when the line
//!   falls idle ([`StreamCodec::abandon_partial`]): the sender of a frame
//!   does not pause inside it.
//!
//! Every skip is reported as a [`StreamItem::Skipped`] with the reason, so a
//! caller can count and log line errors; the decoder never fails and never
//! holds more than [`MAX_FRAME`] bytes of one candidate frame.

use bytes::{Buf, BytesMut};

use super::codec::{decode_frame, encode_frame, DecodeError, EncodeError};
use super::frame::{Frame, ACK, END, MAX_DPLEN, START};

/// Largest frame accepted or sent on a stream: the largest a datagram can
/// carry, since every service is planned to fit one.
pub const MAX_FRAME: usize = MAX_DPLEN;

/// What the decoder made of the next bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StreamItem {
    Frame(Frame),
    /// Bytes dropped while resynchronising, and why.
    Skipped {
        bytes: usize,
        why: DecodeError,
    },
}

/// tokio-util codec for EPSNET frames on a byte stream.
#[derive(Debug, Default, Clone, Copy)]
pub struct StreamCodec;

impl StreamCodec {
    /// The line fell idle while `src` holds the start of a frame that never
    /// completed: drops its first byte so decoding can resynchronise on what
    /// follows. `None` when `src` is empty.
    pub fn abandon_partial(&mut self, src: &mut BytesMut) -> Option<StreamItem> {
        if src.is_empty() {
            return None;
        }
        let why = match decode_frame(src, 0) {
            Err(e) => e,
            // Complete after all: the caller decodes it.
            Ok(_) => return None,
        };
        src.advance(1);
        Some(StreamItem::Skipped { bytes: 1, why })
    }
}

fn skip(src: &mut BytesMut, bytes: usize, why: DecodeError) -> Option<StreamItem> {
    src.advance(bytes);
    Some(StreamItem::Skipped { bytes, why })
}

impl tokio_util::codec::Decoder for StreamCodec {
    type Item = StreamItem;
    type Error = std::io::Error;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<StreamItem>, std::io::Error> {
        let Some(&first) = src.first() else {
            return Ok(None);
        };
        if first != START && first != ACK {
            let run = src
                .iter()
                .position(|&b| b == START || b == ACK)
                .unwrap_or(src.len());
            let why = DecodeError::BadStart {
                offset: 0,
                byte: first,
            };
            return Ok(skip(src, run, why));
        }
        Ok(match decode_frame(src, 0) {
            Ok((frame, len)) => {
                src.advance(len);
                Some(StreamItem::Frame(frame))
            }
            Err(DecodeError::Truncated { needed, .. }) if needed <= MAX_FRAME => {
                src.reserve(needed.saturating_sub(src.len()));
                None
            }
            Err(DecodeError::Truncated { needed, .. }) => {
                let why = DecodeError::FrameTooLong {
                    offset: 0,
                    len: needed,
                };
                skip(src, 1, why)
            }
            Err(why @ DecodeError::FcsMismatch { offset, .. }) => {
                let whole = src.get(offset + 1) == Some(&END);
                skip(src, if whole { offset + 2 } else { 1 }, why)
            }
            Err(why) => skip(src, 1, why),
        })
    }

    fn decode_eof(&mut self, src: &mut BytesMut) -> Result<Option<StreamItem>, std::io::Error> {
        match self.decode(src)? {
            Some(item) => Ok(Some(item)),
            None => Ok(self.abandon_partial(src)),
        }
    }
}

impl tokio_util::codec::Encoder<&Frame> for StreamCodec {
    type Error = std::io::Error;

    fn encode(&mut self, frame: &Frame, dst: &mut BytesMut) -> Result<(), std::io::Error> {
        let bytes =
            encode(frame).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
        dst.extend_from_slice(&bytes);
        Ok(())
    }
}

/// The wire bytes of one frame on a stream.
pub fn encode(frame: &Frame) -> Result<Vec<u8>, EncodeError> {
    if frame.encoded_len() > MAX_FRAME {
        return Err(EncodeError::FrameTooLong(frame.encoded_len()));
    }
    let mut out = Vec::with_capacity(frame.encoded_len());
    encode_frame(frame, &mut out)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::epsnet::frame::DataFrame;
    use proptest::prelude::*;
    use tokio_util::codec::Decoder;

    fn data(fc: u8, payload: &[u8]) -> Frame {
        Frame::Data(DataFrame {
            da: 0,
            sa: 5,
            fc,
            data: payload.to_vec(),
        })
    }

    /// Everything the decoder makes of `bytes` fed in one piece, then EOF.
    fn decode_all(bytes: &[u8]) -> Vec<StreamItem> {
        let mut codec = StreamCodec;
        let mut src = BytesMut::from(bytes);
        let mut items = Vec::new();
        while let Some(item) = codec.decode_eof(&mut src).unwrap() {
            items.push(item);
        }
        assert!(src.is_empty());
        items
    }

    fn frames(items: &[StreamItem]) -> Vec<Frame> {
        items
            .iter()
            .filter_map(|i| match i {
                StreamItem::Frame(f) => Some(f.clone()),
                StreamItem::Skipped { .. } => None,
            })
            .collect()
    }

    #[test]
    fn frames_back_to_back_and_byte_by_byte() {
        let sent = [data(0x63, &[1, 2, 3]), Frame::Ack, data(0x08, &[9; 1232])];
        let mut wire = Vec::new();
        for f in &sent {
            wire.extend(encode(f).unwrap());
        }
        assert_eq!(frames(&decode_all(&wire)), sent);
        // Arriving one byte at a time.
        let mut codec = StreamCodec;
        let mut src = BytesMut::new();
        let mut got = Vec::new();
        for &b in &wire {
            src.extend_from_slice(&[b]);
            while let Some(item) = codec.decode(&mut src).unwrap() {
                got.push(item);
            }
        }
        assert_eq!(frames(&got), sent);
        assert!(src.is_empty());
    }

    #[test]
    fn garbage_is_skipped_as_one_run_with_its_reason() {
        let frame = data(0x63, &[7]);
        let mut wire = vec![0x00, 0x11, 0xFF];
        wire.extend(encode(&frame).unwrap());
        assert_eq!(
            decode_all(&wire),
            [
                StreamItem::Skipped {
                    bytes: 3,
                    why: DecodeError::BadStart {
                        offset: 0,
                        byte: 0x00
                    }
                },
                StreamItem::Frame(frame)
            ]
        );
    }

    #[test]
    fn a_damaged_frame_is_dropped_and_the_next_one_found() {
        let good = data(0x63, &[1, 2, 3, 4]);
        let mut bad = encode(&data(0x63, &[0x68, 0xE5, 0x16])).unwrap();
        let fcs = bad.len() - 2;
        bad[fcs] ^= 0x55;
        let mut wire = bad.clone();
        wire.extend(encode(&good).unwrap());
        let items = decode_all(&wire);
        // Skipped whole (end byte in place): no phantom E5 from its data.
        assert_eq!(frames(&items), std::slice::from_ref(&good));
        assert!(matches!(
            items[0],
            StreamItem::Skipped {
                why: DecodeError::FcsMismatch { .. },
                ..
            }
        ));
        // A length byte damaged: the header is implausible, one byte goes.
        let mut wire = encode(&good).unwrap();
        wire[1] ^= 0x01;
        wire.extend(encode(&good).unwrap());
        assert_eq!(frames(&decode_all(&wire)), [good]);
    }

    #[test]
    fn a_truncated_frame_waits_until_abandoned() {
        let good = data(0x63, &[1, 2, 3]);
        let long = encode(&data(0x08, &[0x42; 200])).unwrap();
        let mut wire = long[..50].to_vec();
        wire.extend(encode(&good).unwrap());
        let mut codec = StreamCodec;
        let mut src = BytesMut::from(&wire[..]);
        // The truncated frame claims more than has come: wait.
        assert_eq!(codec.decode(&mut src).unwrap(), None);
        // The line fell idle: resynchronise, finding the good frame.
        let mut items = vec![codec.abandon_partial(&mut src).unwrap()];
        while let Some(item) = codec.decode(&mut src).unwrap() {
            items.push(item);
        }
        assert_eq!(frames(&items), [good]);
        assert!(src.is_empty());
    }

    #[test]
    fn an_oversize_length_is_skipped_not_waited_for() {
        // Long form claiming 60000 bytes.
        let wire = [0x68, 0, 0, 0x68, 0xEA, 0x60, 0, 5, 0x63];
        let mut codec = StreamCodec;
        let mut src = BytesMut::from(&wire[..]);
        assert!(matches!(
            codec.decode(&mut src).unwrap(),
            Some(StreamItem::Skipped {
                bytes: 1,
                why: DecodeError::FrameTooLong { .. }
            })
        ));
    }

    fn arb_frame() -> impl Strategy<Value = Frame> {
        prop_oneof![
            Just(Frame::Ack),
            (
                any::<u8>(),
                any::<u8>(),
                proptest::collection::vec(any::<u8>(), 0..400)
            )
                .prop_map(|(sa, fc, d)| Frame::Data(DataFrame {
                    da: 0,
                    sa,
                    fc,
                    data: d
                })),
        ]
    }

    proptest! {
        /// Frames separated by noise without start bytes come through
        /// exactly, however the bytes are chunked.
        #[test]
        fn frames_survive_noise_between_them(
            sent in proptest::collection::vec(arb_frame(), 1..8),
            noise in proptest::collection::vec(
                any::<u8>().prop_filter("no start byte", |b| *b != START && *b != ACK), 0..20),
            chunk in 1usize..64,
        ) {
            let mut wire = Vec::new();
            for f in &sent {
                wire.extend_from_slice(&noise);
                wire.extend(encode(f).unwrap());
            }
            let mut codec = StreamCodec;
            let mut src = BytesMut::new();
            let mut got = Vec::new();
            for piece in wire.chunks(chunk) {
                src.extend_from_slice(piece);
                while let Some(item) = codec.decode(&mut src).unwrap() {
                    got.push(item);
                }
            }
            prop_assert_eq!(frames(&got), sent);
        }

        /// Any bytes: no panic, everything consumed by EOF, and never more
        /// than one frame's worth held while waiting.
        #[test]
        fn any_bytes_are_consumed_within_bounds(
            bytes in proptest::collection::vec(
                prop_oneof![Just(START), Just(ACK), Just(END), Just(0u8), any::<u8>()], 0..3000),
        ) {
            let mut codec = StreamCodec;
            let mut src = BytesMut::new();
            for piece in bytes.chunks(97) {
                src.extend_from_slice(piece);
                while codec.decode(&mut src).unwrap().is_some() {}
                prop_assert!(src.len() <= MAX_FRAME);
            }
            while codec.decode_eof(&mut src).unwrap().is_some() {}
            prop_assert!(src.is_empty());
        }
    }
}
