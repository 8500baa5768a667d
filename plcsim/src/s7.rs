//! The simulated PLC as a Siemens S7 CPU (`plcsim --s7`): the same device,
//! program and fault injection as the EPSNET one, over ISO-on-TCP with the
//! frames of `plccoms_plc::s7`. Its memory holds what [`MAP`] lays out:
//! inputs, outputs, the merkers and DB1 to DB16 of 64 KiB each (any other
//! DB "does not exist");
//! its variables are named by an S7 tag file (default `conf/demo-s7.csv`).
//! It grants the PDU asked for up to 960 and 20 items a job, takes bit
//! items (the byte's other bits kept) and tells its RUN/STOP mode in SZL
//! 0x0424 (`halt`/`run` on the control port).
//!
//! Faults: a lost request is never answered (the client's retry is); latency
//! delays each answer, answers leaving in the order their requests came.

use std::sync::Arc;

use bytes::Bytes;
use futures_util::StreamExt;
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};
use tokio_util::codec::{Encoder, FramedRead};

use plccoms_plc::memory::MemoryMap;
use plccoms_plc::s7::codec::TpktCodec;
use plccoms_plc::s7::frame::{Answer, Item, Job, Tpdu};
use plccoms_plc::s7::pack::MAX_ITEMS;
use plccoms_plc::s7::{Region, ReturnCode, BLOCK};
use plccoms_plc::{MemoryImage, WriteData};

use crate::Shared;

/// The data blocks served: DB1 to DB16.
pub const DBS: u16 = 16;

/// Inputs, outputs, the system registers, the merkers and the DBs.
pub const MAP: MemoryMap = MemoryMap {
    sizes: [BLOCK, BLOCK, 4096, (DBS as u32 + 1) * BLOCK],
};

/// Largest PDU granted.
const MAX_PDU: u16 = 960;

pub(crate) async fn serve(listener: TcpListener, shared: Arc<Shared>) {
    crate::accept(listener, shared, connection).await
}

async fn connection(stream: TcpStream, shared: Arc<Shared>) {
    let _ = stream.set_nodelay(true);
    let (read, mut write) = stream.into_split();
    let mut frames = FramedRead::new(read, TpktCodec);
    let mut out = bytes::BytesMut::new();
    // A stream that cannot be framed ends the connection, as on a CPU.
    while let Some(Ok(tpdu)) = frames.next().await {
        let reply = match tpdu {
            Tpdu::ConnectRequest(tsaps) => Tpdu::ConnectConfirm(tsaps),
            Tpdu::Data(pdu) => {
                let Ok((pdu_ref, job)) = Job::parse(&pdu) else {
                    break;
                };
                let Some((answer, latency)) = shared.handle_s7(&job) else {
                    continue;
                };
                if !latency.is_zero() {
                    tokio::time::sleep(latency).await;
                }
                let mut pdu = bytes::BytesMut::new();
                answer.encode(pdu_ref, &mut pdu);
                Tpdu::Data(pdu.freeze())
            }
            _ => break,
        };
        out.clear();
        if TpktCodec.encode(reply, &mut out).is_err() || write.write_all(&out).await.is_err() {
            break;
        }
    }
}

/// The answer to `job` on the image; `run`: the CPU's mode.
pub fn apply(image: &mut MemoryImage, run: bool, job: &Job) -> Answer {
    // Where `len` bytes of `item` lie: within its block, in a DB served.
    let place = |item: &Item, len: u32| match item.region {
        Region::Db(n) if n > DBS => Err(ReturnCode::NO_OBJECT),
        _ if item.start + len > BLOCK => Err(ReturnCode::OUT_OF_RANGE),
        region => Ok(region.place(item.start)),
    };
    match job {
        Job::Setup { jobs, pdu } => Answer::Setup {
            jobs: (*jobs).clamp(1, 8),
            pdu: (*pdu).clamp(240, MAX_PDU),
        },
        Job::Read(items) if items.len() > MAX_ITEMS => Answer::Refused(ReturnCode::Job(0x8500)),
        Job::Read(items) => Answer::Read(
            items
                .iter()
                .map(|item| {
                    let len = if item.bit.is_some() {
                        1
                    } else {
                        u32::from(item.len)
                    };
                    let (area, offset) = place(item, len)?;
                    let bytes = image
                        .read(area, offset, len)
                        .map_err(|_| ReturnCode::OUT_OF_RANGE)?;
                    Ok(match item.bit {
                        Some(bit) => Bytes::from(vec![bytes[0] >> bit & 1]),
                        None => Bytes::copy_from_slice(bytes),
                    })
                })
                .collect(),
        ),
        Job::Write(items) if items.len() > MAX_ITEMS => Answer::Refused(ReturnCode::Job(0x8500)),
        Job::Write(items) => Answer::Write(
            items
                .iter()
                .map(|(item, data)| {
                    let (area, offset) = place(item, data.len() as u32)?;
                    let write = match item.bit {
                        Some(bit) => WriteData::Bit {
                            bit,
                            value: data.first().is_some_and(|b| b & 1 != 0),
                        },
                        None => WriteData::Bytes(data.to_vec()),
                    };
                    image
                        .write(area, offset, &write)
                        .map_err(|_| ReturnCode::OUT_OF_RANGE)
                })
                .collect(),
        ),
        Job::ReadSzl { id: 0x0424, .. } => {
            // Header (id, index, record length 20, one record), then the
            // record whose fourth byte is the mode (8 RUN, 4 STOP).
            let mut szl = vec![0x04, 0x24, 0, 0, 0, 20, 0, 1];
            let mut record = [0u8; 20];
            record[0..2].copy_from_slice(&[0x51, 0x44]);
            record[2] = 0xFF;
            record[3] = if run { 0x08 } else { 0x04 };
            szl.extend_from_slice(&record);
            Answer::Szl(Ok(Bytes::from(szl)))
        }
        Job::ReadSzl { .. } => Answer::Szl(Err(ReturnCode::Job(0x8104))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_plc::s7::frame::cpu_running;

    #[test]
    fn serves_dbs_merkers_and_bits() {
        let mut image = MemoryImage::new(MAP);
        let write = Job::Write(vec![
            (
                Item::bytes(Region::Db(1), 4, 2),
                Bytes::from_static(&[1, 2]),
            ),
            (
                Item {
                    region: Region::Merkers,
                    start: 3,
                    bit: Some(5),
                    len: 1,
                },
                Bytes::from_static(&[1]),
            ),
            (
                Item::bytes(Region::Db(DBS + 1), 0, 1),
                Bytes::from_static(&[1]),
            ),
        ]);
        assert_eq!(
            apply(&mut image, true, &write),
            Answer::Write(vec![Ok(()), Ok(()), Err(ReturnCode::NO_OBJECT)])
        );
        let read = Job::Read(vec![
            Item::bytes(Region::Db(1), 4, 2),
            Item::bytes(Region::Merkers, 3, 1),
            Item::bytes(Region::Db(1), 65535, 2),
        ]);
        assert_eq!(
            apply(&mut image, true, &read),
            Answer::Read(vec![
                Ok(Bytes::from_static(&[1, 2])),
                Ok(Bytes::from_static(&[0x20])),
                Err(ReturnCode::OUT_OF_RANGE),
            ])
        );
        let Answer::Szl(Ok(szl)) = apply(
            &mut image,
            false,
            &Job::ReadSzl {
                id: 0x424,
                index: 0,
            },
        ) else {
            panic!("no SZL");
        };
        assert_eq!(cpu_running(&szl), Some(false));
    }
}
