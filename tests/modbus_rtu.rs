//! Modbus RTU against a third-party device: pymodbus's serial server
//! (PyPI `pymodbus` with `pyserial`) on one end of a socat pty pair, the
//! real `plccoms` binary on the other; and pymodbus's TCP server with the
//! RTU framer, as a serial device server in RTU-over-TCP mode.
//!
//! A pty ignores baud, parity and RTS, and pymodbus frames by length, not
//! silence: the slow unit, the noise on the line and the unplugged adapter
//! are made by a small relay of ours between two pty pairs ([`Relay`]),
//! which delays, corrupts or drops the device's answers, or by unplugging
//! the pty pair the server's port is on.

mod common;

use std::collections::HashMap;
use std::io::{Read, Write};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::line::PtyLine;
use common::modbus::every_type::{self, TAGS};
use common::modbus::{until, Image, Pymodbus, RtuOn};
use common::process::{free_port, ServerProcess};
use common::Client;

/// Two registers, `v` (read-only by use) and `w` (written by the tests).
const SMALL_TAGS: &str = "name,type,table,address\nv,INT,holding,0\nw,INT,holding,1\n";

fn small(v: u16) -> Image {
    Image {
        holding: vec![(0, vec![v, 0])],
        ..Image::default()
    }
}

/// The server with one section per `(name, keys)`, each on its own client
/// port; the ports in order.
fn server(
    dir: &std::path::Path,
    tags: &str,
    sections: &[(&str, String)],
) -> (ServerProcess, Vec<u16>) {
    let tags_path = dir.join("tags.csv");
    std::fs::write(&tags_path, tags).expect("write tags");
    let mut ini = String::from("[*]\n");
    let mut ports = Vec::new();
    for (name, keys) in sections {
        let port = free_port();
        ports.push(port);
        ini.push_str(&format!(
            "[{name}]\n{keys}\nMODBUS_TAGS = {}\nSERVER_PORT = {port}\n",
            tags_path.display()
        ));
    }
    let last = *ports.last().expect("a section");
    (ServerProcess::with_config(&ini, last), ports)
}

fn rtu_keys(device: &str, unit: u8, timeout_ms: u32) -> String {
    format!(
        "PROTOCOL = MODBUS_RTU\nSERIAL_DEVICE = {device}\nSERIAL_SPEED = 115200\n\
         MODBUS_UNIT = {unit}\nMODBUS_TIMEOUT = {timeout_ms}"
    )
}

async fn client(port: u16) -> Client {
    Client::connect(std::net::SocketAddr::from(([127, 0, 0, 1], port))).await
}

#[tokio::test]
async fn every_type_and_order_on_a_serial_line() {
    let line = PtyLine::new();
    let image = every_type::image();
    let _device = Pymodbus::rtu(RtuOn::Serial(&line.plc_device()), &[(1, &image)]);
    let dir = tempfile::tempdir().unwrap();
    let (_server, ports) = server(
        dir.path(),
        TAGS,
        &[("M", rtu_keys(&line.server_device(), 1, 2000))],
    );
    let mut c = client(ports[0]).await;
    every_type::check(&mut c).await;
    c.ask("GETINFO:PROTOCOL\r\n", "GETINFO:PROTOCOL,MODBUS_RTU\r\n")
        .await;
}

#[tokio::test]
async fn three_units_on_one_line_one_absent_writes_land_on_their_unit() {
    let line = PtyLine::new();
    let (one, three) = (small(11), small(33));
    let _device = Pymodbus::rtu(RtuOn::Serial(&line.plc_device()), &[(1, &one), (3, &three)]);
    let dir = tempfile::tempdir().unwrap();
    let device = line.server_device();
    let (server, ports) = server(
        dir.path(),
        SMALL_TAGS,
        &[
            ("U1", rtu_keys(&device, 1, 300)),
            ("U2", rtu_keys(&device, 2, 300)),
            ("U3", rtu_keys(&device, 3, 300)),
            ("ALL", rtu_keys(&device, 0, 300)),
        ],
    );
    let (mut u1, mut u2, mut u3, mut all) = (
        client(ports[0]).await,
        client(ports[1]).await,
        client(ports[2]).await,
        client(ports[3]).await,
    );
    until(&mut u1, "GET:v", "GET:V,11", 20).await;
    until(&mut u3, "GET:v", "GET:V,33", 20).await;
    // Unit 2 is not on the line: its section is lost, the others are not.
    until(&mut u2, "GET:v", "ERROR:10 Unable to connect to PLC.", 20).await;
    for _ in 0..5 {
        u1.ask("GET:v\r\n", "GET:V,11\r\n").await;
        u3.ask("GET:v\r\n", "GET:V,33\r\n").await;
    }
    // Each write reaches its own unit only.
    u1.ask("SET:w,5\r\n", "DIFF:W,5\r\n").await;
    u3.ask("SET:w,7\r\n", "DIFF:W,7\r\n").await;
    u1.ask("GET:w\r\n", "GET:W,5\r\n").await;
    // A broadcast write (unit 0) reaches both, unanswered; it cannot be
    // read back (nobody answers unit 0).
    all.send(b"SET:w,9\r\n").await;
    // The write went out; its read-back is refused here (exception 1)
    // without line time, and SET reports that refusal.
    let answer = String::from_utf8(all.line().await).unwrap();
    assert_eq!(
        answer,
        "ERROR:81 Unable to set data in to address: 'W: Modbus exception 1 (illegal function)'\r\n"
    );
    until(&mut u1, "GET:w", "GET:W,9", 10).await;
    until(&mut u3, "GET:w", "GET:W,9", 10).await;
    let log = server.log();
    assert_eq!(log.matches("PLC lost").count(), 0, "{log}");
}

