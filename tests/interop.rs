//! The built `plccoms` binary against the real clients people use with it:
//! `telnet` (Debian package `telnet`) and PuTTY's `plink -telnet` (Debian
//! package `putty-tools`). A missing client fails the test; `.ci/run` installs
//! both. Also the binary's built-in configuration over plain TCP.
//!
//! Each client session goes through a recording relay, so the test also sees
//! the bytes the client put on the wire (run with `--nocapture` to print them).

mod common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::thread;
use std::time::{Duration, Instant};

use common::process::{free_port, port_is_free, which, Capture, ChildGuard, Relay, ServerProcess};

/// What every client sends, one command a line, as a person would type it.
const SCRIPT: &str = "LIST:\nGET:text\nSET:setpoint,21.5\nEN:sinus\n";

/// Time for the DIFF lines to come, and for the close after Ctrl+D.
const STEP_TIMEOUT: Duration = Duration::from_secs(5);

/// The demo program's variable count (fixed public file included).
const DEMO_VARIABLES: usize = 29;

const WARNING_252: &str = "WARNING:252 Changed active variables in public file: '[3/29]'";

/// Banner lines `telnet` prints on its standard output around the session.
const TELNET_BANNER: [&str; 3] = [
    "Trying 127.0.0.1...",
    "Connected to 127.0.0.1.",
    "Escape character is '^]'.",
];

/// A section with the simulated demo PLC, listening on loopback only.
fn demo_ini(port: u16) -> String {
    format!(
        "[*]\n\
         [Interop]\n\
         SIMULATOR = Yes\n\
         SIMULATOR_PROGRAM = demo\n\
         IPADDR_LOCAL = 127.0.0.1\n\
         SERVER_PORT = {port}\n\
         PUBFILE_WRITE = No\n\
         PUBFILE = //demo.pub\n"
    )
}

/// The client program's path; fails the test when it is not installed.
fn require(program: &str, package: &str) -> String {
    match which(program) {
        Some(path) => path.to_string_lossy().into_owned(),
        None => panic!(
            "`{program}` is not installed: this test drives the real client program. \
             Install it with `apt-get install -y {package}` (Debian/Ubuntu; .ci/run installs it)."
        ),
    }
}

/// A client program's session: what it showed and what went over the wire.
struct Session {
    stdout: Vec<u8>,
    stderr: String,
    upstream: Vec<u8>,
    downstream: Vec<u8>,
    elapsed: Duration,
}

/// Runs `program <args for the relay's port>` against a fresh demo server: types
/// `SCRIPT`, waits for two different DIFF:SINUS values, types Ctrl+D on its
/// own line and waits for the program to exit because the server closed
/// the connection (its standard input stays open until then).
fn run_client(program: &str, args: impl Fn(u16) -> Vec<String>) -> Session {
    let started = Instant::now();
    let port = free_port();
    let server = ServerProcess::with_config(&demo_ini(port), port);
    let relay = Relay::start(server.addr);
    let args = args(relay.addr.port());
    let mut client = ChildGuard::spawn(
        program,
        Command::new(program)
            .args(&args)
            .env("TERM", "dumb")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped()),
    );
    let mut stdin = client.child().stdin.take().expect("stdin");
    let stdout = Capture::start(client.child().stdout.take().expect("stdout"));
    let stderr = Capture::start(client.child().stderr.take().expect("stderr"));
    let context = |what: &str| {
        format!(
            "{what}\n--- {program} stdout:\n{}\n--- stderr:\n{}\n--- sent on the wire: {}\n--- server log:\n{}",
            stdout.text(),
            stderr.text(),
            escape(&relay.upstream()),
            server.log()
        )
    };

    stdin.write_all(SCRIPT.as_bytes()).expect("type the script");
    stdin.flush().expect("flush");
    let deadline = Instant::now() + STEP_TIMEOUT;
    while distinct_sinus(&lines(&stdout.bytes())) < 2 {
        if let Some(status) = client.exited() {
            panic!("{}", context(&format!("{program} exited early ({status})")));
        }
        if Instant::now() >= deadline {
            panic!("{}", context("no two different DIFF:SINUS values arrived"));
        }
        thread::sleep(Duration::from_millis(20));
    }

    stdin.write_all(b"\x04\n").expect("type Ctrl+D");
    stdin.flush().expect("flush");
    let Some(status) = client.wait_timeout(STEP_TIMEOUT) else {
        panic!(
            "{}",
            context("the server did not close the session after Ctrl+D")
        );
    };
    drop(stdin);
    let session = Session {
        stdout: stdout.finish(),
        stderr: String::from_utf8_lossy(&stderr.finish()).into_owned(),
        upstream: relay.upstream(),
        downstream: relay.downstream(),
        elapsed: started.elapsed(),
    };
    assert!(
        status.success(),
        "{program} exited with {status}; stderr: {}",
        session.stderr
    );
    eprintln!(
        "{program} {args:?}: {:?}; it sent: {}",
        session.elapsed,
        escape(&session.upstream)
    );
    session
}

