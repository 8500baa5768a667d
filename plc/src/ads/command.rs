//! ADS commands: requests (the client encodes, a device decodes) and their
//! answers (the device encodes, the client decodes against the command it
//! sent), and the device notification stream. A body that does not fit is
//! a [`BodyError`] naming the command and what was wrong; nothing here
//! panics or allocates more than the body it was given.

use bytes::{Buf, BufMut, Bytes, BytesMut};

use super::frame::CommandId;
use super::{AdsError, AdsState};

/// A request's data.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request {
    ReadDeviceInfo,
    ReadState,
    Read {
        group: u32,
        offset: u32,
        len: u32,
    },
    Write {
        group: u32,
        offset: u32,
        data: Bytes,
    },
    ReadWrite {
        group: u32,
        offset: u32,
        read_len: u32,
        data: Bytes,
    },
    AddNotification {
        group: u32,
        offset: u32,
        len: u32,
        mode: TransMode,
        /// Longest the device may hold a change back, in 100 ns.
        max_delay: u32,
        /// The device's check cycle, in 100 ns.
        cycle: u32,
    },
    DeleteNotification {
        handle: u32,
    },
}

/// When a device notification is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TransMode(pub u32);

impl TransMode {
    /// Every cycle, changed or not.
    pub const CYCLIC: TransMode = TransMode(3);
    /// When the value changed, checked every cycle.
    pub const ON_CHANGE: TransMode = TransMode(4);
}

impl Request {
    pub fn command(&self) -> CommandId {
        match self {
            Request::ReadDeviceInfo => CommandId::READ_DEVICE_INFO,
            Request::ReadState => CommandId::READ_STATE,
            Request::Read { .. } => CommandId::READ,
            Request::Write { .. } => CommandId::WRITE,
            Request::ReadWrite { .. } => CommandId::READ_WRITE,
            Request::AddNotification { .. } => CommandId::ADD_NOTIFICATION,
            Request::DeleteNotification { .. } => CommandId::DELETE_NOTIFICATION,
        }
    }

    pub fn encode(&self) -> Bytes {
        let mut out = BytesMut::new();
        match self {
            Request::ReadDeviceInfo | Request::ReadState => {}
            Request::Read { group, offset, len } => {
                out.put_u32_le(*group);
                out.put_u32_le(*offset);
                out.put_u32_le(*len);
            }
            Request::Write {
                group,
                offset,
                data,
            } => {
                out.put_u32_le(*group);
                out.put_u32_le(*offset);
                out.put_u32_le(data.len() as u32);
                out.put_slice(data);
            }
            Request::ReadWrite {
                group,
                offset,
                read_len,
                data,
            } => {
                out.put_u32_le(*group);
                out.put_u32_le(*offset);
                out.put_u32_le(*read_len);
                out.put_u32_le(data.len() as u32);
                out.put_slice(data);
            }
            Request::AddNotification {
                group,
                offset,
                len,
                mode,
                max_delay,
                cycle,
            } => {
                out.put_u32_le(*group);
                out.put_u32_le(*offset);
                out.put_u32_le(*len);
                out.put_u32_le(mode.0);
                out.put_u32_le(*max_delay);
                out.put_u32_le(*cycle);
                out.put_bytes(0, 16);
            }
            Request::DeleteNotification { handle } => out.put_u32_le(*handle),
        }
        out.freeze()
    }

    /// A request's data as a device reads it.
    pub fn decode(command: CommandId, data: &Bytes) -> Result<Request, BodyError> {
        let mut body = Body::new(command, data);
        let request = match command {
            CommandId::READ_DEVICE_INFO => Request::ReadDeviceInfo,
            CommandId::READ_STATE => Request::ReadState,
            CommandId::READ => Request::Read {
                group: body.u32("index group")?,
                offset: body.u32("index offset")?,
                len: body.u32("length")?,
            },
            CommandId::WRITE => {
                let (group, offset) = (body.u32("index group")?, body.u32("index offset")?);
                let len = body.u32("length")?;
                Request::Write {
                    group,
                    offset,
                    data: body.bytes(len, "data")?,
                }
            }
            CommandId::READ_WRITE => {
                let (group, offset) = (body.u32("index group")?, body.u32("index offset")?);
                let read_len = body.u32("read length")?;
                let len = body.u32("write length")?;
                Request::ReadWrite {
                    group,
                    offset,
                    read_len,
                    data: body.bytes(len, "write data")?,
                }
            }
            CommandId::ADD_NOTIFICATION => Request::AddNotification {
                group: body.u32("index group")?,
                offset: body.u32("index offset")?,
                len: body.u32("length")?,
                mode: TransMode(body.u32("transmission mode")?),
                max_delay: body.u32("max delay")?,
                cycle: body.u32("cycle time")?,
            },
            CommandId::DELETE_NOTIFICATION => Request::DeleteNotification {
                handle: body.u32("handle")?,
            },
            _ => return Err(body.error("unknown command".into())),
        };
        Ok(request)
    }
}

