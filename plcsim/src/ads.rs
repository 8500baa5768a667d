//! The simulated PLC as a Beckhoff ADS device (AMS/TCP): the same device,
//! program and fault injection as the EPSNET one, its public file's
//! variables served as ADS symbols, readable by handle, by sum command and
//! by index group/offset, and sent as device notifications.
//!
//! A variable of R is a symbol of index group 0x4020 (TwinCAT's %M) at its
//! byte offset, of X 0xF020 (%I), of Y 0xF030 (%Q); a BOOL is a byte 0/1 at
//! the bit groups 0x4021, 0xF021, 0xF031 (offset: byte x 8 + bit), as
//! TwinCAT addresses bits. DATE and DT (8 bytes here, 4 in TwinCAT) and the
//! system variables are not served. The symbol version follows `__PF_CRC`,
//! so loading another public file (the control port's `pub`) is a new
//! program; a handle carries the version it was given under and is refused
//! (0x710) after a change, as TwinCAT's are.
//!
//! Faults: a lost request is never answered; latency delays each answer.

use std::sync::Arc;
use std::time::Duration;

use bytes::{Bytes, BytesMut};
use futures_util::StreamExt;
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};
use tokio_util::codec::{Encoder, FramedRead};

use plccoms_plc::ads::command::{
    encode_notification, encode_refusal, Request, Response, Sample, Stamp,
};
use plccoms_plc::ads::frame::{AmsCodec, AmsHeader, AmsPacket, CommandId, STATE_ADS};
use plccoms_plc::ads::symbols::{encode_symbol, Symbol};
use plccoms_plc::ads::{group, unix_to_filetime, AdsError, AdsState, MAX_SUM};
use plccoms_plc::{MemoryImage, WriteData};
use plccoms_protocol::{Area, IecType};

use crate::{lock, Shared};

/// Notifications one connection may hold (TwinCAT's limit is per router;
/// this keeps a client that never deletes its own bounded).
const MAX_NOTIFICATIONS: usize = 10_000;

