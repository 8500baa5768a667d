//! Link health at the vendor's default timeouts (EPSTOUT 1000 ms,
//! EPSTOUT_STEP 500 ms, COMM_LOOP_DELAY 100 ms), against the simulated PLC
//! over real UDP, through the real start-up path:
//! - a polled value is served only while its poll is fresh (2 x
//!   COMM_LOOP_DELAY + EPSTOUT = 1.2 s); after that, GET reads the PLC or
//!   answers the link error, never the old value;
//! - a silent PLC is declared lost within EPSTOUT plus one retry (2.5 s);
//!   while it is lost, requests are answered at once, SETs are refused and
//!   never applied later;
//! - a PLC that is off at start-up: every section listens at once, and the
//!   section serves when the PLC appears (public file local or on the PLC);
//! - the change stream marks the outage.
//!
//! Bounds on times are generous (CI machines are slow and shared); the
//! measured figures are printed (`--nocapture`).

mod common;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use common::health::{answer, LOSS, SLACK};
use common::Client;
use plccoms_core::changes::{LinkEvent, Quality};
use plccoms_protocol::Area;
use plcsim::{SimConfig, SimHandle};

const SETPOINT: u32 = 124;
const COUNTER: u32 = 130;

async fn spawn_sim(bind: SocketAddr, files: &std::path::Path) -> SimHandle {
    plcsim::spawn(SimConfig {
        bind,
        files: Some(files.to_path_buf()),
        program: "idle".parse().unwrap(),
        ..SimConfig::default()
    })
    .await
    .expect("spawn simulator")
}

/// Restarts a simulator on `addr` (the port may linger for a moment).
async fn respawn(addr: SocketAddr, files: &std::path::Path) -> SimHandle {
    let start = Instant::now();
    loop {
        match plcsim::spawn(SimConfig {
            bind: addr,
            files: Some(files.to_path_buf()),
            program: "idle".parse().unwrap(),
            ..SimConfig::default()
        })
        .await
        {
            Ok(sim) => return sim,
            Err(e) => {
                assert!(start.elapsed() < Duration::from_secs(10), "rebind: {e}");
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
    }
}

fn poke(sim: &SimHandle, offset: u32, bytes: &[u8]) {
    sim.device()
        .lock()
        .unwrap()
        .write(
            Area::R,
            offset,
            &plccoms_core::driver::WriteData::Bytes(bytes.to_vec()),
        )
        .unwrap();
}

fn peek(sim: &SimHandle, offset: u32, len: u32) -> Vec<u8> {
    sim.device()
        .lock()
        .unwrap()
        .read(Area::R, offset, len)
        .unwrap()
}

/// A section at the vendor's default timeouts on the PLC at `plc`.
fn section(name: &str, port: u16, plc: SocketAddr, extra: &str) -> String {
    format!(
        "[{name}]\nIPADDR = 127.0.0.1\nEPSPORT = {}\nIPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {port}\n\
         PUBFILE = //demo.pub\n{extra}\n",
        plc.port()
    )
}

/// A simulated PLC on loopback serving the demo public file, SETPOINT at
/// 1.5; the folder of its files lives as long as the handle is kept.
async fn plc_with_setpoint() -> (SimHandle, tempfile::TempDir) {
    let files = tempfile::tempdir().unwrap();
    std::fs::write(files.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    let sim = spawn_sim("127.0.0.1:0".parse().unwrap(), files.path()).await;
    poke(&sim, SETPOINT, &1.5f32.to_le_bytes());
    (sim, files)
}

/// A UDP port on loopback where nothing answers (yet).
fn silent_addr() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], common::process::free_udp_port()))
}

