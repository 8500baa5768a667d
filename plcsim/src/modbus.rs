//! The simulated PLC as a Modbus TCP device: the same device, program and
//! fault injection as the EPSNET one, its memory laid out as
//! `plccoms_plc::modbus` describes (coils in Y one a byte, discrete inputs in
//! X, holding registers in R from 0, input registers from 131072, high byte
//! first), its variables named by a tag file. Every address of every table
//! exists.
//!
//! Faults: a lost request is never answered (the client's retry is); latency
//! delays each answer, answers leaving in the order their requests came.

use std::sync::Arc;

use futures_util::StreamExt;
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::codec::FramedRead;

use plccoms_plc::modbus::codec::{decode_request, encode_response, Adu, AduDecoder};
use plccoms_plc::modbus::frame::{Request, Response};
use plccoms_plc::modbus::{ExceptionCode, Table};
use plccoms_plc::{MemoryImage, WriteData};
use plccoms_protocol::Area;

use crate::Shared;

/// Answers of one connection waiting for their latency.
const MAX_QUEUED: usize = 256;

pub(crate) async fn serve(listener: TcpListener, shared: Arc<Shared>) {
    crate::accept(listener, shared, connection).await
}

async fn connection(stream: TcpStream, shared: Arc<Shared>) {
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
