//! Test harness: a server section on loopback over the in-process backend,
//! and a raw TCP client that checks exact bytes.
#![allow(dead_code)]

pub mod epsnet;
pub mod health;
pub mod http;
pub mod line;
pub mod logs;
pub mod memory;
pub mod modbus;
pub mod mqtt;
pub mod process;
pub mod s7;

use std::net::SocketAddr;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use memory::MemoryBackend;
use plccoms::startup::{start_section, RunningSection};
use plccoms_core::config;
use plccoms_core::vars::VarTable;
use plccoms_plc::pubfile;
use plccoms_plc::MemoryMap;
use plcsim::Device;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

pub const FIXED_PUB: &[u8] =
    b" __PLC_RUN S B 2 .2 BOOL PUB_INOUT\r\n __PF_CRC S B 70 DWORD PUB_INOUT\r\n";

/// A user public file with every type; cp1250 bytes (0xEC is `ě`).
pub fn user_pub() -> Vec<u8> {
    let mut text = b"; test project\r\n\
 TEST_1 R B 0 INT PUB_INOUT\r\n\
 test_2 R F 4 REAL PUB_INOUT\r\n\
 TEST_STRING R B 8 STRING[20] PUB_INOUT\r\n\
 TEST_BTN_UP R B 30 .0 BOOL PUB_INOUT\r\n\
 TEST_BTN_DOWN R B 30 .1 BOOL PUB_INOUT\r\n\
 V_LREAL R F 32 LREAL PUB_INOUT\r\n\
 V_BYTE R B 40 BYTE PUB_INOUT\r\n\
 V_WORD R B 42 WORD PUB_INOUT\r\n\
 V_DWORD R B 44 DWORD PUB_INOUT\r\n\
 V_LWORD R B 48 LWORD PUB_INOUT\r\n\
 V_SINT R B 56 SINT PUB_INOUT\r\n\
 V_DINT R B 60 DINT PUB_INOUT\r\n\
 V_LINT R B 64 LINT PUB_INOUT\r\n\
 V_USINT R B 72 USINT PUB_INOUT\r\n\
 V_UINT R B 74 UINT PUB_INOUT\r\n\
 V_UDINT R B 76 UDINT PUB_INOUT\r\n\
 V_ULINT R B 80 ULINT PUB_INOUT\r\n\
 V_DATE R B 88 DATE PUB_INOUT\r\n\
 V_TIME R B 96 TIME PUB_INOUT\r\n\
 V_TOD R B 100 TIME_OF_DAY PUB_INOUT\r\n\
 V_DT R B 104 DATE_AND_TIME PUB_INOUT\r\n\
 Meteo.WindDirection R B 112 UINT PUB_INOUT\r\n\
 T_ZONES_SET[0].TOPIT_TC R B 114 BOOL PUB_INOUT\r\n"
        .to_vec();
    text.extend_from_slice(b" teplota_kuchyn\xEC R F 116 REAL PUB_INOUT\r\n");
    text
}

pub struct TestServer {
    pub section: RunningSection,
    pub device: Arc<Mutex<Device>>,
    pub addr: SocketAddr,
    /// The section's root folder for local files (`./name`).
    pub root: tempfile::TempDir,
    /// The folder the in-process PLC serves as its file system.
    pub plc_files: tempfile::TempDir,
}

/// The simulator's demo.pub with one more variable, `extra` (INT at R300),
/// and no CRC trailer: a changed user program.
pub fn demo_pub_with_extra() -> Vec<u8> {
    let mut text: Vec<u8> = plcsim::DEMO_PUB
        .split_inclusive(|&b| b == b'\n')
        .filter(|line| !line.starts_with(b";*"))
        .flatten()
        .copied()
        .collect();
    text.extend_from_slice(b" extra R B 300 INT PUB_INOUT\r\n");
    text
}

/// The configuration of a test section `[Test]` with the `[*]` keys in
/// `global_ini`, and its variable table from a fixed and a user public file.
pub fn section_parts(
    global_ini: &str,
    fixed: &[u8],
    (user_name, user): (&str, &[u8]),
) -> (Arc<config::Global>, config::Section, VarTable) {
    let ini = format!("[*]\n{global_ini}\n[Test]\nSERVER_PORT = 5010\n");
    let loaded = config::parse(Path::new("test.ini"), &ini).expect("test ini");
    let global = Arc::new(loaded.config.global);
    let section = loaded.config.sections.into_iter().next().unwrap();
    let mut warnings = Vec::new();
    let table = VarTable::build(
        "FIXED.pub",
        &pubfile::parse(fixed),
        Some((user_name, &pubfile::parse(user))),
        &MemoryMap::FOXTROT,
        &mut warnings,
    )
    .expect("table");
    (global, section, table)
}

