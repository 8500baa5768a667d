//! `plcsim --s7` as the CPU of the real server's S7 section: the demo
//! program's values in DB1 and the merkers, writes (a merker bit with its
//! neighbours kept), HALT/RUN as `__PLC_RUN`, a DB it lacks refused, and
//! the fault injection (all requests lost: the link is lost and back).

mod common;

use std::net::{Ipv4Addr, SocketAddr};
use std::time::Duration;

use common::modbus::until;
use common::s7::s7_server;
use common::Client;
use plccoms_plc::s7::Region;
use plccoms_protocol::Area;
use plcsim::{PubSource, SimConfig, DEMO_S7_TAGS};

#[tokio::test]
async fn plcsim_s7_serves_the_demo_program() {
    let sim = plcsim::spawn(SimConfig {
        s7: Some(SocketAddr::from((Ipv4Addr::LOCALHOST, 0))),
        pubfile: PubSource::Bytes(DEMO_S7_TAGS.to_vec()),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let tags = format!(
        "{}nowhere,DB99.DBW0,INT\n",
        String::from_utf8(DEMO_S7_TAGS.to_vec()).unwrap()
    );
    let server = s7_server(dir.path(), sim.local_addr().port(), &tags, "");
    let mut c = Client::connect(server.addr).await;
    c.ask("GET:text\r\n", "GET:TEXT,\"Have a nice day\"\r\n")
        .await;
    c.ask("LIST:stamp\r\n", "LIST:STAMP,DT*\r\nLIST:\r\n").await;
    for (request, answer) in [
        ("SET:setpoint,21.5", "DIFF:SETPOINT,21.500000"),
        ("SET:levels[3],-3", "DIFF:LEVELS[3],-3"),
        ("SET:counter,123456", "DIFF:COUNTER,123456"),
        ("SET:switch,1", "DIFF:SWITCH,1"),
        (
            "GET:nowhere",
            "ERROR:80 Unable to get data from address: 'NOWHERE: S7 object does not exist (0x0A)'",
        ),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    // The demo program runs: tim changes, and the switch sits beside
    // `positive` in M0 without disturbing it.
    let tim = |line: String| {
        line.trim_end()
            .trim_start_matches("GET:TIM,")
            .parse::<u64>()
            .unwrap()
    };
    c.send(b"GET:tim\r\n").await;
    let first = tim(String::from_utf8(c.line().await).unwrap());
    tokio::time::sleep(Duration::from_millis(200)).await;
    c.send(b"GET:tim\r\n").await;
    let second = tim(String::from_utf8(c.line().await).unwrap());
    assert_ne!(first, second);
    let (area, offset) = Region::Merkers.place(0);
    assert_eq!(area, Area::R);
    let m0 = sim.device().lock().unwrap().read(area, offset, 1).unwrap()[0];
    assert_eq!(m0 & 0b10, 0b10, "switch");

    sim.halt();
    until(&mut c, "GET:__PLC_RUN", "GET:__PLC_RUN,0", 5).await;
    sim.run();
    until(&mut c, "GET:__PLC_RUN", "GET:__PLC_RUN,1", 5).await;

    sim.set_loss(1.0);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(6);
    loop {
        c.send(b"GET:text\r\n").await;
        if String::from_utf8(c.line().await)
            .unwrap()
            .starts_with("ERROR:")
        {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the link is not lost"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    sim.set_loss(0.0);
    until(&mut c, "GET:text", "GET:TEXT,\"Have a nice day\"", 5).await;
}
