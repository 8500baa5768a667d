//! Modbus TCP: the backend for Siemens (MB_SERVER), Beckhoff, B&R, Saia,
//! Schneider PLCs and energy meters, behind the same line protocol as a
//! Tecomat PLC; and Modbus RTU (`PROTOCOL = MODBUS_RTU` on a serial line,
//! `MODBUS_RTU_TCP` through a serial device server), the same backend over
//! another transport: a line shared by every section on it ([`line`]).
//!
//! Its variables come from a tag file (`MODBUS_TAGS`, see
//! `plccoms_plc::modbus::tags`) and live in this layout of the X/Y/S/R
//! areas, which the poll planner, GET, SET and GETMEM address like any PLC's
//! memory:
//!
//! | table | area | byte offset |
//! | --- | --- | --- |
//! | coil (FC 1 read; FC 5, 15 write) | Y | `address` (one byte per coil, 0 or 1) |
//! | discrete input (FC 2) | X | `address` (one byte per input) |
//! | holding register (FC 3 read; FC 6, 16, 22 write) | R | `2 x address`, high byte first |
//! | input register (FC 4) | R | `131072 + 2 x address`, high byte first |
//! | system registers, answered here | S | `__PLC_RUN` S2.2 (1 while the device answers), `__PF_CRC` S70 (DWORD: CRC-32 of the tag file) |
//!
//! A read crossing the holding/input boundary or a table's end is split here,
//! and widened to whole registers. `__PF_CRC` follows the tag file's content
//! (checked at every poll), so an edited tag file is loaded again with every
//! client's settings carried over (WARNING:250), as a new program in a
//! Tecomat PLC is.
//!
//! Writes go one transaction at a time, in order. A BOOL bit of a holding
//! register is written with FC 22 (mask write); a device that answers it
//! with "illegal function" gets a read-modify-write (FC 3, then FC 6) from
//! then on, which loses a change the device itself makes to the register's
//! other bits between the two. A write of part of a register (a `%R` byte)
//! is a read-modify-write as well.
//!
//! Exceptions 1-4 (and any other the device sends) are refusals of the one
//! request, answered to the client with the code and its meaning; 10 and 11
//! (a gateway cannot reach the device) are the link's failure: the device
//! is lost, as when it does not answer. Reconnection attempts (a TCP
//! connection and one request sent once) start 100 ms doubling to 1 s
//! apart, start to start, as for every backend: values again within 2 s of
//! the device's return. A device has no file system: GETFILE and the other
//! file services answer as a PLC without one ("service not activated").

pub mod client;
pub mod layout;
pub mod line;

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use plccoms_protocol::Area;
use tracing::{info, warn};

use client::{Connection, Outcome};
use layout::{answer_bytes, plan_read, DeviceLimits, Source};
use line::{Endpoint, Line, SerialLine};
use plccoms_core::config::Protocol;
use plccoms_core::driver::{
    Answer, PlcBackend, PlcError, PlcStatus, ReadRequest, Refusal, WriteData, WriteRequest,
};
use plccoms_core::driver::{Driver, Opened};
use plccoms_core::metrics::BackendCounters;
use plccoms_core::system_area::SystemArea;
use plccoms_plc::modbus::frame::Request;
use plccoms_plc::modbus::{
    ExceptionCode, Reference, Table, INPUT_BASE, MAX_WRITE_BITS, MAX_WRITE_REGISTERS,
};

/// Settings of one Modbus link (the section's keys).
#[derive(Debug, Clone)]
pub struct ModbusConfig {
    /// IPADDR, MODBUS_PORT.
    pub device: SocketAddr,
    /// IPADDR_LOCAL.
    pub local_ip: Option<IpAddr>,
    /// MODBUS_UNIT.
    pub unit: u8,
    /// MODBUS_TIMEOUT: how long one transaction may take.
    pub timeout: Duration,
    /// MODBUS_MAX_REGS, MODBUS_MAX_BITS.
    pub limits: DeviceLimits,
    /// MODBUS_GAP: registers a read may span to join two blocks.
    pub gap: u16,
    /// MODBUS_INFLIGHT: transactions in flight at once.
    pub inflight: usize,
    /// The tag file, whose CRC is `__PF_CRC`.
    pub tags: Option<PathBuf>,
    /// Modbus RTU on this line (shared with the other sections on it)
    /// instead of Modbus TCP to `device`.
    pub rtu: Option<Endpoint>,
}

