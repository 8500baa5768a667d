//! The simulated PLC: demo program, public-file changes, animation, the wire
//! side under malformed input, the control port and the plcsim binary, and
//! many devices in one simulator (`--devices`, `--change-rate`).

mod common;

use std::time::Duration;

use common::process::{free_port, free_ports};
use plccoms_core::driver::{PlcBackend, ReadRequest, WriteRequest};
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_plc::epsnet::codec::encode_packet;
use plccoms_plc::epsnet::frame::{DataFrame, Frame, Packet};
use plccoms_plc::epsnet::service::{Request, SETTID};
use plccoms_plc::pubfile;
use plccoms_plc::WriteData;
use plccoms_protocol::Area;
use plcsim::program::ProgramKind;
use plcsim::{PubSource, SimConfig, DEMO_PUB};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpStream, UdpSocket};

fn local() -> std::net::SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

fn backend(plc: std::net::SocketAddr) -> EpsnetBackend {
    let mut config = EpsnetConfig::new(plc);
    config.local_ip = "127.0.0.1".parse().unwrap();
    config.timeout = Duration::from_millis(300);
    EpsnetBackend::new(config)
}

fn var(file: &pubfile::PubFile, name: &str) -> ReadRequest {
    let v = file
        .vars
        .iter()
        .map(|def| &def.var)
        .find(|v| v.name.eq_ignore_ascii_case(name.as_bytes()))
        .unwrap_or_else(|| panic!("{name} in demo.pub"));
    ReadRequest {
        area: v.area,
        offset: v.offset,
        len: v.ty.size() as u32,
    }
}

async fn read(plc: &mut EpsnetBackend, r: ReadRequest) -> Vec<u8> {
    plc.read(&[r]).await.unwrap().pop().unwrap().unwrap()
}

fn f64_of(bytes: &[u8]) -> f64 {
    f64::from_le_bytes(bytes.try_into().unwrap())
}

#[test]
fn demo_pub_is_complete_and_its_crc_matches() {
    let file = pubfile::parse(DEMO_PUB);
    assert!(file.warnings.is_empty(), "{:?}", file.warnings);
    assert_eq!(
        file.crc,
        Some(pubfile::crc_of(pubfile::crc_content(DEMO_PUB)))
    );
    let on_disk = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/conf/demo.pub")).unwrap();
    assert_eq!(on_disk, DEMO_PUB);
    for name in [
        "dat", "tim", "sinus", "cosinus", "c", "positive", "text", "setpoint", "switch", "counter",
        "note",
    ] {
        var(&file, name);
    }
    let mut types: Vec<String> = file.vars.iter().map(|def| def.var.ty.to_string()).collect();
    types.sort();
    types.dedup();
    assert_eq!(
        types.len(),
        21,
        "every IEC type, two STRING sizes: {types:?}"
    );
    assert!(file.vars.iter().any(|def| def.var.name.contains(&0xEC)));
    let fixed = pubfile::parse(plcsim::FIXED_PUB);
    assert_eq!(fixed.vars.len(), 2);
}

#[tokio::test]
async fn demo_program_runs_by_name_and_stops_in_halt() {
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        cycle: Duration::from_millis(5),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let file = pubfile::parse(DEMO_PUB);
    let mut plc = backend(sim.local_addr());
    tokio::time::sleep(Duration::from_millis(50)).await;
    let text = read(&mut plc, var(&file, "text")).await;
    assert!(text.starts_with(b"Have a nice day\0"));
    let c1 = f64_of(&read(&mut plc, var(&file, "c")).await);
    assert!(c1 > 0.0);
    let sinus = f64_of(&read(&mut plc, var(&file, "sinus")).await);
    assert!(sinus > 0.0 && sinus < 1.0);
    let positive = read(&mut plc, var(&file, "positive")).await;
    assert_eq!(positive[0] & 1, 1);
    let dat = f64_of(&read(&mut plc, var(&file, "dat")).await);
    assert_eq!(dat % 86_400.0, 0.0);
    assert!(dat > 1.7e9);
    let crc = read(
        &mut plc,
        ReadRequest {
            area: Area::S,
            offset: 70,
            len: 4,
        },
    )
    .await;
    assert_eq!(
        u32::from_le_bytes(crc.try_into().unwrap()),
        file.crc.unwrap()
    );

    sim.halt();
    tokio::time::sleep(Duration::from_millis(20)).await;
    let frozen = read(&mut plc, var(&file, "c")).await;
    tokio::time::sleep(Duration::from_millis(40)).await;
    assert_eq!(read(&mut plc, var(&file, "c")).await, frozen);
    sim.run();
    tokio::time::sleep(Duration::from_millis(40)).await;
    assert_ne!(read(&mut plc, var(&file, "c")).await, frozen);
}

