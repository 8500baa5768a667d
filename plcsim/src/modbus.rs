//! The simulated PLC as a Modbus TCP device: the same device, program and
//! fault injection as the EPSNET one, its memory laid out as
//! `plccoms_plc::modbus` describes (coils in Y one a byte, discrete inputs in
//! X, holding registers in R from 0, input registers from 131072, high byte
//! first), its variables named by a tag file. Every address of every table
//! exists.
//!
//! The same device speaks Modbus RTU on a serial line ([`serve_rtu`]).
//!
//! Faults: a lost request is never answered (the client's retry is); latency
//! delays each answer, answers leaving in the order their requests came.

use std::sync::Arc;
use std::time::Duration;

use std::sync::atomic::Ordering;

use bytes::BytesMut;
use futures_util::StreamExt;
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::codec::{Decoder, FramedRead};

use plccoms_plc::modbus::codec::{
    decode_request, encode_response, Adu, AduDecoder, Header, HEADER_LEN,
};
use plccoms_plc::modbus::frame::{Request, Response};
use plccoms_plc::modbus::rtu::{self, RtuDecoder, RtuItem, Side};
use plccoms_plc::modbus::{ExceptionCode, Table};
use plccoms_plc::{MemoryImage, WriteData};
use plccoms_protocol::Area;

use crate::serial::{self, SerialLine};
use crate::Shared;

/// Answers of one connection waiting for their latency.
const MAX_QUEUED: usize = 256;

/// Serves `units`: one device answers every unit id; of several, unit id
/// `k` (1..=N) is device `k - 1`, any other the first.
pub(crate) async fn serve(listener: TcpListener, units: Arc<[Arc<Shared>]>) {
    crate::accept(listener, units, connection).await
}

fn by_unit(units: &[Arc<Shared>], unit: u8) -> &Shared {
    match units {
        [one] => one,
        _ => units
            .get(usize::from(unit).wrapping_sub(1))
            .unwrap_or(&units[0]),
    }
}

async fn connection(stream: TcpStream, units: Arc<[Arc<Shared>]>) {
    let _ = stream.set_nodelay(true);
    let (read, mut write) = stream.into_split();
    let mut frames = FramedRead::new(read, AduDecoder);
    let (answers, mut queue) = mpsc::channel::<(Instant, Vec<u8>)>(MAX_QUEUED);
    let writer = tokio::spawn(async move {
        while let Some((due, bytes)) = queue.recv().await {
            // The timer has millisecond steps: no detour through it
            // without latency.
            if due > Instant::now() {
                tokio::time::sleep_until(due).await;
            }
            if write.write_all(&bytes).await.is_err() {
                break;
            }
        }
    });
    // A stream that cannot be framed ends the connection, as on a device.
    while let Some(Ok(adu)) = frames.next().await {
        let shared = by_unit(&units, adu.header.unit);
        let Some((answer, latency)) = shared.handle_modbus(&adu) else {
            continue;
        };
        if answers
            .try_send((Instant::now() + latency, answer))
            .is_err()
        {
            // Too many answers held back: dropped, as a lost request.
            continue;
        }
    }
    drop(answers);
    let _ = writer.await;
}

/// Serves Modbus RTU as `units` (one memory) on a serial line until the
/// task is aborted: requests to them are answered, broadcasts (unit 0)
/// obeyed silently, other units' frames ignored (the line is shared). With
/// [`SerialLine::emulate`] each answer is held back for the line time of the
/// request and the answer at 11 bits a character (8E1) and the 3.5
/// characters of silence that end the request.
pub(crate) async fn serve_rtu(
    mut port: tokio_serial::SerialStream,
    line: SerialLine,
    units: Vec<u8>,
    shared: Arc<Shared>,
) {
    let mut decoder = RtuDecoder::new(Side::Requests);
    let mut buf = BytesMut::with_capacity(rtu::MAX_FRAME);
    let stats = &shared.line;
    // A frame stopped half-way is given up after this quiet time.
    let idle = Duration::from_millis(20);
    loop {
        while let Ok(Some(item)) = decoder.decode(&mut buf) {
            let frame = match item {
                RtuItem::Frame(frame) => frame,
                RtuItem::Skipped { bytes, .. } => {
                    stats.rx_skipped.fetch_add(bytes as u64, Ordering::Relaxed);
                    continue;
                }
            };
            stats.rx_frames.fetch_add(1, Ordering::Relaxed);
            if !units.contains(&frame.unit) && frame.unit != rtu::BROADCAST {
                continue;
            }
            let adu = Adu {
                header: Header {
                    transaction: 0,
                    unit: frame.unit,
                },
                pdu: frame.pdu.clone(),
            };
            let Some((tcp, latency)) = shared.handle_modbus(&adu) else {
                continue;
            };
            if frame.unit == rtu::BROADCAST {
                continue;
            }
            let mut bytes = Vec::with_capacity(rtu::MAX_FRAME);
            rtu::encode_pdu(
                frame.unit,
                tcp.get(HEADER_LEN..).unwrap_or_default(),
                &mut bytes,
            );
            let mut due = Instant::now() + latency;
            if line.emulate {
                let on_line = frame.pdu.len() + 3 + bytes.len();
                due += rtu::line_time(line.speed, 11, on_line) + rtu::silence(line.speed, 11);
                // To the microsecond: the timer's millisecond steps would
                // add up to 4 % to a transaction at 115,200 baud.
                if due > Instant::now() + Duration::from_millis(2) {
                    tokio::time::sleep_until(due - Duration::from_millis(1)).await;
                }
                while Instant::now() < due {
                    tokio::task::yield_now().await;
                }
            } else if !latency.is_zero() {
                tokio::time::sleep_until(due).await;
            }
            if !serial::send(&mut port, &bytes, &line, stats).await {
                return;
            }
        }
        if serial::read_more(&mut port, &mut buf, stats, idle).await {
            if let Some(RtuItem::Skipped { bytes, .. }) = decoder.abandon_partial(&mut buf) {
                stats.rx_skipped.fetch_add(bytes as u64, Ordering::Relaxed);
            }
        }
    }
}

