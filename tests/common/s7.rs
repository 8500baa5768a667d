//! S7 servers for the tests: python-snap7's, started as a process with a
//! known memory image, in its two kinds (3.x: pure Python; 1.x: the Snap7 C
//! library its wheel ships), each in a venv of its own under target/
//! (`tests/data/s7/venvs.sh` makes them when missing), and the server under
//! test configured for an S7 section.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use super::process::{ChildGuard, ServerProcess};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// Which python-snap7 serves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// python-snap7 3.3's pure-Python server: PDU at most 480, bits read
    /// and written as their whole byte, only a multi-item write's first
    /// item kept, no CPU mode.
    Python,
    /// The Snap7 C server of python-snap7 1.4.1's wheel: PDU 960, bit
    /// items, multi-item writes, CPU mode, at most 20 items a job.
    C,
}

impl Kind {
    fn python(self) -> PathBuf {
        let venv = match self {
            Kind::Python => "py3",
            Kind::C => "c1",
        };
        Path::new(ROOT)
            .join("target/s7-venvs")
            .join(venv)
            .join("bin/python")
    }
}

/// One area: `("DB", 1, bytes)`, `("MK", 0, ..)`, `("PE", 0, ..)`, `("PA", 0, ..)`.
pub type Area = (&'static str, u16, Vec<u8>);

/// A running python-snap7 server; killed when dropped.
pub struct Snap7 {
    pub port: u16,
    pub kind: Kind,
    child: ChildGuard,
    stdin: ChildStdin,
    lines: Receiver<String>,
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

impl Snap7 {
    /// Starts `kind` on `port` serving `areas`; returns once it listens.
    pub fn start(kind: Kind, port: u16, areas: &[Area]) -> Snap7 {
        let python = kind.python();
        if !python.exists() {
            let status = Command::new("bash")
                .arg(Path::new(ROOT).join("tests/data/s7/venvs.sh"))
                .status()
                .expect("run tests/data/s7/venvs.sh");
            assert!(
                status.success() && python.exists(),
                "cannot make the python-snap7 venvs (tests/data/s7/venvs.sh; .ci/run runs it): this test runs their S7 servers"
            );
        }
        let areas: Vec<String> = areas
            .iter()
            .map(|(area, index, data)| format!("[\"{area}\", {index}, \"{}\"]", hex(data)))
            .collect();
        let config = format!("{{\"port\": {port}, \"areas\": [{}]}}", areas.join(","));
        let mut child = ChildGuard::spawn(
            "snap7 server",
            Command::new(python)
                .arg(Path::new(ROOT).join("tests/data/s7/snap7_server.py"))
                .arg(config)
                .stdin(Stdio::piped())
                .stdout(Stdio::piped())
                .stderr(Stdio::null()),
        );
        let (stdin, lines) = child.command_lines();
        let mut server = Snap7 {
            port,
            kind,
            child,
            stdin,
            lines,
        };
        let ready = server.answer(Duration::from_secs(30));
        assert!(ready.starts_with("ready"), "snap7 server: {ready}");
        server
    }

    fn answer(&mut self, within: Duration) -> String {
        let deadline = Instant::now() + within;
        loop {
            match self.lines.recv_timeout(Duration::from_millis(100)) {
                Ok(line) => return line,
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => {
                    panic!(
                        "snap7 server on {} exited: {:?}",
                        self.port,
                        self.child.exited()
                    )
                }
            }
            if let Some(status) = self.child.exited() {
                panic!("snap7 server on {} exited ({status})", self.port);
            }
            assert!(
                Instant::now() < deadline,
                "snap7 server on {} is silent",
                self.port
            );
        }
    }

    fn command(&mut self, line: &str) -> String {
        writeln!(self.stdin, "{line}").expect("snap7 server's stdin");
        self.stdin.flush().expect("flush");
        self.answer(Duration::from_secs(10))
    }

    /// `len` bytes of an area as the server holds them.
    pub fn peek(&mut self, area: &str, index: u16, start: u32, len: u32) -> Vec<u8> {
        let answer = self.command(&format!("peek {area} {index} {start} {len}"));
        let text = answer.strip_prefix("peek ").expect("peek answer");
        (0..text.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&text[i..i + 2], 16).unwrap())
            .collect()
    }

    pub fn poke(&mut self, area: &str, index: u16, start: u32, bytes: &[u8]) {
        assert_eq!(
            self.command(&format!("poke {area} {index} {start} {}", hex(bytes))),
            "poked"
        );
    }

    /// The server's process id (to stop it with SIGSTOP: a silent CPU).
    pub fn pid(&mut self) -> u32 {
        self.child.child().id()
    }

    /// The CPU's mode (the C server's SZL 0x0424).
    pub fn set_run(&mut self, run: bool) {
        assert_eq!(self.command(if run { "run" } else { "stop" }), "ok");
    }
}

/// The server under test with one S7 section `[S]` on the server at
/// `port`, its tag file `tags` (written to `dir`), and `extra` keys.
pub fn s7_server(dir: &Path, device_port: u16, tags: &str, extra: &str) -> ServerProcess {
    let tags_path = dir.join("tags.csv");
    std::fs::write(&tags_path, tags).expect("write tags");
    let port = super::process::free_port();
    let ini = format!(
        "[*]\n[S]\nPROTOCOL = S7\nIPADDR = 127.0.0.1\nS7_PORT = {device_port}\n\
         S7_TAGS = {}\nSERVER_PORT = {port}\n{extra}\n",
        tags_path.display()
    );
    ServerProcess::with_config(&ini, port)
}
