//! ADS values again within 2 s of the PLC's return, by the method of
//! tests/return_within_2s.rs, against pyads's test server (our fixture,
//! tests/ads/fixture.py, whose program writes `MAIN.tim`, the time of day
//! in ms, every 10 ms) at ADS_TIMEOUT 1000 ms and COMM_LOOP_DELAY 100 ms.
//!
//! Eight outages of 1 to 10 s rather than twenty of 1 to 20 s: the probes'
//! back-off reaches its 1 s maximum within the first 2 s of an outage, so
//! the longer ones add nothing but a phase of that cycle, which these
//! lengths already spread; and a restart of the fixture costs a Python
//! start-up. They alternate between a silent PLC (every request dropped on
//! an open connection: a cable pulled) and one that is off (the fixture
//! killed and started again on the same port: a refused connection).

mod common;
#[path = "ads/fixture.rs"]
#[allow(dead_code)]
mod fixture;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use common::health::{answer, fresh, time_of_day_ms};
use common::process::{free_port, ServerProcess};
use common::Client;
use fixture::Fixture;

const OUTAGES: [f64; 8] = [1.0, 1.5, 2.2, 3.3, 4.8, 6.8, 1.2, 9.6];
const RETURN: Duration = Duration::from_secs(2);

async fn get_tim(c: &mut Client) -> Option<i64> {
    let (line, _) = answer(c, "GET:MAIN.tim\n").await;
    line.strip_prefix("GET:MAIN.TIM,")
        .and_then(|v| v.trim_end().parse().ok())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ads_values_again_within_2_s_of_the_return() {
    let mut device = Some(Fixture::start(0));
    let device_port = device.as_ref().unwrap().port;
    let port = free_port();
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 100\n[A]\nPROTOCOL = ADS\nIPADDR = 127.0.0.1\n\
         ADS_TCP_PORT = {device_port}\nADS_TIMEOUT = 1000\nSERVER_PORT = {port}\n"
    );
    let server = ServerProcess::with_config(&ini, port);
    let mut c = Client::connect(SocketAddr::from(([127, 0, 0, 1], port))).await;
    let start = Instant::now();
    while get_tim(&mut c).await.is_none() {
        assert!(start.elapsed() < Duration::from_secs(20), "no value");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut times = Vec::new();
    for (i, secs) in OUTAGES.iter().enumerate() {
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let off = i % 2 == 1;
        if off {
            device = None;
        } else {
            device.as_mut().unwrap().ask("silent 1");
        }
        tokio::time::sleep(Duration::from_secs_f64(*secs)).await;
        match device.as_mut() {
            Some(d) => {
                d.ask("silent 0");
            }
            None => device = Some(Fixture::start(device_port)),
        }
        let back = Instant::now();
        let back_ms = time_of_day_ms();
        let took = loop {
            if let Some(tim) = get_tim(&mut c).await {
                if fresh(tim, back_ms) {
                    break back.elapsed();
                }
            }
            assert!(
                back.elapsed() < Duration::from_secs(10),
                "no fresh value 10 s after the return"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        println!(
            "ADS: outage {secs:.1} s ({}): values again {:.0} ms after the return",
            if off { "off" } else { "silent" },
            took.as_secs_f64() * 1000.0
        );
        times.push((*secs, took));
    }
    let late: Vec<_> = times.iter().filter(|(_, t)| *t >= RETURN).collect();
    assert!(
        late.is_empty(),
        "values later than 2 s after the return: {late:?}\n{}",
        server.log()
    );
    // One line per outage in the log, not one per probe.
    let log = server.log();
    let lost = log.matches("PLC lost").count() + log.matches("cannot reach PLC").count();
    assert!(
        lost <= OUTAGES.len() + 1,
        "{lost} loss lines for {} outages:\n{log}",
        OUTAGES.len()
    );
}