/// What a device answered to one request (its result code already checked).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Response {
    DeviceInfo {
        version: (u8, u8, u16),
        name: String,
    },
    State {
        ads: AdsState,
        device: u16,
    },
    /// Read and ReadWrite.
    Data(Bytes),
    /// Write, WriteControl, DeleteNotification.
    Done,
    /// AddNotification.
    Handle(u32),
}

impl Response {
    /// The answer to `command` in `data`: the device's refusal (its result
    /// code), or what it answered.
    pub fn decode(
        command: CommandId,
        data: &Bytes,
    ) -> Result<Result<Response, AdsError>, BodyError> {
        let mut body = Body::new(command, data);
        let result = body.u32("result")?;
        if result != 0 {
            return Ok(Err(AdsError(result)));
        }
        let response = match command {
            CommandId::READ_DEVICE_INFO => {
                let version = (
                    body.u8("major version")?,
                    body.u8("minor version")?,
                    body.u16("build")?,
                );
                let name = body.bytes(16.min(body.rest.len() as u32), "name")?;
                let end = name.iter().position(|&b| b == 0).unwrap_or(name.len());
                Response::DeviceInfo {
                    version,
                    name: String::from_utf8_lossy(&name[..end]).into_owned(),
                }
            }
            CommandId::READ_STATE => Response::State {
                ads: AdsState(body.u16("ADS state")?),
                device: body.u16("device state")?,
            },
            CommandId::READ | CommandId::READ_WRITE => {
                let len = body.u32("length")?;
                Response::Data(body.bytes(len, "data")?)
            }
            CommandId::ADD_NOTIFICATION => Response::Handle(body.u32("notification handle")?),
            CommandId::WRITE | CommandId::WRITE_CONTROL | CommandId::DELETE_NOTIFICATION => {
                Response::Done
            }
            _ => return Err(body.error("not a command with an answer".into())),
        };
        Ok(Ok(response))
    }

    /// The answer's data as a device writes it (result 0).
    pub fn encode(&self) -> Bytes {
        let mut out = BytesMut::new();
        out.put_u32_le(0);
        match self {
            Response::DeviceInfo { version, name } => {
                out.put_u8(version.0);
                out.put_u8(version.1);
                out.put_u16_le(version.2);
                let mut field = [0u8; 16];
                let n = name.len().min(15);
                field[..n].copy_from_slice(&name.as_bytes()[..n]);
                out.put_slice(&field);
            }
            Response::State { ads, device } => {
                out.put_u16_le(ads.0);
                out.put_u16_le(*device);
            }
            Response::Data(data) => {
                out.put_u32_le(data.len() as u32);
                out.put_slice(data);
            }
            Response::Done => {}
            Response::Handle(handle) => out.put_u32_le(*handle),
        }
        out.freeze()
    }
}

/// A refusal's data as a device writes it: the result code alone (with a
/// zero length for the commands whose answer carries one).
pub fn encode_refusal(command: CommandId, error: AdsError) -> Bytes {
    let mut out = BytesMut::new();
    out.put_u32_le(error.0);
    if matches!(command, CommandId::READ | CommandId::READ_WRITE) {
        out.put_u32_le(0);
    }
    out.freeze()
}

/// One sample of a device notification.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Sample {
    pub handle: u32,
    pub data: Bytes,
}

/// The samples a device took at one time.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stamp {
    /// FILETIME: 100 ns since 1601-01-01 UTC, the device's clock.
    pub filetime: u64,
    pub samples: Vec<Sample>,
}

