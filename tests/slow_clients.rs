//! Slow and abusive clients: output limits (OUTPUT_SOFT_LIMIT held for
//! OUTPUT_SOFT_TIMEOUT, OUTPUT_HARD_LIMIT), other clients unaffected, big
//! answers still delivered, idle clients kept, TCP keepalive.

mod common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{start_with, Client, TestServer};
use plccoms_core::driver::WriteData;
use plccoms_protocol::Area;
use tokio::io::AsyncReadExt;
use tokio::net::{TcpSocket, TcpStream};

/// `MARK` (DINT at R0) and `count` INTs after it.
fn busy_pub(count: usize) -> Vec<u8> {
    let mut text = b" MARK R B 0 DINT PUB_INOUT\r\n".to_vec();
    for i in 0..count {
        text.extend_from_slice(format!(" V{i:04} R B {} INT PUB_INOUT\r\n", 4 + 2 * i).as_bytes());
    }
    text
}

/// A client whose receive buffer is small, so that output backs up in the
/// server quickly when it stops reading.
async fn stalled_client(server: &TestServer) -> TcpStream {
    let socket = TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    socket.connect(server.addr).await.unwrap()
}

async fn wait_clients(server: &TestServer, count: usize, within: Duration) {
    let start = Instant::now();
    while server.section.section.clients().len() != count {
        assert!(
            start.elapsed() < within,
            "{} clients connected after {within:?}, expected {count}",
            server.section.section.clients().len()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Reads until the server closes the connection (end or reset), at most
/// `within`.
async fn read_to_close(stream: &mut TcpStream, within: Duration) {
    let deadline = Instant::now() + within;
    let mut chunk = vec![0u8; 65536];
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        assert!(!left.is_zero(), "the server did not close the connection");
        match tokio::time::timeout(left, stream.read(&mut chunk)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return,
            Ok(Ok(_)) => {}
            Err(_) => panic!("the server did not close the connection"),
        }
    }
}

/// Changes every `V` variable every few milliseconds until `stop`.
fn animate(
    server: &TestServer,
    count: usize,
    stop: Arc<AtomicBool>,
) -> std::thread::JoinHandle<u64> {
    let device = server.device.clone();
    std::thread::spawn(move || {
        let mut round: u16 = 0;
        let mut rounds = 0;
        let start = Instant::now();
        while !stop.load(Ordering::Relaxed) && start.elapsed() < Duration::from_secs(120) {
            round = round.wrapping_add(1);
            let bytes: Vec<u8> = (0..count).flat_map(|_| round.to_le_bytes()).collect();
            device
                .lock()
                .unwrap()
                .write(Area::R, 4, &WriteData::Bytes(bytes))
                .unwrap();
            rounds += 1;
            std::thread::sleep(Duration::from_millis(5));
        }
        rounds
    })
}

/// Sets MARK to `mark` and waits for its DIFF among the others; the time it
/// took.
async fn mark_latency(server: &TestServer, c: &mut Client, mark: i32) -> Duration {
    let sent = Instant::now();
    server.poke(Area::R, 0, &mark.to_le_bytes());
    let want = format!("DIFF:MARK,{mark}\r\n");
    let mut lines = 0;
    loop {
        let line = c.line().await;
        lines += 1;
        assert!(lines < 10_000_000);
        if line == want.as_bytes() {
            return sent.elapsed();
        }
        assert!(
            sent.elapsed() < Duration::from_secs(10),
            "no DIFF for MARK within 10 s"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_is_dropped_and_others_keep_their_diffs() {
    const VARS: usize = 400;
    let server = start_with(
        "PF_VAR_DISABLED = No\nCOMM_LOOP_DELAY = 10\nOUTPUT_SOFT_LIMIT = 65536\nOUTPUT_SOFT_TIMEOUT = 2",
        &busy_pub(VARS),
    )
    .await;
    let mut reader = server.client().await;
    let stop = Arc::new(AtomicBool::new(false));
    let animation = animate(&server, VARS, stop.clone());

    // DIFF latency of a reading client with no stalled client around.
    let mut before = Vec::new();
    for mark in 1..=5 {
        before.push(mark_latency(&server, &mut reader, mark).await);
    }

    // A client that connects (all variables enabled) and never reads.
    let mut stalled = stalled_client(&server).await;
    wait_clients(&server, 2, Duration::from_secs(5)).await;
    let stalled_at = Instant::now();
    let mut during = Vec::new();
    let mut mark = 100;
    while server.section.section.clients().len() == 2 {
        assert!(
            stalled_at.elapsed() < Duration::from_secs(40),
            "the stalled client was not dropped within 40 s"
        );
        mark += 1;
        during.push(mark_latency(&server, &mut reader, mark).await);
    }
    let dropped_after = stalled_at.elapsed();
    // Still served after the drop.
    let after = mark_latency(&server, &mut reader, 1_000_000).await;
    stop.store(true, Ordering::Relaxed);
    let rounds = animation.join().unwrap();
    read_to_close(&mut stalled, Duration::from_secs(20)).await;

    let max = |v: &[Duration]| v.iter().copied().max().unwrap_or_default();
    eprintln!(
        "{rounds} rounds of {VARS} changes; DIFF latency before {:?} (max), with a stalled client {:?} (max of {}), after {after:?}; stalled client dropped after {dropped_after:?}",
        max(&before),
        max(&during),
        during.len()
    );
    assert!(
        dropped_after >= Duration::from_secs(2),
        "dropped before OUTPUT_SOFT_TIMEOUT"
    );
    // Generous bounds for a shared CI machine: a poll cycle is 10 ms.
    assert!(max(&during) < Duration::from_secs(2), "{during:?}");
    assert!(after < Duration::from_secs(2));
}

#[tokio::test]
async fn output_over_the_hard_limit_disconnects_at_once() {
    let server = start_with(
        "OUTPUT_HARD_LIMIT = 65536\nOUTPUT_SOFT_TIMEOUT = 3600",
        &busy_pub(20),
    )
    .await;
    let mut greedy = stalled_client(&server).await;
    // ~900 bytes of answer per request, never read: far beyond the kernel's
    // buffers and the hard limit.
    let requests = b"LIST:\n".repeat(20_000);
    use tokio::io::AsyncWriteExt;
    let start = Instant::now();
    // The server stops reading once dropped: the write may fail then.
    let _ = tokio::time::timeout(Duration::from_secs(30), greedy.write_all(&requests)).await;
    wait_clients(&server, 0, Duration::from_secs(30)).await;
    assert!(start.elapsed() < Duration::from_secs(30));
    read_to_close(&mut greedy, Duration::from_secs(20)).await;
    // Others are served.
    let mut c = server.client().await;
    c.ask("LIST:MARK\n", "LIST:MARK,DINT*\r\nLIST:\r\n").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_list_of_50000_variables_reaches_a_reading_client_with_the_default_limits() {
    let mut text = Vec::new();
    for i in 0..50_000 {
        text.extend_from_slice(
            format!(
                " PLANT_AREA_VARIABLE_{i:05} R B {} INT PUB_INOUT\r\n",
                2 * i
            )
            .as_bytes(),
        );
    }
    let server = start_with("", &text).await;
    let mut c = server.client().await;
    c.send(b"LIST:\n").await;
    let mut bytes = 0;
    let mut lines = 0;
    loop {
        let line = c.line().await;
        bytes += line.len();
        lines += 1;
        if line == b"LIST:\r\n" {
            break;
        }
    }
    assert_eq!(lines, 50_000 + 2 + 1);
    assert!(bytes > 1_500_000, "{bytes}");
    c.ask("LIST:__PLC_RUN\n", "LIST:__PLC_RUN,BOOL\r\nLIST:\r\n")
        .await;
    assert_eq!(server.section.section.clients().len(), 1);
}

#[tokio::test]
async fn idle_clients_are_kept() {
    let server = start_with("", &busy_pub(2)).await;
    let mut c = server.client().await;
    c.silent(3000).await;
    c.ask("LIST:MARK\n", "LIST:MARK,DINT*\r\nLIST:\r\n").await;
}
