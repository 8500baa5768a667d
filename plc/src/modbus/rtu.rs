//! Modbus RTU framing: `unit, PDU, CRC-16/MODBUS (low byte first)`, frames
//! back to back on a serial line or a TCP stream to a serial device server.
//!
//! RTU has no length field: a frame ends with 3.5 characters of silence on
//! the line. Silence does not survive a USB adapter, a pty or a TCP hop, so
//! the decoder takes a frame's length from its function (and byte count),
//! as every practical master does ([`frame_len`]), and checks the CRC. What
//! cannot be framed (a damaged frame, an unknown function, a foreign
//! master's noise) is skipped a byte at a time until a frame with a good
//! CRC starts, and reported as [`RtuItem::Skipped`] with the reason; a frame
//! that stops half-way is given up by [`RtuDecoder::abandon_partial`] once
//! the line has been quiet. Never panics, never holds more than one frame.

use std::fmt;
use std::time::Duration;

use bytes::{Buf, Bytes, BytesMut};

use super::codec::{request_pdu, response_pdu};
use super::frame::{Request, Response};
use super::ExceptionCode;

/// CRC-16/MODBUS (poly 0x8005 reflected, init 0xFFFF).
pub const CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_MODBUS);

/// Longest RTU frame: unit, 253 bytes of PDU, CRC.
pub const MAX_FRAME: usize = 256;
/// Shortest: unit, function, one byte, CRC (an exception).
pub const MIN_FRAME: usize = 5;
/// The broadcast address: every unit obeys a write, none answers.
pub const BROADCAST: u8 = 0;

/// Which end's frames a decoder reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// A master reads answers.
    Responses,
    /// A unit reads requests.
    Requests,
}

/// One frame with a good CRC.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RtuFrame {
    pub unit: u8,
    pub pdu: Bytes,
}

/// Why bytes were skipped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SkipReason {
    /// A frame of the right length whose CRC does not match.
    Crc { got: u16, computed: u16 },
    /// A function this side cannot frame.
    Function(u8),
    /// A byte count that no frame of its function has.
    ByteCount { function: u8, count: u8 },
    /// The line went quiet in the middle of a frame.
    Unfinished,
}

impl fmt::Display for SkipReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SkipReason::Crc { got, computed } => {
                write!(f, "CRC 0x{got:04X} where the frame's is 0x{computed:04X}")
            }
            SkipReason::Function(function) => write!(f, "unknown function 0x{function:02X}"),
            SkipReason::ByteCount { function, count } => {
                write!(f, "byte count {count} for function 0x{function:02X}")
            }
            SkipReason::Unfinished => f.write_str("the line went quiet in the middle of a frame"),
        }
    }
}

/// What the decoder found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RtuItem {
    Frame(RtuFrame),
    /// `bytes` that are no frame, and why the first of them is not.
    Skipped {
        bytes: usize,
        why: SkipReason,
    },
}

/// How long the frame starting `head` is, from its function and byte count:
/// `Ok(None)` when more bytes are needed to tell.
pub fn frame_len(side: Side, head: &[u8]) -> Result<Option<usize>, SkipReason> {
    let Some(&function) = head.get(1) else {
        return Ok(None);
    };
    // Unit, function, `body` bytes, CRC.
    let fixed = |body: usize| Ok(Some(4 + body));
    let counted = |at: usize, max: usize| match head.get(at) {
        None => Ok(None),
        Some(&count) if usize::from(count) > max || count == 0 => {
            Err(SkipReason::ByteCount { function, count })
        }
        Some(&count) => Ok(Some(at + 1 + usize::from(count) + 2)),
    };
    match (side, function) {
        (Side::Responses, f) if f & 0x80 != 0 && f != 0x80 => fixed(1),
        (Side::Responses, 1..=4) => counted(2, 250),
        (Side::Responses, 5 | 6 | 15 | 16) => fixed(4),
        (Side::Responses, 22) => fixed(6),
        (Side::Requests, 1..=6) => fixed(4),
        (Side::Requests, 15 | 16) => counted(6, 246),
        (Side::Requests, 22) => fixed(6),
        _ => Err(SkipReason::Function(function)),
    }
}

/// Splits a byte stream into RTU frames (a tokio-util decoder).
#[derive(Debug, Clone, Copy)]
pub struct RtuDecoder {
    pub side: Side,
}

impl RtuDecoder {
    pub fn new(side: Side) -> RtuDecoder {
        RtuDecoder { side }
    }

