//! The simulated PLC: a UDP server speaking EPSNET (or a serial line,
//! [`serial`], or a TCP server speaking Modbus TCP, [`modbus`], S7comm,
//! [`s7`], or Beckhoff ADS, [`ads`]) over a
//! [`Device`], a PLC program engine, a directory-backed file store and fault
//! injection.
//!
//! [`spawn`] starts it inside the current tokio runtime and returns a
//! [`SimHandle`]: its address, the device, and the fault controls (packet
//! loss, latency, HALT/RUN, another public file or program). Dropping the
//! handle stops the simulator. The `plcsim` binary wraps the same API and
//! adds a loopback TCP control port ([`control`]).

pub mod ads;
pub mod cli;
pub mod control;
pub mod device;
pub mod genpub;
pub mod modbus;
pub mod program;
pub mod s7;
pub mod serial;
pub mod server;
pub mod store;

pub use device::Device;
pub use store::FileStore;

use std::io;
use std::net::{Ipv4Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::net::UdpSocket;
use tokio::sync::Semaphore;
use tokio::task::JoinHandle;

use self::program::{Program, ProgramKind};
use self::server::Rng;
use plccoms_plc::epsnet::frame::{DEFAULT_PORT, MAX_PACKET};
use plccoms_plc::Var;
use plccoms_plc::{pubfile, time, MemoryMap};

use crate::device::{PF_CRC_OFFSET, PLC_RUN_BIT, PLC_RUN_BYTE};

/// The demo program's public file, built in (same bytes as `conf/demo.pub`).
pub const DEMO_PUB: &[u8] = include_bytes!("../../conf/demo.pub");
/// The fixed public file (same bytes as `conf/FIXED.pub`).
pub const FIXED_PUB: &[u8] = include_bytes!("../../conf/FIXED.pub");
/// The demo program's variables as a Modbus tag file (`conf/demo-modbus.csv`).
pub const DEMO_TAGS: &[u8] = include_bytes!("../../conf/demo-modbus.csv");
/// The demo program's variables as an S7 tag file (`conf/demo-s7.csv`).
pub const DEMO_S7_TAGS: &[u8] = include_bytes!("../../conf/demo-s7.csv");

/// Answers delayed by injected latency and not yet sent; beyond this the
/// simulator drops datagrams (memory stays bounded).
const MAX_DELAYED: usize = 256;

/// Where the user public file comes from.
#[derive(Debug, Clone)]
pub enum PubSource {
    Path(PathBuf),
    Bytes(Vec<u8>),
}

#[derive(Debug, Clone)]
pub struct SimConfig {
    /// UDP address to serve (default 127.0.0.1:61682; port 0 picks one).
    pub bind: SocketAddr,
    /// The user public file (default: the built-in demo file).
    pub pubfile: PubSource,
    /// The fixed public file; only checked against the device's fixed places.
    pub fixed: Option<PathBuf>,
    /// Directory served as the PLC's file system; `None`: file services
    /// answer "not activated".
    pub files: Option<PathBuf>,
    pub program: ProgramKind,
    /// Variable name masks (`*` wildcard, case-insensitive) to animate.
    pub animate: Vec<String>,
    /// Fraction of incoming datagrams dropped, 0.0..=1.0.
    pub loss: f64,
    /// Delay before each answer.
    pub latency: Duration,
    /// PLC cycle.
    pub cycle: Duration,
    /// Loopback TCP control port (see [`control`]).
    pub control: Option<SocketAddr>,
    pub ident: String,
    pub map: MemoryMap,
    /// Seed of the packet-loss generator (default: from the clock).
    pub seed: Option<u64>,
    /// Serve this serial line instead of UDP (`bind` is then unused).
    pub serial: Option<serial::SerialLine>,
    /// Serve Modbus TCP on this address instead of EPSNET; `pubfile` is then
    /// a Modbus tag file, and the memory is laid out as Modbus tables.
    pub modbus: Option<SocketAddr>,
    /// Serve S7comm (ISO-on-TCP) on this address instead of EPSNET;
    /// `pubfile` is then an S7 tag file, and the memory laid out as
    /// [`s7::MAP`].
    pub s7: Option<SocketAddr>,
    /// Serve Beckhoff ADS (AMS/TCP) on this address instead of EPSNET: the
    /// public file's variables as ADS symbols ([`ads`]).
    pub ads: Option<SocketAddr>,
    /// Serve Modbus RTU on `serial` as these units (one memory for all)
    /// instead of EPSNET, when not empty (the memory and `pubfile` as with
    /// `modbus`).
    pub modbus_rtu: Vec<u8>,
    /// Devices served, each with its own memory and program, on
    /// consecutive ports from the address's port (port 0: each its own).
    pub devices: usize,
    /// Fraction of the animated variables changed per second, in turn
    /// (see [`Program::with_rate`]); `None`: all of them every cycle.
    pub change_rate: Option<f64>,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            bind: SocketAddr::from((Ipv4Addr::LOCALHOST, DEFAULT_PORT)),
            pubfile: PubSource::Bytes(DEMO_PUB.to_vec()),
            fixed: None,
            files: None,
            program: ProgramKind::Demo,
            animate: Vec::new(),
            loss: 0.0,
            latency: Duration::ZERO,
            cycle: Duration::from_millis(10),
            control: None,
            ident: crate::device::DEFAULT_IDENT.to_string(),
            map: MemoryMap::FOXTROT,
            seed: None,
            serial: None,
            modbus: None,
            s7: None,
            ads: None,
            modbus_rtu: Vec::new(),
            devices: 1,
            change_rate: None,
        }
    }
}