/// Starts a section configured by the `[*]` keys in `global_ini` on the
/// in-process backend with `user_pub()`.
pub async fn start(global_ini: &str) -> TestServer {
    start_with(global_ini, &user_pub()).await
}

pub async fn start_with(global_ini: &str, user: &[u8]) -> TestServer {
    start_on(global_ini, user, None).await
}

/// Like [`start_with`], on `backend` instead of the in-process device (which
/// is then only used by `poke`/`peek`).
pub async fn start_on(
    global_ini: &str,
    user: &[u8],
    backend: Option<Box<dyn plccoms_core::driver::PlcBackend>>,
) -> TestServer {
    let (global, section, table) = section_parts(global_ini, FIXED_PUB, ("test.pub", user));
    let device = Arc::new(Mutex::new(Device::new(MemoryMap::FOXTROT)));
    let root = tempfile::tempdir().expect("root dir");
    let plc_files = tempfile::tempdir().expect("plc files dir");
    device.lock().unwrap().files =
        Some(plcsim::FileStore::open(plc_files.path()).expect("file store"));
    let backend = backend.unwrap_or_else(|| Box::new(MemoryBackend::new(device.clone())));
    let section = start_section(
        global,
        section,
        table,
        Some(backend),
        "127.0.0.1:0".parse().unwrap(),
        root.path().to_path_buf(),
        None,
    )
    .await
    .expect("start section");
    let addr = section.local_addr;
    TestServer {
        section,
        device,
        addr,
        root,
        plc_files,
    }
}

impl TestServer {
    pub async fn client(&self) -> Client {
        Client::connect(self.addr).await
    }

    /// Writes raw bytes into the PLC's memory, as its program would.
    pub fn poke(&self, area: plccoms_protocol::Area, offset: u32, bytes: &[u8]) {
        let mut device = self.device.lock().unwrap();
        device
            .write(
                area,
                offset,
                &plccoms_core::driver::WriteData::Bytes(bytes.to_vec()),
            )
            .unwrap();
    }

    pub fn peek(&self, area: plccoms_protocol::Area, offset: u32, len: u32) -> Vec<u8> {
        self.device.lock().unwrap().read(area, offset, len).unwrap()
    }
}

pub const TIMEOUT: Duration = Duration::from_secs(5);

pub struct Client {
    pub stream: TcpStream,
    buf: Vec<u8>,
}

impl Client {
    pub async fn connect(addr: SocketAddr) -> Client {
        let stream = TcpStream::connect(addr).await.expect("connect");
        Client {
            stream,
            buf: Vec::new(),
        }
    }

    pub async fn send(&mut self, bytes: &[u8]) {
        self.stream.write_all(bytes).await.expect("send");
    }

    async fn fill(&mut self) -> usize {
        let mut chunk = vec![0u8; 65536];
        let n = tokio::time::timeout(TIMEOUT, self.stream.read(&mut chunk))
            .await
            .unwrap_or_else(|_| {
                panic!(
                    "timed out waiting for the server; received so far: {:?}",
                    String::from_utf8_lossy(&self.buf)
                )
            })
            .expect("read");
        self.buf.extend_from_slice(&chunk[..n]);
        n
    }

    /// Reads exactly `want.len()` bytes and asserts they are `want`.
    pub async fn expect(&mut self, want: &[u8]) {
        while self.buf.len() < want.len() {
            if self.fill().await == 0 {
                break;
            }
        }
        let got: Vec<u8> = self.buf.drain(..want.len().min(self.buf.len())).collect();
        assert_eq!(
            String::from_utf8_lossy(&got),
            String::from_utf8_lossy(want),
            "bytes on the wire differ"
        );
        assert_eq!(got, want);
    }

    /// One line including its line end.
    pub async fn line(&mut self) -> Vec<u8> {
        loop {
            if let Some(pos) = self.buf.iter().position(|&b| b == b'\n') {
                return self.buf.drain(..=pos).collect();
            }
            if self.fill().await == 0 {
                panic!(
                    "connection closed; partial: {:?}",
                    String::from_utf8_lossy(&self.buf)
                );
            }
        }
    }

