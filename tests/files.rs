//! GETMEM, GETFILE, GETFILEINFO, WRITEFILE and WRITEFILEINFO over TCP, byte
//! for byte: on the in-process PLC (its file store in a tempdir), on local
//! files in the section's root folder, and once through the EPSNET simulator.

mod common;

use std::fs;
use std::path::Path;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use common::{start, start_on, user_pub, Client, TestServer};
use plccoms_plc::time::{ttida_from_system, ttida_from_unix};
use plccoms_protocol::Area;

/// Bytes every binary test carries: NUL, CR, LF, CRLF, 0xFF, IAC-like runs.
const BINARY: &[u8] = b"a\0b\rc\nd\r\ne\xFF\xFF\xFE=[0]=\x04end";

fn block(command: &str, name: &str, data: &[u8]) -> Vec<u8> {
    let mut out = format!("{command}:{name}[{}]=", data.len()).into_bytes();
    out.extend_from_slice(data);
    out.extend_from_slice(b"\r\n");
    out
}

/// The full answer: `data` in blocks of `blksize`, then the terminator.
fn blocks(command: &str, name: &str, data: &[u8], blksize: usize) -> Vec<u8> {
    let mut out = Vec::new();
    for chunk in data.chunks(blksize) {
        out.extend_from_slice(&block(command, name, chunk));
    }
    out.extend_from_slice(&block(command, name, b""));
    out
}

fn pattern(len: usize) -> Vec<u8> {
    (0..len).map(|i| (i * 7 + i / 251) as u8).collect()
}

fn info_line(name: &str, path: &Path, attributes: u32) -> String {
    let meta = fs::metadata(path).unwrap();
    let modified = ttida_from_system(meta.modified().unwrap());
    let created = meta.created().map(ttida_from_system).unwrap_or(modified);
    let size = if meta.is_dir() { 0 } else { meta.len() };
    let text = format!("{size} {attributes} {created} {modified}");
    format!("GETFILEINFO:{name}[{}]={text}\r\n", text.len())
}

// ---------------------------------------------------------------- GETMEM

#[tokio::test]
async fn getmem_blocks_and_errors() {
    let s = start("MEM_BLKSIZE = 4").await;
    s.poke(Area::R, 200, b"Hello!\0\r\n\xFF");
    s.poke(Area::R, 0, &[0x34, 0x12]);
    let mut c = s.client().await;
    c.send(b"GETMEM:%R200 10\n").await;
    c.expect(&blocks("GETMEM", "%R200", b"Hello!\0\r\n\xFF", 4))
        .await;
    // A variable name, printed as the client wrote it.
    c.send(b"GETMEM:test_1 2\n").await;
    c.expect(&blocks("GETMEM", "test_1", &[0x34, 0x12], 4))
        .await;
    c.ask(
        "GETMEM:%R200 0\n",
        "ERROR:81 Unable to set data in to address: '%R200'\r\n",
    )
    .await;
    c.ask(
        "GETMEM:%Q1 2\n",
        "ERROR:81 Unable to set data in to address: '%Q1'\r\n",
    )
    .await;
    c.ask(
        "GETMEM:%R200 99999999\n",
        "ERROR:81 Unable to set data in to address: '%R200'\r\n",
    )
    .await;
    c.ask(
        "GETMEM:%R4000000000 16\n",
        "ERROR:80 Unable to get data from address: '%R4000000000'\r\n",
    )
    .await;
    c.ask(
        "GETMEM:nosuch 2\n",
        "ERROR:33 Unknown variable name in request: 'GETMEM:nosuch 2'\r\n",
    )
    .await;
    c.ask("GETMEM:%R200\n", "ERROR:31 Incomplete client request.\r\n")
        .await;
}

// ---------------------------------------------------------------- GETFILE

