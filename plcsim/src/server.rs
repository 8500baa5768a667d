//! The simulated PLC's EPSNET side: one datagram in, one datagram out, using
//! the same frames, codec and service table as the client.
//!
//! A datagram that does not decode, or carries a frame not addressed to this
//! PLC (or an `E5`), is dropped without an answer, as a PLC on a bus ignores
//! what is not for it. A well-formed frame with an unknown or malformed
//! request is answered with the PLC's error byte.

use plccoms_plc::epsnet::codec;
use plccoms_plc::epsnet::frame::{Frame, Packet, MAX_DPLEN};
use plccoms_plc::epsnet::service::{
    self, answer_frame, dir_entry_len, Request, Response, MAX_DIR_PAGE, MAX_FILE_BLOCK, MAX_READ,
};
use plccoms_plc::epsnet::PLC_EPS_ADDR;
use plccoms_plc::{time, Exception, WriteData};

use crate::Device;
use plccoms_protocol::cp1250;

/// Runs one request against the device. `clock_offset` is the PLC clock's
/// offset from the host clock in seconds (set by SETTID).
pub fn execute(
    request: Request,
    device: &mut Device,
    clock_offset: &mut f64,
) -> Result<Response, Exception> {
    const BAD: Exception = Exception::BadParameters;
    match request {
        Request::Ident => {
            let mut ident = cp1250::try_encode(&device.ident)
                .unwrap_or_else(|| device.ident.bytes().filter(u8::is_ascii).collect());
            // Clients plan for at most this much (see `Request::max_answer_len`).
            ident.truncate(service::MAX_IDENT);
            Ok(Response::Ident(ident))
        }
        Request::Status => Ok(Response::Status { run: device.run() }),
        Request::SetTime(t) => {
            let valid = (1..=12).contains(&t.month)
                && (1..=31).contains(&t.day)
                && t.hour < 24
                && t.minute < 60
                && t.second < 60
                && (1..=7).contains(&t.weekday);
            if !valid {
                return Err(BAD);
            }
            let days = time::days_from_civil(i64::from(t.year), t.month.into(), t.day.into());
            let target = days as f64 * 86_400.0
                + f64::from(t.hour) * 3600.0
                + f64::from(t.minute) * 60.0
                + f64::from(t.second);
            *clock_offset = target - time::unix_now();
            Ok(Response::Done)
        }
        Request::Read { area, offset, len } => {
            if u32::from(len) > MAX_READ {
                return Err(BAD);
            }
            device.read(area, offset, len.into()).map(Response::Data)
        }
        Request::Write { area, offset, data } => {
            if data.len() > MAX_READ as usize {
                return Err(BAD);
            }
            device
                .write(area, offset, &WriteData::Bytes(data))
                .map(|()| Response::Done)
        }
        Request::WriteBits {
            area,
            offset,
            mask,
            value,
        } => {
            let old = device.read(area, offset, 1)?[0];
            let new = (old & !mask) | (value & mask);
            device
                .write(area, offset, &WriteData::Bytes(vec![new]))
                .map(|()| Response::Done)
        }
        Request::FileInfo { path } => files(device)?.info(&path).map(Response::FileInfo),
        Request::FileRead { path, offset, len } => {
            if u32::from(len) > MAX_FILE_BLOCK {
                return Err(BAD);
            }
            files(device)?
                .read(&path, offset, len.into())
                .map(Response::Data)
        }
        Request::FileWrite {
            path,
            offset,
            last,
            data,
        } => {
            if data.len() > MAX_FILE_BLOCK as usize {
                return Err(BAD);
            }
            files(device)?
                .write(&path, offset, &data, last)
                .map(|()| Response::Done)
        }
        Request::FileWriteInfo { path, info } => files(device)?
            .write_info(&path, &info)
            .map(|()| Response::Done),
        Request::DirList { path, start } => {
            let all = files(device)?.list(&path)?;
            let start = usize::from(start);
            if start > all.len() {
                return Err(BAD);
            }
            let mut size = 1;
            let mut entries = Vec::new();
            for entry in &all[start..] {
                let len = dir_entry_len(entry);
                if size + len > MAX_DIR_PAGE {
                    break;
                }
                size += len;
                entries.push(entry.clone());
            }
            let more = start + entries.len() < all.len();
            Ok(Response::DirPage { entries, more })
        }
    }
}

fn files(device: &mut Device) -> Result<&mut crate::FileStore, Exception> {
    device.files.as_mut().ok_or(Exception::NotActivated)
}

/// Answers one request frame; `None` means stay silent (an `E5`, or a
/// frame for another station).
pub fn handle_frame(frame: &Frame, device: &mut Device, clock_offset: &mut f64) -> Option<Frame> {
    let Frame::Data(f) = frame else { return None };
    if f.da != PLC_EPS_ADDR {
        return None;
    }
    let code = f.data.first().copied().unwrap_or(0);
    let answer = Request::decode(f.fc, &f.data).and_then(|r| execute(r, device, clock_offset));
    Some(answer_frame(f.sa, PLC_EPS_ADDR, code, &answer))
}