#[tokio::test]
async fn another_pub_file_changes_pf_crc_and_animation_follows_it() {
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        program: ProgramKind::Idle,
        animate: vec!["LEVEL*".into(), "Alarm".into()],
        cycle: Duration::from_millis(5),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let before = sim.pf_crc();
    let other = b" Level_1 R B 0 INT\r\n level_2 R F 4 REAL\r\n alarm R B 8 .3 BOOL\r\n quiet R B 10 INT\r\n";
    let crc = sim.load_pub(other);
    assert_ne!(crc, before);
    assert_eq!(crc, pubfile::crc_of(other));
    assert_eq!(sim.pf_crc(), crc);
    let mut plc = backend(sim.local_addr());
    let r = ReadRequest {
        area: Area::R,
        offset: 0,
        len: 12,
    };
    tokio::time::sleep(Duration::from_millis(30)).await;
    let a = read(&mut plc, r).await;
    tokio::time::sleep(Duration::from_millis(30)).await;
    let b = read(&mut plc, r).await;
    assert_ne!(a[0..2], b[0..2], "INT ramps");
    assert_ne!(a[4..8], b[4..8], "REAL moves");
    assert_eq!(a[8] & !0x08, 0, "only the BOOL's own bit");
    assert_eq!(&b[10..12], &[0, 0], "not animated");
}

#[tokio::test]
async fn malformed_datagrams_never_stop_the_plc() {
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        program: ProgramKind::Idle,
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let socket = UdpSocket::bind(local()).await.unwrap();
    socket.connect(sim.local_addr()).await.unwrap();
    let good = encode_packet(&Packet {
        mesi: 77,
        frames: vec![Request::Status.to_frame(0, 9)],
    })
    .unwrap();
    let mut junk: Vec<Vec<u8>> = vec![
        vec![],
        vec![0],
        vec![0, 1, 2, 0, 0xFF, 0xFF],
        vec![0xFF; 3000],
    ];
    for cut in 0..good.len() - 1 {
        junk.push(good[..cut].to_vec());
    }
    for i in 6..good.len() {
        let mut bad = good.clone();
        bad[i] ^= 0x5A;
        junk.push(bad);
    }
    for bytes in &junk {
        socket.send(bytes).await.unwrap();
    }
    // Unknown service and a bad SETTID get error bytes, in one datagram.
    let errors = encode_packet(&Packet {
        mesi: 78,
        frames: vec![
            Frame::Data(DataFrame {
                da: 0,
                sa: 9,
                fc: 0x63,
                data: vec![0x7F],
            }),
            Frame::Data(DataFrame {
                da: 0,
                sa: 9,
                fc: 0x63,
                data: vec![SETTID, 24, 13, 1, 0, 0, 0, 1],
            }),
        ],
    })
    .unwrap();
    socket.send(&errors).await.unwrap();
    socket.send(&good).await.unwrap();
    let mut buf = [0u8; 2048];
    let mut seen = Vec::new();
    while seen.len() < 2 {
        let n = tokio::time::timeout(Duration::from_secs(2), socket.recv(&mut buf))
            .await
            .expect("the PLC still answers")
            .unwrap();
        seen.push(plccoms_plc::epsnet::codec::decode_packet(&buf[..n]).unwrap());
    }
    let by_mesi = |m| seen.iter().find(|p| p.mesi == m).unwrap();
    let e = by_mesi(78);
    assert_eq!(e.frames.len(), 2);
    let byte = |f: &Frame| match f {
        Frame::Data(d) => d.data[1],
        Frame::Ack => 0,
    };
    assert_eq!(byte(&e.frames[0]), 0x02);
    assert_eq!(byte(&e.frames[1]), 0x0C);
    assert_eq!(by_mesi(77).frames.len(), 1);
}

