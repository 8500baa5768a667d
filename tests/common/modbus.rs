//! Modbus devices for the tests: pymodbus's server (a third-party
//! implementation) started as a process with a known register image, and the
//! server under test configured for a Modbus section.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use super::process::{which, ChildGuard, ServerProcess};

/// The script that runs pymodbus's server.
const SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/data/modbus/pymodbus_server.py"
);

/// A device's tables: blocks of values from their first address; every
/// other address is invalid (exception 2).
#[derive(Debug, Clone, Default)]
pub struct Image {
    pub coils: Vec<(u16, Vec<bool>)>,
    pub discrete: Vec<(u16, Vec<bool>)>,
    pub holding: Vec<(u16, Vec<u16>)>,
    pub input: Vec<(u16, Vec<u16>)>,
}

impl Image {
    fn json(&self, port: u16) -> String {
        fn table<T: ToString>(blocks: &[(u16, Vec<T>)]) -> String {
            let entries: Vec<String> = blocks
                .iter()
                .map(|(address, values)| {
                    let values: Vec<String> = values.iter().map(T::to_string).collect();
                    format!("\"{address}\": [{}]", values.join(","))
                })
                .collect();
            format!("{{{}}}", entries.join(","))
        }
        let bits = |blocks: &[(u16, Vec<bool>)]| {
            let numbers: Vec<(u16, Vec<u8>)> = blocks
                .iter()
                .map(|(a, v)| (*a, v.iter().map(|&b| u8::from(b)).collect()))
                .collect();
            table(&numbers)
        };
        format!(
            "{{\"port\": {port}, \"coils\": {}, \"discrete\": {}, \"holding\": {}, \"input\": {}}}",
            bits(&self.coils),
            bits(&self.discrete),
            table(&self.holding),
            table(&self.input)
        )
    }
}

/// pymodbus serving an [`Image`] on 127.0.0.1; killed when dropped.
pub struct Pymodbus {
    pub port: u16,
    _child: ChildGuard,
}

impl Pymodbus {
    /// Starts the server on `port`; returns once it listens.
    pub fn start(port: u16, image: &Image) -> Pymodbus {
        let python = which("python3").unwrap_or_else(|| {
            panic!("python3 is not installed: this test runs pymodbus's server")
        });
        let probe = Command::new(&python)
            .args(["-c", "import pymodbus"])
            .stderr(Stdio::null())
            .status()
            .expect("run python3");
        assert!(
            probe.success(),
            "pymodbus is not installed: this test runs its Modbus server. \
             Install it with `python3 -m pip install pymodbus==3.16.1` (.ci/run installs it)."
        );
        let mut child = ChildGuard::spawn(
            "pymodbus",
            Command::new(python)
                .arg(SCRIPT)
                .arg(image.json(port))
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::null()),
        );
        let stdout = child.child().stdout.take().expect("stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if line.starts_with("ready") {
                    let _ = tx.send(());
                }
            }
        });
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if rx.recv_timeout(Duration::from_millis(100)).is_ok() {
                break;
            }
            if let Some(status) = child.exited() {
                panic!("pymodbus exited ({status}) before listening on {port}");
            }
            assert!(
                Instant::now() < deadline,
                "pymodbus did not listen on {port} within 30 s"
            );
        }
        Pymodbus {
            port,
            _child: child,
        }
    }
}

/// The server under test with one Modbus section `[M]` on the device at
/// `port`, its tag file `tags` (written to `dir`), and `extra` keys.
pub fn modbus_server(dir: &Path, device_port: u16, tags: &str, extra: &str) -> ServerProcess {
    let tags_path = dir.join("tags.csv");
    std::fs::write(&tags_path, tags).expect("write tags");
    let port = super::process::free_port();
    let ini = format!(
        "[*]\n[M]\nPROTOCOL = MODBUS_TCP\nIPADDR = 127.0.0.1\nMODBUS_PORT = {device_port}\n\
         MODBUS_TAGS = {}\nSERVER_PORT = {port}\n{extra}\n",
        tags_path.display()
    );
    ServerProcess::with_config(&ini, port)
}

/// `value`'s 16-bit words, high word first.
pub fn words(bytes: &[u8]) -> Vec<u16> {
    bytes
        .chunks(2)
        .map(|w| u16::from_be_bytes([w[0], *w.get(1).unwrap_or(&0)]))
        .collect()
}

/// Asks `request` until it is answered `answer`, within `secs` seconds.
pub async fn until(c: &mut super::Client, request: &str, answer: &str, secs: u64) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(secs);
    loop {
        c.send(format!("{request}\r\n").as_bytes()).await;
        let line = String::from_utf8(c.line().await).unwrap();
        if line.trim_end() == answer {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{request}: still {line:?} after {secs} s"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}
