//! Memory one client can take: pipelining without reading, uploads that
//! never finish. RSS is read from this process (the server runs in it), so
//! these tests run one at a time in a binary of their own.

mod common;

use std::time::{Duration, Instant};

use common::{rss_kib, simulated as server, Client};

/// One memory measurement at a time.
static ALONE: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

#[tokio::test]
async fn pipelining_without_reading_holds_bounded_memory_and_gives_it_back() {
    let _alone = ALONE.lock().await;
    let (_server, addr, _dir) = server(
        "",
        "PUBFILE = //project.pub",
        Some(&plcsim::genpub::plain(2000)),
    )
    .await;
    let before = rss_kib();
    // Four clients pipeline 200,000 GET:* each and never read.
    let mut flooders = Vec::new();
    for _ in 0..4 {
        let c = tokio::net::TcpStream::connect(addr).await.unwrap();
        flooders.push(tokio::spawn(async move {
            use tokio::io::AsyncWriteExt;
            let mut c = c;
            let chunk = "GET:*\n".repeat(10_000);
            for _ in 0..20 {
                if tokio::time::timeout(Duration::from_secs(2), c.write_all(chunk.as_bytes()))
                    .await
                    .is_err()
                {
                    break;
                }
            }
            c
        }));
    }
    let mut peak = before;
    let mut other = Client::connect(addr).await;
    let mut worst = Duration::ZERO;
    for _ in 0..20 {
        peak = peak.max(rss_kib());
        let started = Instant::now();
        other.ask("GET:__plc_run\n", "GET:__PLC_RUN,1\r\n").await;
        worst = worst.max(started.elapsed());
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let streams: Vec<_> = futures::future::join_all(flooders).await;
    peak = peak.max(rss_kib());
    drop(streams);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let after = rss_kib();
    println!(
        "RSS {before} KiB before, {peak} KiB at most while 4 clients flooded, {after} KiB after; \
         other client's GET at most {:.1} ms",
        worst.as_secs_f64() * 1000.0
    );
    assert!(peak < before + 96 * 1024, "peak {peak} KiB from {before}");
    assert!(
        after < before + 32 * 1024,
        "after {after} KiB from {before}"
    );
    assert!(worst < Duration::from_secs(2), "{worst:?}");
}

#[tokio::test]
async fn unfinished_uploads_to_the_plc_hold_disk_not_memory() {
    let _alone = ALONE.lock().await;
    let (_server, addr, _dir) = server("FFILE_TIMEOUT_WR = 60", "", None).await;
    let before = rss_kib();
    let block = vec![b'x'; 60_000];
    let mut clients = Vec::new();
    for i in 0..8 {
        let mut c = Client::connect(addr).await;
        // 16 MB each, never the zero block.
        for _ in 0..266 {
            let mut request = format!("WRITEFILE:up{i}.bin[{}]=", block.len()).into_bytes();
            request.extend_from_slice(&block);
            request.extend_from_slice(b"\r\n");
            c.send(&request).await;
        }
        clients.push(c);
    }
    // Each block is taken (the last is answered only at the zero block).
    let mut probe = Client::connect(addr).await;
    probe.ask("GET:__plc_run\n", "GET:__PLC_RUN,1\r\n").await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let during = rss_kib();
    println!("RSS {before} KiB before, {during} KiB with 8 open 16 MB uploads");
    assert!(during < before + 48 * 1024, "{during} KiB from {before}");
    drop(clients);
}

/// A public file of `vars` variables named with `name_len` bytes each, all
/// inside the PLC's memory.
fn wide_pub(vars: usize, name_len: usize) -> Vec<u8> {
    let mut text = Vec::with_capacity(vars * (name_len + 30));
    for i in 0..vars {
        let name = format!("V{i:0>width$}", width = name_len - 1);
        let offset = (i % 100_000) * 4;
        text.extend_from_slice(format!(" {name} R B {offset} DINT\r\n").as_bytes());
    }
    text
}

/// How long a public file at the variable bound may take to load.
const BIG_FILE_WITHIN: Duration = Duration::from_secs(60);

#[tokio::test]
async fn public_files_are_bounded_in_variables_and_the_bound_fits_in_memory() {
    let _alone = ALONE.lock().await;
    let (_server, addr, dir) = server("", "", None).await;
    let bound = plccoms_plc::pubfile::MAX_VARS;
    let longest = plccoms_plc::pubfile::MAX_NAME;
    let mut c = Client::connect(addr).await;

    // At the bound, every name as long as accepted (a 27 MB file): taken,
    // and what it costs per variable is measured.
    std::fs::write(dir.path().join("at.pub"), wide_pub(bound, longest)).unwrap();
    let before = rss_kib();
    // Parsing 27 MB in a debug build on a busy machine can outlast the
    // usual 5 s answer bound: this one is a liveness bound.
    c.send(b"SETCONF:pubfile,//at.pub\n").await;
    assert_eq!(
        c.line_within(BIG_FILE_WITHIN).await.as_deref(),
        Some(&b"WARNING:250 Changed public file: 'at.pub'\r\n"[..])
    );
    let after = rss_kib();
    let per_var = (after.saturating_sub(before) * 1024) as usize / bound;
    println!(
        "RSS {before} KiB before, {after} KiB with {bound} variables of {longest}-byte names: \
         {per_var} bytes a variable"
    );
    assert!(after < before + 200 * 1024, "{after} KiB from {before}");

    // One variable past the bound, with short names (a 2 MB file): refused,
    // the table stays.
    std::fs::write(
        dir.path().join("over.pub"),
        plcsim::genpub::plain(bound + 1),
    )
    .unwrap();
    c.send(b"SETCONF:pubfile,//over.pub\n").await;
    assert_eq!(
        c.line_within(BIG_FILE_WITHIN).await.as_deref(),
        Some(&b"ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,//over.pub'\r\n"[..])
    );
    c.ask("GET:__plc_run\n", "GET:__PLC_RUN,1\r\n").await;
}
