//! Attacks a hostile or broken client on the plant network can make, each
//! with the bound it must stay under (SECURITY.md; the memory bounds are in
//! `memory_bounds.rs`):
//! - the server's own files (configuration, log, public files in use, hidden
//!   names, the root folder) cannot be written, touched or read when secret;
//! - SETCONF:pubfile stays inside the configuration's folder, answers the
//!   same for a missing and a refused file, refuses the server's own files,
//!   bounds size and log volume, keeps polling while it loads, and enforces
//!   PUBFILE_CRC; SETCONF_KEYS keeps keys away from clients;
//! - one client pipelining without reading, uploading without finishing, or
//!   sending megabytes of star masks cannot take the memory or the CPU;
//! - refusals a client causes at will are logged rate-limited.
//!
//! Memory is read from this process (the server runs in it), so each test
//! measures its own growth; the bounds are generous for a shared machine.

mod common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::Client;

use common::simulated as server;

fn mtime(path: &Path) -> std::time::SystemTime {
    std::fs::metadata(path).unwrap().modified().unwrap()
}

#[tokio::test]
async fn clients_cannot_rewrite_touch_or_read_the_servers_own_files() {
    let (_server, addr, dir) = server("", "", None).await;
    let ini = dir.path().join("PLCComS.ini");
    let before = std::fs::read(&ini).unwrap();
    let ini_time = mtime(&ini);
    let root_mode = std::fs::metadata(dir.path()).unwrap().permissions();
    std::fs::write(dir.path().join(".hidden"), b"state").unwrap();
    let mut c = Client::connect(addr).await;

    // The configuration: not rewritten, not touched, not read.
    assert_eq!(
        c.writefile("./PLCComS.ini", b"[*]\n[X]\nSERVER_PORT=1\n")
            .await,
        "ERROR:42 Unable to write file: './PLCComS.ini'\r\n"
    );
    c.ask(
        "WRITEFILEINFO:./PLCComS.ini[27]=0 1 24700000000 24700000000\n",
        "ERROR:43 Unable to write file information: './PLCComS.ini'\r\n",
    )
    .await;
    c.ask(
        "GETFILE:./PLCComS.ini\n",
        "ERROR:41 Unable to get file: './PLCComS.ini'\r\n",
    )
    .await;
    c.ask(
        "GETFILEINFO:./PLCComS.ini\n",
        "ERROR:40 Unable to get information about file: './PLCComS.ini'\r\n",
    )
    .await;
    // The root folder itself, hidden names, the public file in use.
    c.ask(
        "WRITEFILEINFO:./[27]=0 1 24700000000 24700000000\n",
        "ERROR:43 Unable to write file information: './'\r\n",
    )
    .await;
    assert_eq!(
        c.writefile("./.hidden", b"x").await,
        "ERROR:42 Unable to write file: './.hidden'\r\n"
    );
    c.ask(
        "GETFILE:./.hidden\n",
        "ERROR:41 Unable to get file: './.hidden'\r\n",
    )
    .await;
    std::fs::write(dir.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    assert_eq!(
        c.writefile("./demo.pub", b" X R B 0 INT\r\n").await,
        "ERROR:42 Unable to write file: './demo.pub'\r\n"
    );
    // Other files of the root work as before.
    assert_eq!(
        c.writefile("./notes.txt", b"hello").await,
        "WRITEFILE:./notes.txt OK\r\n"
    );
    c.ask("GETFILE:./notes.txt\n", "GETFILE:./notes.txt[5]=hello\r\n")
        .await;

    assert_eq!(std::fs::read(&ini).unwrap(), before);
    assert_eq!(mtime(&ini), ini_time);
    assert_eq!(
        std::fs::metadata(dir.path()).unwrap().permissions(),
        root_mode
    );
    assert_eq!(std::fs::read(dir.path().join(".hidden")).unwrap(), b"state");
    assert_eq!(
        std::fs::read(dir.path().join("demo.pub")).unwrap(),
        plcsim::DEMO_PUB
    );
}

#[tokio::test]
async fn files_root_gives_pc_files_a_folder_of_their_own() {
    let (_server, addr, dir) = server("FILES_ROOT = files", "", None).await;
    // Created at start.
    assert!(dir.path().join("files").is_dir());
    let mut c = Client::connect(addr).await;
    assert_eq!(
        c.writefile("./a.txt", b"abc").await,
        "WRITEFILE:./a.txt OK\r\n"
    );
    assert_eq!(
        std::fs::read(dir.path().join("files/a.txt")).unwrap(),
        b"abc"
    );
    // The configuration is not in the root at all.
    c.ask(
        "GETFILE:./PLCComS.ini\n",
        "ERROR:41 Unable to get file: './PLCComS.ini'\r\n",
    )
    .await;
    c.ask(
        "GETFILE:./../PLCComS.ini\n",
        "ERROR:41 Unable to get file: './../PLCComS.ini'\r\n",
    )
    .await;
}

#[tokio::test]
async fn writefile_to_the_files_root_is_bounded_by_its_quota() {
    let (_server, addr, dir) = server("FILES_ROOT = files\nFILES_QUOTA = 100000", "", None).await;
    let root = dir.path().join("files");
    std::fs::create_dir_all(root.join("old")).unwrap();
    // What is in the root already counts, in subfolders too.
    std::fs::write(root.join("old/log.bin"), vec![0u8; 50_000]).unwrap();
    let mut c = Client::connect(addr).await;
    assert_eq!(
        c.writefile("./a.bin", &[1; 30_000]).await,
        "WRITEFILE:./a.bin OK\r\n"
    );
    // 80,000 bytes in the root, 30,000 more would pass 100,000.
    assert_eq!(
        c.writefile("./b.bin", &[2; 30_000]).await,
        "ERROR:42 Unable to write file: './b.bin'\r\n"
    );
    assert!(!root.join("b.bin").exists());
    // Room is made by deleting: the root is measured again.
    std::fs::remove_file(root.join("old/log.bin")).unwrap();
    let start = Instant::now();
    loop {
        let answer = c.writefile("./b.bin", &[2; 30_000]).await;
        if answer == "WRITEFILE:./b.bin OK\r\n" {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(10), "{answer}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(std::fs::read(root.join("b.bin")).unwrap().len(), 30_000);
    // Nothing of the refused uploads is left behind.
    let names: Vec<_> = std::fs::read_dir(&root)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert_eq!(names.len(), 3, "{names:?}");
}

/// The server's own files in the root (the history, the queues, when the
/// root is the configuration's folder) are not the clients' and do not
/// count towards their quota.
#[tokio::test]
async fn the_servers_own_files_in_the_root_do_not_count_towards_the_quota() {
    let (_server, addr, dir) = server("FILES_QUOTA = 100000\nHISTORY_DIR = hist", "", None).await;
    std::fs::create_dir_all(dir.path().join("hist")).unwrap();
    std::fs::write(dir.path().join("hist/big.db"), vec![0u8; 200_000]).unwrap();
    let mut c = Client::connect(addr).await;
    assert_eq!(
        c.writefile("./a.bin", &[1; 30_000]).await,
        "WRITEFILE:./a.bin OK\r\n"
    );
}

#[tokio::test]
async fn setconf_pubfile_stays_in_its_folder_and_answers_alike() {
    let (_server, addr, dir) = server("", "PUBFILE_CRC = No", None).await;
    let outside = tempfile::tempdir().unwrap();
    std::fs::write(outside.path().join("x.pub"), plcsim::DEMO_PUB).unwrap();
    std::os::unix::fs::symlink(outside.path().join("x.pub"), dir.path().join("link.pub")).unwrap();
    std::fs::write(dir.path().join("PLCComS.log"), b"log\n").unwrap();
    plccoms_core::localfs::protect(&dir.path().join("PLCComS.log"), false);
    let mut c = Client::connect(addr).await;
    c.ask(
        "EN:sinus\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    for name in [
        "/etc/passwd",
        "//../../etc/passwd",
        "../x.pub",
        "//a/../../x.pub",
        "C:/x.pub",
    ] {
        c.ask(
            &format!("SETCONF:pubfile,{name}\n"),
            &format!("ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,{name}'\r\n"),
        )
        .await;
    }
    // A link leading out, the server's own files, and a missing file: the
    // same answer (nothing to probe with).
    for name in [
        "//link.pub",
        "//PLCComS.log",
        "//PLCComS.ini",
        "//missing.pub",
    ] {
        c.send(format!("SETCONF:pubfile,{name}\n").as_bytes()).await;
        let line = loop {
            let line = String::from_utf8_lossy(&c.line().await).into_owned();
            if !line.starts_with("DIFF:") {
                break line;
            }
        };
        assert_eq!(
            line,
            format!("ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,{name}'\r\n")
        );
    }
    // Nothing changed: the demo file still serves.
    c.ask("GET:text\n", "GET:TEXT,\"Have a nice day\"\r\n")
        .await;
}

#[tokio::test]
async fn pubfile_crc_is_enforced_and_setconf_keys_limit_clients() {
    let (_server, addr, dir) = server(
        "",
        "PUBFILE_CRC = Yes\nSETCONF_KEYS = crlf, diff, pubfile",
        None,
    )
    .await;
    let no_crc: Vec<u8> = plcsim::DEMO_PUB
        .split_inclusive(|&b| b == b'\n')
        .filter(|l| !l.starts_with(b";*"))
        .flatten()
        .copied()
        .collect();
    std::fs::write(dir.path().join("nocrc.pub"), &no_crc).unwrap();
    // Another program's file, with its own (right) CRC line.
    let mut other = common::demo_pub_with_extra();
    let crc = plccoms_plc::pubfile::crc_of(&other);
    other.extend_from_slice(format!(";* Crc=\"{crc:08X}\"\r\n").as_bytes());
    std::fs::write(dir.path().join("other.pub"), &other).unwrap();
    std::fs::write(dir.path().join("same.pub"), plcsim::DEMO_PUB).unwrap();
    let mut c = Client::connect(addr).await;
    c.ask(
        "SETCONF:pubfile,//nocrc.pub\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,//nocrc.pub'\r\n",
    )
    .await;
    c.ask(
        "SETCONF:pubfile,//same.pub\n",
        "WARNING:250 Changed public file: 'same.pub'\r\n",
    )
    .await;
    c.ask(
        "SETCONF:ipaddr,127.0.0.1\n",
        "ERROR:30 Bad client request: 'SETCONF:ipaddr,127.0.0.1'\r\n",
    )
    .await;
    c.ask("SETCONF:crlf,yes\n", "SETCONF:CRLF,YES\r\n").await;
}

#[tokio::test]
async fn megabytes_of_star_masks_do_not_starve_other_clients() {
    let (_server, addr, _dir) = server(
        "",
        "PUBFILE = //project.pub",
        Some(&plcsim::genpub::plain(2000)),
    )
    .await;
    let mut other = Client::connect(addr).await;
    let flood = tokio::spawn(async move {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let c = tokio::net::TcpStream::connect(addr).await.unwrap();
        let (mut r, mut w) = c.into_split();
        // Read and drop the answers, so only the CPU is at stake.
        let reader = tokio::spawn(async move {
            let mut buf = vec![0; 65536];
            while r.read(&mut buf).await.is_ok_and(|n| n > 0) {}
        });
        let line = format!("GET:{}\n", "*a".repeat(8000));
        let started = Instant::now();
        for _ in 0..640 {
            w.write_all(line.as_bytes()).await.unwrap();
        }
        let _ = w.shutdown().await;
        let _ = reader.await;
        started.elapsed()
    });
    let mut worst = Duration::ZERO;
    while !flood.is_finished() {
        let started = Instant::now();
        other.ask("GET:__plc_run\n", "GET:__PLC_RUN,1\r\n").await;
        worst = worst.max(started.elapsed());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let took = flood.await.unwrap();
    println!(
        "10 MB of star masks handled in {:.0} ms; another client's GET at most {:.1} ms",
        took.as_secs_f64() * 1000.0,
        worst.as_secs_f64() * 1000.0
    );
    assert!(took < Duration::from_secs(5), "{took:?}");
    assert!(worst < Duration::from_millis(1000), "{worst:?}");
}