impl ModbusConfig {
    /// Where the device is, for messages.
    pub fn place(&self) -> String {
        match &self.rtu {
            Some(line) => format!("{line} unit {}", self.unit),
            None => format!("{} unit {}", self.device, self.unit),
        }
    }
}

impl ModbusConfig {
    pub fn new(device: SocketAddr) -> ModbusConfig {
        ModbusConfig {
            device,
            local_ip: None,
            unit: 1,
            timeout: Duration::from_millis(1000),
            limits: DeviceLimits {
                max_regs: 125,
                max_bits: 2000,
            },
            gap: 8,
            inflight: 1,
            tags: None,
            rtu: None,
        }
    }
}

pub struct ModbusBackend {
    config: ModbusConfig,
    connection: Option<Link>,
    /// The RTU line, held from the first connection on, across losses:
    /// closing the port at each would lose what the line brings meanwhile,
    /// and the other end of a pty takes the last close for a hang-up.
    line: Option<Arc<Line>>,
    counters: Arc<BackendCounters>,
    system: SystemArea,
    /// The device takes FC 22 (until it says otherwise).
    mask_write: bool,
}

/// The transport of a connected backend.
enum Link {
    Tcp(Connection),
    /// A hold on a shared RTU line; `retries` per transaction.
    Rtu {
        line: Arc<Line>,
        retries: u32,
    },
}

impl Link {
    fn probing(&mut self, probing: bool) {
        match self {
            Link::Tcp(connection) => connection.probing(probing),
            Link::Rtu { retries, .. } => *retries = if probing { 0 } else { client::RETRIES },
        }
    }
}

fn not_connected() -> PlcError {
    PlcError::Io(std::io::Error::new(
        std::io::ErrorKind::NotConnected,
        "no connection to the device",
    ))
}

impl ModbusBackend {
    pub fn new(config: ModbusConfig) -> ModbusBackend {
        let system = SystemArea::new(config.tags.clone());
        ModbusBackend {
            config,
            connection: None,
            line: None,
            counters: Arc::default(),
            system,
            mask_write: true,
        }
    }

    pub fn config(&self) -> &ModbusConfig {
        &self.config
    }

    /// Runs `requests` on the connection; a failed exchange gives the
    /// connection up, and a gateway's "device unreachable" is the link's
    /// failure.
    async fn exchange(
        &mut self,
        requests: &[Request],
        window: usize,
    ) -> Result<Vec<Outcome>, PlcError> {
        if requests.is_empty() {
            return Ok(Vec::new());
        }
        let connection = self.connection.as_mut().ok_or_else(not_connected)?;
        let result = match connection {
            Link::Tcp(connection) => {
                connection
                    .exchange(requests, window, self.config.timeout, &self.counters)
                    .await
            }
            Link::Rtu { line, retries } => {
                line.exchange(
                    self.config.unit,
                    requests,
                    self.config.timeout,
                    *retries,
                    &self.counters,
                )
                .await
            }
        };
        let outcomes = match result {
            Ok(outcomes) => outcomes,
            Err(err) => {
                self.connection = None;
                return Err(err);
            }
        };
        if let Some(Err(code)) = outcomes
            .iter()
            .find(|o| matches!(o, Err(c) if c.is_gateway()))
        {
            self.counters.errors.inc();
            self.connection = None;
            return Err(PlcError::Timeout(format!(
                "{}: {code}",
                self.config.place()
            )));
        }
        Ok(outcomes)
    }

