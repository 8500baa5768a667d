//! The Modbus backend against `plcsim --modbus` (the simulator's Modbus TCP
//! device, in process, with its demo program): packet loss and latency,
//! pipelined transactions, a tag file edited under a running section, the
//! embedded simulator (`SIMULATOR = Yes`), and a device that sends late and
//! foreign answers.

mod common;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use common::modbus::{modbus_server, until};
use common::process::ServerProcess;
use common::Client;
use plccoms_core::driver::{PlcBackend, ReadRequest};
use plccoms_core::metrics::BackendCounters;
use plccoms_driver_modbus::{ModbusBackend, ModbusConfig};
use plccoms_plc::modbus::codec::{decode_request, encode_response, AduDecoder, Header};
use plccoms_plc::modbus::frame::Response;
use plccoms_protocol::Area;
use plcsim::{PubSource, SimConfig, SimHandle, DEMO_TAGS};
use tokio::io::AsyncWriteExt;

/// `plcsim --modbus` with the demo program on its demo tags.
async fn device(loss: f64, latency: Duration) -> SimHandle {
    spawn(SimConfig {
        pubfile: PubSource::Bytes(DEMO_TAGS.to_vec()),
        loss,
        latency,
        seed: Some(7),
        ..SimConfig::default()
    })
    .await
}

/// `plcsim --modbus` on 127.0.0.1 as `config` asks.
async fn spawn(config: SimConfig) -> SimHandle {
    plcsim::spawn(SimConfig {
        modbus: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
        ..config
    })
    .await
    .expect("plcsim")
}