/// Standard output as lines, line ends (`\n`, `\r\n`) removed, cp1250 bytes
/// shown lossily.
fn lines(stdout: &[u8]) -> Vec<String> {
    stdout
        .split(|&b| b == b'\n')
        .map(|line| String::from_utf8_lossy(line.strip_suffix(b"\r").unwrap_or(line)).into_owned())
        .collect()
}

/// `^DIFF:SINUS,-?\d+\.\d{10}$`
fn is_sinus_diff(line: &str) -> bool {
    let Some(value) = line.strip_prefix("DIFF:SINUS,") else {
        return false;
    };
    let value = value.strip_prefix('-').unwrap_or(value);
    let Some((int, frac)) = value.split_once('.') else {
        return false;
    };
    !int.is_empty()
        && int.bytes().all(|b| b.is_ascii_digit())
        && frac.len() == 10
        && frac.bytes().all(|b| b.is_ascii_digit())
}

fn distinct_sinus(lines: &[String]) -> usize {
    let mut values: Vec<&str> = lines
        .iter()
        .filter(|l| is_sinus_diff(l))
        .map(String::as_str)
        .collect();
    values.sort_unstable();
    values.dedup();
    values.len()
}

fn escape(bytes: &[u8]) -> String {
    bytes.escape_ascii().to_string()
}

/// The checks every client's session must pass.
fn check_session(session: &Session, banner: &[&str]) {
    let all = lines(&session.stdout);
    let mut shown: Vec<&str> = all
        .iter()
        .map(String::as_str)
        .filter(|l| !banner.contains(l))
        .collect();
    if shown.last() == Some(&"") {
        shown.pop();
    }
    let transcript = shown.join("\n");

    let end = shown
        .iter()
        .position(|&l| l == "LIST:")
        .unwrap_or_else(|| panic!("no LIST: terminator in:\n{transcript}"));
    let list = &shown[..end];
    assert_eq!(
        list.len(),
        DEMO_VARIABLES,
        "LIST lines before the terminator:\n{transcript}"
    );
    assert!(list.iter().all(|l| l.starts_with("LIST:")), "{transcript}");
    for want in [
        "LIST:__PLC_RUN,BOOL",
        "LIST:SINUS,LREAL*",
        "LIST:TEXT,STRING[80]*",
        "LIST:SETPOINT,REAL*",
    ] {
        assert!(list.contains(&want), "no {want} in:\n{transcript}");
    }
    assert_eq!(
        &shown[end + 1..end + 4],
        [
            "GET:TEXT,\"Have a nice day\"",
            "DIFF:SETPOINT,21.500000",
            WARNING_252
        ],
        "answers to GET, SET and EN in:\n{transcript}"
    );
    let diffs = &shown[end + 4..];
    for line in diffs {
        assert!(
            is_sinus_diff(line),
            "after EN:sinus only DIFF:SINUS lines, got {line:?} in:\n{transcript}"
        );
    }
    let diffs: Vec<String> = diffs.iter().map(|l| l.to_string()).collect();
    assert!(distinct_sinus(&diffs) >= 2, "{transcript}");

    // The wire: CRLF line ends, no NUL, and nothing answered to telnet
    // negotiation (no IAC back).
    let down = &session.downstream;
    assert!(down.ends_with(b"\r\n"), "last bytes: {}", escape(down));
    assert_eq!(
        down.windows(2)
            .filter(|w| w[1] == b'\n' && w[0] != b'\r')
            .count(),
        0,
        "a bare LF from the server: {}",
        escape(down)
    );
    assert!(!down.contains(&0), "NUL from the server");
    assert!(
        !down.contains(&0xFF),
        "the server answered telnet negotiation: {}",
        escape(down)
    );
    // Ctrl+D went out as a line of its own.
    let up = &session.upstream;
    assert!(
        up.windows(2).any(|w| w == b"\n\x04"),
        "no Ctrl+D line sent: {}",
        escape(up)
    );
}