    /// A new connection and one request to see that the device answers;
    /// `probing`: that request is sent once.
    async fn connect_with(&mut self, probing: bool) -> Result<String, PlcError> {
        self.connection = None;
        let mut connection = match &self.config.rtu {
            None => Link::Tcp(
                Connection::open(
                    self.config.device,
                    self.config.local_ip,
                    self.config.unit,
                    self.config.timeout,
                )
                .await?,
            ),
            Some(endpoint) => Link::Rtu {
                line: self
                    .line
                    .get_or_insert_with(|| line::attach(endpoint))
                    .clone(),
                retries: client::RETRIES,
            },
        };
        connection.probing(probing);
        self.connection = Some(connection);
        // Any answer, an exception included, says the device is there; a
        // gateway's "unreachable" is failed by `exchange`.
        let _any_answer: Outcome = self
            .one(Request::ReadHoldingRegisters {
                address: 0,
                count: 1,
            })
            .await?;
        if let Some(connection) = self.connection.as_mut() {
            connection.probing(false);
        }
        Ok(match self.config.rtu {
            None => format!("Modbus TCP unit {}", self.config.unit),
            Some(_) => format!("Modbus RTU unit {}", self.config.unit),
        })
    }

    async fn one(&mut self, request: Request) -> Result<Outcome, PlcError> {
        let mut outcomes = self.exchange(std::slice::from_ref(&request), 1).await?;
        outcomes
            .pop()
            .ok_or_else(|| PlcError::Protocol("no answer".into()))
    }

    /// Reads holding registers `[first, first + count)` as bytes.
    async fn read_holding(&mut self, first: u16, count: u16) -> Result<Answer<Vec<u8>>, PlcError> {
        Ok(self
            .one(Request::ReadHoldingRegisters {
                address: first,
                count,
            })
            .await?
            .map(|r| answer_bytes(&r))
            .map_err(Refusal::Modbus))
    }

    /// Writes whole holding registers from `first` (high byte first).
    async fn write_holding(&mut self, first: u16, bytes: &[u8]) -> Result<Answer<()>, PlcError> {
        let values: Vec<u16> = bytes
            .chunks_exact(2)
            .map(|w| u16::from_be_bytes([w[0], w[1]]))
            .collect();
        let mut address = first;
        for chunk in values.chunks(usize::from(MAX_WRITE_REGISTERS)) {
            let request = match chunk {
                [value] => Request::WriteSingleRegister {
                    address,
                    value: *value,
                },
                _ => Request::WriteMultipleRegisters {
                    address,
                    values: chunk.to_vec(),
                },
            };
            if let Err(code) = self.one(request).await? {
                return Ok(Err(Refusal::Modbus(code)));
            }
            address = address.wrapping_add(chunk.len() as u16);
        }
        Ok(Ok(()))
    }

    async fn write_coils(&mut self, first: u16, bytes: &[u8]) -> Result<Answer<()>, PlcError> {
        let mut address = first;
        for chunk in bytes.chunks(usize::from(MAX_WRITE_BITS)) {
            let request = match chunk {
                [value] => Request::WriteSingleCoil {
                    address,
                    value: *value != 0,
                },
                _ => Request::WriteMultipleCoils {
                    address,
                    values: chunk.iter().map(|&b| b != 0).collect(),
                },
            };
            if let Err(code) = self.one(request).await? {
                return Ok(Err(Refusal::Modbus(code)));
            }
            address = address.wrapping_add(chunk.len() as u16);
        }
        Ok(Ok(()))
    }

