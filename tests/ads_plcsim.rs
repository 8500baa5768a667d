//! The ADS backend against `plcsim --ads` (the simulator's demo program as
//! an ADS device, in process): its public file's variables as symbols,
//! writes, notifications with the simulated PLC's clock, HALT/RUN as the
//! ADS state, and a new program (another public file) reloaded live.

mod common;

use std::net::SocketAddr;
use std::time::Duration;

use common::modbus::until;
use common::process::{free_port, ServerProcess};
use common::Client;
use plcsim::{SimConfig, DEMO_PUB};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_demo_program_as_an_ads_device() {
    let sim = plcsim::spawn(SimConfig {
        ads: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
        ..SimConfig::default()
    })
    .await
    .expect("plcsim --ads");
    let port = free_port();
    let ini = format!(
        "[*]\n[A]\nPROTOCOL = ADS\nIPADDR = 127.0.0.1\nADS_TCP_PORT = {}\n\
         SERVER_PORT = {port}\nADS_NOTIFY = tim\nADS_CYCLE = 10\n",
        sim.local_addr().port()
    );
    let server = ServerProcess::with_config(&ini, port);
    let mut c = Client::connect(server.addr).await;
    until(&mut c, "GET:__PLC_RUN", "GET:__PLC_RUN,1", 15).await;
    // The demo program's variables; DATE and DT are not served over ADS.
    c.ask("SET:setpoint,2.5\r\n", "DIFF:SETPOINT,2.500000\r\n")
        .await;
    c.ask("SET:flag_b,1\r\n", "DIFF:FLAG_B,1\r\n").await;
    c.ask("GET:flag_a\r\n", "GET:FLAG_A,0\r\n").await;
    c.ask("SET:note,\"over ADS\"\r\n", "DIFF:NOTE,\"over ADS\"\r\n")
        .await;
    c.ask(
        "GET:v_dt\r\n",
        "ERROR:33 Unknown variable name in request: 'GET:v_dt'\r\n",
    )
    .await;
    // The program clock by notification: its changes keep coming.
    c.send(b"EN:tim\r\n").await;
    let mut diffs = Vec::new();
    while diffs.len() < 3 {
        let line = c
            .line_within(Duration::from_secs(5))
            .await
            .expect("DIFF:TIM within 5 s");
        if line.starts_with(b"DIFF:TIM,") {
            diffs.push(line);
        }
    }
    assert!(diffs[0] != diffs[1] && diffs[1] != diffs[2], "{diffs:?}");
    c.send(b"DI:tim\r\n").await;

    // HALT: __PLC_RUN from the ADS state.
    sim.halt();
    until(&mut c, "GET:__PLC_RUN", "GET:__PLC_RUN,0", 5).await;
    sim.run();
    until(&mut c, "GET:__PLC_RUN", "GET:__PLC_RUN,1", 5).await;

    // A new program: another public file, a new symbol version.
    // (Before the CRC trailer, which covers what precedes it.)
    let mut other = b" extra R B 300 INT PUB_INOUT\n".to_vec();
    other.extend_from_slice(DEMO_PUB);
    sim.load_pub(&other);
    until(&mut c, "GET:extra", "GET:EXTRA,0", 10).await;
    assert!(
        server.log().contains("symbols uploaded"),
        "{}",
        server.log()
    );
}
