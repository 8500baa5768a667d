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
        format!("{{\"port\": {port}, {}}}", self.tables())
    }

    /// The tables as JSON members, without braces.
    fn tables(&self) -> String {
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
            "\"coils\": {}, \"discrete\": {}, \"holding\": {}, \"input\": {}",
            bits(&self.coils),
            bits(&self.discrete),
            table(&self.holding),
            table(&self.input)
        )
    }
}

/// Where pymodbus serves Modbus RTU.
pub enum RtuOn<'a> {
    /// A tty: one end of a pty pair.
    Serial(&'a str),
    /// RTU frames over TCP on this port of 127.0.0.1.
    Tcp(u16),
}

/// pymodbus serving an [`Image`] on 127.0.0.1; killed when dropped.
pub struct Pymodbus {
    pub port: u16,
    /// TCP connections it accepted.
    pub connections: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    _child: ChildGuard,
}

impl Pymodbus {
    /// Starts the server on `port`; returns once it listens.
    pub fn start(port: u16, image: &Image) -> Pymodbus {
        Pymodbus::spawn(image.json(port), port)
    }

    /// Serves Modbus RTU as `units` (each its id and image), every other
    /// unit silent; returns once it serves.
    pub fn rtu(on: RtuOn<'_>, units: &[(u8, &Image)]) -> Pymodbus {
        let units: Vec<String> = units
            .iter()
            .map(|(unit, image)| format!("\"{unit}\": {{{}}}", image.tables()))
            .collect();
        let units = units.join(",");
        match on {
            RtuOn::Serial(tty) => Pymodbus::spawn(
                format!("{{\"serial\": \"{tty}\", \"units\": {{{units}}}}}"),
                0,
            ),
            RtuOn::Tcp(port) => Pymodbus::spawn(
                format!("{{\"port\": {port}, \"rtu\": true, \"units\": {{{units}}}}}"),
                port,
            ),
        }
    }