    /// Bit `bit` (0-15) of holding register `register`: FC 22, or a
    /// read-modify-write where the device lacks it.
    async fn write_register_bit(
        &mut self,
        register: u16,
        bit: u8,
        value: bool,
    ) -> Result<Answer<()>, PlcError> {
        let mask = 1u16 << bit;
        if self.mask_write {
            let request = Request::MaskWriteRegister {
                address: register,
                and_mask: !mask,
                or_mask: if value { mask } else { 0 },
            };
            match self.one(request).await? {
                Ok(_) => return Ok(Ok(())),
                Err(ExceptionCode::ILLEGAL_FUNCTION) => {
                    info!(device = %self.config.place(), "the device has no mask write (FC 22): register bits are written by read-modify-write");
                    self.mask_write = false;
                }
                Err(code) => return Ok(Err(Refusal::Modbus(code))),
            }
        }
        let current = match self.read_holding(register, 1).await? {
            Ok(bytes) => u16::from_be_bytes([bytes[0], bytes[1]]),
            Err(e) => return Ok(Err(e)),
        };
        let new = if value {
            current | mask
        } else {
            current & !mask
        };
        self.write_holding(register, &new.to_be_bytes()).await
    }

    async fn write_one(&mut self, write: &WriteRequest) -> Result<Answer<()>, PlcError> {
        let refused = |code| Ok(Err(Refusal::Modbus(code)));
        let len = match &write.data {
            WriteData::Bytes(bytes) => bytes.len() as u32,
            WriteData::Bit { .. } => 1,
        };
        if !plccoms_plc::modbus::MAP.contains(write.area, write.offset, len) || len == 0 {
            return refused(ExceptionCode::ILLEGAL_DATA_ADDRESS);
        }
        match (write.area, &write.data) {
            // Discrete inputs, input registers and the system registers
            // have no write function.
            (Area::X | Area::S, _) => refused(ExceptionCode::ILLEGAL_FUNCTION),
            (Area::R, _) if write.offset + len > INPUT_BASE => {
                refused(ExceptionCode::ILLEGAL_FUNCTION)
            }
            (Area::Y, WriteData::Bit { bit: 0, value }) => {
                self.write_coils(write.offset as u16, &[u8::from(*value)])
                    .await
            }
            (Area::Y, WriteData::Bit { .. }) => refused(ExceptionCode::ILLEGAL_DATA_ADDRESS),
            (Area::Y, WriteData::Bytes(bytes)) => {
                self.write_coils(write.offset as u16, bytes).await
            }
            (Area::R, WriteData::Bit { bit, value }) if *bit < 8 => {
                // The high byte (even offset) holds bits 8-15.
                let bit = bit + if write.offset & 1 == 0 { 8 } else { 0 };
                self.write_register_bit((write.offset / 2) as u16, bit, *value)
                    .await
            }
            (Area::R, WriteData::Bit { .. }) => refused(ExceptionCode::ILLEGAL_DATA_ADDRESS),
            (Area::R, WriteData::Bytes(bytes)) => {
                let first = write.offset / 2;
                let end = write.offset + len;
                let last = end.div_ceil(2);
                if (write.offset | end) & 1 == 0 {
                    return self.write_holding(first as u16, bytes).await;
                }
                // Part of a register: read what is around it.
                let mut whole = Vec::with_capacity(2 * (last - first) as usize);
                for (register, count) in chunks(first, last, u32::from(self.config.limits.max_regs))
                {
                    match self.read_holding(register as u16, count as u16).await? {
                        Ok(bytes) => whole.extend_from_slice(&bytes),
                        Err(e) => return Ok(Err(e)),
                    }
                }
                let at = (write.offset - 2 * first) as usize;
                whole[at..at + bytes.len()].copy_from_slice(bytes);
                self.write_holding(first as u16, &whole).await
            }
        }
    }
}

/// `[first, last)` in pieces of at most `max`.
fn chunks(first: u32, last: u32, max: u32) -> impl Iterator<Item = (u32, u32)> {
    let max = max.max(1);
    (first..last)
        .step_by(max as usize)
        .map(move |at| (at, (last - at).min(max)))
}

#[async_trait]
impl PlcBackend for ModbusBackend {
    fn describe(&self) -> String {
        match self.config.rtu {
            None => format!("Modbus TCP {}", self.config.place()),
            Some(_) => format!("Modbus RTU {}", self.config.place()),
        }
    }