#[tokio::test]
async fn settid_sets_the_plc_clock() {
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        cycle: Duration::from_millis(5),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let mut plc = backend(sim.local_addr());
    let t = plccoms_plc::epsnet::service::PlcTime {
        year: 2030,
        month: 6,
        day: 1,
        hour: 12,
        minute: 0,
        second: 0,
        weekday: 6,
    };
    assert_eq!(plc.set_time(t).await.unwrap(), Ok(()));
    tokio::time::sleep(Duration::from_millis(30)).await;
    let file = pubfile::parse(DEMO_PUB);
    let dat = f64_of(&read(&mut plc, var(&file, "dat")).await);
    let days = plccoms_plc::time::days_from_civil(2030, 6, 1);
    assert_eq!(dat, days as f64 * 86_400.0);
}

async fn control(stream: &mut BufReader<TcpStream>, line: &str) -> String {
    stream
        .get_mut()
        .write_all(format!("{line}\n").as_bytes())
        .await
        .unwrap();
    let mut answer = String::new();
    stream.read_line(&mut answer).await.unwrap();
    answer.trim_end().to_string()
}

/// A simulator of `config` on loopback with a control port, connected.
async fn with_control(config: SimConfig) -> (plcsim::SimHandle, BufReader<TcpStream>) {
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        control: Some(local()),
        ..config
    })
    .await
    .unwrap();
    let stream = TcpStream::connect(sim.control_addr().unwrap())
        .await
        .unwrap();
    (sim, BufReader::new(stream))
}

#[tokio::test]
async fn control_port_commands() {
    let dir = tempfile::tempdir().unwrap();
    let other = dir.path().join("other.pub");
    std::fs::write(&other, b" x R B 0 INT\n").unwrap();
    let (sim, mut c) = with_control(SimConfig {
        pubfile: PubSource::Bytes(DEMO_PUB.to_vec()),
        ..SimConfig::default()
    })
    .await;
    assert_eq!(control(&mut c, "halt").await, "OK");
    assert!(!sim.is_running());
    assert_eq!(control(&mut c, "run").await, "OK");
    assert!(sim.is_running());
    assert_eq!(control(&mut c, "loss 0.2").await, "OK");
    assert!(control(&mut c, "loss 2").await.starts_with("ERR"));
    assert_eq!(control(&mut c, "latency 0").await, "OK");
    assert_eq!(control(&mut c, "loss 0").await, "OK");
    assert_eq!(control(&mut c, "program idle").await, "OK");
    assert!(control(&mut c, "program chess").await.starts_with("ERR"));
    let answer = control(&mut c, &format!("pub {}", other.display())).await;
    assert_eq!(
        answer,
        format!("OK crc={:08X}", pubfile::crc_of(b" x R B 0 INT\n"))
    );
    assert!(control(&mut c, "pub /nonexistent.pub")
        .await
        .starts_with("ERR"));
    assert!(control(&mut c, "fly")
        .await
        .starts_with("ERR unknown command"));
    assert!(control(&mut c, "status").await.starts_with("OK run crc="));
}

