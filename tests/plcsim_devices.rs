//! One simulator process, many devices (`plcsim --devices N`): each device
//! its own memory on its own port (Modbus TCP also by unit id on the first
//! port, EPSNET over UDP), all of them answering, one of them made dead
//! through the control port, and the change rate the bench counts on.

mod common;

use std::net::{Ipv4Addr, SocketAddr};
use std::time::Duration;

use common::process::{free_port, plcsim_bin};
use plccoms_core::driver::{PlcBackend, ReadRequest, WriteRequest};
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_plc::WriteData;
use plccoms_protocol::Area;
use plcsim::program::ProgramKind;
use plcsim::{PubSource, SimConfig};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

fn local() -> SocketAddr {
    SocketAddr::from((Ipv4Addr::LOCALHOST, 0))
}

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
    let mut ports: Vec<u16> = addrs.iter().map(SocketAddr::port).collect();
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

fn epsnet(plc: SocketAddr) -> EpsnetBackend {
    let mut config = EpsnetConfig::new(plc);
    config.local_ip = "127.0.0.1".parse().unwrap();
    config.timeout = Duration::from_millis(300);
    EpsnetBackend::new(config)
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
        let mut plc = epsnet(addr);
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

/// `n` consecutive TCP ports on 127.0.0.1 that were free a moment ago, in
/// the tests' range (23000..32000; see `common::process::free_port`).
fn free_ports(n: u16) -> u16 {
    let mut seed = u64::from(free_port()) << 16 | u64::from(std::process::id() as u16);
    for _ in 0..5000 {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let base = 23_000 + ((seed >> 33) % u64::from(9_000 - n)) as u16;
        if (base..base + n).all(|p| std::net::TcpListener::bind((Ipv4Addr::LOCALHOST, p)).is_ok()) {
            return base;
        }
    }
    panic!("no {n} consecutive free ports");
}

async fn control(stream: &mut BufReader<TcpStream>, line: &str) -> String {
    let command = format!("{line}\n");
    stream
        .get_mut()
        .write_all(command.as_bytes())
        .await
        .unwrap();
    let mut answer = String::new();
    stream.read_line(&mut answer).await.unwrap();
    answer.trim_end().to_string()
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
    let mut child = tokio::process::Command::new(plcsim_bin())
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
    let mut stream = None;
    for _ in 0..200 {
        if let Ok(s) = TcpStream::connect(("127.0.0.1", control_port)).await {
            stream = Some(s);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut c = BufReader::new(stream.expect("plcsim control port"));
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
    let sim = plcsim::spawn(SimConfig {
        bind: local(),
        control: Some(local()),
        program: ProgramKind::Idle,
        devices: 3,
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let stream = TcpStream::connect(sim.control_addr().unwrap())
        .await
        .unwrap();
    let mut c = BufReader::new(stream);
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