#[tokio::test]
async fn the_device_killed_and_back() {
    let line = PtyLine::new();
    let image = small(1234);
    let device = Pymodbus::rtu(RtuOn::Serial(&line.plc_device()), &[(1, &image)]);
    let dir = tempfile::tempdir().unwrap();
    let (server, ports) = server(
        dir.path(),
        SMALL_TAGS,
        &[("M", rtu_keys(&line.server_device(), 1, 300))],
    );
    let mut c = client(ports[0]).await;
    until(&mut c, "GET:v", "GET:V,1234", 20).await;
    drop(device);
    until(&mut c, "GET:v", "ERROR:10 Unable to connect to PLC.", 10).await;
    let _device = Pymodbus::rtu(RtuOn::Serial(&line.plc_device()), &[(1, &image)]);
    until(&mut c, "GET:v", "GET:V,1234", 40).await;
    let log = server.log();
    assert_eq!(log.matches("PLC lost").count(), 1, "{log}");
    assert_eq!(log.matches("PLC connected again").count(), 1, "{log}");
}

#[tokio::test]
async fn rtu_over_tcp_several_sections_share_one_connection() {
    let port = free_port();
    let (one, three) = (small(11), small(33));
    let device = Pymodbus::rtu(RtuOn::Tcp(port), &[(1, &one), (3, &three)]);
    let dir = tempfile::tempdir().unwrap();
    let keys = |unit: u8| {
        format!(
            "PROTOCOL = MODBUS_RTU_TCP\nIPADDR = 127.0.0.1\nMODBUS_PORT = {port}\n\
             MODBUS_UNIT = {unit}\nMODBUS_TIMEOUT = 1000"
        )
    };
    let (_server, ports) = server(dir.path(), SMALL_TAGS, &[("U1", keys(1)), ("U3", keys(3))]);
    let (mut u1, mut u3) = (client(ports[0]).await, client(ports[1]).await);
    until(&mut u1, "GET:v", "GET:V,11", 20).await;
    until(&mut u3, "GET:v", "GET:V,33", 20).await;
    u1.ask("SET:w,5\r\n", "DIFF:W,5\r\n").await;
    u3.ask("SET:w,7\r\n", "DIFF:W,7\r\n").await;
    u1.ask("GET:w\r\n", "GET:W,5\r\n").await;
    for _ in 0..5 {
        u1.ask("GET:v\r\n", "GET:V,11\r\n").await;
        u3.ask("GET:v\r\n", "GET:V,33\r\n").await;
    }
    assert_eq!(
        device.connections.load(std::sync::atomic::Ordering::SeqCst),
        1,
        "both sections on one connection"
    );
}

/// What the relay does to a unit's answers.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fault {
    /// Held back this long.
    Delay(Duration),
    /// Every other answer of the unit has a byte flipped, and noise
    /// before it.
    Corrupt,
    /// Never passed on.
    Drop,
}

/// A relay between the server's pty pair (`near`, whose `plc` end it
/// holds) and the device's (`far`, whose `server` end it holds): requests
/// pass as they are, answers (by their first byte, the unit) meet the
/// fault set for their unit. It reopens an end that went away (unplugged).
struct Relay {
    faults: Arc<Mutex<HashMap<u8, Fault>>>,
}

impl Relay {
    fn start(near: PathBuf, far: PathBuf) -> Relay {
        let faults: Arc<Mutex<HashMap<u8, Fault>>> = Arc::default();
        let near_out = Arc::new(Mutex::new(None::<std::fs::File>));
        let far_out = Arc::new(Mutex::new(None::<std::fs::File>));
        // Requests: near -> far.
        pump(near.clone(), near_out.clone(), far_out.clone(), None);
        // Answers: far -> near, with the faults.
        pump(far, far_out, near_out, Some(faults.clone()));
        Relay { faults }
    }