/// The control port of a plcsim process just started, once it listens.
async fn control_port_of_child(addr: std::net::SocketAddr) -> BufReader<TcpStream> {
    for _ in 0..200 {
        if let Ok(stream) = TcpStream::connect(addr).await {
            return BufReader::new(stream);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("plcsim control port {addr} did not open");
}

#[tokio::test]
async fn plcsim_binary_serves_and_obeys_its_control_port() {
    // Find two free loopback ports.
    let udp = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let udp_addr = udp.local_addr().unwrap();
    drop(udp);
    let tcp = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let tcp_addr = tcp.local_addr().unwrap();
    drop(tcp);
    let pub_path = concat!(env!("CARGO_MANIFEST_DIR"), "/conf/demo.pub");
    let fixed_path = concat!(env!("CARGO_MANIFEST_DIR"), "/conf/FIXED.pub");
    let mut child = tokio::process::Command::new(common::process::plcsim_bin())
        .args(["--bind", &udp_addr.to_string()])
        .args(["--control", &tcp_addr.to_string()])
        .args(["--pub", pub_path, "--fixed", fixed_path])
        .args([
            "--animate",
            "v_*",
            "--cycle",
            "5",
            "--loss",
            "0",
            "--latency",
            "0",
        ])
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut c = control_port_of_child(tcp_addr).await;
    let mut plc = backend(udp_addr);
    assert!(plc.connect().await.is_ok());
    assert_eq!(control(&mut c, "halt").await, "OK");
    assert!(!plc.status().await.unwrap().run);
    assert_eq!(control(&mut c, "run").await, "OK");
    assert!(plc.status().await.unwrap().run);
    child.start_kill().unwrap();
    let _ = child.wait().await;
}

// One simulator process, many devices (`plcsim --devices N`): each device
// its own memory on its own port (Modbus TCP also by unit id on the first
// port, EPSNET over UDP), all of them answering, one of them made dead
// through the control port, and the change rate the bench counts on.

/// One Modbus TCP transaction on `stream`: the answer's PDU.
async fn modbus(stream: &mut TcpStream, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut adu = vec![0, 1, 0, 0];
    adu.extend_from_slice(&(pdu.len() as u16 + 1).to_be_bytes());
    adu.push(unit);
    adu.extend_from_slice(pdu);
    stream.write_all(&adu).await.unwrap();
    let mut header = [0u8; 7];
    stream.read_exact(&mut header).await.unwrap();
    assert_eq!(header[6], unit, "answer from the unit asked");
    let len = u16::from_be_bytes([header[4], header[5]]) as usize - 1;
    let mut answer = vec![0u8; len];
    stream.read_exact(&mut answer).await.unwrap();
    answer
}

/// Holding register 0 of the device behind `stream` as `unit`.
async fn register0(stream: &mut TcpStream, unit: u8) -> u16 {
    let answer = modbus(stream, unit, &[3, 0, 0, 0, 1]).await;
    assert_eq!(answer[..2], [3, 2], "{answer:?}");
    u16::from_be_bytes([answer[2], answer[3]])
}

async fn set_register0(stream: &mut TcpStream, unit: u8, value: u16) {
    let [hi, lo] = value.to_be_bytes();
    assert_eq!(
        modbus(stream, unit, &[6, 0, 0, hi, lo]).await,
        [6, 0, 0, hi, lo]
    );
}

#[tokio::test]
async fn modbus_devices_have_their_own_memory_on_their_own_port_and_unit_id() {
    let sim = plcsim::spawn(SimConfig {
        modbus: Some(local()),
        program: ProgramKind::Idle,
        pubfile: PubSource::Bytes(plcsim::DEMO_TAGS.to_vec()),
        devices: 5,
        ..SimConfig::default()
    })
    .await
    .unwrap();
    assert_eq!(sim.devices(), 5);
    let addrs = sim.local_addrs();
    let mut ports: Vec<u16> = addrs.iter().map(std::net::SocketAddr::port).collect();
    ports.dedup();
    assert_eq!(ports.len(), 5);
    let mut streams = Vec::new();
    for addr in &addrs {
        streams.push(TcpStream::connect(addr).await.unwrap());
    }
    for (i, stream) in streams.iter_mut().enumerate() {
        set_register0(stream, 1, 100 + i as u16).await;
    }
    // A write to one device is not seen in another.
    for (i, stream) in streams.iter_mut().enumerate() {
        assert_eq!(register0(stream, 1).await, 100 + i as u16);
    }
    // The first port serves device k as unit id k, any other unit as device 0.
    let first = &mut streams[0];
    for k in 1..=5u8 {
        assert_eq!(register0(first, k).await, 99 + u16::from(k));
    }
    assert_eq!(register0(first, 77).await, 100);
    set_register0(first, 4, 7).await;
    assert_eq!(
        register0(&mut streams[3], 9).await,
        7,
        "any unit on its own port"
    );
    let device = sim.device_at(3).unwrap();
    assert_eq!(device.lock().unwrap().read(Area::R, 0, 2).unwrap(), [0, 7]);
    assert!(sim.device_at(5).is_none());
}

#[tokio::test]
async fn epsnet_plcs_have_their_own_memory_on_their_own_udp_port() {
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        program: ProgramKind::Idle,
        devices: 3,
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let mut plcs = Vec::new();
    for addr in sim.local_addrs() {
        let mut plc = backend(addr);
        plc.connect().await.unwrap();
        plcs.push(plc);
    }
    for (i, plc) in plcs.iter_mut().enumerate() {
        let written = plc
            .write(&[WriteRequest {
                area: Area::R,
                offset: 40,
                data: WriteData::Bytes(vec![i as u8 + 1; 4]),
            }])
            .await
            .unwrap();
        assert!(written.iter().all(Result::is_ok));
    }
    for (i, plc) in plcs.iter_mut().enumerate() {
        let read = plc
            .read(&[ReadRequest {
                area: Area::R,
                offset: 40,
                len: 4,
            }])
            .await
            .unwrap();
        assert_eq!(read[0].as_ref().unwrap(), &vec![i as u8 + 1; 4]);
        assert!(plc.status().await.unwrap().run);
    }
}

fn changes(status: &str) -> u64 {
    status
        .split_whitespace()
        .find_map(|w| w.strip_prefix("changes="))
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("changes= in {status}"))
}

#[tokio::test]
async fn plcsim_binary_serves_n_modbus_devices_and_one_can_be_made_dead() {
    const N: u16 = 16;
    let base = free_ports(N);
    let control_port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let tags = dir.path().join("tags.csv");
    let mut csv = String::from("name,type,table,address\n");
    for k in 0..10 {
        csv += &format!("t{k},INT,holding,{}\n", 10 + k);
    }
    std::fs::write(&tags, csv).unwrap();
    let mut child = tokio::process::Command::new(common::process::plcsim_bin())
        .args(["--modbus", &format!("127.0.0.1:{base}")])
        .args(["--devices", &N.to_string()])
        .args(["--control", &format!("127.0.0.1:{control_port}")])
        .args(["--tags", tags.to_str().unwrap()])
        .args([
            "--program",
            "idle",
            "--animate",
            "t*",
            "--change-rate",
            "0.5",
        ])
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut c = control_port_of_child(([127, 0, 0, 1], control_port).into()).await;
    // Every port answers, each its own device.
    let mut streams = Vec::new();
    for i in 0..N {
        let mut stream = TcpStream::connect(("127.0.0.1", base + i)).await.unwrap();
        set_register0(&mut stream, 1, 1000 + i).await;
        streams.push(stream);
    }
    for (i, stream) in streams.iter_mut().enumerate() {
        assert_eq!(register0(stream, 1).await, 1000 + i as u16);
    }
    let status = control(&mut c, "status").await;
    assert!(status.starts_with("OK run crc="), "{status}");
    assert!(status.contains(&format!("devices={N}")), "{status}");
    let first = changes(&status);
    // Device 7 dead (drops every request); its neighbours answer.
    assert_eq!(control(&mut c, "device 7 loss 1").await, "OK");
    assert!(control(&mut c, &format!("device {N} halt"))
        .await
        .starts_with("ERR no device"));
    let dead = &mut streams[7];
    let [hi, lo] = 5u16.to_be_bytes();
    dead.write_all(&[0, 9, 0, 0, 0, 6, 1, 6, 0, 0, hi, lo])
        .await
        .unwrap();
    let mut byte = [0u8; 1];
    let silent = tokio::time::timeout(Duration::from_millis(500), dead.read(&mut byte)).await;
    assert!(silent.is_err(), "a dead device answered");
    register0(&mut streams[6], 1).await;
    register0(&mut streams[8], 1).await;
    // The animation goes on counting its changes.
    let mut later = first;
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(50)).await;
        later = changes(&control(&mut c, "status").await);
        if later > first {
            break;
        }
    }
    assert!(later > first, "no changes counted: {first}, then {later}");
    child.start_kill().unwrap();
    let _ = child.wait().await;
}