/// State the server, the program task and the controls share. Lock order:
/// `state` before `device`.
pub(crate) struct Shared {
    device: Arc<Mutex<Device>>,
    state: Mutex<SimState>,
    /// Bytes and frames on a serial line.
    line: serial::LineStats,
    /// The variables come from Modbus tag files.
    modbus: bool,
    /// The variables come from S7 tag files.
    s7: bool,
}

struct SimState {
    loss: f64,
    latency: Duration,
    /// PLC clock minus host clock, seconds (SETTID).
    clock_offset: f64,
    program: Program,
    rng: Rng,
    cycle_ms: u64,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    // Plain data: still valid after a panic elsewhere.
    mutex.lock().unwrap_or_else(|p| p.into_inner())
}

/// The variables of a Modbus tag file, and its CRC.
pub fn load_tags_bytes(bytes: &[u8]) -> (Vec<Var>, u32) {
    let parsed = plccoms_plc::modbus::tags::parse(bytes);
    for warning in &parsed.warnings {
        tracing::warn!("plcsim: tag file {warning}");
    }
    let vars = parsed.tags.iter().map(|tag| tag.var()).collect();
    (vars, pubfile::crc_of(bytes))
}

/// The variables of an S7 tag file, and its CRC.
pub fn load_s7_tags_bytes(bytes: &[u8]) -> (Vec<Var>, u32) {
    let parsed = plccoms_plc::s7::tags::parse(bytes);
    for warning in &parsed.warnings {
        tracing::warn!("plcsim: tag file {warning}");
    }
    let vars = parsed.tags.iter().map(|tag| tag.var()).collect();
    (vars, pubfile::crc_of(bytes))
}

/// The variables and `__PF_CRC` of a public file.
pub fn load_pub_bytes(bytes: &[u8]) -> (Vec<Var>, u32) {
    let parsed = pubfile::parse(bytes);
    for warning in &parsed.warnings {
        tracing::warn!("plcsim: public file {warning}");
    }
    let computed = pubfile::crc_of(pubfile::crc_content(bytes));
    let crc = match parsed.crc {
        Some(trailer) if trailer == computed => trailer,
        Some(trailer) => {
            tracing::warn!(
                "plcsim: public file CRC trailer {trailer:08X} does not match the content \
                 ({computed:08X}); __PF_CRC = {computed:08X}"
            );
            computed
        }
        None => computed,
    };
    let vars = parsed.vars.into_iter().map(|def| def.var).collect();
    (vars, crc)
}

impl Shared {
    fn set_loss(&self, fraction: f64) {
        lock(&self.state).loss = if fraction.is_nan() {
            0.0
        } else {
            fraction.clamp(0.0, 1.0)
        };
    }

    fn set_latency(&self, latency: Duration) {
        lock(&self.state).latency = latency.min(Duration::from_secs(60));
    }

    fn set_run(&self, run: bool) {
        lock(&self.device).set_run(run);
    }

    fn set_program(&self, kind: ProgramKind) {
        let mut state = lock(&self.state);
        state.program = state.program.with_kind(kind);
    }