/// A device notification's data: length, stamp count, then each stamp with
/// its samples.
pub fn decode_notification(data: &Bytes) -> Result<Vec<Stamp>, BodyError> {
    let mut body = Body::new(CommandId::NOTIFICATION, data);
    let len = body.u32("length")?;
    if len as usize != body.rest.len() {
        return Err(body.error(format!(
            "length {len} where {} bytes follow",
            body.rest.len()
        )));
    }
    let count = body.u32("stamp count")?;
    // Each stamp takes at least 12 bytes: a count past that is a lie.
    let mut stamps = Vec::with_capacity((count as usize).min(body.rest.len() / 12));
    for _ in 0..count {
        let filetime = body.u64("time stamp")?;
        let samples = body.u32("sample count")?;
        let mut stamp = Stamp {
            filetime,
            samples: Vec::with_capacity((samples as usize).min(body.rest.len() / 8)),
        };
        for _ in 0..samples {
            let handle = body.u32("notification handle")?;
            let size = body.u32("sample size")?;
            stamp.samples.push(Sample {
                handle,
                data: body.bytes(size, "sample")?,
            });
        }
        stamps.push(stamp);
    }
    body.end()?;
    Ok(stamps)
}

/// A device notification's data from `stamps`.
pub fn encode_notification(stamps: &[Stamp]) -> Bytes {
    let mut inner = BytesMut::new();
    inner.put_u32_le(stamps.len() as u32);
    for stamp in stamps {
        inner.put_u64_le(stamp.filetime);
        inner.put_u32_le(stamp.samples.len() as u32);
        for sample in &stamp.samples {
            inner.put_u32_le(sample.handle);
            inner.put_u32_le(sample.data.len() as u32);
            inner.put_slice(&sample.data);
        }
    }
    let mut out = BytesMut::with_capacity(4 + inner.len());
    out.put_u32_le(inner.len() as u32);
    out.put_slice(&inner);
    out.freeze()
}

/// One result of a sum command: the device's code and the data.
pub type SumResult = Result<Bytes, AdsError>;

/// The data of a sum read's answer (index group SUMUP_READ): one result
/// code per sub-request, then each one's data, `sizes` long, whatever its
/// code (TwinCAT keeps a refused sub-request's room; pyads reads it so).
pub fn decode_sum_read(data: &Bytes, sizes: &[u32]) -> Result<Vec<SumResult>, BodyError> {
    let mut body = Body::new(CommandId::READ_WRITE, data);
    let mut codes = Vec::with_capacity(sizes.len());
    for _ in sizes {
        codes.push(body.u32("sum result")?);
    }
    let mut results = Vec::with_capacity(sizes.len());
    for (code, &size) in codes.into_iter().zip(sizes) {
        let data = body.bytes(size, "sum data")?;
        results.push(match code {
            0 => Ok(data),
            code => Err(AdsError(code)),
        });
    }
    Ok(results)
}

/// The data of a sum write or sum read-write answer: per sub-request a
/// result code (and for read-write, a length), then the read-write data.
pub fn decode_sum_read_write(data: &Bytes, count: usize) -> Result<Vec<SumResult>, BodyError> {
    let mut body = Body::new(CommandId::READ_WRITE, data);
    let mut heads = Vec::with_capacity(count.min(body.rest.len() / 8));
    for _ in 0..count {
        heads.push((body.u32("sum result")?, body.u32("sum length")?));
    }
    let mut results = Vec::with_capacity(heads.len());
    for (code, len) in heads {
        let data = body.bytes(len, "sum data")?;
        results.push(match code {
            0 => Ok(data),
            code => Err(AdsError(code)),
        });
    }
    Ok(results)
}

/// A body that does not fit its command.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("ADS command {command} at byte {at}: {message}")]
pub struct BodyError {
    pub command: u16,
    pub at: usize,
    pub message: String,
}

/// A cursor over a body, each read naming what it reads.
struct Body<'a> {
    command: CommandId,
    all: &'a Bytes,
    rest: &'a [u8],
}

