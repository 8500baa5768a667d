//! Siemens S7-300/400/1200/1500 over S7comm (ISO-on-TCP, port 102),
//! without a program in the PLC: data blocks, merkers, inputs and outputs
//! read and written directly, behind the same line protocol as a Tecomat
//! PLC.
//!
//! Its variables come from a tag file (`S7_TAGS`, see
//! `plccoms_plc::s7::tags`) in the layout of `plccoms_plc::s7` (inputs in X,
//! outputs in Y, merkers and DBs in R, `__PLC_RUN` S2.2 and `__PF_CRC` S70
//! answered here). The connection: TCP, a COTP connect with the TSAPs of
//! `S7_RACK`/`S7_SLOT` (or `S7_TSAP`), then setup communication, whose
//! granted PDU size (at most `S7_PDU`) sizes every job; it is shown in
//! GETINFO's VERSION_PLC.
//!
//! Reads: the poll planner joins ranges whose gap is below what an item is
//! worth ([`Budget::gap`]), and the blocks of a cycle are packed into as
//! few multi-item jobs as the PDU and the item limit allow
//! (`plccoms_plc::s7::pack`), pipelined up to the parallel jobs the CPU
//! granted. Writes likewise (a BOOL as a bit item, so the byte's other bits
//! are kept); the link reads them back for the DIFF. A server that answers
//! a multi-item write for its first item only (python-snap7 3.x's) has the
//! rest written again, one item a job, as every write from then on.
//!
//! `__PLC_RUN`: the CPU's mode from SZL 0x0424 (RUN or STOP), read at most
//! once a second when the S area is polled; a server without that list
//! (python-snap7 3.x) shows 1 while it answers. A refusal is the item's:
//! "object does not exist" (a DB the CPU lacks), "address out of range"
//! (past a DB's end), "access denied" (an S7-1200/1500 without PUT/GET or
//! an optimised DB), logged with the address and what to do; the other
//! items of the job are unaffected. Reconnection attempts (TCP, COTP and
//! setup, each sent once) run 100 ms doubling to 1 s apart, as for every
//! backend: values again within 2 s of the CPU's return.

pub mod client;

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use async_trait::async_trait;
use bytes::Bytes;
use plccoms_protocol::Area;
use tracing::{info, warn};

use client::Connection;
use plccoms_core::config::Protocol;
use plccoms_core::driver::{
    Answer, Driver, Opened, PlcBackend, PlcError, PlcStatus, ReadRequest, Refusal, WriteData,
    WriteRequest,
};
use plccoms_core::metrics::BackendCounters;
use plccoms_core::system_area::SystemArea;
use plccoms_plc::s7::frame::{cpu_running, Answer as S7Answer, Item, Job, Tsaps};
use plccoms_plc::s7::pack::{self, Block, Budget};
use plccoms_plc::s7::{address_text, Region, ReturnCode, BLOCK};

/// Settings of one S7 link (the section's keys).
#[derive(Debug, Clone)]
pub struct S7Config {
    /// IPADDR, S7_PORT.
    pub device: SocketAddr,
    /// From S7_RACK/S7_SLOT or S7_TSAP.
    pub tsaps: Tsaps,
    /// S7_PDU: asked for in setup communication.
    pub pdu: u16,
    /// S7_TIMEOUT.
    pub timeout: Duration,
    /// The tag file, whose CRC is `__PF_CRC`.
    pub tags: Option<PathBuf>,
}

impl S7Config {
    pub fn new(device: SocketAddr) -> S7Config {
        S7Config {
            device,
            tsaps: Tsaps::rack_slot(0, 1),
            pdu: 960,
            timeout: Duration::from_millis(1000),
            tags: None,
        }
    }
}

/// How often the CPU's mode is asked for, at most.
const CPU_STATE_EVERY: Duration = Duration::from_secs(1);

pub struct S7Backend {
    config: S7Config,
    connection: Option<Connection>,
    counters: Arc<BackendCounters>,
    system: SystemArea,
    /// RUN (true) or STOP as last read; `None` before the first answer.
    run: Option<bool>,
    /// When the mode was last asked for.
    run_read: Option<Instant>,
    /// The server has no SZL 0x0424 (found on this connection).
    no_cpu_state: bool,
    /// Writes go one item a job (the server kept only the first item of
    /// a multi-item write).
    single_item_writes: bool,
}