fn tags() -> String {
    String::from_utf8(DEMO_TAGS.to_vec()).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn values_and_writes_survive_loss_and_latency() {
    let sim = device(0.1, Duration::from_millis(10)).await;
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(
        dir.path(),
        sim.local_addr().port(),
        &tags(),
        "MODBUS_TIMEOUT = 300",
    );
    let mut watcher = Client::connect(server.addr).await;
    watcher.send(b"EN:sinus\r\n").await;
    let mut sinus = std::collections::BTreeSet::new();
    while sinus.len() < 5 {
        let line = watcher.line().await;
        if line.starts_with(b"DIFF:SINUS,") {
            sinus.insert(line);
        }
    }
    // Every SET is answered: with the value read back, or an error when
    // both attempts of a transaction were lost; never with silence.
    let mut c = Client::connect(server.addr).await;
    let mut last = None;
    for i in 0..20 {
        let value = format!("{}.5", i);
        c.send(format!("SET:setpoint,{value}\r\n").as_bytes()).await;
        let line = String::from_utf8(c.line().await).unwrap();
        if line == format!("DIFF:SETPOINT,{value}00000\r\n") {
            last = Some(value);
        } else {
            assert!(line.starts_with("ERROR:"), "{line:?}");
        }
    }
    let last = last.expect("some SET got through 10 % loss");
    sim.set_loss(0.0);
    until(
        &mut c,
        "GET:setpoint",
        &format!("GET:SETPOINT,{last}00000"),
        20,
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pipelined_transactions_under_latency() {
    let sim = device(0.0, Duration::from_millis(30)).await;
    // 40 registers, read 4 at a time: 10 transactions, 4 in flight.
    let mut tags = String::from("name,type,table,address\n");
    for i in 0..40 {
        tags.push_str(&format!("r{i},UINT,holding,{}\n", 100 + i));
    }
    {
        let device = sim.device();
        let mut device = device.lock().unwrap();
        for i in 0..40u32 {
            let offset = 2 * (100 + i);
            device.image.area_mut(Area::R)[offset as usize..offset as usize + 2]
                .copy_from_slice(&(1000 + i as u16).to_be_bytes());
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(
        dir.path(),
        sim.local_addr().port(),
        &tags,
        "MODBUS_INFLIGHT = 4\nMODBUS_MAX_REGS = 4",
    );
    let mut c = Client::connect(server.addr).await;
    c.send(b"GET:r*\r\n").await;
    for i in 0..40 {
        assert_eq!(
            String::from_utf8(c.line().await).unwrap(),
            format!("GET:R{i},{}\r\n", 1000 + i)
        );
    }
    c.expect(b"GET:\r\n").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edited_tag_file_is_loaded_with_settings_carried_over() {
    let sim = device(0.0, Duration::ZERO).await;
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(dir.path(), sim.local_addr().port(), &tags(), "");
    let mut c = Client::connect(server.addr).await;
    c.ask("SET:setpoint,1.5\r\n", "DIFF:SETPOINT,1.500000\r\n")
        .await;
    c.ask(
        "EN:setpoint\r\n",
        "WARNING:252 Changed active variables in public file: '[3/15]'\r\n",
    )
    .await;
    c.expect(b"DIFF:SETPOINT,1.500000\r\n").await;

    let mut edited = tags();
    edited.push_str("extra,INT,holding,60\n");
    std::fs::write(dir.path().join("tags.csv"), edited).unwrap();
    c.wait_for_line(
        b"WARNING:250 Changed public file: 'tags.csv'\r\n",
        Duration::from_secs(10),
    )
    .await;
    c.ask("GET:extra\r\n", "GET:EXTRA,0\r\n").await;
    // SETPOINT is still enabled: another client's SET reaches this one.
    let mut other = Client::connect(server.addr).await;
    other
        .ask("SET:setpoint,2.5\r\n", "DIFF:SETPOINT,2.500000\r\n")
        .await;
    c.wait_for_line(b"DIFF:SETPOINT,2.500000\r\n", Duration::from_secs(5))
        .await;
    // The log speaks of the tag file, not of a PLC program or public file.
    let want = "tag file tags.csv loaded: new variable table";
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let log = loop {
        let log = server.log();
        if log.contains(want) {
            break log;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{want:?} not in:\n{log}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(
        log.contains("tag file changed, reloading (__PF_CRC "),
        "{log}"
    );
    for epsnet in ["public file", "program", "FIXED.pub"] {
        assert!(!log.contains(epsnet), "{epsnet:?} in the log:\n{log}");
    }
}

#[tokio::test]
async fn simulator_yes_runs_a_modbus_device_inside_the_server() {
    let port = common::process::free_port();
    let ini = format!("[*]\n[M]\nPROTOCOL = MODBUS_TCP\nSIMULATOR = Yes\nSERVER_PORT = {port}\n");
    let server = ServerProcess::with_config(&ini, port);
    let mut c = Client::connect(server.addr).await;
    c.ask("GET:text\r\n", "GET:TEXT,\"Have a nice day\"\r\n")
        .await;
    c.ask("SET:switch,1\r\n", "DIFF:SWITCH,1\r\n").await;
    c.ask("GETINFO:protocol\r\n", "GETINFO:PROTOCOL,MODBUS_TCP\r\n")
        .await;
}

/// A device that answers every request with a foreign transaction id at
/// once, then correctly after `delay`, twice.
async fn double_talker(delay: Duration) -> SocketAddr {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        while let Ok((stream, _)) = listener.accept().await {
            tokio::spawn(async move {
                use futures::StreamExt;
                let (read, mut write) = stream.into_split();
                let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<Vec<u8>>();
                tokio::spawn(async move {
                    while let Some(bytes) = rx.recv().await {
                        let _ = write.write_all(&bytes).await;
                    }
                });
                let mut frames = tokio_util::codec::FramedRead::new(read, AduDecoder);
                while let Some(Ok(adu)) = frames.next().await {
                    let request = decode_request(&adu.pdu).unwrap();
                    let answer = Ok(Response::Registers(vec![0xBEEF]));
                    let encode = |header| {
                        let mut bytes = Vec::new();
                        encode_response(header, 3, Some(&request), &answer, &mut bytes);
                        bytes
                    };
                    let foreign = Header {
                        transaction: adu.header.transaction.wrapping_add(1000),
                        ..adu.header
                    };
                    let _ = tx.send(encode(foreign));
                    let real = encode(adu.header);
                    let tx = tx.clone();
                    tokio::spawn(async move {
                        tokio::time::sleep(delay).await;
                        let _ = tx.send(real.clone());
                        let _ = tx.send(real);
                    });
                }
            });
        }
    });
    addr
}

#[tokio::test]
async fn late_and_foreign_answers_are_dropped() {
    let addr = double_talker(Duration::from_millis(150)).await;
    let mut config = ModbusConfig::new(addr);
    config.timeout = Duration::from_millis(100);
    let mut backend = ModbusBackend::new(config);
    let counters = Arc::new(BackendCounters::default());
    backend.set_counters(counters.clone());
    backend.connect().await.expect("connect");
    for _ in 0..3 {
        let answers = backend
            .read(&[ReadRequest {
                area: Area::R,
                offset: 0,
                len: 2,
            }])
            .await
            .expect("read");
        assert_eq!(answers, vec![Ok(vec![0xBE, 0xEF])]);
    }
    // Each first attempt timed out and was sent again; its answer, late,
    // was taken, and every foreign or duplicate answer dropped.
    assert!(counters.retries.get() >= 4, "{}", counters.retries.get());
    assert!(counters.errors.get() >= 4, "{}", counters.errors.get());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sets_between_poll_slices_are_never_undone_by_the_poll() {
    // 400 registers read 2 at a time under 2 ms latency: a poll takes
    // hundreds of milliseconds, and SETs go between its slices.
    let mut tags = String::from("name,type,table,address\nvalue,UINT,holding,0\n");
    for i in 1..400 {
        tags.push_str(&format!("r{i},UINT,holding,{i}\n"));
    }
    let sim = spawn(SimConfig {
        pubfile: PubSource::Bytes(tags.clone().into_bytes()),
        program: plcsim::program::ProgramKind::Idle,
        latency: Duration::from_millis(2),
        ..SimConfig::default()
    })
    .await;
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(
        dir.path(),
        sim.local_addr().port(),
        &tags,
        "MODBUS_MAX_REGS = 2\nMODBUS_TIMEOUT = 2000",
    );
    let mut watcher = Client::connect(server.addr).await;
    watcher.send(b"EN:*\r\n").await;
    let mut writer = Client::connect(server.addr).await;
    for value in 1..=30u32 {
        writer
            .ask(
                &format!("SET:value,{value}\r\n"),
                &format!("DIFF:VALUE,{value}\r\n"),
            )
            .await;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The watcher's VALUE only ever goes up: no poll slice read before a
    // SET is published after it.
    let mut last = 0;
    loop {
        let line = String::from_utf8(watcher.line().await).unwrap();
        if let Some(value) = line.strip_prefix("DIFF:VALUE,") {
            let value: u32 = value.trim_end().parse().unwrap();
            assert!(value > last, "VALUE went from {last} back to {value}");
            last = value;
            if value == 30 {
                break;
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn setconf_pubfile_names_another_tag_file() {
    let sim = device(0.0, Duration::ZERO).await;
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(dir.path(), sim.local_addr().port(), &tags(), "");
    // In the configuration's folder: a client names files there (issue 19).
    let other = server.dir.path().join("other.csv");
    std::fs::write(
        &other,
        "name,type,table,address,bit,order\nonly,REAL,holding,26,,CDAB\n",
    )
    .unwrap();
    let mut c = Client::connect(server.addr).await;
    c.ask("SET:setpoint,4.5\r\n", "DIFF:SETPOINT,4.500000\r\n")
        .await;
    c.ask(
        "SETCONF:pubfile,other.csv\r\n",
        "WARNING:250 Changed public file: 'other.csv'\r\n",
    )
    .await;
    c.ask("GET:only\r\n", "GET:ONLY,4.500000\r\n").await;
    c.ask(
        "GET:setpoint\r\n",
        "ERROR:33 Unknown variable name in request: 'GET:setpoint'\r\n",
    )
    .await;
}
