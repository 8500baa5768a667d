//! Modbus TCP bytes <-> frames, for both ends: the MBAP header that frames
//! each ADU on the TCP stream ([`AduDecoder`], a tokio-util decoder), requests
//! (the client encodes, the server decodes) and answers (the server encodes,
//! the client decodes against the request it sent). Never panics on what
//! the wire brings: a malformed ADU is a typed error.
//!
//! MBAP header: transaction id (2 bytes), protocol id (2, always 0), length
//! (2: the bytes that follow, unit id included), unit id (1); then the PDU,
//! at most 253 bytes. All fields big-endian.

use bytes::{Buf, Bytes, BytesMut};

use super::frame::*;
use super::{
    ExceptionCode, MAX_READ_BITS, MAX_READ_REGISTERS, MAX_WRITE_BITS, MAX_WRITE_REGISTERS,
};

pub const HEADER_LEN: usize = 7;
pub const MAX_PDU: usize = 253;
pub const MAX_ADU: usize = HEADER_LEN + MAX_PDU;

/// The MBAP fields that identify a transaction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    pub transaction: u16,
    pub unit: u8,
}

/// One ADU as read from the stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Adu {
    pub header: Header,
    pub pdu: Bytes,
}

/// The stream cannot be framed any more (the connection must be closed).
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    #[error("protocol id {0} is not Modbus (0)")]
    Protocol(u16),
    #[error("ADU length field {0} is outside 2..=254")]
    Length(u16),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// An answer that does not answer the request it was matched with.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AnswerError {
    #[error("empty PDU")]
    Empty,
    #[error("function 0x{got:02X} answers a request of function 0x{sent:02X}")]
    Function { sent: u8, got: u8 },
    #[error("{0} bytes where the function needs {1}")]
    Length(usize, usize),
    #[error("byte count {0} where {1} were asked for")]
    ByteCount(u8, usize),
    #[error("the write echo does not match the request")]
    Echo,
}

/// Splits a TCP stream into ADUs.
#[derive(Debug, Default, Clone, Copy)]
pub struct AduDecoder;

impl tokio_util::codec::Decoder for AduDecoder {
    type Item = Adu;
    type Error = FrameError;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<Adu>, FrameError> {
        if src.len() < HEADER_LEN {
            return Ok(None);
        }
        let protocol = u16::from_be_bytes([src[2], src[3]]);
        if protocol != 0 {
            return Err(FrameError::Protocol(protocol));
        }
        let length = u16::from_be_bytes([src[4], src[5]]);
        if !(2..=(MAX_PDU as u16 + 1)).contains(&length) {
            return Err(FrameError::Length(length));
        }
        let total = HEADER_LEN - 1 + usize::from(length);
        if src.len() < total {
            src.reserve(total - src.len());
            return Ok(None);
        }
        let header = Header {
            transaction: u16::from_be_bytes([src[0], src[1]]),
            unit: src[6],
        };
        src.advance(HEADER_LEN);
        let pdu = src.split_to(total - HEADER_LEN).freeze();
        Ok(Some(Adu { header, pdu }))
    }
}

fn put_header(header: Header, pdu_len: usize, out: &mut Vec<u8>) {
    out.extend_from_slice(&header.transaction.to_be_bytes());
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&(pdu_len as u16 + 1).to_be_bytes());
    out.push(header.unit);
}

fn pack_bits(bits: &[bool]) -> Vec<u8> {
    let mut bytes = vec![0u8; bits.len().div_ceil(8)];
    for (i, _) in bits.iter().enumerate().filter(|(_, on)| **on) {
        bytes[i / 8] |= 1 << (i % 8);
    }
    bytes
}

fn unpack_bits(bytes: &[u8], count: usize) -> Vec<bool> {
    (0..count)
        .map(|i| bytes[i / 8] & (1 << (i % 8)) != 0)
        .collect()
}

fn words(bytes: &[u8]) -> Vec<u16> {
    bytes
        .chunks_exact(2)
        .map(|w| u16::from_be_bytes([w[0], w[1]]))
        .collect()
}