/// telnet reports that the server, not telnet, ended the connection.
fn assert_closed_by_server(session: &Session) {
    assert!(
        session
            .stderr
            .contains("Connection closed by foreign host."),
        "telnet's stderr: {}",
        session.stderr
    );
}

#[test]
fn telnet_client() {
    let telnet = require("telnet", "telnet");
    let session = run_client(&telnet, |port| vec!["127.0.0.1".into(), port.to_string()]);
    check_session(&session, &TELNET_BANNER);
    assert_closed_by_server(&session);
    // Line mode: each typed line goes out with CRLF, Ctrl+D too.
    assert!(
        session.upstream.starts_with(b"LIST:\r\nGET:text\r\n"),
        "{}",
        escape(&session.upstream)
    );
    assert!(session.upstream.ends_with(b"\x04\r\n"));
}

/// `telnet host -port` negotiates options as on the telnet port (the leading
/// `-` asks for it); the server skips the IAC sequences silently.
#[test]
fn telnet_client_with_option_negotiation() {
    let telnet = require("telnet", "telnet");
    let session = run_client(&telnet, |port| {
        vec!["--".into(), "127.0.0.1".into(), format!("-{port}")]
    });
    check_session(&session, &TELNET_BANNER);
    assert_closed_by_server(&session);
    assert_eq!(
        session.upstream.first(),
        Some(&0xFF),
        "telnet negotiated nothing: {}",
        escape(&session.upstream)
    );
}

#[test]
fn plink_telnet_client() {
    let plink = require("plink", "putty-tools");
    let session = run_client(&plink, |port| {
        ["-batch", "-telnet", "-P", &port.to_string(), "127.0.0.1"]
            .map(String::from)
            .to_vec()
    });
    check_session(&session, &[]);
    // PuTTY opens with option negotiation (IAC WILL NAWS ...).
    assert_eq!(
        session.upstream.first(),
        Some(&0xFF),
        "plink negotiated nothing: {}",
        escape(&session.upstream)
    );
}

/// Tests that need port 5010 (the built-in configuration's) run one at a
/// time.
static PORT_5010: Mutex<()> = Mutex::new(());

/// A line reader over a plain TCP connection.
struct Lines {
    stream: TcpStream,
    buf: Vec<u8>,
    seen: String,
}

impl Lines {
    fn connect(addr: SocketAddr) -> Lines {
        let stream = TcpStream::connect(addr).expect("connect");
        stream
            .set_read_timeout(Some(STEP_TIMEOUT))
            .expect("read timeout");
        Lines {
            stream,
            buf: Vec::new(),
            seen: String::new(),
        }
    }

    fn send(&mut self, request: &str) {
        self.stream.write_all(request.as_bytes()).expect("send");
    }

