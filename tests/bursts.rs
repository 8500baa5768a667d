//! Polling scripts and home-automation libraries send a burst of `GET:`
//! lines in one segment and some read the answers with a single `recv()`,
//! parsing only what that read returned. Answers to requests that arrived
//! together must leave in one write once all are ready, even when some of
//! them wait for the PLC and others are served from the poll at once.

mod common;

use std::time::Duration;

use common::{simulated, Client};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[tokio::test]
async fn a_burst_of_gets_is_answered_in_one_write() {
    let project = plcsim::genpub::plain(300);
    let (server, addr, _dir) = simulated("", "PUBFILE = //project.pub", Some(&project)).await;
    // The PLC answers after 5 ms: GETs of variables nobody polls wait for it.
    server.simulators()[0].set_latency(Duration::from_millis(5));
    let mut enabler = Client::connect(addr).await;
    enabler
        .ask(
            "EN:VAR_000*\n",
            "WARNING:252 Changed active variables in public file: '[102/302]'\r\n",
        )
        .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    // 150 GETs: every other one polled (VAR_000nn), the others not.
    let mut burst = String::new();
    for i in 0..150 {
        let n = if i % 2 == 0 { i / 2 } else { 100 + i };
        burst.push_str(&format!("GET:var_{n:05}\n"));
    }
    for round in 0..40 {
        let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
        stream.write_all(burst.as_bytes()).await.unwrap();
        let mut buf = vec![0u8; 65536];
        let n = tokio::time::timeout(Duration::from_secs(10), stream.read(&mut buf))
            .await
            .expect("an answer")
            .unwrap();
        let answers = buf[..n]
            .split(|&b| b == b'\n')
            .filter(|l| !l.is_empty())
            .count();
        assert_eq!(
            answers,
            150,
            "round {round}: the first recv held {answers} of 150 answers:\n{}",
            String::from_utf8_lossy(&buf[..n])
        );
        assert!(buf[..n].starts_with(b"GET:VAR_00000,"));
    }
    // A request alone is answered as soon as it can be.
    let mut c = Client::connect(addr).await;
    c.ask("GET:var_00200\n", "GET:VAR_00200,0\r\n").await;
}