    /// Loads another public file: the program now works on its variables,
    /// and `__PF_CRC` changes to its CRC. The file system serves it under
    /// `name`, or, without one, under the name of the file it replaces.
    fn load_pub(&self, bytes: &[u8], name: Option<&str>) -> u32 {
        let (vars, crc) = if self.modbus {
            load_tags_bytes(bytes)
        } else if self.s7 {
            load_s7_tags_bytes(bytes)
        } else {
            load_pub_bytes(bytes)
        };
        if let Some(files) = lock(&self.device).files.as_mut() {
            let name = name.or(files.program_file_name()).map(str::to_string);
            if let Some(name) = name {
                if let Err(e) = files.set_program_file(&name, bytes.to_vec()) {
                    tracing::warn!("public file not served by the file system: {e}");
                }
            }
        }
        let mut state = lock(&self.state);
        let program = Program::new(
            state.program.kind(),
            vars,
            &state.program.masks(),
            state.cycle_ms,
        )
        .replacing(&state.program);
        state.program = program;
        lock(&self.device).set_pf_crc(crc);
        crc
    }

    fn set_animate(&self, masks: &[String]) {
        let mut state = lock(&self.state);
        state.program = Program::new(
            state.program.kind(),
            state.program.vars().to_vec(),
            masks,
            state.cycle_ms,
        )
        .replacing(&state.program);
    }

    fn changes(&self) -> u64 {
        lock(&self.state).program.changes()
    }

    /// One PLC cycle: the program runs only in RUN.
    fn cycle(&self) {
        let mut state = lock(&self.state);
        let now = time::unix_now() + state.clock_offset;
        let mut device = lock(&self.device);
        if device.run() {
            state.program.step(&mut device.image, now);
        }
    }

    /// Decides the fate of one datagram: `None` to drop it, else the answer
    /// (possibly empty: stay silent) and its delay.
    fn handle(&self, bytes: &[u8]) -> Option<(Option<Vec<u8>>, Duration)> {
        let mut state = lock(&self.state);
        if state.loss > 0.0 && state.rng.next_f64() < state.loss {
            return None;
        }
        let latency = state.latency;
        let mut offset = state.clock_offset;
        let answer = server::handle_datagram(bytes, &mut lock(&self.device), &mut offset);
        state.clock_offset = offset;
        Some((answer, latency))
    }

    /// Decides the fate of one frame from a serial line: `None` to stay
    /// silent, else the answer, its delay and the damage the line does to it.
    fn handle_frame(
        &self,
        frame: &plccoms_plc::epsnet::frame::Frame,
    ) -> Option<(
        plccoms_plc::epsnet::frame::Frame,
        Duration,
        Option<serial::Damage>,
    )> {
        let mut state = lock(&self.state);
        let mut offset = state.clock_offset;
        let answer = server::handle_frame(frame, &mut lock(&self.device), &mut offset)?;
        state.clock_offset = offset;
        let damage = (state.loss > 0.0 && state.rng.next_f64() < state.loss)
            .then(|| serial::Damage::draw(&mut state.rng, answer.encoded_len()));
        Some((answer, state.latency, damage))
    }

    fn damage(&self, damage: serial::Damage, bytes: Vec<u8>) -> Vec<u8> {
        damage.apply(bytes, &mut lock(&self.state).rng)
    }

    /// The answer to one S7 job, and its delay; `None` to drop it.
    fn handle_s7(
        &self,
        job: &plccoms_plc::s7::frame::Job,
    ) -> Option<(plccoms_plc::s7::frame::Answer, Duration)> {
        let mut state = lock(&self.state);
        if state.loss > 0.0 && state.rng.next_f64() < state.loss {
            return None;
        }
        let mut device = lock(&self.device);
        let run = device.run();
        Some((s7::apply(&mut device.image, run, job), state.latency))
    }

    /// The answer to one Modbus request, and its delay; `None` to drop it.
    fn handle_modbus(&self, adu: &plccoms_plc::modbus::codec::Adu) -> Option<(Vec<u8>, Duration)> {
        let mut state = lock(&self.state);
        if state.loss > 0.0 && state.rng.next_f64() < state.loss {
            return None;
        }
        let answer = modbus::answer(&mut lock(&self.device).image, adu);
        Some((answer, state.latency))
    }
}