fn not_connected() -> PlcError {
    PlcError::Io(std::io::Error::new(
        std::io::ErrorKind::NotConnected,
        "no connection to the CPU",
    ))
}

/// Where a read or write of `area`/`offset` goes: its blocks, cut at DB
/// boundaries.
fn blocks_of(area: Area, offset: u32, len: u32) -> Option<Vec<Block>> {
    let mut blocks = Vec::new();
    let mut at = offset;
    let end = offset.checked_add(len)?;
    while at < end {
        let (region, start) = Region::locate(area, at)?;
        let len = (end - at).min(BLOCK - start);
        blocks.push(Block { region, start, len });
        at += len;
    }
    Some(blocks)
}

impl S7Backend {
    pub fn new(config: S7Config) -> S7Backend {
        let system = SystemArea::new(config.tags.clone());
        S7Backend {
            config,
            connection: None,
            counters: Arc::default(),
            system,
            run: None,
            run_read: None,
            no_cpu_state: false,
            single_item_writes: false,
        }
    }

    pub fn config(&self) -> &S7Config {
        &self.config
    }

    fn budget(&self) -> Budget {
        Budget::new(self.connection.as_ref().map_or(self.config.pdu, |c| c.pdu))
    }

    /// Runs `jobs`; a failed exchange gives the connection up.
    async fn exchange(&mut self, jobs: &[Job]) -> Result<Vec<S7Answer>, PlcError> {
        if jobs.is_empty() {
            return Ok(Vec::new());
        }
        let connection = self.connection.as_mut().ok_or_else(not_connected)?;
        match connection
            .exchange(jobs, self.config.timeout, &self.counters)
            .await
        {
            Ok(answers) => Ok(answers),
            Err(e) => {
                self.connection = None;
                Err(e)
            }
        }
    }

    async fn connect_with(&mut self, probing: bool) -> Result<String, PlcError> {
        self.connection = None;
        self.run = None;
        self.run_read = None;
        self.no_cpu_state = false;
        let mut connection = Connection::open(
            self.config.device,
            self.config.tsaps,
            self.config.pdu,
            self.config.timeout,
            &self.counters,
        )
        .await?;
        connection.probing(probing);
        let (pdu, jobs) = (connection.pdu, connection.jobs);
        self.connection = Some(connection);
        if let Some(connection) = self.connection.as_mut() {
            connection.probing(false);
        }
        let tsaps = self.config.tsaps;
        Ok(format!(
            "S7 TSAP {:04X}/{:04X}, PDU {pdu} (asked {}), {jobs} parallel job(s)",
            tsaps.local, tsaps.remote, self.config.pdu
        ))
    }

    /// Whether to ask for the CPU's mode with this cycle's jobs.
    fn cpu_state_due(&self) -> bool {
        !self.no_cpu_state
            && self
                .run_read
                .is_none_or(|at| at.elapsed() >= CPU_STATE_EVERY)
    }

    fn take_cpu_state(&mut self, answer: &S7Answer) {
        self.run_read = Some(Instant::now());
        match answer {
            S7Answer::Szl(Ok(records)) => match cpu_running(records) {
                Some(run) => {
                    if self.run.is_some_and(|was| was != run) {
                        info!(device = %self.config.device, "CPU in {}", if run { "RUN" } else { "STOP" });
                    }
                    self.run = Some(run);
                }
                None => self.no_cpu_state = true,
            },
            _ => {
                if !self.no_cpu_state {
                    info!(device = %self.config.device, "the server does not tell its CPU mode (SZL 0x0424): __PLC_RUN is 1 while it answers");
                }
                self.no_cpu_state = true;
            }
        }
    }