    fn set(&self, unit: u8, fault: Option<Fault>) {
        let mut faults = self.faults.lock().unwrap();
        match fault {
            Some(fault) => faults.insert(unit, fault),
            None => faults.remove(&unit),
        };
    }
}

/// Copies what `from` brings to the file in `to`, reopening `from` (and
/// publishing it in `mine` for the other direction) when it goes away.
fn pump(
    from: PathBuf,
    mine: Arc<Mutex<Option<std::fs::File>>>,
    to: Arc<Mutex<Option<std::fs::File>>>,
    faults: Option<Arc<Mutex<HashMap<u8, Fault>>>>,
) {
    std::thread::spawn(move || {
        // Per unit: the sections on the line poll in any order, and a
        // retry must meet the other half of its own unit's alternation.
        let mut flips: HashMap<u8, bool> = HashMap::new();
        loop {
            let Ok(mut reader) = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open(&from)
            else {
                std::thread::sleep(Duration::from_millis(20));
                continue;
            };
            *mine.lock().unwrap() = reader.try_clone().ok();
            let mut buf = [0u8; 512];
            loop {
                let n = match reader.read(&mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => n,
                };
                let mut bytes = buf[..n].to_vec();
                let fault = faults
                    .as_ref()
                    .and_then(|f| f.lock().unwrap().get(&bytes[0]).copied());
                let to = to.clone();
                let send = move |bytes: &[u8]| {
                    if let Some(file) = to.lock().unwrap().as_mut() {
                        let _ = file.write_all(bytes);
                    }
                };
                match fault {
                    None => send(&bytes),
                    Some(Fault::Drop) => {}
                    Some(Fault::Delay(delay)) => {
                        std::thread::spawn(move || {
                            std::thread::sleep(delay);
                            send(&bytes);
                        });
                    }
                    Some(Fault::Corrupt) => {
                        let flip = flips.entry(bytes[0]).or_default();
                        *flip = !*flip;
                        if *flip {
                            let last = bytes.len() - 1;
                            bytes[last / 2] ^= 0x5A;
                            let mut noisy = vec![0xFF, 0x00, 0x42];
                            noisy.extend_from_slice(&bytes);
                            send(&noisy);
                        } else {
                            send(&bytes);
                        }
                    }
                }
            }
            *mine.lock().unwrap() = None;
            std::thread::sleep(Duration::from_millis(20));
        }
    });
}

/// Units 1 and 3 behind the relay, a section for each.
struct Bench {
    near: PtyLine,
    relay: Relay,
    server: ServerProcess,
    u1: Client,
    u3: Client,
    _far: PtyLine,
    _device: Pymodbus,
    _dir: tempfile::TempDir,
}

async fn behind_relay(timeout_ms: u32) -> Bench {
    let near = PtyLine::new();
    let far = PtyLine::new();
    let relay = Relay::start(near.plc.clone(), far.server.clone());
    let device = Pymodbus::rtu(
        RtuOn::Serial(&far.plc_device()),
        &[(1, &small(11)), (3, &small(33))],
    );
    let dir = tempfile::tempdir().unwrap();
    let serial = near.server_device();
    let (server, ports) = server(
        dir.path(),
        SMALL_TAGS,
        &[
            ("U1", rtu_keys(&serial, 1, timeout_ms)),
            ("U3", rtu_keys(&serial, 3, timeout_ms)),
        ],
    );
    let (mut u1, mut u3) = (client(ports[0]).await, client(ports[1]).await);
    until(&mut u1, "GET:v", "GET:V,11", 20).await;
    until(&mut u3, "GET:v", "GET:V,33", 20).await;
    Bench {
        near,
        relay,
        server,
        u1,
        u3,
        _far: far,
        _device: device,
        _dir: dir,
    }
}

#[tokio::test]
async fn a_slow_unit_costs_only_its_own_time() {
    let mut b = behind_relay(300).await;
    // Unit 3 answers late but within its timeout: both units keep their
    // values. (An answer later than the timeout is taken by the retry, or
    // by the next request of the same unit: RTU has no transaction ids. A
    // unit that does not answer at all: the next test.)
    b.relay
        .set(3, Some(Fault::Delay(Duration::from_millis(200))));
    for _ in 0..10 {
        b.u1.ask("GET:v\r\n", "GET:V,11\r\n").await;
        b.u3.ask("GET:v\r\n", "GET:V,33\r\n").await;
    }
    b.u3.ask("SET:w,3\r\n", "DIFF:W,3\r\n").await;
    b.u1.ask("SET:w,4\r\n", "DIFF:W,4\r\n").await;
    let log = b.server.log();
    assert_eq!(log.matches("PLC lost").count(), 0, "{log}");
}

