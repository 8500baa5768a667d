//! What an operator reads in the log when a PLC goes away and comes back:
//! one line for the loss, one for each connection, however long the outage.
//!
//! A test binary of its own with a global subscriber: tracing caches per
//! call site whether anyone listens, and a thread-scoped subscriber set while
//! other tests' threads first hit the same call sites can be missed (seen on
//! CI), so log lines are only counted where no other test runs.

mod common;

use std::time::Duration;

use common::epsnet::{eventually, poke, watched_idle_plc, SLOW};
use common::logs::Logs;
use plccoms_protocol::Area;
use plcsim::program::ProgramKind;
use plcsim::SimConfig;

#[tokio::test]
async fn an_outage_is_logged_once_and_the_recovery_once() {
    let logs = Logs::install();
    let (sim, server, mut watcher) = watched_idle_plc().await;
    let plc = sim.local_addr();

    sim.stop().await;
    eventually("the link notices", SLOW, || {
        server.section.link_state() != plccoms_core::link::LinkState::Online
    })
    .await;
    // Long enough for the reconnect back-off to try several times (100 ms,
    // doubling to 1 s): each failed attempt must stay quiet.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    assert!(server.section.link_state() != plccoms_core::link::LinkState::Online);

    let sim = plcsim::spawn(SimConfig {
        bind: plc,
        program: ProgramKind::Idle,
        ..SimConfig::default()
    })
    .await
    .expect("the same port again");
    poke(&sim, Area::R, 124, &2.5f32.to_le_bytes());
    watcher
        .wait_for_line(b"DIFF:SETPOINT,2.500000\r\n", SLOW)
        .await;

    let all = logs.text();
    assert_eq!(logs.count("PLC lost"), 1, "{all}");
    assert_eq!(logs.count("cannot reach PLC"), 0, "{all}");
    assert_eq!(logs.count("PLC connected"), 2, "{all}");
}