    /// Reads `blocks` in as few jobs as the budget allows (and the CPU's
    /// mode with them when `with_state`): each block's bytes or refusal.
    async fn read_blocks(
        &mut self,
        blocks: &[Block],
        with_state: bool,
    ) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let plan = pack::reads(blocks, self.budget());
        let mut jobs: Vec<Job> = plan
            .iter()
            .map(|job| Job::Read(job.iter().map(|p| p.item).collect()))
            .collect();
        if with_state {
            jobs.push(Job::ReadSzl {
                id: 0x0424,
                index: 0,
            });
        }
        let mut answers = self.exchange(&jobs).await?;
        if with_state {
            if let Some(state) = answers.pop() {
                self.take_cpu_state(&state);
            }
        }
        let mut out: Vec<Answer<Vec<u8>>> =
            blocks.iter().map(|b| Ok(vec![0; b.len as usize])).collect();
        for (job, answer) in plan.iter().zip(answers) {
            let items: Vec<Result<Bytes, ReturnCode>> = match answer {
                S7Answer::Read(items) if items.len() == job.len() => items,
                S7Answer::Refused(code) => vec![Err(code); job.len()],
                other => {
                    self.counters.errors.inc();
                    self.connection = None;
                    return Err(PlcError::Protocol(format!(
                        "{}: {} items asked, answered {other:?}",
                        self.config.device,
                        job.len()
                    )));
                }
            };
            for (piece, item) in job.iter().zip(items) {
                let Ok(buffer) = &mut out[piece.block] else {
                    continue;
                };
                match item {
                    Ok(bytes) if bytes.len() == usize::from(piece.item.len) => {
                        let at = piece.at as usize;
                        buffer[at..at + bytes.len()].copy_from_slice(&bytes);
                    }
                    Ok(_) => out[piece.block] = Err(Refusal::S7(ReturnCode::TYPE_INCONSISTENT)),
                    Err(code) => out[piece.block] = Err(Refusal::S7(code)),
                }
            }
        }
        Ok(out)
    }

    /// Writes `items` (with their data), each job within the budget; each
    /// item's outcome. A job answered with fewer return codes than it had
    /// items (python-snap7 3.x's server writes only the first) has the rest
    /// written again, one item a job, as every write from then on.
    async fn write_items(
        &mut self,
        items: &[(Item, Bytes)],
    ) -> Result<Vec<Result<(), ReturnCode>>, PlcError> {
        let mut out: Vec<Option<Result<(), ReturnCode>>> = vec![None; items.len()];
        let mut todo: Vec<usize> = (0..items.len()).collect();
        for _ in 0..2 {
            let mut budget = self.budget();
            if self.single_item_writes {
                budget.max_items = 1;
            }
            let lens: Vec<usize> = todo.iter().map(|&i| items[i].1.len()).collect();
            let plan = pack::writes(&lens, budget);
            let jobs: Vec<Job> = plan
                .iter()
                .map(|job| Job::Write(job.iter().map(|&k| items[todo[k]].clone()).collect()))
                .collect();
            let answers = self.exchange(&jobs).await?;
            let mut missing = Vec::new();
            for (job, answer) in plan.iter().zip(answers) {
                let codes = match answer {
                    S7Answer::Write(codes) if !codes.is_empty() && codes.len() <= job.len() => {
                        codes
                    }
                    S7Answer::Refused(code) => vec![Err(code); job.len()],
                    other => {
                        self.counters.errors.inc();
                        self.connection = None;
                        return Err(PlcError::Protocol(format!(
                            "{}: {} items written, answered {other:?}",
                            self.config.device,
                            job.len()
                        )));
                    }
                };
                for (n, &k) in job.iter().enumerate() {
                    match codes.get(n) {
                        Some(code) => out[todo[k]] = Some(*code),
                        None => missing.push(todo[k]),
                    }
                }
            }
            if missing.is_empty() {
                break;
            }
            if !self.single_item_writes {
                warn!(device = %self.config.device, "the server answered a write of several items for its first only: writing one item a request from now on");
                self.single_item_writes = true;
            }
            todo = missing;
        }
        out.into_iter()
            .map(|o| o.ok_or_else(|| PlcError::Protocol("write items left unanswered".into())))
            .collect()
    }
}

/// The log line's place and advice for a refusal at `area`/`offset`.
fn describe_refusal(area: Area, offset: u32, refusal: &Refusal) -> Option<String> {
    let Refusal::S7(code) = refusal else {
        return None;
    };
    let (region, byte) = Region::locate(area, offset)?;
    let place = address_text(region, byte, None);
    Some(match *code {
        ReturnCode::NO_OBJECT => match region {
            Region::Db(n) => format!("{place}: DB{n} does not exist in the CPU (check the tag file's DB number)"),
            _ => format!("{place}: the CPU has no such area"),
        },
        ReturnCode::OUT_OF_RANGE => format!("{place}: past the end of {region} (check the DB's length or the tag's byte)"),
        ReturnCode::ACCESS_DENIED => format!("{place}: on an S7-1200/1500 allow PUT/GET access (protection settings) and clear 'optimized block access' of {region}"),
        ReturnCode::FUNCTION_NOT_ALLOWED => format!("{place}: on an S7-1200/1500 allow PUT/GET access in the CPU's protection settings"),
        _ => place,
    })
}