#[tokio::test]
async fn getfile_local_binary_empty_and_directories() {
    let s = start("FFILE_BLKSIZE = 8").await;
    let root = s.root.path();
    fs::write(root.join("bin.dat"), BINARY).unwrap();
    fs::write(root.join("empty.txt"), b"").unwrap();
    fs::create_dir(root.join("sub")).unwrap();
    fs::write(root.join("sub/exact.txt"), b"12345678").unwrap();
    let mut c = s.client().await;
    c.send(b"GETFILE:./bin.dat\n").await;
    c.expect(&blocks("GETFILE", "./bin.dat", BINARY, 8)).await;
    c.send(b"GETFILE:./empty.txt\n").await;
    c.expect(b"GETFILE:./empty.txt[0]=\r\n").await;
    c.send(b"GETFILE:./sub/exact.txt\n").await;
    c.expect(b"GETFILE:./sub/exact.txt[8]=12345678\r\nGETFILE:./sub/exact.txt[0]=\r\n")
        .await;
    // Directories: one entry a line, folders marked with `/`.
    c.send(b"GETFILE:./\n").await;
    c.expect(&blocks(
        "GETFILE",
        "./",
        b"bin.dat\r\nempty.txt\r\nsub/\r\n",
        8,
    ))
    .await;
    c.send(b"GETFILE:./sub/\n").await;
    c.expect(&blocks("GETFILE", "./sub/", b"exact.txt\r\n", 8))
        .await;
    c.ask(
        "GETFILE:./missing.txt\n",
        "ERROR:41 Unable to get file: './missing.txt'\r\n",
    )
    .await;
    c.ask(
        "GETFILE:./sub\n",
        "ERROR:41 Unable to get file: './sub'\r\n",
    )
    .await;
}

#[tokio::test]
async fn getfile_plc_binary_large_empty_and_directories() {
    // Blocks larger than the backend's 1150-byte file block.
    let s = start("FFILE_BLKSIZE = 3000").await;
    let plc = s.plc_files.path();
    let big = pattern(7000);
    fs::write(plc.join("big.bin"), &big).unwrap();
    fs::write(plc.join("bin.dat"), BINARY).unwrap();
    fs::write(plc.join("empty"), b"").unwrap();
    fs::create_dir(plc.join("www")).unwrap();
    fs::write(plc.join("www/TEST.TXT"), b"This is test string.").unwrap();
    let mut c = s.client().await;
    c.send(b"GETFILE:big.bin\n").await;
    c.expect(&blocks("GETFILE", "big.bin", &big, 3000)).await;
    // Again, now from the cache: the same bytes.
    c.send(b"GETFILE:big.bin\n").await;
    c.expect(&blocks("GETFILE", "big.bin", &big, 3000)).await;
    c.send(b"GETFILE:bin.dat\n").await;
    c.expect(&blocks("GETFILE", "bin.dat", BINARY, 3000)).await;
    c.send(b"GETFILE:empty\n").await;
    c.expect(b"GETFILE:empty[0]=\r\n").await;
    c.send(b"GETFILE://www/TEST.TXT\n").await;
    c.expect(b"GETFILE://www/TEST.TXT[20]=This is test string.\r\nGETFILE://www/TEST.TXT[0]=\r\n")
        .await;
    c.send(b"GETFILE:/\n").await;
    c.expect(&blocks(
        "GETFILE",
        "/",
        b"big.bin\r\nbin.dat\r\nempty\r\nwww/\r\n",
        3000,
    ))
    .await;
    c.ask(
        "GETFILE:nothing.txt\n",
        "ERROR:41 Unable to get file: 'nothing.txt'\r\n",
    )
    .await;
    c.ask(
        "GETFILE:nodir/\n",
        "ERROR:41 Unable to get file: 'nodir/'\r\n",
    )
    .await;
}

#[tokio::test]
async fn plc_read_failing_mid_transfer_is_error_46() {
    let s = start("FFILE_BLKSIZE = 65536").await;
    // Larger than what loopback socket buffers absorb.
    let data = pattern(32 * 1024 * 1024);
    fs::write(s.plc_files.path().join("huge.bin"), &data).unwrap();
    let mut c = s.client().await;
    c.send(b"GETFILE:huge.bin\n").await;
    // The first block arrives; the server stops at its output limit while
    // this client does not read, and the file disappears meanwhile.
    c.expect(b"GETFILE:huge.bin[65536]=").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    fs::remove_file(s.plc_files.path().join("huge.bin")).unwrap();
    let mut received = 65536 + 2;
    c.take(65536 + 2).await;
    loop {
        let head = c.line_until(b'=', b'\n').await;
        if head.starts_with(b"ERROR:") {
            assert_eq!(head, b"ERROR:46 Aborted get file: 'huge.bin'\r\n");
            break;
        }
        let n: usize = std::str::from_utf8(&head[b"GETFILE:huge.bin[".len()..head.len() - 2])
            .unwrap()
            .parse()
            .unwrap();
        assert_ne!(n, 0, "the whole file came after all");
        received += c.take(n + 2).await.len();
    }
    assert!(received < data.len());
}

