//! A client flooding requests while they wait behind an unanswered SETCONF
//! is not read without bound. A binary of its own: the section's poll thread
//! is still finishing a slow PLC read when the test ends, which would
//! disturb the descriptor counts of `tests/resources.rs`.

mod common;

use std::time::{Duration, Instant};

use common::epsnet::{any_port, spawn_sim, start_server, Link};
use common::rss_kib;
use tokio::io::AsyncWriteExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_behind_a_slow_setconf_is_not_buffered() {
    let sim = spawn_sim(any_port(), plcsim::program::ProgramKind::Idle).await;
    let link = Link {
        timeout_ms: 5_000,
        step_ms: 0,
        retries: 0,
    };
    let server = start_server(sim.local_addr(), "", link).await;
    let mut flood = common::Client::connect(server.local_addr).await;
    flood.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;
    // The PLC answers after 3 s: the SETCONF waits behind the GET, and the
    // requests after it wait for the SETCONF.
    sim.set_latency(Duration::from_secs(3));
    flood.send(b"GET:%RW130\nSETCONF:pubfile,//x.pub\n").await;
    let before = rss_kib();
    let lines = b"GET:%RW130\n".repeat(100_000);
    let mut sent = 0usize;
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(2) {
        match tokio::time::timeout(Duration::from_millis(200), flood.stream.write_all(&lines)).await
        {
            Ok(result) => {
                result.unwrap();
                sent += lines.len();
            }
            Err(_) => break,
        }
    }
    let peak = rss_kib();
    eprintln!(
        "flood behind a SETCONF: at least {sent} bytes taken before the server stopped reading; VmRSS {before} kB before, {peak} kB after"
    );
    // The session holds at most 64 KiB of unhandled input; the kernel
    // buffers a few MB more. Without the bound it reads everything.
    assert!(sent < 64 << 20, "{sent} bytes taken");
    assert!(
        peak < before + 32 * 1024,
        "peak {peak} kB, before {before} kB"
    );
}