#[tokio::test]
async fn a_silent_plc_stops_fresh_values_is_lost_in_time_and_refuses_sets_at_once() {
    let (sim, files) = plc_with_setpoint().await;
    let plc = sim.local_addr();
    let (server, port, _conf) =
        common::start_on_free_port(|port| format!("[*]\n{}", section("PLC", port, plc, ""))).await;
    let mut stream = server.sections[0].section.subscribe(&["setpoint"]);
    let mut c = Client::connect(SocketAddr::from(([127, 0, 0, 1], port))).await;
    c.ask(
        "EN:setpoint\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    c.expect(b"DIFF:SETPOINT,1.500000\r\n").await;
    let batch = stream.next().await.unwrap();
    let id = batch.changes[0];
    assert_eq!(batch.snapshot.quality(id), Quality::Good);
    let polled = batch.snapshot.polled.unwrap();
    let now_ms = plccoms_core::changes::unix_ms(std::time::SystemTime::now());
    assert!(
        (now_ms - polled.unix_ms).abs() < 5000,
        "poll time {polled:?}"
    );

    // kill -9 of the PLC: not one more answer.
    sim.stop().await;
    let killed = Instant::now();
    let (first_error, longest) = common::health::outage(
        &mut c,
        "GET:setpoint\n",
        "GET:SETPOINT,1.500000\r\n",
        killed,
    )
    .await;
    println!(
        "first error {:.0} ms after the kill; answers while lost took at most {:.1} ms",
        first_error.as_secs_f64() * 1000.0,
        longest.as_secs_f64() * 1000.0
    );
    // The change stream marks the outage.
    let lost = loop {
        let batch = stream.next().await.unwrap();
        if batch.link == Some(LinkEvent::Lost) {
            break batch;
        }
    };
    assert_eq!(lost.snapshot.quality(id), Quality::LinkLost);

    // A SET while lost: refused at once, and never applied later.
    let (line, took) = answer(&mut c, "SET:counter,77\n").await;
    assert_eq!(line, "ERROR:10 Unable to connect to PLC.\r\n");
    assert!(
        took < Duration::from_millis(500),
        "SET refused after {took:?}"
    );

    // The PLC returns: values again within 2 s.
    let sim = respawn(plc, files.path()).await;
    let back = Instant::now();
    poke(&sim, SETPOINT, &2.5f32.to_le_bytes());
    c.wait_for_line(b"DIFF:SETPOINT,2.500000\r\n", Duration::from_secs(20))
        .await;
    let resumed = back.elapsed();
    println!(
        "values again {:.0} ms after the PLC returned",
        resumed.as_secs_f64() * 1000.0
    );
    assert!(resumed < Duration::from_secs(2) + SLACK, "{resumed:?}");
    let restored = loop {
        let batch = stream.next().await.unwrap();
        if batch.link == Some(LinkEvent::Restored) {
            break batch;
        }
    };
    assert_eq!(restored.snapshot.quality(id), Quality::Good);
    assert_eq!(
        peek(&sim, COUNTER, 2),
        [0, 0],
        "the refused SET stayed refused"
    );
    c.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;
}

#[tokio::test]
async fn pipelined_sets_of_one_variable_each_answer_their_own_value() {
    let files = tempfile::tempdir().unwrap();
    std::fs::write(files.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    let sim = spawn_sim("127.0.0.1:0".parse().unwrap(), files.path()).await;
    let plc = sim.local_addr();
    let (_server, port, _conf) =
        common::start_on_free_port(|port| format!("[*]\n{}", section("PLC", port, plc, ""))).await;
    let mut c = Client::connect(SocketAddr::from(([127, 0, 0, 1], port))).await;
    for _ in 0..10 {
        c.send(b"SET:counter,1\nSET:counter,2\nSET:setpoint,4\nSET:counter,3\nGET:counter\n")
            .await;
        c.expect(
            b"DIFF:COUNTER,1\r\nDIFF:COUNTER,2\r\nDIFF:SETPOINT,4.000000\r\nDIFF:COUNTER,3\r\nGET:COUNTER,3\r\n",
        )
        .await;
    }
}

/// Starts the server of `ini` and returns how long `start` took.
async fn timed_start(
    ini: impl Fn(u16) -> String,
) -> (plccoms::startup::Server, u16, tempfile::TempDir, Duration) {
    let started = Instant::now();
    let (server, port, conf) = common::start_on_free_port(ini).await;
    (server, port, conf, started.elapsed())
}

#[tokio::test]
async fn a_plc_off_at_start_up_with_its_public_file_on_the_plc() {
    let plc = silent_addr();
    let (server, port, _conf, took) =
        timed_start(|port| format!("[*]\n{}", section("PLC", port, plc, ""))).await;
    println!(
        "listening {:.0} ms after start",
        took.as_secs_f64() * 1000.0
    );
    assert!(took < Duration::from_secs(2), "start-up waited {took:?}");
    let mut c = Client::connect(SocketAddr::from(([127, 0, 0, 1], port))).await;
    // The first connection attempt fails: the fixed variables only, and
    // the link error.
    c.ask("LIST:\n", "LIST:__PLC_RUN,BOOL\r\n").await;
    c.expect(b"LIST:__PF_CRC,DWORD\r\nLIST:\r\n").await;
    c.ask("GET:__plc_run\n", "ERROR:10 Unable to connect to PLC.\r\n")
        .await;

    let files = tempfile::tempdir().unwrap();
    std::fs::write(files.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    let sim = respawn(plc, files.path()).await;
    let appeared = Instant::now();
    poke(&sim, COUNTER, &7u16.to_le_bytes());
    c.wait_for_line(
        b"WARNING:250 Changed public file: 'demo.pub'\r\n",
        Duration::from_secs(20),
    )
    .await;
    c.ask("GET:counter\n", "GET:COUNTER,7\r\n").await;
    let serving = appeared.elapsed();
    println!(
        "public file read and values served {:.0} ms after the PLC appeared",
        serving.as_secs_f64() * 1000.0
    );
    assert!(serving < Duration::from_secs(3) + SLACK, "{serving:?}");
    assert!(server.sections.len() == 1);
}

#[tokio::test]
async fn a_plc_off_at_start_up_with_a_local_public_file_and_a_live_neighbour() {
    let files = tempfile::tempdir().unwrap();
    std::fs::write(files.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    let live = spawn_sim("127.0.0.1:0".parse().unwrap(), files.path()).await;
    poke(&live, COUNTER, &3u16.to_le_bytes());
    let dead = silent_addr();
    let other_port = common::process::free_port();
    let (server, port, _conf, took) = timed_start(|port| {
        format!(
            "[*]\n{}{}",
            section("Dead", port, dead, ""),
            section("Live", other_port, live.local_addr(), "")
        )
    })
    .await;
    assert_eq!(server.sections.len(), 2);
    println!(
        "both listening {:.0} ms after start",
        took.as_secs_f64() * 1000.0
    );
    // The live section is not held up by its neighbour's missing PLC.
    let mut live_client = Client::connect(SocketAddr::from(([127, 0, 0, 1], other_port))).await;
    let (line, first) = answer(&mut live_client, "GET:counter\n").await;
    assert_eq!(line, "GET:COUNTER,3\r\n");
    println!(
        "live section answered in {:.0} ms",
        first.as_secs_f64() * 1000.0
    );
    assert!(first < Duration::from_secs(1), "{first:?}");
    drop(server);
    let _ = port;
}

#[tokio::test]
async fn a_plc_off_at_start_up_with_a_local_public_file() {
    let plc = silent_addr();
    let conf_dir = tempfile::tempdir().unwrap();
    std::fs::write(conf_dir.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    // The local file sits beside the configuration.
    let dir = conf_dir.path().to_path_buf();
    let port = common::process::free_port();
    let path = dir.join("PLCComS.ini");
    std::fs::write(&path, format!("[*]\n{}", section("PLC", port, plc, ""))).unwrap();
    let loaded = plccoms_core::config::load(&path).unwrap();
    let started = Instant::now();
    let _server = plccoms::startup::start(&loaded.config)
        .await
        .expect("start");
    assert!(started.elapsed() < Duration::from_secs(2));
    let mut c = Client::connect(SocketAddr::from(([127, 0, 0, 1], port))).await;
    c.ask(
        "EN:counter\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    // Wait out the first attempt (at most 2.5 s), then errors at once.
    let deadline = Instant::now() + LOSS + SLACK;
    loop {
        let (line, took) = answer(&mut c, "GET:counter\n").await;
        if line == "ERROR:10 Unable to connect to PLC.\r\n" && took < Duration::from_millis(500) {
            break;
        }
        assert!(Instant::now() < deadline, "still {line:?} after {took:?}");
    }
    let files = tempfile::tempdir().unwrap();
    let sim = respawn(plc, files.path()).await;
    let appeared = Instant::now();
    poke(&sim, COUNTER, &9u16.to_le_bytes());
    c.wait_for_line(b"DIFF:COUNTER,9\r\n", Duration::from_secs(20))
        .await;
    let resumed = appeared.elapsed();
    println!(
        "values {:.0} ms after the PLC appeared",
        resumed.as_secs_f64() * 1000.0
    );
    assert!(resumed < Duration::from_secs(2) + SLACK, "{resumed:?}");
}

/// The web page's `/values` quality of `var`, over real HTTP.
fn web_quality(http: SocketAddr, var: &str) -> String {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(http).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    write!(
        stream,
        "GET /api/sections/PLC/values?vars={var} HTTP/1.1\r\nHost: {http}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut raw = String::new();
    let _ = stream.read_to_string(&mut raw);
    let body = raw.split_once("\r\n\r\n").map(|(_, b)| b).unwrap_or("");
    let value: serde_json::Value = serde_json::from_str(body).unwrap_or_default();
    value["values"][0]["quality"]
        .as_str()
        .unwrap_or("none")
        .to_string()
}

#[tokio::test]
async fn the_web_page_calls_a_value_good_only_while_get_serves_it() {
    let (sim, _files) = plc_with_setpoint().await;
    let plc = sim.local_addr();
    let http_port = common::process::free_port();
    let (_server, port, _conf) = common::start_on_free_port(|port| {
        format!(
            "[*]\nHTTP_PORT = {http_port}\n{}",
            section("PLC", port, plc, "")
        )
    })
    .await;
    let http = SocketAddr::from(([127, 0, 0, 1], http_port));
    let mut c = Client::connect(SocketAddr::from(([127, 0, 0, 1], port))).await;
    c.ask(
        "EN:setpoint\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    c.expect(b"DIFF:SETPOINT,1.500000\r\n").await;
    let quality = || tokio::task::spawn_blocking(move || web_quality(http, "setpoint"));
    assert_eq!(quality().await.unwrap(), "good");

    sim.stop().await;
    let killed = Instant::now();
    // The page is asked all along, apart from the GETs.
    let sampler = std::thread::spawn(move || {
        let mut samples = Vec::new();
        while killed.elapsed() < LOSS + SLACK {
            let asked = killed.elapsed();
            samples.push((asked, web_quality(http, "setpoint")));
            std::thread::sleep(Duration::from_millis(20));
        }
        samples
    });
    // When the first GET was sent that was not served the polled value.
    let mut first_refused = None;
    while killed.elapsed() < LOSS + SLACK && first_refused.is_none() {
        let sent = killed.elapsed();
        let (line, _) = answer(&mut c, "GET:setpoint\n").await;
        if line != "GET:SETPOINT,1.500000\r\n" {
            first_refused = Some(sent);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let first_refused = first_refused.expect("GET stopped serving the polled value");
    let samples = tokio::task::spawn_blocking(move || sampler.join().unwrap())
        .await
        .unwrap();
    let good_after: Vec<_> = samples
        .iter()
        .filter(|(asked, quality)| *asked > first_refused && quality == "good")
        .map(|(asked, _)| *asked)
        .collect();
    assert!(
        good_after.is_empty(),
        "GET stopped serving the value at {first_refused:?} after the kill, \
         the page said good at {good_after:?}"
    );
    assert_eq!(quality().await.unwrap(), "link_lost");
}