// ---------------------------------------------------------------- GETFILEINFO

#[tokio::test]
async fn getfileinfo_local_and_plc() {
    let s = start("").await;
    let root = s.root.path();
    fs::write(root.join("a.txt"), b"hello").unwrap();
    fs::create_dir(root.join("dir")).unwrap();
    let when = UNIX_EPOCH + Duration::from_secs(1_710_510_330);
    fs::File::options()
        .write(true)
        .open(root.join("a.txt"))
        .unwrap()
        .set_modified(when)
        .unwrap();
    let mut c = s.client().await;
    let want = info_line("./a.txt", &root.join("a.txt"), 0x20);
    assert!(want.contains(&ttida_from_unix(1_710_510_330).to_string()));
    c.ask("GETFILEINFO:./a.txt\n", &want).await;
    c.ask(
        "GETFILEINFO:./dir\n",
        &info_line("./dir", &root.join("dir"), 0x10),
    )
    .await;
    c.ask(
        "GETFILEINFO:./none\n",
        "ERROR:40 Unable to get information about file: './none'\r\n",
    )
    .await;
    let plc = s.plc_files.path();
    fs::write(plc.join("p.txt"), BINARY).unwrap();
    fs::create_dir(plc.join("www")).unwrap();
    c.ask(
        "GETFILEINFO:p.txt\n",
        &info_line("p.txt", &plc.join("p.txt"), 0x20),
    )
    .await;
    c.ask(
        "GETFILEINFO:www\n",
        &info_line("www", &plc.join("www"), 0x10),
    )
    .await;
    c.ask(
        "GETFILEINFO:none\n",
        "ERROR:40 Unable to get information about file: 'none'\r\n",
    )
    .await;
}

// ---------------------------------------------------------------- confinement

#[tokio::test]
async fn traversal_and_symlinks_are_refused() {
    let outside = tempfile::tempdir().unwrap();
    fs::write(outside.path().join("secret"), b"secret").unwrap();
    let s = start("").await;
    let root = s.root.path();
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(outside.path(), root.join("out")).unwrap();
        std::os::unix::fs::symlink(outside.path().join("secret"), root.join("ln")).unwrap();
    }
    let mut c = s.client().await;
    let rel = format!(
        "../{}/secret",
        outside.path().file_name().unwrap().to_str().unwrap()
    );
    for name in ["../etc/passwd", "./../x", "./a/../../x", rel.as_str()] {
        c.ask(
            &format!("GETFILE:{name}\n"),
            &format!("ERROR:41 Unable to get file: '{name}'\r\n"),
        )
        .await;
        c.ask(
            &format!("GETFILEINFO:{name}\n"),
            &format!("ERROR:40 Unable to get information about file: '{name}'\r\n"),
        )
        .await;
        c.send(&block("WRITEFILE", name, b"x")).await;
        c.send(&block("WRITEFILE", name, b"")).await;
        c.expect(format!("ERROR:42 Unable to write file: '{name}'\r\n").as_bytes())
            .await;
    }
    #[cfg(unix)]
    for name in ["./out/secret", "./ln", "./out/"] {
        c.ask(
            &format!("GETFILE:{name}\n"),
            &format!("ERROR:41 Unable to get file: '{name}'\r\n"),
        )
        .await;
        c.send(&block("WRITEFILE", name, b"x")).await;
        c.send(&block("WRITEFILE", name, b"")).await;
        c.expect(format!("ERROR:42 Unable to write file: '{name}'\r\n").as_bytes())
            .await;
    }
    assert_eq!(
        fs::read(outside.path().join("secret")).unwrap(),
        b"secret".to_vec()
    );
    assert_eq!(fs::read_dir(outside.path()).unwrap().count(), 1);
}

// ---------------------------------------------------------------- WRITEFILE