pub(crate) async fn serve(listener: TcpListener, shared: Arc<Shared>) {
    loop {
        match listener.accept().await {
            Ok((stream, _)) => {
                tokio::spawn(connection(stream, shared.clone()));
            }
            Err(e) => {
                tracing::debug!("plcsim: accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    }
}

/// One variable as an ADS symbol.
struct SimSymbol {
    symbol: Symbol,
    area: Area,
    offset: u32,
    bit: Option<u8>,
}

/// The program's variables as symbols, and the symbol version.
fn symbols(shared: &Shared) -> (Vec<SimSymbol>, u8) {
    let state = lock(&shared.state);
    let crc = lock(&shared.device).pf_crc();
    let list = state
        .program
        .vars()
        .iter()
        .filter(|v| !v.name.starts_with(b"__"))
        .filter_map(|var| {
            let (group, bit_group) = match var.area {
                Area::R => (0x4020, 0x4021),
                Area::X => (0xF020, 0xF021),
                Area::Y => (0xF030, 0xF031),
                Area::S => return None,
            };
            let (type_name, id) = match var.ty {
                IecType::Date | IecType::Dt => return None,
                IecType::String(n) => (format!("STRING({n})"), 30),
                IecType::Bool => ("BOOL".into(), 33),
                ty => (ty.to_string(), 65),
            };
            let (group, offset) = match var.bit {
                Some(bit) => (bit_group, var.offset * 8 + u32::from(bit)),
                None => (group, var.offset),
            };
            Some(SimSymbol {
                symbol: Symbol {
                    name: String::from_utf8_lossy(&var.name).into_owned(),
                    group,
                    offset,
                    size: var.ty.size() as u32,
                    data_type: id,
                    type_name,
                    comment: String::new(),
                },
                area: var.area,
                offset: var.offset,
                bit: var.bit,
            })
        })
        .collect();
    (list, (crc % 255) as u8 + 1)
}

fn value(image: &MemoryImage, s: &SimSymbol) -> Option<Vec<u8>> {
    let bytes = image.read(s.area, s.offset, s.symbol.size).ok()?;
    Some(match s.bit {
        Some(bit) => vec![(bytes[0] >> bit) & 1],
        None => bytes.to_vec(),
    })
}

/// A handle: the symbol version in the top byte, the symbol's index + 1.
fn handle(version: u8, index: usize) -> u32 {
    (u32::from(version) << 24) | (index as u32 + 1)
}

fn by_handle(handle: u32, version: u8, count: usize) -> Option<usize> {
    let index = (handle & 0x00FF_FFFF) as usize;
    (handle >> 24 == u32::from(version) && (1..=count).contains(&index)).then(|| index - 1)
}

/// A notification a client asked for.
struct Note {
    handle: u32,
    symbol: String,
    version: u8,
    last: Option<Vec<u8>>,
}

struct Conn {
    shared: Arc<Shared>,
    notes: Vec<Note>,
    next_note: u32,
    /// Notification samples sent, for the log at the end (bench/ads
    /// compares them with what the historian recorded).
    sent: u64,
}

async fn connection(stream: TcpStream, shared: Arc<Shared>) {
    let _ = stream.set_nodelay(true);
    let (read, mut write) = stream.into_split();
    let mut frames = FramedRead::new(read, AmsCodec);
    let mut conn = Conn {
        shared,
        notes: Vec::new(),
        next_note: 1,
        sent: 0,
    };
    let mut ticks = tokio::time::interval(Duration::from_millis(1));
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // Who the notifications go to: the last request's sender.
    let mut client: Option<AmsHeader> = None;
    loop {
        let mut out = BytesMut::new();
        tokio::select! {
            frame = frames.next() => {
                let Some(Ok(packet)) = frame else { break };
                if packet.header.is_response() {
                    continue;
                }
                let (lost, latency) = {
                    let mut state = lock(&conn.shared.state);
                    let lost = state.loss > 0.0 && state.rng.next_f64() < state.loss;
                    (lost, state.latency)
                };
                if lost {
                    continue;
                }
                client = Some(packet.header);
                let data = conn.answer(&packet);
                if !latency.is_zero() {
                    tokio::time::sleep(latency).await;
                }
                let answer = AmsPacket { header: packet.header.response(0), data };
                let _ = AmsCodec.encode(answer, &mut out);
            }
            _ = ticks.tick(), if !conn.notes.is_empty() => {
                let (Some(header), Some(data)) = (client, conn.changes()) else { continue };
                let packet = AmsPacket {
                    header: AmsHeader {
                        target: header.source,
                        source: header.target,
                        command: CommandId::NOTIFICATION,
                        state: STATE_ADS,
                        error: 0,
                        invoke_id: 0,
                    },
                    data,
                };
                let _ = AmsCodec.encode(packet, &mut out);
            }
        }
        if write.write_all(&out).await.is_err() {
            break;
        }
    }
    tracing::info!(
        "plcsim: ADS connection closed: {} notification samples sent",
        conn.sent
    );
}

impl Conn {
    /// The notified values that changed, as one stamp at the PLC's time.
    fn changes(&mut self) -> Option<Bytes> {
        let (list, version) = symbols(&self.shared);
        let now = {
            let state = lock(&self.shared.state);
            plccoms_plc::time::unix_now() + state.clock_offset
        };
        let device = lock(&self.shared.device);
        let mut samples = Vec::new();
        for note in &mut self.notes {
            let Some(s) = list.iter().find(|s| s.symbol.name == note.symbol) else {
                continue;
            };
            if note.version != version {
                continue;
            }
            let Some(bytes) = value(&device.image, s) else {
                continue;
            };
            if note.last.as_ref() != Some(&bytes) {
                note.last = Some(bytes.clone());
                samples.push(Sample {
                    handle: note.handle,
                    data: Bytes::from(bytes),
                });
            }
        }
        self.sent += samples.len() as u64;
        (!samples.is_empty()).then(|| {
            encode_notification(&[Stamp {
                filetime: unix_to_filetime(now),
                samples,
            }])
        })
    }

    fn answer(&mut self, packet: &AmsPacket) -> Bytes {
        let command = packet.header.command;
        let request = match Request::decode(command, &packet.data) {
            Ok(request) => request,
            Err(_) => return encode_refusal(command, AdsError(0x70B)),
        };
        match self.serve(request) {
            Ok(response) => response.encode(),
            Err(e) => encode_refusal(command, e),
        }
    }

    fn serve(&mut self, request: Request) -> Result<Response, AdsError> {
        let (list, version) = symbols(&self.shared);
        match request {
            Request::ReadDeviceInfo => Ok(Response::DeviceInfo {
                version: (3, 1, 4024),
                name: "plcsim".into(),
            }),
            Request::ReadState => {
                let run = lock(&self.shared.device).run();
                let ads = if run { AdsState::RUN } else { AdsState::STOP };
                Ok(Response::State { ads, device: 0 })
            }
            Request::Read { group, offset, len } => {
                let data = self.read(&list, version, group, offset, len)?;
                Ok(Response::Data(data))
            }
            Request::Write {
                group,
                offset,
                data,
            } => {
                self.write(&list, version, group, offset, &data)?;
                Ok(Response::Done)
            }
            Request::ReadWrite {
                group,
                offset,
                read_len,
                data,
            } => self
                .read_write(&list, version, group, offset, read_len, &data)
                .map(Response::Data),
            Request::AddNotification {
                group, offset, len, ..
            } => {
                if self.notes.len() >= MAX_NOTIFICATIONS {
                    return Err(AdsError(0x716));
                }
                let index = locate(&list, version, group, offset)?;
                if len != list[index].symbol.size {
                    return Err(AdsError::INVALID_SIZE);
                }
                let handle = self.next_note;
                self.next_note += 1;
                self.notes.push(Note {
                    handle,
                    symbol: list[index].symbol.name.clone(),
                    version,
                    last: None,
                });
                Ok(Response::Handle(handle))
            }
            Request::DeleteNotification { handle } => {
                let before = self.notes.len();
                self.notes.retain(|n| n.handle != handle);
                if self.notes.len() == before {
                    return Err(AdsError::INVALID_NOTIFICATION_HANDLE);
                }
                Ok(Response::Done)
            }
        }
    }

    fn read(
        &self,
        list: &[SimSymbol],
        version: u8,
        group: u32,
        offset: u32,
        len: u32,
    ) -> Result<Bytes, AdsError> {
        match group {
            group::SYM_VERSION => Ok(Bytes::from(vec![version])),
            group::SYM_UPLOADINFO2 => {
                let table: usize = list.iter().map(|s| encode_symbol(&s.symbol).len()).sum();
                let mut info = Vec::new();
                for word in [list.len(), table, 0, 0, 0, 0] {
                    info.extend_from_slice(&(word as u32).to_le_bytes());
                }
                Ok(Bytes::from(info))
            }
            group::SYM_UPLOAD => Ok(Bytes::from(
                list.iter()
                    .flat_map(|s| encode_symbol(&s.symbol))
                    .collect::<Vec<u8>>(),
            )),
            group::SYM_DT_UPLOAD => Ok(Bytes::new()),
            _ => {
                let index = locate(list, version, group, offset)?;
                let device = lock(&self.shared.device);
                let bytes = value(&device.image, &list[index]).ok_or(AdsError::INVALID_OFFSET)?;
                if len != list[index].symbol.size {
                    return Err(AdsError::INVALID_SIZE);
                }
                Ok(Bytes::from(bytes))
            }
        }
    }

    fn write(
        &self,
        list: &[SimSymbol],
        version: u8,
        group: u32,
        offset: u32,
        data: &[u8],
    ) -> Result<(), AdsError> {
        if group == group::SYM_RELEASEHND {
            // Handles are the symbols' own: nothing to release.
            return Ok(());
        }
        let index = locate(list, version, group, offset)?;
        let s = &list[index];
        if data.len() as u32 != s.symbol.size {
            return Err(AdsError::INVALID_SIZE);
        }
        let write = match s.bit {
            Some(bit) => WriteData::Bit {
                bit,
                value: data[0] != 0,
            },
            None => WriteData::Bytes(data.to_vec()),
        };
        lock(&self.shared.device)
            .image
            .write(s.area, s.offset, &write)
            .map_err(|_| AdsError::INVALID_OFFSET)
    }

    fn read_write(
        &self,
        list: &[SimSymbol],
        version: u8,
        group: u32,
        offset: u32,
        read_len: u32,
        data: &[u8],
    ) -> Result<Bytes, AdsError> {
        let word = |at: usize| {
            data.get(at..at + 4)
                .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
                .ok_or(AdsError::INVALID_SIZE)
        };
        let count = offset as usize;
        match group {
            group::SYM_HNDBYNAME => {
                let name = String::from_utf8_lossy(data);
                let name = name.trim_end_matches('\0');
                let index = list
                    .iter()
                    .position(|s| s.symbol.name.eq_ignore_ascii_case(name))
                    .ok_or(AdsError::SYMBOL_NOT_FOUND)?;
                if read_len < 4 {
                    return Err(AdsError::INVALID_SIZE);
                }
                Ok(Bytes::copy_from_slice(
                    &handle(version, index).to_le_bytes(),
                ))
            }
            group::SUMUP_READ if count <= MAX_SUM => {
                let mut codes = Vec::new();
                let mut values = Vec::new();
                for i in 0..count {
                    let (g, o, len) = (word(12 * i)?, word(12 * i + 4)?, word(12 * i + 8)?);
                    match self.read(list, version, g, o, len) {
                        Ok(bytes) => {
                            codes.extend_from_slice(&0u32.to_le_bytes());
                            values.extend_from_slice(&bytes);
                        }
                        Err(e) => {
                            codes.extend_from_slice(&e.0.to_le_bytes());
                            values.resize(values.len() + len as usize, 0);
                        }
                    }
                }
                codes.extend(values);
                Ok(Bytes::from(codes))
            }
            group::SUMUP_READWRITE if count <= MAX_SUM => {
                let mut heads = Vec::new();
                let mut tails = Vec::new();
                let mut at = 16 * count;
                for i in 0..count {
                    let (g, o) = (word(16 * i)?, word(16 * i + 4)?);
                    let (rlen, wlen) = (word(16 * i + 8)?, word(16 * i + 12)? as usize);
                    let write = data.get(at..at + wlen).ok_or(AdsError::INVALID_SIZE)?;
                    at += wlen;
                    match self.read_write(list, version, g, o, rlen, write) {
                        Ok(bytes) => {
                            heads.extend_from_slice(&0u32.to_le_bytes());
                            heads.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
                            tails.extend_from_slice(&bytes);
                        }
                        Err(e) => {
                            heads.extend_from_slice(&e.0.to_le_bytes());
                            heads.extend_from_slice(&0u32.to_le_bytes());
                        }
                    }
                }
                heads.extend(tails);
                Ok(Bytes::from(heads))
            }
            group::SUMUP_READ | group::SUMUP_READWRITE => Err(AdsError::INVALID_SIZE),
            _ => Err(AdsError::SERVICE_NOT_SUPPORTED),
        }
    }
}

/// The symbol at `group`/`offset`, or of the handle in `offset`.
fn locate(list: &[SimSymbol], version: u8, group: u32, offset: u32) -> Result<usize, AdsError> {
    if group == group::SYM_VALBYHND {
        return by_handle(offset, version, list.len()).ok_or(AdsError::SYMBOL_NOT_FOUND);
    }
    list.iter()
        .position(|s| s.symbol.group == group && s.symbol.offset == offset)
        .ok_or(AdsError::INVALID_OFFSET)
}
