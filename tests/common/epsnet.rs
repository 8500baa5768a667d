//! Fixtures for tests that run a section against a simulated EPSNET PLC
//! over real UDP on 127.0.0.1.

use std::net::SocketAddr;
use std::time::Duration;

use plccoms::startup::{start_section, RunningSection};
use plccoms_core::driver::WriteData;
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_protocol::Area;
use plcsim::program::ProgramKind;
use plcsim::{SimConfig, SimHandle};

use super::Client;

/// Generous: the machine is shared, and a PLC coming back takes a reconnect.
pub const SLOW: Duration = Duration::from_secs(20);

/// EPSNET link settings of a test section.
#[derive(Clone, Copy)]
pub struct Link {
    pub timeout_ms: u64,
    pub step_ms: u64,
    pub retries: u32,
}

/// Short timeouts: a dead PLC is noticed in well under a second.
pub const FAST_LINK: Link = Link {
    timeout_ms: 100,
    step_ms: 50,
    retries: 3,
};

pub async fn spawn_sim(bind: SocketAddr, program: ProgramKind) -> SimHandle {
    plcsim::spawn(SimConfig {
        bind,
        program,
        ..SimConfig::default()
    })
    .await
    .expect("spawn simulator")
}

pub fn any_port() -> SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

/// A section serving `conf/demo.pub` (with the fixed file) from the PLC at
/// `plc`, configured by the `[*]` keys in `global_ini`.
pub async fn start_server(plc: SocketAddr, global_ini: &str, link: Link) -> RunningSection {
    let (global, section, table) = super::section_parts(
        global_ini,
        plcsim::FIXED_PUB,
        ("demo.pub", plcsim::DEMO_PUB),
    );
    let mut eps = EpsnetConfig::new(plc);
    eps.local_ip = "127.0.0.1".parse().unwrap();
    eps.timeout = Duration::from_millis(link.timeout_ms);
    eps.timeout_step = Duration::from_millis(link.step_ms);
    eps.retries = link.retries;
    start_section(
        global,
        section,
        table,
        Some(Box::new(EpsnetBackend::new(eps))),
        any_port(),
        std::env::temp_dir(),
        None,
    )
    .await
    .expect("start section")
}

pub fn poke(sim: &SimHandle, area: Area, offset: u32, bytes: &[u8]) {
    sim.device()
        .lock()
        .unwrap()
        .write(area, offset, &WriteData::Bytes(bytes.to_vec()))
        .unwrap();
}

pub fn peek(sim: &SimHandle, area: Area, offset: u32, len: u32) -> Vec<u8> {
    sim.device()
        .lock()
        .unwrap()
        .read(area, offset, len)
        .unwrap()
}

/// Waits until `cond` holds, polling; panics after `within`.
pub async fn eventually(what: &str, within: Duration, mut cond: impl FnMut() -> bool) {
    let deadline = tokio::time::Instant::now() + within;
    while !cond() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{what}: not within {within:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// An idle simulated PLC with SETPOINT = 1.5, a section on it, and a client
/// that enabled SETPOINT and got its first DIFF.
pub async fn watched_idle_plc() -> (SimHandle, RunningSection, Client) {
    let sim = spawn_sim(any_port(), ProgramKind::Idle).await;
    poke(&sim, Area::R, 124, &1.5f32.to_le_bytes());
    let server = start_server(sim.local_addr(), "", FAST_LINK).await;
    let mut watcher = Client::connect(server.local_addr).await;
    watcher
        .ask(
            "EN:setpoint\n",
            "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
        )
        .await;
    watcher.expect(b"DIFF:SETPOINT,1.500000\r\n").await;
    (sim, server, watcher)
}