#[tokio::test]
async fn noise_and_damaged_answers_are_dropped_never_taken() {
    let mut b = behind_relay(300).await;
    // Every other answer damaged, with noise before it: the retry gets the
    // good one; no value is ever wrong.
    b.relay.set(1, Some(Fault::Corrupt));
    b.relay.set(3, Some(Fault::Corrupt));
    for _ in 0..20 {
        b.u1.ask("GET:v\r\n", "GET:V,11\r\n").await;
        b.u3.ask("GET:v\r\n", "GET:V,33\r\n").await;
    }
    b.u1.ask("SET:w,6\r\n", "DIFF:W,6\r\n").await;
    b.u3.ask("GET:w\r\n", "GET:W,0\r\n").await;
    let log = b.server.log();
    assert_eq!(log.matches("PLC lost").count(), 0, "{log}");
}

#[tokio::test]
async fn an_unplugged_adapter_is_found_again() {
    let mut b = behind_relay(300).await;
    b.near.unplug();
    until(&mut b.u1, "GET:v", "ERROR:10 Unable to connect to PLC.", 20).await;
    until(&mut b.u3, "GET:v", "ERROR:10 Unable to connect to PLC.", 20).await;
    b.near.plug();
    until(&mut b.u1, "GET:v", "GET:V,11", 20).await;
    until(&mut b.u3, "GET:v", "GET:V,33", 20).await;
}

#[tokio::test]
async fn a_unit_that_drops_every_answer_leaves_the_others_polling() {
    let mut b = behind_relay(300).await;
    b.relay.set(3, Some(Fault::Drop));
    until(&mut b.u3, "GET:v", "ERROR:10 Unable to connect to PLC.", 20).await;
    // Unit 1 keeps its values and takes writes while unit 3 is probed.
    for _ in 0..10 {
        b.u1.ask("GET:v\r\n", "GET:V,11\r\n").await;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    b.u1.ask("SET:w,4\r\n", "DIFF:W,4\r\n").await;
    b.relay.set(3, None);
    until(&mut b.u3, "GET:v", "GET:V,33", 20).await;
    let log = b.server.log();
    assert_eq!(log.matches("PLC lost").count(), 1, "{log}");
    assert_eq!(log.matches("PLC connected again").count(), 1, "{log}");
}

/// RS-485 direction on a GPIO pin (SERIAL_RTS): exported as an output, high
/// while a frame is on the line (the line time at 9600 baud: 9 ms for a
/// request, seen by a thread reading the pin), low after. The backend in
/// this process, its GPIO folder a temporary one.
#[tokio::test]
async fn rts_on_a_gpio_pin_is_high_while_sending() {
    use plccoms_core::driver::{PlcBackend, ReadRequest};
    use plccoms_driver_modbus::line::{Endpoint, SerialLine};
    use plccoms_driver_modbus::{ModbusBackend, ModbusConfig};
    use plccoms_protocol::Area;

    let line = PtyLine::new();
    let _device = Pymodbus::rtu(RtuOn::Serial(&line.plc_device()), &[(1, &small(5))]);
    let gpio = tempfile::tempdir().unwrap();
    std::fs::create_dir(gpio.path().join("gpio17")).unwrap();
    let value = gpio.path().join("gpio17/value");
    let mut serial = SerialLine::new(&line.server_device());
    serial.rts = Some(17);
    serial.gpio_root = gpio.path().to_path_buf();
    let mut config = ModbusConfig::new(std::net::SocketAddr::from(([0, 0, 0, 0], 0)));
    config.rtu = Some(Endpoint::Serial(serial));
    config.timeout = Duration::from_secs(2);
    let mut backend = ModbusBackend::new(config);

    let seen_high = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watcher = {
        let (seen_high, stop, value) = (seen_high.clone(), stop.clone(), value.clone());
        std::thread::spawn(move || {
            while !stop.load(std::sync::atomic::Ordering::SeqCst) {
                if std::fs::read_to_string(&value).is_ok_and(|v| v == "1") {
                    seen_high.store(true, std::sync::atomic::Ordering::SeqCst);
                }
                std::thread::sleep(Duration::from_micros(200));
            }
        })
    };
    backend.connect().await.expect("unit 1 answers");
    for _ in 0..10 {
        let read = ReadRequest {
            area: Area::R,
            offset: 0,
            len: 2,
        };
        let answers = backend.read(&[read]).await.expect("read");
        assert_eq!(answers, [Ok(vec![0, 5])]);
    }
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    watcher.join().unwrap();
    assert_eq!(
        std::fs::read_to_string(gpio.path().join("gpio17/direction")).unwrap(),
        "out"
    );
    assert_eq!(std::fs::read_to_string(&value).unwrap(), "0");
    assert!(
        seen_high.load(std::sync::atomic::Ordering::SeqCst),
        "RTS never seen high in 11 requests"
    );
}
