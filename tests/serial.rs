//! EPSNET on a serial line: the server's SERIAL_DEVICE sections against the
//! simulated PLC on the other end of a real pty pair (socat), through the
//! real start-up path: the public file fetched over the line, LIST, GET,
//! SET, EN/DIFF, GETINFO and SETCONF of the line, the PLC halted and run
//! again, the cable pulled (the simulator stopped) and plugged back, the
//! adapter unplugged (the devices gone), and line noise — with the link
//! health rules of UDP: values never served past their freshness, errors at
//! once while the PLC is lost, and back within seconds.
//!
//! Bounds on times are generous (CI machines are slow and shared).

mod common;

use std::time::{Duration, Instant};

use common::health::{answer, is_link_error, outage, until};
use common::line::PtyLine;
use common::process::{plcsim_bin, ChildGuard};
use common::Client;
use plccoms_protocol::Area;
use plcsim::serial::SerialLine;
use plcsim::{SimConfig, SimHandle};

const SETPOINT: u32 = 124;
/// A PLC coming back: a probe, a connection, the public file.
const BACK: Duration = Duration::from_secs(20);

/// A folder serving `demo.pub` as the PLC's file system.
fn plc_files() -> tempfile::TempDir {
    let files = tempfile::tempdir().unwrap();
    std::fs::write(files.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    files
}

async fn spawn_sim(line: &PtyLine, files: &std::path::Path) -> SimHandle {
    plcsim::spawn(SimConfig {
        serial: Some(SerialLine {
            device: line.plc_device(),
            speed: 115_200,
            emulate: false,
        }),
        files: Some(files.to_path_buf()),
        program: "idle".parse().unwrap(),
        ..SimConfig::default()
    })
    .await
    .expect("spawn simulator on the line")
}

/// A section on the server's end of `line`; its public file comes from the
/// PLC over the line.
fn section(port: u16, device: &str, extra: &str) -> String {
    format!(
        "[*]\n[Line]\nSERIAL_DEVICE = {device}\nSERIAL_SPEED = 115200\nSERVER_PORT = {port}\n\
         PUBFILE = //demo.pub\n{extra}\n"
    )
}

fn poke(sim: &SimHandle, offset: u32, bytes: &[u8]) {
    common::epsnet::poke(sim, Area::R, offset, bytes);
}

fn peek(sim: &SimHandle, offset: u32, len: u32) -> Vec<u8> {
    common::epsnet::peek(sim, Area::R, offset, len)
}

#[tokio::test]
async fn commands_over_the_line_and_the_plc_halted_and_run() {
    let line = PtyLine::new();
    let files = plc_files();
    let sim = spawn_sim(&line, files.path()).await;
    poke(&sim, SETPOINT, &1.5f32.to_le_bytes());
    let device = line.server_device();
    let (server, port, _conf) = common::start_on_free_port(|port| section(port, &device, "")).await;
    let mut c = Client::connect(([127, 0, 0, 1], port).into()).await;
    // The public file came from the PLC, over the line.
    until(&mut c, "GET:setpoint\n", "GET:SETPOINT,1.500000\r\n", BACK).await;

    c.send(b"LIST:\n").await;
    let mut listed = Vec::new();
    loop {
        let line = String::from_utf8_lossy(&c.line().await).into_owned();
        if line == "LIST:\r\n" {
            break;
        }
        listed.push(line);
    }
    assert_eq!(listed.len(), 29, "{listed:?}");
    assert!(listed.contains(&"LIST:SETPOINT,REAL*\r\n".to_string()));

    c.ask("SET:setpoint,21.5\n", "DIFF:SETPOINT,21.500000\r\n")
        .await;
    assert_eq!(peek(&sim, SETPOINT, 4), 21.5f32.to_le_bytes());
    c.ask("SET:switch,1\n", "DIFF:SWITCH,1\r\n").await;
    assert_eq!(peek(&sim, 128, 1)[0] & 1, 1);

    c.ask(
        "EN:setpoint\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    c.expect(b"DIFF:SETPOINT,21.500000\r\n").await;
    poke(&sim, SETPOINT, &(-3.25f32).to_le_bytes());
    c.expect(b"DIFF:SETPOINT,-3.250000\r\n").await;

    let (info, _) = answer(&mut c, "GETINFO:serial_device\n").await;
    assert_eq!(info, format!("GETINFO:SERIAL_DEVICE,{device} 115200\r\n"));

    // HALT, then RUN: __PLC_RUN follows, and the link is made anew.
    c.send(b"EN:__plc_run\n").await;
    c.wait_for_line(b"DIFF:__PLC_RUN,1\r\n", BACK).await;
    sim.halt();
    c.wait_for_line(b"DIFF:__PLC_RUN,0\r\n", BACK).await;
    sim.run();
    c.wait_for_line(b"DIFF:__PLC_RUN,1\r\n", BACK).await;
    c.ask("SET:setpoint,4\n", "DIFF:SETPOINT,4.000000\r\n")
        .await;

    // SETCONF of the line: a new speed reconnects (a pty takes any), a
    // device where no PLC is changes nothing.
    let (same, _) = answer(&mut c, "SETCONF:serial_speed,9600\n").await;
    assert_eq!(same, "WARNING:251 Public file not changed: 'demo.pub'\r\n");
    let (info, _) = answer(&mut c, "GETINFO:serial_device\n").await;
    assert_eq!(info, format!("GETINFO:SERIAL_DEVICE,{device} 9600\r\n"));
    let (refused, _) = answer(&mut c, "SETCONF:serial_device,/nonexistent/tty\n").await;
    assert_eq!(refused, "ERROR:10 Unable to connect to PLC.\r\n");
    let (info, _) = answer(&mut c, "GETINFO:serial_device\n").await;
    assert_eq!(info, format!("GETINFO:SERIAL_DEVICE,{device} 9600\r\n"));
    c.ask("SET:setpoint,5\n", "DIFF:SETPOINT,5.000000\r\n")
        .await;
    drop(server);
}

/// The `plcsim` binary on the PLC's end of the line.
fn plcsim_process(line: &PtyLine, files: &std::path::Path) -> ChildGuard {
    ChildGuard::spawn(
        "plcsim",
        std::process::Command::new(plcsim_bin())
            .args(["--serial", &line.plc_device(), "--program", "idle"])
            .arg("--files")
            .arg(files)
            .env_remove("RUST_LOG")
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null()),
    )
}

#[tokio::test]
async fn cable_pulled_and_plugged_back_adapter_unplugged_and_back() {
    let mut line = PtyLine::new();
    let files = plc_files();
    let plc = plcsim_process(&line, files.path());
    let device = line.server_device();
    let (server, port, _conf) = common::start_on_free_port(|port| section(port, &device, "")).await;
    let mut c = Client::connect(([127, 0, 0, 1], port).into()).await;
    until(&mut c, "GET:setpoint\n", "GET:SETPOINT,0.000000\r\n", BACK).await;
    c.ask("SET:setpoint,7.5\n", "DIFF:SETPOINT,7.500000\r\n")
        .await;
    c.ask(
        "EN:setpoint\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    c.expect(b"DIFF:SETPOINT,7.500000\r\n").await;

    // The cable pulled: the line stays, nothing answers on it.
    drop(plc);
    let pulled = Instant::now();
    outage(
        &mut c,
        "GET:setpoint\n",
        "GET:SETPOINT,7.500000\r\n",
        pulled,
    )
    .await;
    let (refused, took) = answer(&mut c, "SET:setpoint,1\n").await;
    assert!(is_link_error(&refused), "{refused:?}");
    // At once, not after a timeout (EPSTOUT is 1 s here): the bound leaves
    // a loaded machine room without letting a timed-out request pass.
    assert!(
        took < Duration::from_millis(900),
        "SET refused after {took:?}"
    );

    // Plugged back: a fresh PLC (memory zero) answers within seconds.
    let plc = plcsim_process(&line, files.path());
    until(&mut c, "GET:setpoint\n", "GET:SETPOINT,0.000000\r\n", BACK).await;
    c.ask("SET:setpoint,2\n", "DIFF:SETPOINT,2.000000\r\n")
        .await;

    // The adapter unplugged: the server's device disappears, then comes
    // back under the same name.
    drop(plc);
    line.unplug();
    let pulled = Instant::now();
    outage(
        &mut c,
        "GET:setpoint\n",
        "GET:SETPOINT,2.000000\r\n",
        pulled,
    )
    .await;
    line.plug();
    let _plc = plcsim_process(&line, files.path());
    until(&mut c, "GET:setpoint\n", "GET:SETPOINT,0.000000\r\n", BACK).await;
    c.ask("SET:setpoint,3\n", "DIFF:SETPOINT,3.000000\r\n")
        .await;
    drop(server);
}

#[tokio::test]
async fn line_noise_never_yields_a_wrong_value() {
    let line = PtyLine::new();
    let files = plc_files();
    let sim = spawn_sim(&line, files.path()).await;
    let device = line.server_device();
    let (server, port, _conf) = common::start_on_free_port(|port| section(port, &device, "")).await;
    let mut c = Client::connect(([127, 0, 0, 1], port).into()).await;
    until(&mut c, "GET:setpoint\n", "GET:SETPOINT,0.000000\r\n", BACK).await;

    // One exchange in ten damaged (lost, cut, corrupted, after noise): the
    // retries carry most through; whatever is answered is right. At least
    // 30 SETs confirmed, and on until a bad answer and a retry were counted
    // (a few dozen exchanges may chance to have neither).
    sim.set_loss(0.1);
    let metrics = &server.sections[0].section.metrics().backend;
    let (mut good, mut errors) = (0, 0);
    let start = Instant::now();
    let mut i = 0u32;
    while good < 30 || metrics.errors.get() == 0 || metrics.retries.get() == 0 {
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "in 120 s: {good} SETs confirmed, {} bad answers and {} retries counted",
            metrics.errors.get(),
            metrics.retries.get()
        );
        i += 1;
        let value = f64::from(i) + 0.5;
        let (set, _) = answer(&mut c, &format!("SET:setpoint,{value}\n")).await;
        if set == format!("DIFF:SETPOINT,{value:.6}\r\n") {
            assert_eq!(peek(&sim, SETPOINT, 4), (value as f32).to_le_bytes());
            good += 1;
        } else {
            // Lost for a moment: refused at once until it is back.
            assert!(is_link_error(&set), "{set:?}");
            errors += 1;
            tokio::time::sleep(Duration::from_millis(200)).await;
            continue;
        }
        let (get, _) = answer(&mut c, "GET:setpoint\n").await;
        assert!(
            get == format!("GET:SETPOINT,{value:.6}\r\n") || is_link_error(&get),
            "{get:?} after SET {value}"
        );
    }
    println!("with 10 % damaged exchanges: {good} SETs confirmed, {errors} refused");

    // Every exchange damaged (only answers after mere noise get through,
    // and an attempt in four is such): the link fails soon, and still no
    // wrong value; the noise stops: back. (The last SET may have been
    // written but not read back: the PLC's value is the truth.) How soon it
    // fails is chance (an exchange survives both attempts 7 times in 16),
    // so the bound is generous.
    let value = f32::from_le_bytes(peek(&sim, SETPOINT, 4).try_into().unwrap());
    let right = format!("GET:SETPOINT,{value:.6}\r\n");
    sim.set_loss(1.0);
    let start = Instant::now();
    let mut failed = 0;
    while failed < 3 {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "every exchange damaged for 60 s, and {failed} errors"
        );
        let (get, _) = answer(&mut c, "GET:v_dint\n").await;
        if is_link_error(&get) {
            failed += 1;
        } else {
            assert_eq!(get, "GET:V_DINT,0\r\n");
        }
        let (get, _) = answer(&mut c, "GET:setpoint\n").await;
        assert!(get == right || is_link_error(&get), "{get:?}");
    }
    sim.set_loss(0.0);
    until(&mut c, "GET:setpoint\n", &right, BACK).await;
}
