//! Backend plugins (SHM_NAME): the example plugin behaves like the
//! simulated PLC, through the real start-up path; the deliberately bad
//! plugin (`plugins/bad-plugin`) gets clear errors for wrong lengths, bad
//! status codes, slow calls and bad tables, and a plugin that crashes stops
//! the server with a line in its log that names it.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::health::{answer, is_link_error, until};
use common::process::{plugin_lib, ChildGuard, PLCCOMS};
use common::Client;

const BACK: Duration = Duration::from_secs(20);

fn section(port: u16, plugin: &Path, keys: &str) -> String {
    format!(
        "[*]\n[Plug]\nSHM_NAME = {}\nSERVER_PORT = {port}\n{keys}\n",
        plugin.display()
    )
}

#[tokio::test]
async fn the_example_plugin_behaves_like_the_simulated_plc() {
    let demo = plugin_lib("demo");
    let (server, port, _conf) = common::start_on_free_port(|port| {
        section(
            port,
            &demo,
            "SHM_SOCKET = 0\nSHM_PORT = 5\nPUBFILE = //demo.pub",
        )
    })
    .await;
    let mut c = Client::connect(([127, 0, 0, 1], port).into()).await;
    // The public file came from the plugin's file services.
    until(&mut c, "GET:setpoint\n", "GET:SETPOINT,0.000000\r\n", BACK).await;
    let (ident, _) = answer(&mut c, "GETINFO:version_plc\n").await;
    assert_eq!(ident, "GETINFO:VERSION_PLC,CP1000    PLUGIN 1.0 port 5\r\n");
    c.send(b"LIST:\n").await;
    let lines = c.wait_for_line(b"LIST:\r\n", BACK).await;
    assert_eq!(lines.len(), 29);

    c.ask("SET:setpoint,21.5\n", "DIFF:SETPOINT,21.500000\r\n")
        .await;
    c.ask("SET:switch,1\n", "DIFF:SWITCH,1\r\n").await;
    c.ask("GET:switch\n", "GET:SWITCH,1\r\n").await;
    c.ask("SET:note,\"plugged\"\n", "DIFF:NOTE,\"plugged\"\r\n")
        .await;

    // The demo program runs: the sine moves, DIFF by DIFF.
    c.ask(
        "EN:sinus\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    let first = c.line_within(BACK).await.expect("a DIFF");
    let later = loop {
        let line = c.line_within(BACK).await.expect("another DIFF");
        if line != first {
            break line;
        }
    };
    assert!(first.starts_with(b"DIFF:SINUS,") && later.starts_with(b"DIFF:SINUS,"));
    let backend = &server.sections[0].section.metrics().backend;
    assert!(backend.requests.get() > 0);
    assert_eq!(backend.timeouts.get(), 0);
}

/// A server on the bad plugin in `mode` (its SHM_SOCKET), polling only the
/// fixed variables.
async fn bad(mode: u32, extra: &str) -> (plccoms::startup::Server, Client, tempfile::TempDir) {
    let lib = plugin_lib("bad");
    let (server, port, conf) = common::start_on_free_port(|port| {
        section(port, &lib, &format!("SHM_SOCKET = {mode}\n{extra}"))
    })
    .await;
    let c = Client::connect(([127, 0, 0, 1], port).into()).await;
    (server, c, conf)
}

#[tokio::test]
async fn wrong_lengths_and_bad_codes_get_clear_errors() {
    // A good one first: the same plugin, well behaved.
    let (_server, mut c, _conf) = bad(0, "").await;
    until(&mut c, "GET:__plc_run\n", "GET:__PLC_RUN,0\r\n", BACK).await;
    c.ask("SET:__plc_run,1\n", "DIFF:__PLC_RUN,1\r\n").await;

    // Reads one byte short (1); statuses the ABI does not define and a
    // message without its end (2): errors, never data.
    for mode in [1, 2] {
        let (server, mut c, _conf) = bad(mode, "").await;
        let start = Instant::now();
        while server.sections[0].section.metrics().backend.errors.get() == 0 {
            assert!(
                start.elapsed() < BACK,
                "mode {mode}: no plugin error counted"
            );
            let (line, _) = answer(&mut c, "GET:__pf_crc\n").await;
            assert!(line.starts_with("ERROR:"), "mode {mode}: {line:?}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    // No connection: open refused, an identification too long.
    for mode in [5, 6] {
        let (_server, mut c, _conf) = bad(mode, "").await;
        let (line, _) = answer(&mut c, "GET:__plc_run\n").await;
        assert_eq!(
            line, "ERROR:10 Unable to connect to PLC.\r\n",
            "mode {mode}"
        );
    }
}

#[tokio::test]
async fn the_plcs_refusals_are_errors_of_their_request_only() {
    // Writes refused (7): a byte write with a status the ABI does not
    // define, a bit write with the EPSNET byte 0x0C and a message longer
    // than its buffer; a read out of the plugin's range refused with 0x0C.
    let files = tempfile::tempdir().unwrap();
    let project = files.path().join("bad.pub");
    std::fs::write(
        &project,
        " v R B 100 BYTE PUB_INOUT\r\n far R B 70000 BYTE PUB_INOUT\r\n",
    )
    .unwrap();
    let (server, mut c, _conf) = bad(7, &format!("PUBFILE = {}", project.display())).await;
    until(&mut c, "GET:v\n", "GET:V,0\r\n", BACK).await;
    let metrics = &server.sections[0].section.metrics();
    let served = |line: &str| line == "GET:V,0\r\n";

    // A refused write is the vendor's answer to a write that failed; the
    // PLC stays: the next request is served at once.
    let (bits, _) = answer(&mut c, "SET:__plc_run,1\n").await;
    assert_eq!(bits, "ERROR:21 Unable to send data to PLC.\r\n");
    let (next, _) = answer(&mut c, "GET:v\n").await;
    assert!(served(&next), "after the refused bit: {next:?}");
    let (far, _) = answer(&mut c, "GET:far\n").await;
    assert_eq!(far, "ERROR:20 Unable to get data from PLC.\r\n");
    let (next, _) = answer(&mut c, "GET:v\n").await;
    assert!(served(&next), "after the refused read: {next:?}");
    // A status the ABI does not define: a bad answer, counted.
    let errors = metrics.backend.errors.get();
    let (bytes, _) = answer(&mut c, "SET:v,5\n").await;
    assert_eq!(bytes, "ERROR:21 Unable to send data to PLC.\r\n");
    assert!(
        metrics.backend.errors.get() > errors,
        "an undefined status not counted"
    );
    let (next, _) = answer(&mut c, "GET:v\n").await;
    assert!(served(&next), "after the undefined status: {next:?}");
    assert_eq!(metrics.link_up.get(), 1, "the PLC was lost");
    assert_eq!(metrics.backend.timeouts.get(), 0);
}

#[tokio::test]
async fn slow_calls_are_bounded_by_the_timeout_and_counted() {
    // Reads take 3 s; a call may take EPSTOUT + EPSTOUT + STEP = 500 ms.
    let (server, mut c, _conf) = bad(3, "SHM_PORT = 3000\nEPSTOUT = 200\nEPSTOUT_STEP = 100").await;
    let mut other = Client::connect(server.sections[0].local_addr).await;
    let start = Instant::now();
    let backend = &server.sections[0].section.metrics().backend;
    while backend.timeouts.get() < 2 {
        assert!(start.elapsed() < BACK, "no timeout counted");
        let (line, took) = answer(&mut c, "GET:__pf_crc\n").await;
        assert!(is_link_error(&line), "{line:?}");
        // At most: waiting behind a poll's call, then its own.
        assert!(took < Duration::from_secs(3), "answered after {took:?}");
        // The server serves other clients meanwhile.
        let (list, took) = answer(&mut other, "GETINFO:version\n").await;
        assert!(list.starts_with("GETINFO:VERSION,"), "{list:?}");
        assert!(took < Duration::from_secs(1), "{took:?}");
    }
}

/// Runs the server binary on `ini` with `env`; returns it and its folder,
/// where `plccoms.log` is its log: stderr, or with `log_file` the file it
/// writes itself (`-l`, reopened on SIGHUP).
fn server_process(
    ini: &str,
    env: &[(&str, &str)],
    log_file: bool,
) -> (ChildGuard, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("plccoms.ini"), ini).unwrap();
    let mut command = Command::new(PLCCOMS);
    command
        .args(["-c", "plccoms.ini"])
        .current_dir(dir.path())
        .envs(env.iter().copied())
        .env_remove("RUST_LOG")
        .stdin(Stdio::null())
        .stdout(Stdio::null());
    if log_file {
        command.args(["-l", "plccoms.log"]).stderr(Stdio::null());
    } else {
        let log = std::fs::File::create(dir.path().join("plccoms.log")).unwrap();
        command.stderr(log);
    }
    (ChildGuard::spawn("plccoms", &mut command), dir)
}

fn log_of(dir: &tempfile::TempDir) -> String {
    std::fs::read_to_string(dir.path().join("plccoms.log")).unwrap_or_default()
}

fn wait_log(dir: &tempfile::TempDir, text: &str) -> String {
    let start = Instant::now();
    loop {
        let log = log_of(dir);
        if log.contains(text) {
            return log;
        }
        assert!(start.elapsed() < BACK, "{text:?} not in the log:\n{log}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn bad_tables_are_refused_with_the_reason() {
    let lib = plugin_lib("bad");
    for (entry, reason) in [
        ("null", "the entry returned no table for ABI version 1"),
        ("version", "ABI version 99, this server speaks 1"),
        ("short", "table of 8 bytes"),
        ("nofn", "the table has no read function"),
    ] {
        let port = common::process::free_port();
        let (_server, dir) = server_process(
            &section(port, &lib, ""),
            &[("BAD_PLUGIN_ENTRY", entry)],
            false,
        );
        let log = wait_log(&dir, "cannot reach PLC");
        assert!(log.contains(reason), "{entry}: {log}");
    }
}

#[test]
fn a_crashing_plugin_stops_the_server_and_says_so() {
    use std::os::unix::process::ExitStatusExt;
    let lib = plugin_lib("bad");
    let port = common::process::free_port();
    let (mut server, dir) = server_process(&section(port, &lib, "SHM_SOCKET = 4"), &[], false);
    let status = server
        .wait_timeout(BACK)
        .expect("the server ends when its plugin crashes");
    assert_eq!(status.signal(), Some(libc::SIGSEGV), "{status:?}");
    let log = log_of(&dir);
    let fatal = format!(
        "plccoms: FATAL: signal SIGSEGV inside plugin {} (section Plug): read; \
         a crash inside a plugin is not isolated: the server stops",
        lib.display()
    );
    assert!(log.contains(&fatal), "{log}");
}

#[test]
fn a_crash_after_the_log_was_rotated_is_in_the_new_log() {
    use std::os::unix::process::ExitStatusExt;
    let lib = plugin_lib("bad");
    let port = common::process::free_port();
    // The plugin crashes 8 s into its first read: time to rotate the log.
    let ini = section(port, &lib, "SHM_SOCKET = 4\nSHM_PORT = 8000");
    let (mut server, dir) = server_process(&ini, &[], true);
    wait_log(&dir, "listening");
    let rotated = dir.path().join("plccoms.log.1");
    std::fs::rename(dir.path().join("plccoms.log"), &rotated).unwrap();
    // SAFETY: a signal to our own child.
    unsafe { libc::kill(server.child().id() as libc::pid_t, libc::SIGHUP) };
    wait_log(&dir, "reopened");
    let status = server
        .wait_timeout(BACK)
        .expect("the server ends when its plugin crashes");
    assert_eq!(status.signal(), Some(libc::SIGSEGV), "{status:?}");
    let fatal = "plccoms: FATAL: signal SIGSEGV inside plugin";
    let log = log_of(&dir);
    assert!(log.contains(fatal), "not in the new log:\n{log}");
    let old = std::fs::read_to_string(&rotated).unwrap();
    assert!(!old.contains(fatal), "in the rotated log:\n{old}");
}