    /// Bytes up to and including the first `stop` (or `end`, whichever
    /// comes first).
    pub async fn line_until(&mut self, stop: u8, end: u8) -> Vec<u8> {
        loop {
            if let Some(pos) = self.buf.iter().position(|&b| b == stop || b == end) {
                return self.buf.drain(..=pos).collect();
            }
            if self.fill().await == 0 {
                panic!("connection closed");
            }
        }
    }

    /// Exactly `n` bytes.
    pub async fn take(&mut self, n: usize) -> Vec<u8> {
        while self.buf.len() < n {
            if self.fill().await == 0 {
                panic!("connection closed");
            }
        }
        self.buf.drain(..n).collect()
    }

    /// Pauses briefly, so the server's output backs up.
    pub async fn slow_down(&mut self) {
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }

    /// Sends a WRITEFILE of `data` to `name` in one block and the closing
    /// zero block; returns the answer line.
    pub async fn writefile(&mut self, name: &str, data: &[u8]) -> String {
        let mut request = format!("WRITEFILE:{name}[{}]=", data.len()).into_bytes();
        request.extend_from_slice(data);
        request.extend_from_slice(format!("\r\nWRITEFILE:{name}[0]=\r\n").as_bytes());
        self.send(&request).await;
        String::from_utf8_lossy(&self.line().await).into_owned()
    }

    /// Sends a request and checks the whole answer.
    pub async fn ask(&mut self, request: &str, answer: &str) {
        self.send(request.as_bytes()).await;
        self.expect(answer.as_bytes()).await;
    }

    /// `LIST:`'s answer, the closing line too, each line ended by `\n`.
    pub async fn list(&mut self) -> String {
        self.send(b"LIST:\r\n").await;
        let mut list = String::new();
        loop {
            let line = String::from_utf8(self.line().await).unwrap();
            list.push_str(line.trim_end());
            list.push('\n');
            if line == "LIST:\r\n" {
                return list;
            }
        }
    }

    /// `GETINFO:`'s lines, without their line ends and the closing line.
    pub async fn getinfo(&mut self) -> Vec<String> {
        self.send(b"GETINFO:\r\n").await;
        let mut info = Vec::new();
        loop {
            let line = String::from_utf8(self.line().await).unwrap();
            if line == "GETINFO:\r\n" {
                return info;
            }
            info.push(line.trim_end().to_string());
        }
    }

    /// Asserts nothing arrives within `ms`.
    pub async fn silent(&mut self, ms: u64) {
        assert!(
            self.buf.is_empty(),
            "unexpected: {:?}",
            String::from_utf8_lossy(&self.buf)
        );
        let mut chunk = [0u8; 1024];
        if let Ok(result) =
            tokio::time::timeout(Duration::from_millis(ms), self.stream.read(&mut chunk)).await
        {
            let n = result.expect("read");
            panic!(
                "unexpected bytes: {:?}",
                String::from_utf8_lossy(&chunk[..n])
            );
        }
    }

    /// Waits for the server to close the connection (all data read first).
    pub async fn closed(&mut self) {
        loop {
            if self.fill().await == 0 {
                assert!(
                    self.buf.is_empty(),
                    "left over: {:?}",
                    String::from_utf8_lossy(&self.buf)
                );
                return;
            }
        }
    }