/// Serves each connection `listener` accepts with `connection`, in a task
/// of its own (the TCP devices: Modbus, S7).
pub(crate) async fn accept<S, F, Fut>(listener: tokio::net::TcpListener, shared: S, connection: F)
where
    S: Clone,
    F: Fn(tokio::net::TcpStream, S) -> Fut,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
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

/// One simulated device of a running simulator.
struct Unit {
    local_addr: SocketAddr,
    shared: Arc<Shared>,
}

/// A running simulator: one device, or [`SimConfig::devices`] of them on
/// consecutive ports. The single-device methods act on the first.
/// Dropping it stops every task of it.
pub struct SimHandle {
    units: Vec<Unit>,
    control_addr: Option<SocketAddr>,
    tasks: Vec<JoinHandle<()>>,
}

/// Starts a simulated PLC (or [`SimConfig::devices`] of them, all in this
/// runtime, one task a device and one program task for all) in the
/// current tokio runtime.
pub async fn spawn(config: SimConfig) -> io::Result<SimHandle> {
    let pub_bytes = match &config.pubfile {
        PubSource::Bytes(bytes) => bytes.clone(),
        PubSource::Path(path) => std::fs::read(path).map_err(|e| with_path(e, path))?,
    };
    if let Some(path) = &config.fixed {
        check_fixed(&std::fs::read(path).map_err(|e| with_path(e, path))?);
    }
    let count = config.devices.max(1);
    if count > 1 && config.serial.is_some() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "several devices need a network address, not a serial line",
        ));
    }
    let modbus = config.modbus.is_some() || !config.modbus_rtu.is_empty();
    let map = if modbus {
        plccoms_plc::modbus::MAP
    } else if config.s7.is_some() {
        s7::MAP
    } else {
        config.map
    };
    let cycle_ms = config.cycle.as_millis().clamp(1, 60_000) as u64;
    let (vars, crc) = if modbus {
        load_tags_bytes(&pub_bytes)
    } else if config.s7.is_some() {
        load_s7_tags_bytes(&pub_bytes)
    } else {
        load_pub_bytes(&pub_bytes)
    };
    let mut devices = Vec::with_capacity(count);
    for index in 0..count {
        let mut device = Device::new(map);
        device.ident = config.ident.clone();
        if let Some(dir) = &config.files {
            let mut files = FileStore::open(dir).map_err(|e| with_path(e, dir))?;
            if let PubSource::Path(path) = &config.pubfile {
                let name = path
                    .file_name()
                    .and_then(|n| n.to_str())
                    .unwrap_or_default();
                files
                    .set_program_file(name, pub_bytes.clone())
                    .map_err(|e| {
                        io::Error::new(
                            io::ErrorKind::InvalidInput,
                            format!("{}: {e}", path.display()),
                        )
                    })?;
            }
            device.files = Some(files);
        }
        device.set_pf_crc(crc);
        let shared = Arc::new(Shared {
            device: Arc::new(Mutex::new(device)),
            state: Mutex::new(SimState {
                loss: 0.0,
                latency: Duration::ZERO,
                clock_offset: 0.0,
                program: Program::new(config.program, vars.clone(), &config.animate, cycle_ms)
                    .with_rate(config.change_rate),
                rng: match config.seed {
                    Some(seed) => Rng::new(seed.wrapping_add(index as u64)),
                    None => Rng::from_time(),
                },
                cycle_ms,
            }),
            line: serial::LineStats::default(),
            modbus,
            s7: config.s7.is_some(),
        });
        shared.set_loss(config.loss);
        shared.set_latency(config.latency);
        // A PLC has run its program before anyone can read it: without this
        // the first datagram may be answered before the first timer tick.
        shared.cycle();
        devices.push(shared);
    }
    let all: Arc<[Arc<Shared>]> = devices.clone().into();

    // One timer for all devices: a thousand 10 ms timers would cost more
    // than the devices' work.
    let mut tasks = vec![tokio::spawn(run_program(
        all.clone(),
        Duration::from_millis(cycle_ms),
    ))];
    let mut units = Vec::with_capacity(count);
    for (index, shared) in devices.into_iter().enumerate() {
        let at = |addr: SocketAddr| -> io::Result<SocketAddr> {
            let port = match addr.port() {
                0 => Some(0),
                port => u16::try_from(usize::from(port) + index).ok(),
            };
            port.map(|port| SocketAddr::new(addr.ip(), port))
                .ok_or_else(|| {
                    io::Error::new(
                        io::ErrorKind::InvalidInput,
                        format!("{count} devices from port {} pass port 65535", addr.port()),
                    )
                })
        };
        let local_addr = match (&config.serial, config.modbus) {
            (None, None) if config.ads.is_some() => {
                let listener = bind_tcp(at(config.ads.expect("checked"))?).await?;
                let local = listener.local_addr()?;
                tasks.push(tokio::spawn(ads::serve(listener, shared.clone())));
                local
            }
            (Some(line), _) if !config.modbus_rtu.is_empty() => {
                let port = serial::open(line)?;
                tasks.push(tokio::spawn(modbus::serve_rtu(
                    port,
                    line.clone(),
                    config.modbus_rtu.clone(),
                    shared.clone(),
                )));
                SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0))
            }
            (Some(line), _) => {
                let port = serial::open(line)?;
                tasks.push(tokio::spawn(serial::serve(
                    port,
                    line.clone(),
                    shared.clone(),
                )));
                SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0))
            }
            (None, Some(addr)) => {
                let listener = bind_tcp(at(addr)?).await?;
                let local = listener.local_addr()?;
                // The first port also serves every device by unit id.
                let by_unit: Arc<[Arc<Shared>]> = if index == 0 {
                    all.clone()
                } else {
                    Arc::new([shared.clone()])
                };
                tasks.push(tokio::spawn(modbus::serve(listener, by_unit)));
                local
            }
            (None, None) if config.s7.is_some() => {
                let listener = bind_tcp(at(config.s7.unwrap_or(config.bind))?).await?;
                let local = listener.local_addr()?;
                tasks.push(tokio::spawn(s7::serve(listener, shared.clone())));
                local
            }
            (None, None) => {
                let socket = Arc::new(
                    UdpSocket::bind(at(config.bind)?)
                        .await
                        .map_err(|e| with_addr(e, at(config.bind)))?,
                );
                let local = socket.local_addr()?;
                tasks.push(tokio::spawn(serve(socket, shared.clone())));
                local
            }
        };
        units.push(Unit { local_addr, shared });
    }
    let mut control_addr = None;
    if let Some(addr) = config.control {
        let listener = tokio::net::TcpListener::bind(addr).await?;
        control_addr = Some(listener.local_addr()?);
        tasks.push(tokio::spawn(control::serve(listener, all)));
    }
    Ok(SimHandle {
        units,
        control_addr,
        tasks,
    })
}