#[tokio::test]
async fn writefile_local_and_plc_binary_and_empty() {
    let s = start("").await;
    let mut c = s.client().await;
    for name in ["./up.bin", "up.bin"] {
        let mut request = block("WRITEFILE", name, &BINARY[..10]);
        request.extend_from_slice(&block("WRITEFILE", name, &BINARY[10..]));
        // Blocks with a bare `\n` after the data too.
        request.extend_from_slice(format!("WRITEFILE:{name}[3]=xyz\n").as_bytes());
        request.extend_from_slice(&block("WRITEFILE", name, b""));
        c.send(&request).await;
        c.expect(format!("WRITEFILE:{name} OK\r\n").as_bytes())
            .await;
    }
    let mut want = BINARY.to_vec();
    want.extend_from_slice(b"xyz");
    assert_eq!(fs::read(s.root.path().join("up.bin")).unwrap(), want);
    assert_eq!(fs::read(s.plc_files.path().join("up.bin")).unwrap(), want);
    // Read back through GETFILE, byte for byte.
    c.send(b"GETFILE:up.bin\n").await;
    c.expect(&blocks("GETFILE", "up.bin", &want, 4096)).await;
    // Only the zero block: an empty file.
    for name in ["./empty", "empty"] {
        c.send(&block("WRITEFILE", name, b"")).await;
        c.expect(format!("WRITEFILE:{name} OK\r\n").as_bytes())
            .await;
    }
    assert_eq!(fs::read(s.root.path().join("empty")).unwrap(), b"");
    assert_eq!(fs::read(s.plc_files.path().join("empty")).unwrap(), b"");
    // A folder that does not exist.
    for name in ["./no/such", "no/such"] {
        c.send(&block("WRITEFILE", name, b"abc")).await;
        c.send(&block("WRITEFILE", name, b"")).await;
        c.expect(format!("ERROR:42 Unable to write file: '{name}'\r\n").as_bytes())
            .await;
    }
    // No staging files are left behind.
    for dir in [s.root.path(), s.plc_files.path()] {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        assert_eq!(names, ["empty", "up.bin"]);
    }
}

#[tokio::test]
async fn writefile_gap_over_timeout_is_error_45_and_nothing_is_written() {
    let s = start("FFILE_TIMEOUT_WR = 1").await;
    let mut c = s.client().await;
    c.send(&block("WRITEFILE", "./slow.txt", b"part one")).await;
    c.send(&block("WRITEFILE", "slow.txt", b"part one")).await;
    // The PLC one opened while the local one was open: unterminated.
    c.expect(b"ERROR:44 Unterminated write file data: './slow.txt'\r\n")
        .await;
    c.silent(700).await;
    c.expect(b"ERROR:45 Timeout write file data: 'slow.txt'\r\n")
        .await;
    // Late blocks of the abandoned transfer never make a file.
    c.send(&block("WRITEFILE", "slow.txt", b"tail")).await;
    c.send(&block("WRITEFILE", "slow.txt", b"")).await;
    c.expect(b"ERROR:45 Timeout write file data: 'slow.txt'\r\n")
        .await;
    assert!(!s.plc_files.path().join("slow.txt").exists());
    assert_eq!(fs::read_dir(s.root.path()).unwrap().count(), 0);
    // The name is free again for a whole new transfer.
    c.send(&block("WRITEFILE", "slow.txt", b"whole")).await;
    c.send(&block("WRITEFILE", "slow.txt", b"")).await;
    c.expect(b"WRITEFILE:slow.txt OK\r\n").await;
    assert_eq!(
        fs::read(s.plc_files.path().join("slow.txt")).unwrap(),
        b"whole"
    );
}

#[tokio::test]
async fn short_block_data_is_error_44() {
    // The manual's example: the count promises more than comes.
    let s = start("FFILE_TIMEOUT_WR = 1").await;
    let mut c = s.client().await;
    c.send(b"WRITEFILE:test.txt[10]=Test\n").await;
    c.expect(b"ERROR:44 Unterminated write file data: 'test.txt'\r\n")
        .await;
    // The session reads requests again afterwards.
    c.ask("GETINFO:epsaddr\n", "GETINFO:EPSADDR,").await;
    assert!(!s.plc_files.path().join("test.txt").exists());
}

#[tokio::test]
async fn disconnect_mid_write_leaves_no_file() {
    let s = start("").await;
    let mut c = s.client().await;
    c.send(&block("WRITEFILE", "./gone.txt", b"first")).await;
    c.send(&block("WRITEFILE", "gone.txt", b"first")).await;
    c.expect(b"ERROR:44 Unterminated write file data: './gone.txt'\r\n")
        .await;
    c.send(b"WRITEFILE:./half.txt[100]=only some").await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    drop(c);
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(fs::read_dir(s.root.path()).unwrap().count(), 0);
    assert_eq!(fs::read_dir(s.plc_files.path()).unwrap().count(), 0);
}