    /// The length of a good frame at the start of `src`, `Ok(None)` when
    /// more bytes are needed, or why none starts there.
    fn frame_at(&self, src: &[u8]) -> Result<Option<usize>, SkipReason> {
        let Some(len) = frame_len(self.side, src)? else {
            return Ok(None);
        };
        let Some(frame) = src.get(..len) else {
            return Ok(None);
        };
        let (body, crc) = frame.split_at(len - 2);
        let got = u16::from_le_bytes([crc[0], crc[1]]);
        let computed = CRC.checksum(body);
        if got == computed {
            Ok(Some(len))
        } else {
            Err(SkipReason::Crc { got, computed })
        }
    }

    /// Gives up what is left in `src` (the line has gone quiet): the bytes
    /// of a frame that will not be finished.
    pub fn abandon_partial(&self, src: &mut BytesMut) -> Option<RtuItem> {
        if src.is_empty() {
            return None;
        }
        let bytes = src.len();
        src.clear();
        Some(RtuItem::Skipped {
            bytes,
            why: SkipReason::Unfinished,
        })
    }
}

impl tokio_util::codec::Decoder for RtuDecoder {
    type Item = RtuItem;
    type Error = std::io::Error;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<RtuItem>, std::io::Error> {
        let mut skipped = 0;
        let mut first_reason = None;
        loop {
            match self.frame_at(&src[skipped..]) {
                Ok(found) => {
                    if skipped > 0 {
                        src.advance(skipped);
                        return Ok(Some(RtuItem::Skipped {
                            bytes: skipped,
                            why: first_reason.unwrap_or(SkipReason::Unfinished),
                        }));
                    }
                    let Some(len) = found else {
                        src.reserve(MAX_FRAME.saturating_sub(src.len()));
                        return Ok(None);
                    };
                    let mut frame = src.split_to(len);
                    frame.truncate(len - 2);
                    let unit = frame[0];
                    frame.advance(1);
                    return Ok(Some(RtuItem::Frame(RtuFrame {
                        unit,
                        pdu: frame.freeze(),
                    })));
                }
                Err(reason) => {
                    first_reason.get_or_insert(reason);
                    skipped += 1;
                }
            }
        }
    }
}

