//! The ADS tests' device: pyads's test server with our extensions
//! (tests/ads/fixture.py), a child process driven over its stdin.

use std::io::{BufRead, BufReader, Write};
use std::process::{ChildStdin, ChildStdout, Command, Stdio};

use super::common::process::{which, ChildGuard};

pub struct Fixture {
    pub port: u16,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    _child: ChildGuard,
}

impl Fixture {
    /// Starts it on `port` (0: any free one). Fails, not skips, without
    /// python3 and pyads (installed by .ci/run).
    pub fn start(port: u16) -> Fixture {
        let python = which("python3")
            .expect("python3 is not installed: the ADS tests run pyads's test server");
        let probe = Command::new(&python)
            .args(["-c", "import pyads.testserver"])
            .status()
            .expect("run python3");
        assert!(
            probe.success(),
            "pyads is not installed (python3 -m pip install pyads==3.6.0)"
        );
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/ads/fixture.py");
        let mut child = ChildGuard::spawn(
            "ADS fixture",
            Command::new(python)
                .args([script, &port.to_string()])
                .stdin(Stdio::piped())
                .stdout(Stdio::piped()),
        );
        let stdin = child.child().stdin.take().unwrap();
        let mut stdout = BufReader::new(child.child().stdout.take().unwrap());
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        let port = line
            .strip_prefix("port ")
            .and_then(|p| p.trim().parse().ok())
            .unwrap_or_else(|| panic!("the ADS fixture did not start: {line:?}"));
        Fixture {
            port,
            stdin,
            stdout,
            _child: child,
        }
    }

    /// One command (see fixture.py) and its answer.
    pub fn ask(&mut self, command: &str) -> String {
        writeln!(self.stdin, "{command}").unwrap();
        self.stdin.flush().unwrap();
        let mut line = String::new();
        self.stdout.read_line(&mut line).unwrap();
        line.trim_end().to_string()
    }
}

/// A plccoms section on the fixture at `port`, with `extra` keys.
pub fn ads_ini(device_port: u16, server_port: u16, extra: &str) -> String {
    format!(
        "[*]\n[A]\nPROTOCOL = ADS\nIPADDR = 127.0.0.1\nADS_TCP_PORT = {device_port}\n\
         ADS_NET_ID = 127.0.0.1.1.1\nADS_PORT = 851\nSERVER_PORT = {server_port}\n{extra}\n"
    )
}