    fn max_read_block(&self, area: Area) -> u32 {
        match area {
            Area::X | Area::Y => u32::from(self.config.limits.max_bits),
            Area::R => 2 * u32::from(self.config.limits.max_regs),
            Area::S => 4096,
        }
    }

    fn read_gap(&self, area: Area) -> Option<u32> {
        let gap = u32::from(self.config.gap);
        Some(match area {
            // A register's worth of bits per register of gap.
            Area::X | Area::Y => 16 * gap,
            Area::R | Area::S => 2 * gap,
        })
    }

    fn read_align(&self, area: Area) -> u32 {
        if area == Area::R {
            2
        } else {
            1
        }
    }

    /// "Illegal data address" for a tag at 10000 or more that reads as a
    /// 1-based reference (40001): say what it maps to (holding 0).
    fn refusal_hint(&self, area: Area, offset: u32, refusal: &Refusal) -> Option<String> {
        if *refusal != Refusal::Modbus(ExceptionCode::ILLEGAL_DATA_ADDRESS) {
            return None;
        }
        let (table, address) = Table::locate(area, offset)?;
        Reference::of_address(address).map(|r| r.hint(table, address))
    }

    fn max_file_block(&self) -> u32 {
        1024
    }

    fn answer_timeout(&self) -> Duration {
        self.config.timeout
    }

    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters;
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        self.connect_with(false).await
    }

    /// A new connection (refused at once by a host whose device is off, or
    /// given up after MODBUS_TIMEOUT) and one request sent once: the link
    /// makes one about every second while the device is away.
    async fn probe(&mut self) -> Result<String, PlcError> {
        self.connect_with(true).await
    }

    async fn read(&mut self, reads: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let mut requests = Vec::new();
        let plans: Vec<Vec<Source>> = reads
            .iter()
            .map(|r| plan_read(r, self.config.limits, &mut requests))
            .collect();
        let outcomes = self.exchange(&requests, self.config.inflight).await?;
        let mut answers = Vec::with_capacity(reads.len());
        for (read, sources) in reads.iter().zip(plans) {
            let mut bytes = Vec::with_capacity(read.len as usize);
            let mut failure = None;
            for source in sources {
                match source {
                    Source::Device { request, from, len } => match &outcomes[request] {
                        Ok(response) => {
                            let data = answer_bytes(response);
                            match data.get(from..from + len) {
                                Some(part) => bytes.extend_from_slice(part),
                                None => failure = Some(Refusal::BAD_PARAMETERS),
                            }
                        }
                        Err(code) => {
                            failure.get_or_insert(Refusal::Modbus(*code));
                        }
                    },
                    Source::System { offset, len } => match self.system.read(true, offset, len) {
                        Some(part) => bytes.extend_from_slice(&part),
                        None => failure = Some(Refusal::BAD_PARAMETERS),
                    },
                    Source::Refused(e) => {
                        failure.get_or_insert(e);
                    }
                }
            }
            answers.push(match failure {
                Some(e) => Err(e),
                None => Ok(bytes),
            });
        }
        Ok(answers)
    }

    async fn write(&mut self, writes: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let mut answers = Vec::with_capacity(writes.len());
        for write in writes {
            let answer = self.write_one(write).await?;
            if let Err(e) = &answer {
                let place = Table::locate(write.area, write.offset)
                    .map(|(table, address)| format!("{table} {address}"))
                    .unwrap_or_else(|| format!("{}{}", write.area, write.offset));
                let hint = self
                    .refusal_hint(write.area, write.offset, e)
                    .map(|hint| format!("; {hint}"))
                    .unwrap_or_default();
                warn!(device = %self.config.place(), "write of {place} refused: {e}{hint}");
            }
            answers.push(answer);
        }
        Ok(answers)
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        match self.connection {
            Some(_) => Ok(PlcStatus { run: true }),
            None => Err(not_connected()),
        }
    }
}

