//! Memory and descriptors stay bounded: a client sending 100 MB without a
//! line end, and 10,000 connect/disconnect cycles. Measured in this process
//! (the server runs in it) with /proc/self/status and /proc/self/fd; the
//! tests of this file run one at a time so they do not disturb each other.

mod common;

use std::time::{Duration, Instant};

use common::{fd_count, rss_kib, start};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hundred_megabytes_without_a_line_end_keeps_memory_bounded() {
    let _serial = SERIAL.lock().await;
    let server = start("").await;
    let mut other = server.client().await;
    other
        .ask("LIST:TEST_1\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
        .await;
    let before = rss_kib();
    let mut flood = server.client().await;
    let chunk = vec![b'A'; 1 << 20];
    let start = Instant::now();
    let mut peak = before;
    for i in 0..100 {
        tokio::time::timeout(Duration::from_secs(60), flood.send(&chunk))
            .await
            .expect("the server stopped reading");
        if i % 10 == 9 {
            peak = peak.max(rss_kib());
            // Meanwhile another client is served as usual.
            other
                .ask("LIST:TEST_1\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
                .await;
        }
    }
    flood.send(b"\nLIST:TEST_1\n").await;
    let mut want = b"ERROR:30 Bad client request: '".to_vec();
    want.extend(std::iter::repeat_n(b'A', 64));
    want.extend_from_slice(b"...'\r\nLIST:TEST_1,INT*\r\nLIST:\r\n");
    flood.expect(&want).await;
    let after = rss_kib();
    eprintln!(
        "100 MiB without a line end in {:?}: VmRSS {before} kB before, {peak} kB peak, {after} kB after",
        start.elapsed()
    );
    // The decoder holds at most a line (16 KiB) or a block (64 KiB); allow
    // a generous margin for allocator and runtime noise.
    assert!(
        peak < before + 32 * 1024,
        "peak {peak} kB, before {before} kB"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ten_thousand_connections_leave_memory_and_descriptors_where_they_were() {
    let _serial = SERIAL.lock().await;
    let server = start("").await;
    let cycle = |ask: bool| {
        let addr = server.addr;
        async move {
            let mut s = TcpStream::connect(addr).await.expect("connect");
            if ask {
                s.write_all(b"LIST:TEST_1\n").await.unwrap();
                let want = b"LIST:TEST_1,INT*\r\nLIST:\r\n";
                let mut buf = [0u8; 64];
                let mut got = 0;
                while got < want.len() {
                    let n = tokio::time::timeout(Duration::from_secs(10), s.read(&mut buf[got..]))
                        .await
                        .expect("answer")
                        .unwrap();
                    assert!(n > 0);
                    got += n;
                }
                assert_eq!(&buf[..got], want);
            }
        }
    };
    // Warm up: the runtime's and allocator's steady state.
    for i in 0..500 {
        cycle(i % 2 == 0).await;
    }
    let settle = |target: usize| {
        let shared = server.section.section.clone();
        async move {
            let start = Instant::now();
            while shared.clients().len() != target {
                assert!(start.elapsed() < Duration::from_secs(20));
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
    };
    settle(0).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let (rss_before, fds_before) = (rss_kib(), fd_count());
    let start = Instant::now();
    for i in 0..10_000 {
        // Half of them ask something first, half leave at once.
        cycle(i % 2 == 0).await;
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "too slow: {i} cycles"
        );
    }
    let elapsed = start.elapsed();
    settle(0).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let (rss_after, fds_after) = (rss_kib(), fd_count());
    eprintln!(
        "10,000 connect/disconnect cycles in {elapsed:?}: VmRSS {rss_before} -> {rss_after} kB, descriptors {fds_before} -> {fds_after}"
    );
    assert_eq!(fds_after, fds_before);
    assert!(
        rss_after < rss_before + 8 * 1024,
        "{rss_before} -> {rss_after} kB"
    );
    let mut c = server.client().await;
    c.ask("LIST:TEST_1\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
        .await;
}
