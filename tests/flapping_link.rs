//! A backend that connects but fails every read (the bad plugin's mode 2:
//! every read answers a status the ABI does not define) must not flap at the
//! poll rate: once it is lost twice in a row before a run of good polls,
//! each reconnection waits longer than the one before, and the log says it
//! once, then a count at most once a minute.
//!
//! A test binary of its own with a global subscriber (see
//! `tests/outage_logging.rs`).

mod common;

use std::time::Duration;

use common::epsnet::eventually;
use common::logs::Logs;
use common::process::plugin_lib;

/// Lines of the log about the link coming and going.
fn link_lines(logs: &Logs) -> usize {
    ["PLC connected", "PLC lost", "cannot reach PLC", "PLC fails"]
        .iter()
        .map(|needle| logs.count(needle))
        .sum()
}

#[tokio::test]
async fn a_plc_that_connects_and_fails_every_read_backs_off_and_logs_once() {
    let logs = Logs::install();
    let lib = plugin_lib("bad");
    let (server, _port, _conf) = common::start_on_free_port(|port| {
        format!(
            "[*]\n[Plug]\nSHM_NAME = {}\nSERVER_PORT = {port}\nSHM_SOCKET = 2\n",
            lib.display()
        )
    })
    .await;
    let metrics = &server.sections[0].section.metrics();
    eventually("a failed read", Duration::from_secs(20), || {
        metrics.backend.errors.get() > 0
    })
    .await;
    let requests = metrics.backend.requests.get();
    // At the poll rate (100 ms) this was some 100 flaps, 200 log lines.
    tokio::time::sleep(Duration::from_secs(10)).await;
    let all = logs.text();
    let lines = link_lines(&logs);
    let attempts = metrics.backend.requests.get() - requests;
    println!("{lines} link lines, {attempts} requests in 10 s:\n{all}");
    // Connected, lost, connected again, failing soon after connecting.
    assert!(lines <= 4, "{lines} link lines in 10 s:\n{all}");
    // Still tried: the pauses double from 100 ms, up to 30 s.
    assert!(attempts >= 3, "{attempts} requests in 10 s");
    assert!(attempts <= 60, "{attempts} requests in 10 s");
}