    /// The next line without its CRLF; panics on timeout or close.
    fn line(&mut self) -> String {
        loop {
            if let Some(pos) = self.buf.windows(2).position(|w| w == b"\r\n") {
                let line: Vec<u8> = self.buf.drain(..pos + 2).take(pos).collect();
                let line = String::from_utf8_lossy(&line).into_owned();
                self.seen.push_str(&line);
                self.seen.push('\n');
                return line;
            }
            let mut chunk = [0u8; 8192];
            match self.stream.read(&mut chunk) {
                Ok(0) => panic!("connection closed; got so far:\n{}", self.seen),
                Ok(n) => self.buf.extend_from_slice(&chunk[..n]),
                Err(e) => panic!("{e} waiting for a line; got so far:\n{}", self.seen),
            }
        }
    }

    /// Reads until the server closes; returns the lines still read.
    /// DIFF lines keep coming until then, so the wait has its own deadline.
    fn until_closed(&mut self) -> Vec<String> {
        let deadline = Instant::now() + STEP_TIMEOUT;
        let mut rest = Vec::new();
        let mut chunk = [0u8; 8192];
        loop {
            match self.stream.read(&mut chunk) {
                Ok(0) => break,
                Ok(n) => self.buf.extend_from_slice(&chunk[..n]),
                Err(e) => panic!("{e} waiting for the close; got so far:\n{}", self.seen),
            }
            assert!(
                Instant::now() < deadline,
                "the server did not close the session after Ctrl+D within {STEP_TIMEOUT:?}"
            );
        }
        for line in self.buf.split(|&b| b == b'\n') {
            if !line.is_empty() {
                rest.push(String::from_utf8_lossy(line).trim_end().to_string());
            }
        }
        rest
    }
}

/// `plccoms` with no arguments in a directory without `PLCComS.ini` runs the
/// built-in configuration: the demo PLC simulated, on port 5010.
#[test]
fn binary_serves_the_built_in_configuration() {
    let _serial = PORT_5010.lock().unwrap_or_else(|e| e.into_inner());
    let deadline = Instant::now() + Duration::from_secs(5);
    while !port_is_free(5010) {
        assert!(
            Instant::now() < deadline,
            "port 5010 is in use by another program; the built-in configuration listens \
             there, so this test needs it free (stop the other server and rerun)"
        );
        thread::sleep(Duration::from_millis(100));
    }
    let started = Instant::now();
    let server = ServerProcess::built_in(5010);
    let mut c = Lines::connect(server.addr);

    c.send("LIST:\r\n");
    let mut list = Vec::new();
    loop {
        let line = c.line();
        if line == "LIST:" {
            break;
        }
        list.push(line);
    }
    assert_eq!(list.len(), DEMO_VARIABLES, "{list:#?}");
    for want in [
        "LIST:SINUS,LREAL*",
        "LIST:COSINUS,LREAL*",
        "LIST:TEXT,STRING[80]*",
        "LIST:SETPOINT,REAL*",
        "LIST:COUNTER,INT*",
        "LIST:SWITCH,BOOL*",
    ] {
        assert!(list.iter().any(|l| l == want), "no {want} in {list:#?}");
    }

    c.send("GET:text\r\n");
    assert_eq!(c.line(), "GET:TEXT,\"Have a nice day\"");

    c.send("EN:sinus\r\n");
    assert_eq!(c.line(), WARNING_252);
    let mut sinus = Vec::new();
    while distinct_sinus(&sinus) < 2 {
        let line = c.line();
        assert!(is_sinus_diff(&line), "after EN:sinus: {line:?}");
        sinus.push(line);
    }

    c.send("SET:counter,5\r\n");
    let answer = loop {
        let line = c.line();
        if !is_sinus_diff(&line) {
            break line;
        }
    };
    assert_eq!(answer, "DIFF:COUNTER,5", "log:\n{}", server.log());

    c.send("\x04\r\n");
    for line in c.until_closed() {
        assert!(is_sinus_diff(&line), "before the close: {line:?}");
    }
    eprintln!("built-in configuration: {:?}", started.elapsed());
}