/// The PDU of `request`.
pub fn request_pdu(request: &Request) -> Vec<u8> {
    let mut pdu = vec![request.function()];
    let mut put = |v: u16| pdu.extend_from_slice(&v.to_be_bytes());
    match request {
        Request::ReadCoils { address, count }
        | Request::ReadDiscreteInputs { address, count }
        | Request::ReadHoldingRegisters { address, count }
        | Request::ReadInputRegisters { address, count } => {
            put(*address);
            put(*count);
        }
        Request::WriteSingleCoil { address, value } => {
            put(*address);
            put(if *value { 0xFF00 } else { 0 });
        }
        Request::WriteSingleRegister { address, value } => {
            put(*address);
            put(*value);
        }
        Request::WriteMultipleCoils { address, values } => {
            put(*address);
            put(values.len() as u16);
            let packed = pack_bits(values);
            pdu.push(packed.len() as u8);
            pdu.extend_from_slice(&packed);
        }
        Request::WriteMultipleRegisters { address, values } => {
            put(*address);
            put(values.len() as u16);
            pdu.push((values.len() * 2) as u8);
            for v in values {
                pdu.extend_from_slice(&v.to_be_bytes());
            }
        }
        Request::MaskWriteRegister {
            address,
            and_mask,
            or_mask,
        } => {
            put(*address);
            put(*and_mask);
            put(*or_mask);
        }
    }
    pdu
}

/// Appends the ADU of `request` (the client's side).
pub fn encode_request(header: Header, request: &Request, out: &mut Vec<u8>) {
    let pdu = request_pdu(request);
    put_header(header, pdu.len(), out);
    out.extend_from_slice(&pdu);
}

/// The answer `pdu` gives to `request` (the client's side): the data, the
/// device's exception, or why it is no answer to it.
pub fn decode_response(
    request: &Request,
    pdu: &[u8],
) -> Result<Result<Response, ExceptionCode>, AnswerError> {
    let (&function, body) = pdu.split_first().ok_or(AnswerError::Empty)?;
    let sent = request.function();
    if function == sent | 0x80 {
        return match body {
            [code] => Ok(Err(ExceptionCode(*code))),
            _ => Err(AnswerError::Length(pdu.len(), 2)),
        };
    }
    if function != sent {
        return Err(AnswerError::Function {
            sent,
            got: function,
        });
    }
    let exact = |len: usize| {
        if body.len() == len {
            Ok(())
        } else {
            Err(AnswerError::Length(pdu.len(), len + 1))
        }
    };
    let counted = |expected: usize| -> Result<&[u8], AnswerError> {
        let (&count, data) = body.split_first().ok_or(AnswerError::Length(1, 2))?;
        if usize::from(count) != expected {
            return Err(AnswerError::ByteCount(count, expected));
        }
        exact(expected + 1)?;
        Ok(data)
    };
    let echo = |expected: &[u8]| {
        exact(expected.len())?;
        if body == expected {
            Ok(Ok(Response::Written))
        } else {
            Err(AnswerError::Echo)
        }
    };
    let sent_pdu = request_pdu(request);
    match request {
        Request::ReadCoils { count, .. } | Request::ReadDiscreteInputs { count, .. } => {
            let count = usize::from(*count);
            let data = counted(count.div_ceil(8))?;
            Ok(Ok(Response::Bits(unpack_bits(data, count))))
        }
        Request::ReadHoldingRegisters { count, .. } | Request::ReadInputRegisters { count, .. } => {
            let data = counted(2 * usize::from(*count))?;
            Ok(Ok(Response::Registers(words(data))))
        }
        Request::WriteSingleCoil { .. }
        | Request::WriteSingleRegister { .. }
        | Request::MaskWriteRegister { .. } => echo(&sent_pdu[1..]),
        // Address and quantity.
        Request::WriteMultipleCoils { .. } | Request::WriteMultipleRegisters { .. } => {
            echo(&sent_pdu[1..5])
        }
    }
}

