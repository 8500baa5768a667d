//! Log volume a client can cause, and polling while a big public file
//! loads. A binary of its own with a global subscriber installed before any
//! server starts (tracing caches per call site whether anyone listens), and
//! one test, so no other test's lines are counted.

mod common;

use std::time::{Duration, Instant};

use common::logs::Logs;
use common::{rss_kib, simulated as server, Client};

/// The time between DIFF lines the watcher got while `during` ran, at most.
async fn longest_gap<F: std::future::Future>(
    watcher: &mut Client,
    during: F,
) -> (F::Output, Duration) {
    let mut during = std::pin::pin!(during);
    let mut last = Instant::now();
    let mut gap = Duration::ZERO;
    loop {
        tokio::select! {
            out = &mut during => return (out, gap.max(last.elapsed())),
            line = watcher.line() => {
                if line.starts_with(b"WARNING:250") {
                    continue;
                }
                assert!(line.starts_with(b"DIFF:TIM,"), "{:?}", String::from_utf8_lossy(&line));
                gap = gap.max(last.elapsed());
                last = Instant::now();
            }
        }
    }
}

#[tokio::test]
async fn what_a_client_can_make_the_server_log_and_polling_during_a_big_load() {
    let logs = Logs::install();

    // SETCONF:pubfile: size bound, log bound, polling goes on.
    let (first, addr, dir) = server("", "PUBFILE_CRC = No", None).await;
    let huge = std::fs::File::create(dir.path().join("huge.pub")).unwrap();
    huge.set_len(1 << 30).unwrap();
    std::fs::write(
        dir.path().join("bad.pub"),
        " not a variable line at all\r\n".repeat(100_000),
    )
    .unwrap();
    // 60 MB of lines the parser has to look at (comments, fast to write).
    std::fs::write(
        dir.path().join("big.pub"),
        format!(
            "{} TIM R B 8 TIME\r\n",
            "; a comment line of a generated project file, long enough\r\n".repeat(1_000_000)
        ),
    )
    .unwrap();
    let mut watcher = Client::connect(addr).await;
    watcher
        .ask(
            "EN:tim\n",
            "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
        )
        .await;
    let mut c = Client::connect(addr).await;
    let rss = rss_kib();
    let started = Instant::now();
    c.ask(
        "SETCONF:pubfile,//huge.pub\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,//huge.pub'\r\n",
    )
    .await;
    let took = started.elapsed();
    assert!(
        rss_kib() < rss + 64 * 1024,
        "RSS {rss} -> {} KiB",
        rss_kib()
    );

    let log_before = logs.len();
    c.ask(
        "SETCONF:pubfile,//bad.pub\n",
        "WARNING:250 Changed public file: 'bad.pub'\r\n",
    )
    .await;
    let logged = logs.len() - log_before;
    assert!(logs.text().contains("more problems not shown"));
    c.ask(
        "SETCONF:pubfile,//demo.pub\n",
        "WARNING:250 Changed public file: 'demo.pub'\r\n",
    )
    .await;
    watcher
        .wait_for_line(
            b"WARNING:250 Changed public file: 'demo.pub'\r\n",
            Duration::from_secs(10),
        )
        .await;
    watcher
        .ask(
            "EN:tim\n",
            "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
        )
        .await;
    let load = async {
        let started = Instant::now();
        c.ask(
            "SETCONF:pubfile,//big.pub\n",
            "WARNING:250 Changed public file: 'big.pub'\r\n",
        )
        .await;
        started.elapsed()
    };
    let (loading, gap) = longest_gap(&mut watcher, load).await;
    println!(
        "1 GiB file refused in {:.1} ms; 100,000 bad lines logged {logged} bytes; \
         a 60 MB file loaded in {:.0} ms, DIFFs at most {:.0} ms apart meanwhile",
        took.as_secs_f64() * 1000.0,
        loading.as_secs_f64() * 1000.0,
        gap.as_secs_f64() * 1000.0
    );
    assert!(logged < 4096, "{logged} bytes of log:\n{}", logs.text());
    // A load on the link's thread would stop DIFFs for all of it.
    assert!(
        gap < loading / 2 || loading < Duration::from_millis(100),
        "DIFFs stopped for {gap:?} of a {loading:?} load"
    );
    drop(first);

    // Refused connections: a few lines, with counts.
    let (_second, addr, _dir) = server("NET_CONNECT_MAX = 2", "", None).await;
    let _a = Client::connect(addr).await;
    let _b = Client::connect(addr).await;
    let before = logs.text().matches("NET_CONNECT_MAX").count();
    for _ in 0..200 {
        let mut c = Client::connect(addr).await;
        assert_eq!(c.line().await, b"ERROR:11 Maximum connections reached.\r\n");
    }
    let lines = logs.text().matches("NET_CONNECT_MAX").count() - before;
    println!("200 refused connections logged in {lines} lines");
    assert!(lines <= 5, "{lines} lines:\n{}", logs.text());
}