impl<'a> Body<'a> {
    fn new(command: CommandId, all: &'a Bytes) -> Body<'a> {
        Body {
            command,
            all,
            rest: all,
        }
    }

    fn at(&self) -> usize {
        self.all.len() - self.rest.len()
    }

    fn error(&self, message: String) -> BodyError {
        BodyError {
            command: self.command.0,
            at: self.at(),
            message,
        }
    }

    fn need(&self, n: usize, what: &str) -> Result<(), BodyError> {
        if self.rest.len() < n {
            return Err(self.error(format!("{what} needs {n} bytes, {} left", self.rest.len())));
        }
        Ok(())
    }

    fn u8(&mut self, what: &str) -> Result<u8, BodyError> {
        self.need(1, what)?;
        Ok(self.rest.get_u8())
    }

    fn u16(&mut self, what: &str) -> Result<u16, BodyError> {
        self.need(2, what)?;
        Ok(self.rest.get_u16_le())
    }

    fn u32(&mut self, what: &str) -> Result<u32, BodyError> {
        self.need(4, what)?;
        Ok(self.rest.get_u32_le())
    }

    fn u64(&mut self, what: &str) -> Result<u64, BodyError> {
        self.need(8, what)?;
        Ok(self.rest.get_u64_le())
    }

    fn bytes(&mut self, len: u32, what: &str) -> Result<Bytes, BodyError> {
        let len = len as usize;
        self.need(len, what)?;
        let from = self.at();
        self.rest = &self.rest[len..];
        Ok(self.all.slice(from..from + len))
    }

    fn end(&self) -> Result<(), BodyError> {
        if self.rest.is_empty() {
            Ok(())
        } else {
            Err(self.error(format!("{} bytes past the end", self.rest.len())))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_round_trip() {
        let requests = [
            Request::ReadState,
            Request::Read {
                group: 0xF005,
                offset: 9,
                len: 4,
            },
            Request::Write {
                group: 1,
                offset: 2,
                data: Bytes::from_static(b"ab"),
            },
            Request::ReadWrite {
                group: 0xF003,
                offset: 0,
                read_len: 4,
                data: Bytes::from_static(b"MAIN.x"),
            },
            Request::AddNotification {
                group: 0xF005,
                offset: 3,
                len: 2,
                mode: TransMode::ON_CHANGE,
                max_delay: 0,
                cycle: 100_000,
            },
            Request::DeleteNotification { handle: 12 },
        ];
        for request in requests {
            let data = request.encode();
            assert_eq!(Request::decode(request.command(), &data).unwrap(), request);
        }
    }

    #[test]
    fn answers_and_refusals() {
        let data = Response::Data(Bytes::from_static(&[1, 2])).encode();
        assert_eq!(
            Response::decode(CommandId::READ, &data).unwrap(),
            Ok(Response::Data(Bytes::from_static(&[1, 2])))
        );
        let refused = encode_refusal(CommandId::READ_WRITE, AdsError::SYMBOL_NOT_FOUND);
        assert_eq!(
            Response::decode(CommandId::READ_WRITE, &refused).unwrap(),
            Err(AdsError::SYMBOL_NOT_FOUND)
        );
        // A read answer promising more than it holds.
        let short = Bytes::from_static(&[0, 0, 0, 0, 9, 0, 0, 0, 1]);
        let err = Response::decode(CommandId::READ, &short).unwrap_err();
        assert_eq!(
            err.to_string(),
            "ADS command 2 at byte 8: data needs 9 bytes, 1 left"
        );
    }

    #[test]
    fn notifications_round_trip_with_their_stamps() {
        let stamps = vec![Stamp {
            filetime: 133_549_839_305_000_000,
            samples: vec![
                Sample {
                    handle: 1,
                    data: Bytes::from_static(&[7, 0]),
                },
                Sample {
                    handle: 2,
                    data: Bytes::from_static(&[1]),
                },
            ],
        }];
        let data = encode_notification(&stamps);
        assert_eq!(decode_notification(&data).unwrap(), stamps);
        // A stamp count of 4 billion in 8 bytes fails, without allocating.
        let lie = Bytes::from_static(&[4, 0, 0, 0, 0xFF, 0xFF, 0xFF, 0xFF]);
        assert!(decode_notification(&lie).is_err());
    }

    #[test]
    fn sum_reads_split_by_result() {
        let mut data = BytesMut::new();
        data.put_u32_le(0);
        data.put_u32_le(0x710);
        data.put_u32_le(0);
        data.put_slice(&[1, 2]);
        data.put_slice(&[0]);
        data.put_slice(&[3, 4, 5, 6]);
        let results = decode_sum_read(&data.freeze(), &[2, 1, 4]).unwrap();
        assert_eq!(results[0], Ok(Bytes::from_static(&[1, 2])));
        assert_eq!(results[1], Err(AdsError::SYMBOL_NOT_FOUND));
        assert_eq!(results[2], Ok(Bytes::from_static(&[3, 4, 5, 6])));
    }
}