#[tokio::test]
async fn control_commands_for_one_device_or_all_and_bad_ones_refused() {
    let (sim, mut c) = with_control(SimConfig {
        program: ProgramKind::Idle,
        devices: 3,
        ..SimConfig::default()
    })
    .await;
    let run = |i: usize| sim.device_at(i).unwrap().lock().unwrap().run();
    assert_eq!(control(&mut c, "device 1 halt").await, "OK");
    assert!(run(0) && !run(1) && run(2));
    assert_eq!(control(&mut c, "halt").await, "OK");
    assert!(!run(0) && !run(1) && !run(2));
    assert_eq!(control(&mut c, "DEVICE 2 run").await, "OK");
    assert!(!run(0) && !run(1) && run(2));
    for bad in [
        "device",
        "device x run",
        "device -1 run",
        "device 3 run",
        "device 99999999999999999999999 run",
        "device 0",
        "device 0 device 1 run",
        "device 0 loss 7",
    ] {
        let answer = control(&mut c, bad).await;
        assert!(answer.starts_with("ERR "), "{bad}: {answer}");
    }
    assert!(control(&mut c, "status")
        .await
        .contains(" devices=3 changes=0"));
    assert!(control(&mut c, "device 2 status")
        .await
        .contains(" devices=1 "));
}
