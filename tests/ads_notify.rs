//! ADS device notifications against pyads's test server (our fixture,
//! tests/ads/fixture.py): values sent by the PLC on change, each with the
//! PLC's FILETIME, reach DIFFs and the historian with that time; the
//! notifications are deleted and registered again when the program
//! changes, and none are left on the PLC by a server that goes away.

mod common;
#[path = "ads/fixture.rs"]
#[allow(dead_code)]
mod fixture;

use std::time::Duration;

use common::modbus::until;
use common::process::{free_port, ServerProcess};
use common::Client;
use fixture::Fixture;

/// 2024-03-15T13:45:30.000Z as a FILETIME, and in Unix milliseconds.
const FT0: u64 = 133_549_839_300_000_000;
const MS0: i64 = 1_710_510_330_000;

/// How many notifications the fixture holds for clients.
fn notifications(device: &mut Fixture) -> usize {
    let count = device.ask("count");
    count.split_whitespace().nth(3).unwrap().parse().unwrap()
}

#[tokio::test]
async fn notified_values_carry_the_plcs_time_into_diffs_and_history() {
    let mut device = Fixture::start(0);
    let (port, http) = (free_port(), free_port());
    let ini = format!(
        "[*]\nHTTP_PORT = {http}\nHISTORY_SYNC = 1\n[A]\nPROTOCOL = ADS\nIPADDR = 127.0.0.1\n\
         ADS_TCP_PORT = {}\nSERVER_PORT = {port}\nADS_NOTIFY = MAIN.counter, MAIN.st.n*\n\
         ADS_CYCLE = 10\nHISTORY = MAIN.COUNTER\n",
        device.port
    );
    let server = ServerProcess::with_config(&ini, port);
    let mut c = Client::connect(server.addr).await;
    until(&mut c, "GET:MAIN.counter", "GET:MAIN.COUNTER,0", 15).await;
    // One for the counter, three for the array field's elements.
    assert_eq!(notifications(&mut device), 4);
    c.send(b"EN:MAIN.counter\r\n").await;
    c.wait_for_line(b"DIFF:MAIN.COUNTER,0\r\n", Duration::from_secs(5))
        .await;

    // 20 changes 10 ms apart in the PLC's time, sent as fast as it can.
    for k in 1..=20u64 {
        device.ask(&format!("stamp {}", FT0 + k * 100_000));
        device.ask(&format!("set MAIN.counter {}", hex(k as i32)));
    }
    c.wait_for_line(b"DIFF:MAIN.COUNTER,20\r\n", Duration::from_secs(5))
        .await;
    // Polled like any other variable, from the notified value.
    c.ask("GET:MAIN.counter\r\n", "GET:MAIN.COUNTER,20\r\n")
        .await;
    // A write is read back from the PLC, not from the last notification.
    c.send(b"DI:MAIN.counter\r\n").await;
    warning_252(&mut c).await;
    c.ask("SET:MAIN.counter,30\r\n", "DIFF:MAIN.COUNTER,30\r\n")
        .await;
    c.send(b"EN:MAIN.counter\r\n").await;
    warning_252(&mut c).await;

    // The historian has every sample, each at the PLC's time.
    let from = MS0 - 1000;
    let to = MS0 + 10_000;
    let path = format!("/api/history?section=A&vars=MAIN.COUNTER&from={from}&to={to}&format=csv");
    let csv = common::http::get_until(http, &path, Duration::from_secs(10), |answer| {
        answer.matches("MAIN.COUNTER").count() >= 20
    });
    // None lost, none twice.
    assert_eq!(csv.matches(",MAIN.COUNTER,").count(), 20, "{csv}");
    for k in 1..=20i64 {
        let at = chrono::DateTime::from_timestamp_millis(MS0 + 10 * k)
            .unwrap()
            .format("%Y-%m-%dT%H:%M:%S%.3fZ")
            .to_string();
        assert!(
            csv.lines()
                .any(|l| l.contains(&at) && l.contains(&format!(",{k},"))),
            "no sample {k} at {at} in:\n{csv}"
        );
    }

    // A new program: the notifications are deleted and registered again.
    device.ask("add MAIN.fresh INT 0700");
    until(&mut c, "GET:MAIN.fresh", "GET:MAIN.FRESH,7", 10).await;
    assert_eq!(notifications(&mut device), 4);
    device.ask("stamp 0");
    device.ask(&format!("set MAIN.counter {}", hex(21)));
    c.wait_for_line(b"DIFF:MAIN.COUNTER,21\r\n", Duration::from_secs(5))
        .await;

    // The server gone: nothing left registered on the PLC.
    drop(c);
    drop(server);
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    while notifications(&mut device) != 0 {
        assert!(
            std::time::Instant::now() < deadline,
            "notifications left on the PLC"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Past the WARNING:252 that an EN or DI answers.
async fn warning_252(c: &mut Client) {
    loop {
        let line = c
            .line_within(Duration::from_secs(5))
            .await
            .expect("WARNING:252");
        if line.starts_with(b"WARNING:252") {
            return;
        }
    }
}

fn hex(value: i32) -> String {
    value
        .to_le_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}