/// A TCP listener on `addr`; an error names the address (one of many).
async fn bind_tcp(addr: SocketAddr) -> io::Result<tokio::net::TcpListener> {
    tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| with_addr(e, Ok(addr)))
}

fn with_addr(e: io::Error, addr: io::Result<SocketAddr>) -> io::Error {
    match addr {
        Ok(addr) => io::Error::new(e.kind(), format!("{addr}: {e}")),
        Err(_) => e,
    }
}

fn with_path(e: io::Error, path: &Path) -> io::Error {
    io::Error::new(e.kind(), format!("{}: {e}", path.display()))
}

/// Warns when the fixed file places `__PLC_RUN` / `__PF_CRC` elsewhere than
/// the simulated device keeps them.
fn check_fixed(bytes: &[u8]) {
    let parsed = pubfile::parse(bytes);
    let find = |name: &[u8]| {
        parsed
            .vars
            .iter()
            .map(|def| &def.var)
            .find(|v| v.name.eq_ignore_ascii_case(name))
    };
    match find(b"__PLC_RUN") {
        Some(v)
            if v.area == plccoms_protocol::Area::S
                && v.offset == PLC_RUN_BYTE
                && v.bit == Some(PLC_RUN_BIT) => {}
        _ => tracing::warn!("plcsim: fixed file does not place __PLC_RUN at S2.2"),
    }
    match find(b"__PF_CRC") {
        Some(v) if v.area == plccoms_protocol::Area::S && v.offset == PF_CRC_OFFSET => {}
        _ => tracing::warn!("plcsim: fixed file does not place __PF_CRC at S70"),
    }
}