/// The answer ADU to `adu`.
pub(crate) fn answer(image: &mut MemoryImage, adu: &Adu) -> Vec<u8> {
    let function = adu.pdu.first().copied().unwrap_or(0);
    let request = decode_request(&adu.pdu);
    let outcome = request
        .as_ref()
        .map_err(|e| *e)
        .and_then(|r| apply(image, r));
    let mut out = Vec::with_capacity(16);
    encode_response(
        adu.header,
        function,
        request.as_ref().ok(),
        &outcome,
        &mut out,
    );
    out
}

/// Serves one request on the image.
pub fn apply(image: &mut MemoryImage, request: &Request) -> Result<Response, ExceptionCode> {
    let bits = |image: &MemoryImage, table: Table, address: u16, count: u16| {
        let (area, offset) = table.place(address);
        let bytes = image
            .read(area, offset, u32::from(count))
            .map_err(|_| ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
        Ok(Response::Bits(bytes.iter().map(|b| b & 1 != 0).collect()))
    };
    let registers = |image: &MemoryImage, table: Table, address: u16, count: u16| {
        let (area, offset) = table.place(address);
        let bytes = image
            .read(area, offset, 2 * u32::from(count))
            .map_err(|_| ExceptionCode::ILLEGAL_DATA_ADDRESS)?;
        Ok(Response::Registers(
            bytes
                .chunks_exact(2)
                .map(|w| u16::from_be_bytes([w[0], w[1]]))
                .collect(),
        ))
    };
    let write = |image: &mut MemoryImage, area: Area, offset: u32, data: WriteData| {
        image
            .write(area, offset, &data)
            .map(|_| Response::Written)
            .map_err(|_| ExceptionCode::ILLEGAL_DATA_ADDRESS)
    };
    let coil = |address: u16| Table::Coil.place(address).1;
    let holding = |address: u16| Table::Holding.place(address).1;
    match request {
        Request::ReadCoils { address, count } => bits(image, Table::Coil, *address, *count),
        Request::ReadDiscreteInputs { address, count } => {
            bits(image, Table::Discrete, *address, *count)
        }
        Request::ReadHoldingRegisters { address, count } => {
            registers(image, Table::Holding, *address, *count)
        }
        Request::ReadInputRegisters { address, count } => {
            registers(image, Table::Input, *address, *count)
        }
        Request::WriteSingleCoil { address, value } => write(
            image,
            Area::Y,
            coil(*address),
            WriteData::Bytes(vec![u8::from(*value)]),
        ),
        Request::WriteMultipleCoils { address, values } => write(
            image,
            Area::Y,
            coil(*address),
            WriteData::Bytes(values.iter().map(|&v| u8::from(v)).collect()),
        ),
        Request::WriteSingleRegister { address, value } => write(
            image,
            Area::R,
            holding(*address),
            WriteData::Bytes(value.to_be_bytes().to_vec()),
        ),
        Request::WriteMultipleRegisters { address, values } => write(
            image,
            Area::R,
            holding(*address),
            WriteData::Bytes(values.iter().flat_map(|v| v.to_be_bytes()).collect()),
        ),
        Request::MaskWriteRegister {
            address,
            and_mask,
            or_mask,
        } => {
            let Response::Registers(current) = registers(image, Table::Holding, *address, 1)?
            else {
                return Err(ExceptionCode::SERVER_DEVICE_FAILURE);
            };
            let value = (current[0] & and_mask) | (or_mask & !and_mask);
            write(
                image,
                Area::R,
                holding(*address),
                WriteData::Bytes(value.to_be_bytes().to_vec()),
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_plc::modbus::MAP;

    #[test]
    fn registers_and_coils_on_the_layout() {
        let mut image = MemoryImage::new(MAP);
        apply(
            &mut image,
            &Request::WriteMultipleRegisters {
                address: 65_534,
                values: vec![0x1234, 0xABCD],
            },
        )
        .unwrap();
        assert_eq!(
            image.read(Area::R, 131_068, 4).unwrap(),
            &[0x12, 0x34, 0xAB, 0xCD]
        );
        apply(
            &mut image,
            &Request::MaskWriteRegister {
                address: 65_534,
                and_mask: 0xFF00,
                or_mask: 0x0001,
            },
        )
        .unwrap();
        assert_eq!(
            apply(
                &mut image,
                &Request::ReadHoldingRegisters {
                    address: 65_534,
                    count: 1
                }
            ),
            Ok(Response::Registers(vec![0x1201]))
        );
        apply(
            &mut image,
            &Request::WriteMultipleCoils {
                address: 3,
                values: vec![true, false, true],
            },
        )
        .unwrap();
        assert_eq!(
            apply(
                &mut image,
                &Request::ReadCoils {
                    address: 2,
                    count: 5
                }
            ),
            Ok(Response::Bits(vec![false, true, false, true, false]))
        );
        assert_eq!(
            apply(
                &mut image,
                &Request::ReadInputRegisters {
                    address: 65_535,
                    count: 2
                }
            ),
            Err(ExceptionCode::ILLEGAL_DATA_ADDRESS)
        );
    }
}
