//! The simulated PLC: demo program, public-file changes, animation, the wire
//! side under malformed input, the control port and the plcsim binary.

mod common;

use std::time::Duration;

use plccoms_core::driver::{PlcBackend, ReadRequest};
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_plc::epsnet::codec::encode_packet;
use plccoms_plc::epsnet::frame::{DataFrame, Frame, Packet};
use plccoms_plc::epsnet::service::{Request, SETTID};
use plccoms_plc::pubfile;
use plccoms_protocol::Area;
use plcsim::program::ProgramKind;
use plcsim::{PubSource, SimConfig, DEMO_PUB};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
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

#[tokio::test]
async fn control_port_commands() {
    let dir = tempfile::tempdir().unwrap();
    let other = dir.path().join("other.pub");
    std::fs::write(&other, b" x R B 0 INT\n").unwrap();
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        control: Some(local()),
        pubfile: PubSource::Bytes(DEMO_PUB.to_vec()),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let stream = TcpStream::connect(sim.control_addr().unwrap())
        .await
        .unwrap();
    let mut c = BufReader::new(stream);
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
    let mut stream = None;
    for _ in 0..100 {
        if let Ok(s) = TcpStream::connect(tcp_addr).await {
            stream = Some(s);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut c = BufReader::new(stream.expect("plcsim control port"));
    let mut plc = backend(udp_addr);
    assert!(plc.connect().await.is_ok());
    assert_eq!(control(&mut c, "halt").await, "OK");
    assert!(!plc.status().await.unwrap().run);
    assert_eq!(control(&mut c, "run").await, "OK");
    assert!(plc.status().await.unwrap().run);
    child.start_kill().unwrap();
    let _ = child.wait().await;
}