async fn serve(socket: Arc<UdpSocket>, shared: Arc<Shared>) {
    let delayed = Arc::new(Semaphore::new(MAX_DELAYED));
    let mut buf = vec![0u8; MAX_PACKET + 64];
    loop {
        let (len, from) = match socket.recv_from(&mut buf).await {
            Ok(received) => received,
            Err(e) => {
                // ICMP errors from earlier answers and the like: keep serving.
                tracing::debug!("plcsim: receive error: {e}");
                tokio::time::sleep(Duration::from_millis(1)).await;
                continue;
            }
        };
        let Some((Some(answer), latency)) = shared.handle(&buf[..len]) else {
            continue;
        };
        if latency.is_zero() {
            let _ = socket.send_to(&answer, from).await;
        } else if let Ok(permit) = delayed.clone().try_acquire_owned() {
            let socket = socket.clone();
            tokio::spawn(async move {
                tokio::time::sleep(latency).await;
                let _ = socket.send_to(&answer, from).await;
                drop(permit);
            });
        }
    }
}

async fn run_program(devices: Arc<[Arc<Shared>]>, cycle: Duration) {
    let mut ticks = tokio::time::interval(cycle);
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        ticks.tick().await;
        for shared in devices.iter() {
            shared.cycle();
        }
    }
}

impl SimHandle {
    /// The bound UDP address (the PLC's address for a backend), or the
    /// Modbus TCP address; 0.0.0.0:0 on a serial line.
    pub fn local_addr(&self) -> SocketAddr {
        self.units[0].local_addr
    }

    fn first(&self) -> &Shared {
        &self.units[0].shared
    }

    /// How many devices it serves.
    pub fn devices(&self) -> usize {
        self.units.len()
    }

    /// Each device's address, in order.
    pub fn local_addrs(&self) -> Vec<SocketAddr> {
        self.units.iter().map(|u| u.local_addr).collect()
    }

    /// Device `index` (memory image, run state, files).
    pub fn device_at(&self, index: usize) -> Option<Arc<Mutex<Device>>> {
        self.units.get(index).map(|u| u.shared.device.clone())
    }

    /// Drops this fraction of device `index`'s requests (1.0: a dead device).
    pub fn set_loss_at(&self, index: usize, fraction: f64) {
        if let Some(unit) = self.units.get(index) {
            unit.shared.set_loss(fraction);
        }
    }

    /// Variable changes the animation made so far, all devices together.
    pub fn changes(&self) -> u64 {
        self.units.iter().map(|u| u.shared.changes()).sum()
    }

    /// Bytes and frames on the serial line (zero over UDP).
    pub fn line_stats(&self) -> &serial::LineStats {
        &self.first().line
    }

    /// The bound control port, when one was asked for.
    pub fn control_addr(&self) -> Option<SocketAddr> {
        self.control_addr
    }

    /// The simulated device (memory image, run state, files).
    pub fn device(&self) -> Arc<Mutex<Device>> {
        self.first().device.clone()
    }

    /// Drops this fraction (0.0..=1.0) of incoming datagrams.
    pub fn set_loss(&self, fraction: f64) {
        self.first().set_loss(fraction);
    }

    /// Delays every answer by this much (capped at 60 s).
    pub fn set_latency(&self, latency: Duration) {
        self.first().set_latency(latency);
    }

    pub fn halt(&self) {
        self.first().set_run(false);
    }

    pub fn run(&self) {
        self.first().set_run(true);
    }

    pub fn is_running(&self) -> bool {
        lock(&self.first().device).run()
    }

    pub fn set_program(&self, kind: ProgramKind) {
        self.first().set_program(kind);
    }

    pub fn set_animate(&self, masks: &[String]) {
        self.first().set_animate(masks);
    }

    /// Loads another public file (another PLC program); returns the new
    /// `__PF_CRC`. The file system serves it in place of the previous one.
    pub fn load_pub(&self, bytes: &[u8]) -> u32 {
        self.first().load_pub(bytes, None)
    }

    /// As [`SimHandle::load_pub`], the file system serving it under the
    /// file's own name.
    pub fn load_pub_file(&self, path: &Path) -> io::Result<u32> {
        let bytes = std::fs::read(path).map_err(|e| with_path(e, path))?;
        let name = path.file_name().and_then(|n| n.to_str());
        Ok(self.first().load_pub(&bytes, name))
    }

    pub fn pf_crc(&self) -> u32 {
        lock(&self.first().device).pf_crc()
    }

    /// Stops the simulator and waits until its sockets are closed, so the
    /// port can be bound again.
    pub async fn stop(mut self) {
        for task in &self.tasks {
            task.abort();
        }
        for task in self.tasks.drain(..) {
            let _ = task.await;
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}