// ---------------------------------------------------------------- WRITEFILEINFO

#[tokio::test]
async fn writefileinfo_local_and_plc() {
    let s = start("").await;
    fs::write(s.root.path().join("f.txt"), b"x").unwrap();
    fs::write(s.plc_files.path().join("f.txt"), b"x").unwrap();
    let when = ttida_from_unix(1_710_510_330);
    let text = format!("1 1 {when} {when}");
    let mut c = s.client().await;
    for name in ["./f.txt", "f.txt"] {
        // The manual's single-block form, then the WRITEFILE-like form.
        c.send(&block("WRITEFILEINFO", name, text.as_bytes())).await;
        c.expect(format!("WRITEFILEINFO:{name} OK\r\n").as_bytes())
            .await;
        c.send(&block("WRITEFILEINFO", name, b"1 0 0 0")).await;
        c.send(&block("WRITEFILEINFO", name, b"")).await;
        c.expect(format!("WRITEFILEINFO:{name} OK\r\n").as_bytes())
            .await;
        c.send(&block("WRITEFILEINFO", name, b"not numbers")).await;
        c.expect(format!("ERROR:43 Unable to write file information: '{name}'\r\n").as_bytes())
            .await;
    }
    for dir in [s.root.path(), s.plc_files.path()] {
        let meta = fs::metadata(dir.join("f.txt")).unwrap();
        assert_eq!(
            meta.modified().unwrap(),
            SystemTime::UNIX_EPOCH + Duration::from_secs(1_710_510_330)
        );
        assert!(!meta.permissions().readonly());
    }
    for name in ["./missing", "missing", "../f.txt"] {
        c.send(&block("WRITEFILEINFO", name, text.as_bytes())).await;
        c.expect(format!("ERROR:43 Unable to write file information: '{name}'\r\n").as_bytes())
            .await;
    }
}

// ---------------------------------------------------------------- DIFF ordering

/// Parses a session's output: GETFILE blocks and other lines. Returns the
/// indexes (in the sequence of items) where a DIFF line appeared, and checks
/// that blocks of one GETFILE answer are contiguous.
async fn read_getfile_with_diffs(c: &mut Client, name: &str, want: &[u8]) -> usize {
    let prefix = format!("GETFILE:{name}[");
    let mut got = Vec::new();
    let mut diffs = 0;
    let mut in_answer = false;
    loop {
        let head = c.line_until(b'=', b'\n').await;
        if head.starts_with(b"DIFF:") {
            assert!(!in_answer, "DIFF inside a GETFILE answer");
            diffs += 1;
            continue;
        }
        assert!(head.starts_with(prefix.as_bytes()), "{head:?}");
        let n: usize = std::str::from_utf8(&head[prefix.len()..head.len() - 2])
            .unwrap()
            .parse()
            .unwrap();
        let data = c.take(n + 2).await;
        assert_eq!(&data[n..], b"\r\n");
        if n == 0 {
            break;
        }
        in_answer = true;
        got.extend_from_slice(&data[..n]);
    }
    assert_eq!(got.len(), want.len());
    assert!(got == want);
    diffs
}

#[tokio::test]
async fn diff_lines_never_land_inside_a_getfile_answer() {
    let s = start("COMM_LOOP_DELAY = 10\nFFILE_BLKSIZE = 4096").await;
    let data = pattern(3 * 1024 * 1024);
    fs::write(s.root.path().join("big.bin"), &data).unwrap();
    let mut c = s.client().await;
    c.ask(
        "EN:test_1\n",
        "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
    )
    .await;
    c.expect(b"DIFF:TEST_1,0\r\n").await;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let poker = {
        let device = s.device.clone();
        let stop = stop.clone();
        tokio::spawn(async move {
            let mut v: i16 = 1;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                device
                    .lock()
                    .unwrap()
                    .write(
                        Area::R,
                        0,
                        &plccoms_core::driver::WriteData::Bytes(v.to_le_bytes().to_vec()),
                    )
                    .unwrap();
                v = v.wrapping_add(1);
                tokio::time::sleep(Duration::from_millis(3)).await;
            }
        })
    };
    let mut diffs = 0;
    for _ in 0..3 {
        c.send(b"GETFILE:./big.bin\n").await;
        c.slow_down().await;
        diffs += read_getfile_with_diffs(&mut c, "./big.bin", &data).await;
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    poker.await.unwrap();
    // DIFFs kept flowing between the answers.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let line = c.line().await;
    assert!(line.starts_with(b"DIFF:TEST_1,"), "{line:?}");
    // Changes made during an answer went out right after it.
    assert!(diffs >= 2, "{diffs} DIFF lines between answers");
}