/// The request in `pdu` (the server's side), or the exception that answers
/// it: 1 for a function this project does not serve, 3 for a malformed or
/// out-of-range quantity (the specification's rules).
pub fn decode_request(pdu: &[u8]) -> Result<Request, ExceptionCode> {
    let bad = ExceptionCode::ILLEGAL_DATA_VALUE;
    let (&function, body) = pdu.split_first().ok_or(bad)?;
    let field = |i: usize| -> Result<u16, ExceptionCode> {
        body.get(2 * i..2 * i + 2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
            .ok_or(bad)
    };
    let quantity = |max: u16| -> Result<(u16, u16), ExceptionCode> {
        let (address, count) = (field(0)?, field(1)?);
        if count == 0 || count > max {
            return Err(bad);
        }
        if u32::from(address) + u32::from(count) > 65_536 {
            return Err(ExceptionCode::ILLEGAL_DATA_ADDRESS);
        }
        Ok((address, count))
    };
    let fixed = |len: usize| if body.len() == len { Ok(()) } else { Err(bad) };
    match function {
        READ_COILS | READ_DISCRETE_INPUTS | READ_HOLDING_REGISTERS | READ_INPUT_REGISTERS => {
            fixed(4)?;
            let bits = matches!(function, READ_COILS | READ_DISCRETE_INPUTS);
            let (address, count) = quantity(if bits {
                MAX_READ_BITS
            } else {
                MAX_READ_REGISTERS
            })?;
            Ok(match function {
                READ_COILS => Request::ReadCoils { address, count },
                READ_DISCRETE_INPUTS => Request::ReadDiscreteInputs { address, count },
                READ_HOLDING_REGISTERS => Request::ReadHoldingRegisters { address, count },
                _ => Request::ReadInputRegisters { address, count },
            })
        }
        WRITE_SINGLE_COIL => {
            fixed(4)?;
            let value = match field(1)? {
                0xFF00 => true,
                0 => false,
                _ => return Err(bad),
            };
            Ok(Request::WriteSingleCoil {
                address: field(0)?,
                value,
            })
        }
        WRITE_SINGLE_REGISTER => {
            fixed(4)?;
            Ok(Request::WriteSingleRegister {
                address: field(0)?,
                value: field(1)?,
            })
        }
        WRITE_MULTIPLE_COILS | WRITE_MULTIPLE_REGISTERS => {
            let coils = function == WRITE_MULTIPLE_COILS;
            let (address, count) = quantity(if coils {
                MAX_WRITE_BITS
            } else {
                MAX_WRITE_REGISTERS
            })?;
            let bytes = if coils {
                usize::from(count).div_ceil(8)
            } else {
                2 * usize::from(count)
            };
            if body.get(4).map(|&n| usize::from(n)) != Some(bytes) {
                return Err(bad);
            }
            fixed(5 + bytes)?;
            let data = &body[5..];
            Ok(if coils {
                Request::WriteMultipleCoils {
                    address,
                    values: unpack_bits(data, usize::from(count)),
                }
            } else {
                Request::WriteMultipleRegisters {
                    address,
                    values: words(data),
                }
            })
        }
        MASK_WRITE_REGISTER => {
            fixed(6)?;
            Ok(Request::MaskWriteRegister {
                address: field(0)?,
                and_mask: field(1)?,
                or_mask: field(2)?,
            })
        }
        _ => Err(ExceptionCode::ILLEGAL_FUNCTION),
    }
}

/// Appends the ADU answering a request of `function` (the server's side):
/// the exception, or the data of a read, or the echo of a write.
pub fn encode_response(
    header: Header,
    function: u8,
    request: Option<&Request>,
    answer: &Result<Response, ExceptionCode>,
    out: &mut Vec<u8>,
) {
    let pdu = response_pdu(function, request, answer);
    put_header(header, pdu.len(), out);
    out.extend_from_slice(&pdu);
}

/// The PDU answering a request of `function` (the server's side, any
/// framing).
pub fn response_pdu(
    function: u8,
    request: Option<&Request>,
    answer: &Result<Response, ExceptionCode>,
) -> Vec<u8> {
    match (answer, request) {
        (Err(code), _) => vec![function | 0x80, code.0],
        // Data without the request it answers: the server failed.
        (Ok(_), None) => vec![function | 0x80, ExceptionCode::SERVER_DEVICE_FAILURE.0],
        (Ok(Response::Bits(bits)), Some(_)) => {
            let packed = pack_bits(bits);
            let mut pdu = vec![function, packed.len() as u8];
            pdu.extend_from_slice(&packed);
            pdu
        }
        (Ok(Response::Registers(values)), Some(_)) => {
            let mut pdu = vec![function, (values.len() * 2) as u8];
            for v in values {
                pdu.extend_from_slice(&v.to_be_bytes());
            }
            pdu
        }
        (Ok(Response::Written), Some(request)) => {
            let sent = request_pdu(request);
            let echo = match request {
                Request::WriteMultipleCoils { .. } | Request::WriteMultipleRegisters { .. } => {
                    &sent[..5]
                }
                _ => &sent[..],
            };
            echo.to_vec()
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use tokio_util::codec::Decoder;

    use super::*;

    /// One request of every function, for the framings' tests.
    pub(crate) fn every_request() -> Vec<Request> {
        vec![
            Request::ReadCoils {
                address: 1,
                count: 10,
            },
            Request::ReadDiscreteInputs {
                address: 65_535,
                count: 1,
            },
            Request::ReadHoldingRegisters {
                address: 100,
                count: 125,
            },
            Request::ReadInputRegisters {
                address: 0,
                count: 3,
            },
            Request::WriteSingleCoil {
                address: 7,
                value: true,
            },
            Request::WriteSingleRegister {
                address: 8,
                value: 0xBEEF,
            },
            Request::WriteMultipleCoils {
                address: 9,
                values: vec![true, false, true, true, false, false, false, false, true],
            },
            Request::WriteMultipleRegisters {
                address: 10,
                values: vec![1, 2, 3],
            },
            Request::MaskWriteRegister {
                address: 11,
                and_mask: 0xFFFE,
                or_mask: 1,
            },
        ]
    }

    /// A granted answer to `request`.
    pub(crate) fn answer_to(request: &Request) -> Response {
        match request {
            Request::ReadCoils { count, .. } | Request::ReadDiscreteInputs { count, .. } => {
                Response::Bits((0..*count).map(|i| i % 3 == 0).collect())
            }
            Request::ReadHoldingRegisters { count, .. }
            | Request::ReadInputRegisters { count, .. } => {
                Response::Registers((0..*count).collect())
            }
            _ => Response::Written,
        }
    }

    #[test]
    fn requests_and_answers_round_trip_through_both_ends() {
        for (i, request) in every_request().into_iter().enumerate() {
            let header = Header {
                transaction: i as u16 * 1000,
                unit: 3,
            };
            let mut wire = Vec::new();
            encode_request(header, &request, &mut wire);
            let mut buf = BytesMut::from(&wire[..]);
            let adu = AduDecoder.decode(&mut buf).unwrap().unwrap();
            assert!(buf.is_empty());
            assert_eq!(adu.header, header);
            assert_eq!(decode_request(&adu.pdu), Ok(request.clone()));
            let answer = answer_to(&request);
            let mut out = Vec::new();
            encode_response(
                header,
                request.function(),
                Some(&request),
                &Ok(answer.clone()),
                &mut out,
            );
            let mut buf = BytesMut::from(&out[..]);
            let adu = AduDecoder.decode(&mut buf).unwrap().unwrap();
            assert_eq!(decode_response(&request, &adu.pdu), Ok(Ok(answer)));
            let mut out = Vec::new();
            encode_response(
                header,
                request.function(),
                None,
                &Err(ExceptionCode(2)),
                &mut out,
            );
            let adu = AduDecoder
                .decode(&mut BytesMut::from(&out[..]))
                .unwrap()
                .unwrap();
            assert_eq!(
                decode_response(&request, &adu.pdu),
                Ok(Err(ExceptionCode(2)))
            );
        }
    }

    #[test]
    fn wrong_answers_are_typed_errors() {
        let read = Request::ReadHoldingRegisters {
            address: 0,
            count: 2,
        };
        assert_eq!(decode_response(&read, &[]), Err(AnswerError::Empty));
        assert!(matches!(
            decode_response(&read, &[0x04, 4, 0, 0, 0, 0]),
            Err(AnswerError::Function { .. })
        ));
        assert_eq!(
            decode_response(&read, &[0x03, 2, 0, 0]),
            Err(AnswerError::ByteCount(2, 4))
        );
        assert!(decode_response(&read, &[0x03, 4, 0, 0, 0]).is_err());
        let write = Request::WriteSingleRegister {
            address: 1,
            value: 2,
        };
        assert_eq!(
            decode_response(&write, &[0x06, 0, 1, 0, 3]),
            Err(AnswerError::Echo)
        );
    }

    #[test]
    fn the_decoder_waits_for_whole_adus_and_refuses_garbage() {
        let mut wire = Vec::new();
        encode_request(
            Header {
                transaction: 1,
                unit: 1,
            },
            &Request::ReadCoils {
                address: 0,
                count: 1,
            },
            &mut wire,
        );
        let mut buf = BytesMut::from(&wire[..5]);
        assert!(AduDecoder.decode(&mut buf).unwrap().is_none());
        buf.extend_from_slice(&wire[5..]);
        buf.extend_from_slice(&wire[..3]);
        assert!(AduDecoder.decode(&mut buf).unwrap().is_some());
        assert!(AduDecoder.decode(&mut buf).unwrap().is_none());
        let mut bad = BytesMut::from(&[0u8, 1, 0, 1, 0, 6, 1][..]);
        assert!(matches!(
            AduDecoder.decode(&mut bad),
            Err(FrameError::Protocol(1))
        ));
        let mut bad = BytesMut::from(&[0u8, 1, 0, 0, 1, 0, 1][..]);
        assert!(matches!(
            AduDecoder.decode(&mut bad),
            Err(FrameError::Length(256))
        ));
    }

    #[test]
    fn server_side_refusals() {
        assert_eq!(decode_request(&[0x2B, 0x0E]), Err(ExceptionCode(1)));
        assert_eq!(decode_request(&[0x03, 0, 0, 0, 126]), Err(ExceptionCode(3)));
        assert_eq!(
            decode_request(&[0x03, 0xFF, 0xFF, 0, 2]),
            Err(ExceptionCode(2))
        );
        assert_eq!(
            decode_request(&[0x05, 0, 0, 0x12, 0x34]),
            Err(ExceptionCode(3))
        );
    }
}