/// This driver, for the binary's list: sections with `PROTOCOL =
/// MODBUS_TCP`, `MODBUS_RTU` or `MODBUS_RTU_TCP`.
pub const DRIVER: Driver = Driver {
    name: "modbus",
    open,
};

/// Modbus TCP to `IPADDR:MODBUS_PORT`, or `None` when the section has no
/// device yet (`IPADDR` unset or `0.0.0.0`).
fn open(section: &plccoms_core::config::Section, dir: &std::path::Path) -> Option<Opened> {
    if !section.protocol.is_modbus() {
        return None;
    }
    if section.shm_name.is_some() {
        return Some(Err(format!(
            "PROTOCOL = {}: SHM_NAME does not apply",
            section.protocol
        )));
    }
    if section.protocol == Protocol::ModbusRtu {
        let Some(device) = &section.serial_device else {
            return Some(Err(
                "PROTOCOL = MODBUS_RTU needs SERIAL_DEVICE (the serial line)".to_string(),
            ));
        };
        let mut config = config_of(section, SocketAddr::from(([0, 0, 0, 0], 0)), dir);
        config.rtu = Some(Endpoint::Serial(serial_line_of(section, device)));
        return Some(Ok(Some(Box::new(ModbusBackend::new(config)))));
    }
    if section.serial_device.is_some() {
        return Some(Err(format!(
            "PROTOCOL = {} runs over TCP: SERIAL_DEVICE does not apply (MODBUS_RTU: a serial line)",
            section.protocol
        )));
    }
    Some(match section.ipaddr {
        Some(ip) if !ip.is_unspecified() => {
            let device = SocketAddr::new(IpAddr::V4(ip), section.modbus.port);
            let mut config = config_of(section, device, dir);
            if section.protocol == Protocol::ModbusRtuTcp {
                config.rtu = Some(Endpoint::Tcp {
                    server: device,
                    local: config.local_ip,
                });
            }
            Ok(Some(Box::new(ModbusBackend::new(config))))
        }
        _ => Ok(None),
    })
}

/// The serial line a MODBUS_RTU section names: SERIAL_SPEED and the
/// character format, the Modbus defaults (9600 8E1) where not set, and the
/// RTS pin (SERIAL_RTS, else the device's in SERIAL_DEVICE_CFG).
pub fn serial_line_of(section: &plccoms_core::config::Section, device: &str) -> SerialLine {
    let mut line = SerialLine::new(device);
    line.speed = section.serial_speed.unwrap_or(line.speed);
    line.parity = section.serial_parity.unwrap_or(line.parity);
    line.data_bits = section.serial_data_bits.unwrap_or(line.data_bits);
    line.stop_bits = section.serial_stop_bits.unwrap_or(line.stop_bits);
    line.rts = section.serial_rts.or_else(|| {
        plccoms_core::config::serial::pin_of(
            section.serial_device_cfg.as_deref().unwrap_or_default(),
            device,
        )
    });
    line
}

/// Modbus settings from a section's keys, for a device at `device`.
pub fn config_of(
    section: &plccoms_core::config::Section,
    device: SocketAddr,
    dir: &std::path::Path,
) -> ModbusConfig {
    let mut config = ModbusConfig::new(device);
    config.local_ip = section.ipaddr_local.map(IpAddr::V4);
    if device.ip().is_loopback() {
        config.local_ip = None;
    }
    config.unit = section.modbus.unit;
    config.timeout = section.modbus.timeout;
    config.limits = layout::DeviceLimits {
        max_regs: section.modbus.max_regs,
        max_bits: section.modbus.max_bits,
    };
    config.gap = section.modbus.gap;
    config.inflight = usize::from(section.modbus.inflight);
    config.tags = section
        .modbus
        .tags
        .as_deref()
        .map(|name| section.path_of(dir, name));
    config
}