// ---------------------------------------------------------------- EPSNET

#[tokio::test]
async fn files_through_the_epsnet_simulator() {
    use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
    use plcsim::{program::ProgramKind, SimConfig};
    let files = tempfile::tempdir().unwrap();
    let big = pattern(5000);
    fs::write(files.path().join("big.bin"), &big).unwrap();
    fs::write(files.path().join("bin.dat"), BINARY).unwrap();
    let sim = plcsim::spawn(SimConfig {
        bind: "127.0.0.1:0".parse().unwrap(),
        program: ProgramKind::Idle,
        files: Some(files.path().to_path_buf()),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let mut config = EpsnetConfig::new(sim.local_addr());
    config.local_ip = "127.0.0.1".parse().unwrap();
    let s: TestServer = start_on(
        "FFILE_BLKSIZE = 2000",
        &user_pub(),
        Some(Box::new(EpsnetBackend::new(config))),
    )
    .await;
    let mut c = s.client().await;
    c.send(b"GETFILE:big.bin\n").await;
    c.expect(&blocks("GETFILE", "big.bin", &big, 2000)).await;
    c.send(b"GETFILE:bin.dat\n").await;
    c.expect(&blocks("GETFILE", "bin.dat", BINARY, 2000)).await;
    c.ask(
        "GETFILEINFO:bin.dat\n",
        &info_line("bin.dat", &files.path().join("bin.dat"), 0x20),
    )
    .await;
    let upload = pattern(3000);
    c.send(&block("WRITEFILE", "up.bin", &upload[..1500])).await;
    c.send(&block("WRITEFILE", "up.bin", &upload[1500..])).await;
    c.send(&block("WRITEFILE", "up.bin", b"")).await;
    c.expect(b"WRITEFILE:up.bin OK\r\n").await;
    assert_eq!(fs::read(files.path().join("up.bin")).unwrap(), upload);
    c.send(b"GETFILE:/\n").await;
    c.expect(&blocks(
        "GETFILE",
        "/",
        b"big.bin\r\nbin.dat\r\nup.bin\r\n",
        2000,
    ))
    .await;
    c.ask("GETFILE:none\n", "ERROR:41 Unable to get file: 'none'\r\n")
        .await;
    c.ask(
        "GETFILEINFO:none\n",
        "ERROR:40 Unable to get information about file: 'none'\r\n",
    )
    .await;
    s.poke(Area::R, 0, b"");
    c.send(b"GETMEM:%R0 2\n").await;
    let mem = c.line().await;
    assert!(mem.starts_with(b"GETMEM:%R0[2]="), "{mem:?}");
}

/// The in-process backend the other tests run on: file services reach the
/// device's store, and a path out of it is refused.
#[tokio::test]
async fn the_in_process_backend_keeps_files_in_the_device_store() {
    use plccoms_core::driver::PlcBackend as _;
    let device = std::sync::Arc::new(std::sync::Mutex::new(plcsim::Device::new(
        plccoms_plc::MemoryMap::FOXTROT,
    )));
    let mut backend = common::memory::MemoryBackend::new(device.clone());
    assert_eq!(
        backend.file_info(b"x").await.unwrap(),
        Err(plccoms_core::driver::Refusal::NOT_ACTIVATED)
    );
    let dir = tempfile::tempdir().unwrap();
    device.lock().unwrap().files = Some(plcsim::FileStore::open(dir.path()).unwrap());
    assert_eq!(
        backend.write_file(b"a.txt", 0, b"abc", true).await.unwrap(),
        Ok(())
    );
    assert_eq!(backend.file_info(b"a.txt").await.unwrap().unwrap().size, 3);
    assert_eq!(
        backend.read_file(b"a.txt", 1, 10).await.unwrap(),
        Ok(b"bc".to_vec())
    );
    let list = backend.list_dir(b"/").await.unwrap().unwrap();
    assert_eq!(list[0].name, b"a.txt");
    assert_eq!(
        backend.read_file(b"../a.txt", 0, 1).await.unwrap(),
        Err(plccoms_core::driver::Refusal::BAD_PARAMETERS)
    );
}