    /// One line including its line end, waiting at most `within` for it
    /// (`None` on timeout). For events slower than [`TIMEOUT`], e.g. a PLC
    /// coming back.
    pub async fn line_within(&mut self, within: Duration) -> Option<Vec<u8>> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            if let Some(pos) = self.buf.iter().position(|&b| b == b'\n') {
                return Some(self.buf.drain(..=pos).collect());
            }
            let mut chunk = vec![0u8; 65536];
            match tokio::time::timeout_at(deadline, self.stream.read(&mut chunk)).await {
                Err(_) => return None,
                Ok(Ok(0)) => panic!(
                    "connection closed; partial: {:?}",
                    String::from_utf8_lossy(&self.buf)
                ),
                Ok(Ok(n)) => self.buf.extend_from_slice(&chunk[..n]),
                Ok(Err(e)) => panic!("read: {e}"),
            }
        }
    }

    /// Reads lines until every one of `wants` has come, in any order,
    /// within `within` (values that come from different polls).
    pub async fn wait_for_lines(&mut self, wants: &[&[u8]], within: Duration) {
        let deadline = tokio::time::Instant::now() + within;
        let mut missing: Vec<&[u8]> = wants.to_vec();
        let mut skipped = Vec::new();
        while !missing.is_empty() {
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            match self.line_within(left).await {
                Some(line) => match missing.iter().position(|w| *w == line) {
                    Some(i) => {
                        missing.remove(i);
                    }
                    None => skipped.push(String::from_utf8_lossy(&line).into_owned()),
                },
                None => panic!(
                    "no {:?} within {within:?}; got {skipped:?}",
                    missing
                        .iter()
                        .map(|l| String::from_utf8_lossy(l).into_owned())
                        .collect::<Vec<_>>()
                ),
            }
        }
    }

    /// Reads lines until one equals `want`, within `within`; returns the
    /// lines skipped before it.
    pub async fn wait_for_line(&mut self, want: &[u8], within: Duration) -> Vec<Vec<u8>> {
        let deadline = tokio::time::Instant::now() + within;
        let mut skipped = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            match self.line_within(left).await {
                Some(line) if line == want => return skipped,
                Some(line) => skipped.push(line),
                None => panic!(
                    "no {:?} within {within:?}; got {:?}",
                    String::from_utf8_lossy(want),
                    skipped
                        .iter()
                        .map(|l| String::from_utf8_lossy(l).into_owned())
                        .collect::<Vec<_>>()
                ),
            }
        }
    }

    pub fn buffered(&self) -> &[u8] {
        &self.buf
    }
}

/// VmRSS of this process (the server runs in it), in KiB.
pub fn rss_kib() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS")
}

/// Open descriptors of this process.
pub fn fd_count() -> usize {
    std::fs::read_dir("/proc/self/fd").unwrap().count()
}

/// Starts the server as `plccoms -c` does, from the INI text `ini(port)` for
/// a server port that was free a moment ago. Concurrent tests take ports of
/// the same range for their own connections, so on "Address already in
/// use" another port is tried.
pub async fn start_on_free_port(
    ini: impl Fn(u16) -> String,
) -> (plccoms::startup::Server, u16, tempfile::TempDir) {
    for _ in 0..20 {
        let port = process::free_port();
        let conf = tempfile::tempdir().expect("config dir");
        let path = conf.path().join("PLCComS.ini");
        std::fs::write(&path, ini(port)).expect("write PLCComS.ini");
        let loaded = config::load(&path).expect("load PLCComS.ini");
        match plccoms::startup::start(&loaded.config).await {
            Ok(server) => return (server, port, conf),
            Err(e) if e.contains("Address already in use") => continue,
            Err(e) => panic!("start: {e}"),
        }
    }
    panic!("no free port for the server in 20 tries");
}

/// A server with the embedded simulated PLC running `pub_bytes` (or the
/// demo) in a fresh configuration folder, and `extra` keys for `[*]` and
/// the section.
pub async fn simulated(
    global: &str,
    section: &str,
    pub_bytes: Option<&[u8]>,
) -> (
    plccoms::startup::Server,
    std::net::SocketAddr,
    tempfile::TempDir,
) {
    let dir = tempfile::tempdir().unwrap();
    let sim_pub = match pub_bytes {
        Some(bytes) => {
            std::fs::write(dir.path().join("project.pub"), bytes).unwrap();
            "SIMULATOR_PUB = project.pub\n"
        }
        None => "",
    };
    let path = dir.path().join("PLCComS.ini");
    for _ in 0..20 {
        let port = process::free_port();
        std::fs::write(
            &path,
            format!(
                "[*]\nCOMM_LOOP_DELAY = 20\n{global}\n[PLC]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = demo\n\
                 {sim_pub}SERVER_PORT = {port}\nIPADDR_LOCAL = 127.0.0.1\nPUBFILE = //demo.pub\n{section}\n"
            ),
        )
        .unwrap();
        let loaded = plccoms_core::config::load(&path).unwrap();
        match plccoms::startup::start(&loaded.config).await {
            Ok(server) => {
                return (
                    server,
                    std::net::SocketAddr::from(([127, 0, 0, 1], port)),
                    dir,
                )
            }
            Err(e) if e.contains("Address already in use") => continue,
            Err(e) => panic!("{e}"),
        }
    }
    panic!("no free port");
}