#[async_trait]
impl PlcBackend for S7Backend {
    fn describe(&self) -> String {
        format!(
            "S7 {} TSAP {:04X}/{:04X}",
            self.config.device, self.config.tsaps.local, self.config.tsaps.remote
        )
    }

    /// One item's worth: a block never needs cutting across jobs.
    fn max_read_block(&self, area: Area) -> u32 {
        match area {
            Area::S => 4096,
            _ => self.budget().max_read_item(),
        }
    }

    fn read_gap(&self, _area: Area) -> Option<u32> {
        Some(self.budget().gap())
    }

    fn refusal_hint(&self, area: Area, offset: u32, refusal: &Refusal) -> Option<String> {
        describe_refusal(area, offset, refusal)
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

    /// TCP (refused at once by a host whose CPU is away), COTP and setup,
    /// each sent once within S7_TIMEOUT.
    async fn probe(&mut self) -> Result<String, PlcError> {
        self.connect_with(true).await
    }

    async fn read(&mut self, reads: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let mut blocks = Vec::new();
        // Per read: its blocks (start, count), or None for S or a place
        // outside the layout.
        let mut spans = Vec::with_capacity(reads.len());
        let mut wants_state = false;
        for read in reads {
            if read.area == Area::S {
                wants_state = true;
                spans.push(None);
                continue;
            }
            match blocks_of(read.area, read.offset, read.len) {
                Some(parts) => {
                    spans.push(Some((blocks.len(), parts.len())));
                    blocks.extend(parts);
                }
                None => spans.push(None),
            }
        }
        let with_state = wants_state && self.cpu_state_due();
        let data = self.read_blocks(&blocks, with_state).await?;
        let mut answers = Vec::with_capacity(reads.len());
        for (read, span) in reads.iter().zip(spans) {
            answers.push(match span {
                None if read.area == Area::S => self
                    .system
                    .read(self.run.unwrap_or(true), read.offset, read.len)
                    .ok_or(Refusal::BAD_PARAMETERS),
                None => Err(Refusal::BAD_PARAMETERS),
                Some((first, count)) => {
                    let mut bytes = Vec::with_capacity(read.len as usize);
                    let mut failure = None;
                    for part in &data[first..first + count] {
                        match part {
                            Ok(b) => bytes.extend_from_slice(b),
                            Err(e) => {
                                failure.get_or_insert(*e);
                            }
                        }
                    }
                    match failure {
                        Some(e) => Err(e),
                        None => Ok(bytes),
                    }
                }
            });
        }
        Ok(answers)
    }

    async fn write(&mut self, writes: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let max = self.budget().max_write_item();
        let mut items: Vec<(Item, Bytes)> = Vec::new();
        // Per write: its items (start, count), or the refusal at once.
        let mut spans: Vec<Result<(usize, usize), Refusal>> = Vec::with_capacity(writes.len());
        for write in writes {
            let first = items.len();
            let span = match &write.data {
                WriteData::Bit { bit, value } if *bit < 8 => {
                    match Region::locate(write.area, write.offset) {
                        Some((region, start)) if write.area != Area::S => {
                            items.push((
                                Item {
                                    region,
                                    start,
                                    bit: Some(*bit),
                                    len: 1,
                                },
                                Bytes::from(vec![u8::from(*value)]),
                            ));
                            Ok((first, 1))
                        }
                        _ => Err(Refusal::BAD_PARAMETERS),
                    }
                }
                WriteData::Bit { .. } => Err(Refusal::BAD_PARAMETERS),
                WriteData::Bytes(data) => {
                    match blocks_of(write.area, write.offset, data.len() as u32) {
                        Some(blocks) if write.area != Area::S && !data.is_empty() => {
                            let mut at = 0usize;
                            for block in blocks {
                                let mut done = 0;
                                while done < block.len {
                                    let len = (block.len - done).min(max);
                                    let bytes =
                                        Bytes::copy_from_slice(&data[at..at + len as usize]);
                                    items.push((
                                        Item::bytes(block.region, block.start + done, len as u16),
                                        bytes,
                                    ));
                                    at += len as usize;
                                    done += len;
                                }
                            }
                            Ok((first, items.len() - first))
                        }
                        _ => Err(Refusal::BAD_PARAMETERS),
                    }
                }
            };
            spans.push(span);
        }
        let outcomes = self.write_items(&items).await?;
        let mut answers = Vec::with_capacity(writes.len());
        for (write, span) in writes.iter().zip(spans) {
            let answer = span.and_then(|(first, count)| {
                match outcomes[first..first + count].iter().find_map(|o| o.err()) {
                    Some(code) => Err(Refusal::S7(code)),
                    None => Ok(()),
                }
            });
            if let Err(e) = &answer {
                let hint = describe_refusal(write.area, write.offset, e)
                    .unwrap_or_else(|| format!("{}{}", write.area, write.offset));
                warn!(device = %self.config.device, "write refused: {e}; {hint}");
            }
            answers.push(answer);
        }
        Ok(answers)
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        match self.connection {
            Some(_) => Ok(PlcStatus {
                run: self.run.unwrap_or(true),
            }),
            None => Err(not_connected()),
        }
    }
}

/// This driver, for the binary's list: sections with `PROTOCOL = S7`.
pub const DRIVER: Driver = Driver { name: "s7", open };

/// S7 to `IPADDR:S7_PORT`, or `None` when the section has no CPU yet
/// (`IPADDR` unset or `0.0.0.0`).
fn open(section: &plccoms_core::config::Section, dir: &std::path::Path) -> Option<Opened> {
    if section.protocol != Protocol::S7 {
        return None;
    }
    if section.serial_device.is_some() || section.shm_name.is_some() || section.simulator.is_some()
    {
        return Some(Err(
            "PROTOCOL = S7 runs over TCP: SERIAL_DEVICE, SHM_NAME and SIMULATOR do not apply (run plcsim --s7 for a simulated CPU)"
                .to_string(),
        ));
    }
    Some(match section.ipaddr {
        Some(ip) if !ip.is_unspecified() => {
            let device = SocketAddr::new(IpAddr::V4(ip), section.s7.port);
            Ok(Some(Box::new(S7Backend::new(config_of(
                section, device, dir,
            )))))
        }
        _ => Ok(None),
    })
}

/// S7 settings from a section's keys, for a CPU at `device`.
pub fn config_of(
    section: &plccoms_core::config::Section,
    device: SocketAddr,
    dir: &std::path::Path,
) -> S7Config {
    let mut config = S7Config::new(device);
    config.tsaps = match section.s7.tsap {
        Some((local, remote)) => Tsaps {
            local,
            remote,
            tpdu_size: 0x0A,
        },
        None => Tsaps::rack_slot(section.s7.rack, section.s7.slot),
    };
    config.pdu = section.s7.pdu;
    config.timeout = section.s7.timeout;
    config.tags = section
        .s7
        .tags
        .as_deref()
        .map(|name| section.path_of(dir, name));
    config
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_are_cut_at_db_boundaries() {
        let blocks = blocks_of(Area::R, 2 * BLOCK - 2, 4).unwrap();
        assert_eq!(
            blocks,
            [
                Block {
                    region: Region::Db(1),
                    start: BLOCK - 2,
                    len: 2
                },
                Block {
                    region: Region::Db(2),
                    start: 0,
                    len: 2
                },
            ]
        );
        assert_eq!(
            blocks_of(Area::R, 10, 2).unwrap()[0].region,
            Region::Merkers
        );
        assert_eq!(blocks_of(Area::S, 0, 1), None);
    }

    #[test]
    fn refusals_name_the_address_and_the_fix() {
        let hint = |code| describe_refusal(Area::R, 5 * BLOCK + 4, &Refusal::S7(code)).unwrap();
        assert!(hint(ReturnCode::NO_OBJECT).contains("DB5 does not exist"));
        assert!(hint(ReturnCode::OUT_OF_RANGE).starts_with("DB5.DBB4"));
        assert!(hint(ReturnCode::ACCESS_DENIED).contains("PUT/GET"));
    }
}