/// Answers one datagram; `None` means stay silent.
pub fn handle_datagram(
    bytes: &[u8],
    device: &mut Device,
    clock_offset: &mut f64,
) -> Option<Vec<u8>> {
    let packet = match codec::decode_packet(bytes) {
        Ok(packet) => packet,
        Err(e) => {
            tracing::debug!("plcsim: dropped datagram: {e}");
            return None;
        }
    };
    let mut frames = Vec::with_capacity(packet.frames.len());
    for frame in &packet.frames {
        frames.push(handle_frame(frame, device, clock_offset)?);
    }
    // The answer must fit one datagram too: the largest data answers give
    // way to an error byte until it does.
    let mut total: usize = frames.iter().map(Frame::encoded_len).sum();
    while total > MAX_DPLEN {
        let (i, len) = frames
            .iter()
            .enumerate()
            .map(|(i, f)| (i, f.encoded_len()))
            .max_by_key(|&(_, len)| len)?;
        let Frame::Data(f) = &frames[i] else {
            return None;
        };
        let error = answer_frame(
            f.da,
            PLC_EPS_ADDR,
            f.data.first().copied().unwrap_or(0),
            &Err(Exception::BadParameters),
        );
        if error.encoded_len() >= len {
            return None;
        }
        total = total - len + error.encoded_len();
        frames[i] = error;
    }
    codec::encode_packet(&Packet {
        mesi: packet.mesi,
        frames,
    })
    .ok()
}

/// A source of randomness for packet loss (xorshift64*): no dependency, and
/// reproducible with a seed.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed | 1)
    }

    pub fn from_time() -> Self {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0x9E37_79B9_7F4A_7C15);
        Rng::new(nanos ^ u64::from(std::process::id()) << 32)
    }

    /// Uniform in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let x = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D);
        (x >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_plc::MemoryMap;
    use plccoms_protocol::Area;

    fn request_packet(requests: &[Request]) -> Vec<u8> {
        codec::encode_packet(&Packet {
            mesi: 7,
            frames: requests.iter().map(|r| r.to_frame(0, 5)).collect(),
        })
        .unwrap()
    }

    #[test]
    fn answers_every_frame_in_order_with_the_same_mesi() {
        let mut device = Device::new(MemoryMap::FOXTROT);
        let mut clock = 0.0;
        let bytes = request_packet(&[
            Request::Write {
                area: Area::R,
                offset: 0,
                data: vec![1, 2],
            },
            Request::Read {
                area: Area::R,
                offset: 0,
                len: 2,
            },
            Request::Read {
                area: Area::R,
                offset: 512 * 1024 - 1,
                len: 2,
            },
            Request::FileInfo { path: vec![] },
        ]);
        let answer = handle_datagram(&bytes, &mut device, &mut clock).unwrap();
        let packet = codec::decode_packet(&answer).unwrap();
        assert_eq!(packet.mesi, 7);
        assert_eq!(packet.frames.len(), 4);
        assert_eq!(packet.frames[0], Frame::Ack);
        let read = Request::Read {
            area: Area::R,
            offset: 0,
            len: 2,
        };
        assert_eq!(
            service::decode_answer(&read, &packet.frames[1]),
            Ok(Ok(Response::Data(vec![1, 2])))
        );
        assert_eq!(
            service::decode_answer(&read, &packet.frames[2]),
            Ok(Err(Exception::BadParameters))
        );
        assert_eq!(
            service::decode_answer(&Request::FileInfo { path: vec![] }, &packet.frames[3]),
            Ok(Err(Exception::NotActivated))
        );
    }

    #[test]
    fn silent_on_garbage_and_foreign_frames() {
        let mut device = Device::new(MemoryMap::FOXTROT);
        let mut clock = 0.0;
        assert!(handle_datagram(&[1, 2, 3], &mut device, &mut clock).is_none());
        let foreign = codec::encode_packet(&Packet {
            mesi: 1,
            frames: vec![Request::Ident.to_frame(9, 5)],
        })
        .unwrap();
        assert!(handle_datagram(&foreign, &mut device, &mut clock).is_none());
    }

    #[test]
    fn oversized_answers_become_error_bytes() {
        let mut device = Device::new(MemoryMap::FOXTROT);
        let mut clock = 0.0;
        let read = Request::Read {
            area: Area::R,
            offset: 0,
            len: 1230,
        };
        let bytes = request_packet(&[read.clone(), read.clone()]);
        let answer = handle_datagram(&bytes, &mut device, &mut clock).unwrap();
        assert!(answer.len() <= plccoms_plc::epsnet::frame::MAX_PACKET);
        let packet = codec::decode_packet(&answer).unwrap();
        let errors = packet
            .frames
            .iter()
            .filter(|f| service::decode_answer(&read, f) == Ok(Err(Exception::BadParameters)))
            .count();
        assert_eq!(errors, 1);
    }
}