/// Appends the frame of `pdu` to or from `unit`.
pub fn encode_pdu(unit: u8, pdu: &[u8], out: &mut Vec<u8>) {
    let start = out.len();
    out.push(unit);
    out.extend_from_slice(pdu);
    let crc = CRC.checksum(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// Appends the frame of `request` to `unit` (the master's side).
pub fn encode_request(unit: u8, request: &Request, out: &mut Vec<u8>) {
    encode_pdu(unit, &request_pdu(request), out);
}

/// Appends the frame answering a request of `function` (a unit's side).
pub fn encode_response(
    unit: u8,
    function: u8,
    request: Option<&Request>,
    answer: &Result<Response, ExceptionCode>,
    out: &mut Vec<u8>,
) {
    encode_pdu(unit, &response_pdu(function, request, answer), out);
}

/// Bits one character takes on the line: start, data, parity, stop.
pub fn char_bits(data_bits: u8, parity: bool, stop_bits: u8) -> u32 {
    1 + u32::from(data_bits) + u32::from(parity) + u32::from(stop_bits)
}

/// Time `bytes` characters of `bits` take at `baud`.
pub fn line_time(baud: u32, bits: u32, bytes: usize) -> Duration {
    Duration::from_secs_f64(bytes as f64 * f64::from(bits) / f64::from(baud.max(1)))
}

/// The silence between frames: 3.5 characters, and 1.75 ms above 19,200
/// baud (the specification's fixed value for fast lines).
pub fn silence(baud: u32, bits: u32) -> Duration {
    if baud > 19_200 {
        Duration::from_micros(1750)
    } else {
        Duration::from_secs_f64(3.5 * f64::from(bits) / f64::from(baud.max(1)))
    }
}

/// The length of the answer to `request` when the unit grants it.
pub fn answer_len(request: &Request) -> usize {
    match request {
        Request::ReadCoils { count, .. } | Request::ReadDiscreteInputs { count, .. } => {
            5 + usize::from(*count).div_ceil(8)
        }
        Request::ReadHoldingRegisters { count, .. } | Request::ReadInputRegisters { count, .. } => {
            5 + 2 * usize::from(*count)
        }
        Request::MaskWriteRegister { .. } => 10,
        _ => 8,
    }
}

#[cfg(test)]
mod tests {
    use tokio_util::codec::Decoder;

    use super::*;
    use crate::modbus::codec::tests::{answer_to, every_request};
    use crate::modbus::codec::{decode_request, decode_response};

    #[test]
    fn the_specifications_example_crc() {
        // Read holding 0x006B, 3 registers from unit 0x11: CRC 0x8776 (76 87).
        let mut out = Vec::new();
        encode_request(
            0x11,
            &Request::ReadHoldingRegisters {
                address: 0x6B,
                count: 3,
            },
            &mut out,
        );
        assert_eq!(out, [0x11, 0x03, 0x00, 0x6B, 0x00, 0x03, 0x76, 0x87]);
    }

    fn frames(side: Side, wire: &[u8]) -> Vec<RtuItem> {
        let mut decoder = RtuDecoder::new(side);
        let mut buf = BytesMut::from(wire);
        let mut items = Vec::new();
        while let Some(item) = decoder.decode(&mut buf).unwrap() {
            items.push(item);
        }
        items.extend(decoder.abandon_partial(&mut buf));
        items
    }

    #[test]
    fn requests_and_answers_round_trip_through_both_ends() {
        for request in every_request() {
            let mut wire = Vec::new();
            encode_request(7, &request, &mut wire);
            let [RtuItem::Frame(frame)] = &frames(Side::Requests, &wire)[..] else {
                panic!("{request:?} is not one frame");
            };
            assert_eq!(frame.unit, 7);
            assert_eq!(decode_request(&frame.pdu), Ok(request.clone()));
            let answer = answer_to(&request);
            let mut wire = Vec::new();
            encode_response(
                7,
                request.function(),
                Some(&request),
                &Ok(answer.clone()),
                &mut wire,
            );
            assert_eq!(wire.len(), answer_len(&request));
            encode_response(
                7,
                request.function(),
                None,
                &Err(ExceptionCode(2)),
                &mut wire,
            );
            let items = frames(Side::Responses, &wire);
            let [RtuItem::Frame(data), RtuItem::Frame(refusal)] = &items[..] else {
                panic!("{items:?}");
            };
            assert_eq!(decode_response(&request, &data.pdu), Ok(Ok(answer)));
            assert_eq!(
                decode_response(&request, &refusal.pdu),
                Ok(Err(ExceptionCode(2)))
            );
        }
    }

    #[test]
    fn damage_is_skipped_with_its_reason_and_the_next_frame_found() {
        let read = Request::ReadHoldingRegisters {
            address: 0,
            count: 2,
        };
        let mut good = Vec::new();
        encode_response(
            1,
            3,
            Some(&read),
            &Ok(Response::Registers(vec![5, 6])),
            &mut good,
        );
        let mut damaged = good.clone();
        damaged[4] ^= 0x10;
        let mut wire = damaged.clone();
        wire.extend_from_slice(&good);
        let items = frames(Side::Responses, &wire);
        assert!(
            matches!(&items[0], RtuItem::Skipped { bytes, why: SkipReason::Crc { .. } } if *bytes == damaged.len()),
            "{items:?}"
        );
        assert!(matches!(&items[1], RtuItem::Frame(f) if f.unit == 1));
        assert_eq!(items.len(), 2);

        // Noise of an unknown function, then a frame.
        let mut wire = vec![0x01, 0x42, 0x99];
        wire.extend_from_slice(&good);
        let items = frames(Side::Responses, &wire);
        assert!(matches!(
            &items[0],
            RtuItem::Skipped {
                why: SkipReason::Function(0x42),
                ..
            }
        ));
        assert!(matches!(&items[1], RtuItem::Frame(_)));

        // Half a frame waits, then is given up when the line goes quiet.
        let items = frames(Side::Responses, &good[..5]);
        assert_eq!(
            items,
            [RtuItem::Skipped {
                bytes: 5,
                why: SkipReason::Unfinished
            }]
        );
        assert_eq!(
            frame_len(Side::Responses, &[1, 3, 0]),
            Err(SkipReason::ByteCount {
                function: 3,
                count: 0
            })
        );
    }

    #[test]
    fn silences_and_line_times() {
        let bits = char_bits(8, true, 1);
        assert_eq!(bits, 11);
        // 3.5 x 11 bits at 9600 baud.
        assert_eq!(silence(9600, bits), Duration::from_secs_f64(38.5 / 9600.0));
        assert_eq!(silence(115_200, bits), Duration::from_micros(1750));
        assert_eq!(line_time(9600, 10, 960), Duration::from_secs(1));
    }
}