    fn spawn(json: String, port: u16) -> Pymodbus {
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
                .arg(&json)
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::null()),
        );
        let stdout = child.child().stdout.take().expect("stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        let connections = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = connections.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if line.starts_with("ready") {
                    let _ = tx.send(());
                } else if line == "connect" {
                    counted.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                }
            }
        });
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if rx.recv_timeout(Duration::from_millis(100)).is_ok() {
                break;
            }
            if let Some(status) = child.exited() {
                panic!("pymodbus exited ({status}) before serving {json}");
            }
            assert!(
                Instant::now() < deadline,
                "pymodbus did not serve {json} within 30 s"
            );
        }
        Pymodbus {
            port,
            connections,
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

/// A device with every type in every word order, every table, a missing
/// register, and the reads and writes that check them through the line
/// protocol: for any Modbus transport.
pub mod every_type {
    use super::{words, Image};
    use crate::common::Client;

    pub const TAGS: &str = "\
name,type,table,address,bit,order,scale,offset,access,unit,description
int_a,INT,holding,0
uint_a,UINT,holding,1
dint_a,DINT,holding,2
udint_cdab,UDINT,holding,4,,CDAB
real_badc,REAL,holding,6,,BADC
real_dcba,REAL,holding,8,,dcba
lreal_a,LREAL,holding,10
lint_cdab,LINT,holding,14,,CDAB
ulint_a,ULINT,holding,18
byte_a,BYTE,holding,22
sint_a,SINT,holding,23
stamp,TS48,holding,24
text5,STRING[5],holding,27
flag15,BOOL,holding,30,15
flag0,BOOL,holding,30,0
flag7,BOOL,holding,30,7
temp,INT,holding,31,,,0.1,-40,ro,°C,\"outdoor, north\"
time_a,TIME,holding,32
rw_int,INT,holding,34
rw_real,REAL,holding,35,,CDAB
rw_scaled,INT,holding,37,,,0.5
rw_word,UINT,holding,38,,,,,ro
rw_bit,BOOL,holding,38,3
missing,UINT,holding,40
after,UINT,holding,41
in_int,INT,input,0
in_real,REAL,input,1
coil0,BOOL,coil,0
coil1,BOOL,coil,1
di0,BOOL,discrete,0
di1,BOOL,discrete,1
";

    /// 2024-03-15 13:45:30.500 UTC in milliseconds.
    const STAMP_MS: u64 = 1_710_510_330_500;

    pub fn image() -> Image {
        let mut h: Vec<u16> = vec![0; 40];
        h[0] = (-1234i16) as u16;
        h[1] = 54321;
        h[2..4].copy_from_slice(&words(&(-100_000i32).to_be_bytes()));
        h[4..6].copy_from_slice(&[0x3344, 0x1122]);
        // 1.5 = 3F C0 00 00, bytes swapped within words.
        h[6..8].copy_from_slice(&[0xC03F, 0x0000]);
        // -2.5 little-endian: 00 00 20 C0.
        h[8..10].copy_from_slice(&words(&(-2.5f32).to_le_bytes()));
        h[10..14].copy_from_slice(&words(&std::f64::consts::PI.to_be_bytes()));
        let mut lint = words(&(-5_000_000_000i64).to_be_bytes());
        lint.reverse();
        h[14..18].copy_from_slice(&lint);
        h[18..22].copy_from_slice(&words(&12_345_678_901_234_567_890u64.to_be_bytes()));
        h[22] = 200;
        h[23] = (-5i16) as u16;
        h[24..27].copy_from_slice(&words(&STAMP_MS.to_be_bytes()[2..]));
        h[27..30].copy_from_slice(&words(b"Hello\0"));
        h[30] = 0x8001;
        h[31] = 650;
        h[32..34].copy_from_slice(&words(&123_456u32.to_be_bytes()));
        h[39] = 7;
        let mut input = vec![321u16];
        input.extend(words(&9.75f32.to_be_bytes()));
        Image {
            coils: vec![(0, vec![true, false, true])],
            discrete: vec![(0, vec![true, false])],
            // Register 40 does not exist.
            holding: vec![(0, h), (41, vec![77])],
            input: vec![(0, input)],
        }
    }

    /// Every read, then every write read back, then the refusals.
    pub async fn check(c: &mut Client) {
        let stamp_bits = (STAMP_MS as f64 / 1000.0).to_bits();
        for (request, answer) in [
            ("GET:int_a", "GET:INT_A,-1234".to_string()),
            ("GET:uint_a", "GET:UINT_A,54321".into()),
            ("GET:dint_a", "GET:DINT_A,-100000".into()),
            ("GET:udint_cdab", "GET:UDINT_CDAB,287454020".into()),
            ("GET:real_badc", "GET:REAL_BADC,1.500000".into()),
            ("GET:real_dcba", "GET:REAL_DCBA,-2.500000".into()),
            ("GET:lreal_a", "GET:LREAL_A,3.1415926536".into()),
            ("GET:lint_cdab", "GET:LINT_CDAB,-5000000000".into()),
            ("GET:ulint_a", "GET:ULINT_A,12345678901234567890".into()),
            ("GET:byte_a", "GET:BYTE_A,200".into()),
            ("GET:sint_a", "GET:SINT_A,-5".into()),
            ("GET:stamp", format!("GET:STAMP,{stamp_bits}")),
            ("GET:text5", "GET:TEXT5,\"Hello\"".into()),
            ("GET:flag15", "GET:FLAG15,1".into()),
            ("GET:flag0", "GET:FLAG0,1".into()),
            ("GET:flag7", "GET:FLAG7,0".into()),
            // Scaled: a double in its shortest form (650 x 0.1 - 40).
            ("GET:temp", "GET:TEMP,25".into()),
            ("GET:time_a", "GET:TIME_A,123456".into()),
            ("GET:in_int", "GET:IN_INT,321".into()),
            ("GET:in_real", "GET:IN_REAL,9.750000".into()),
            ("GET:coil0", "GET:COIL0,1".into()),
            ("GET:coil1", "GET:COIL1,0".into()),
            ("GET:di0", "GET:DI0,1".into()),
            ("GET:di1", "GET:DI1,0".into()),
            ("GET:after", "GET:AFTER,77".into()),
            (
                "GET:missing",
                "ERROR:80 Unable to get data from address: \
                 'MISSING: Modbus exception 2 (illegal data address)'"
                    .into(),
            ),
            ("LIST:temp", "LIST:TEMP,LREAL*\r\nLIST:".into()),
        ] {
            c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
                .await;
        }

        // Writes, each read back from the device.
        for (request, answer) in [
            ("SET:rw_int,-42", "DIFF:RW_INT,-42"),
            ("SET:rw_real,12.25", "DIFF:RW_REAL,12.250000"),
            ("SET:rw_scaled,10.5", "DIFF:RW_SCALED,10.5"),
            ("SET:rw_bit,1", "DIFF:RW_BIT,1"),
            ("GET:rw_word", "GET:RW_WORD,8"),
            ("SET:rw_bit,0", "DIFF:RW_BIT,0"),
            ("GET:rw_word", "GET:RW_WORD,0"),
            ("SET:coil1,1", "DIFF:COIL1,1"),
            ("GET:coil1", "GET:COIL1,1"),
            ("SET:text5,\"Hi\"", "DIFF:TEXT5,\"Hi\""),
            ("GET:text5", "GET:TEXT5,\"Hi\""),
            ("SET:flag7,1", "DIFF:FLAG7,1"),
            ("GET:flag15", "GET:FLAG15,1"),
            // The raw value 200000 does not fit an INT: nothing is written.
            (
                "SET:rw_scaled,100000",
                "ERROR:35 Wrong parameter value in request: 'SET:rw_scaled,100000'",
            ),
            ("GET:rw_scaled", "GET:RW_SCALED,10.5"),
            (
                "SET:text5,\"Too long\"",
                "ERROR:35 Wrong parameter value in request: 'SET:text5,\"Too long\"'",
            ),
            // Read-only: inputs, discrete inputs, access = ro.
            (
                "SET:in_int,5",
                "ERROR:30 Bad client request: 'SET:in_int,5'",
            ),
            ("SET:di0,0", "ERROR:30 Bad client request: 'SET:di0,0'"),
            ("SET:temp,20", "ERROR:30 Bad client request: 'SET:temp,20'"),
            // The device refuses a write to a register it lacks.
            (
                "SET:missing,1",
                "ERROR:81 Unable to set data in to address: \
                 'MISSING: Modbus exception 2 (illegal data address)'",
            ),
        ] {
            c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
                .await;
        }
    }
}
