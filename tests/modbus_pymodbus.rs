//! The Modbus backend against a third-party device: pymodbus's server,
//! started by the test with a known register image (every address outside
//! it answers exception 2). Every type, every word order, register bits,
//! coils, discrete and input registers, scale, TS48, STRING, exceptions,
//! one bad tag among good ones, and the device killed and restarted; all
//! through the line protocol of the real `plccoms` binary.

mod common;

use std::time::Duration;

use common::modbus::{modbus_server, until, words, Image, Pymodbus};
use common::process::free_port;
use common::Client;

use common::modbus::every_type::{self, image, TAGS};

#[tokio::test]
async fn every_type_order_and_table() {
    let device = Pymodbus::start(free_port(), &image());
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(dir.path(), device.port, TAGS, "MODBUS_TIMEOUT = 2000");
    let mut c = Client::connect(server.addr).await;
    every_type::check(&mut c).await;

    let info = c.getinfo().await;
    for want in [
        "GETINFO:PROTOCOL,MODBUS_TCP".to_string(),
        "GETINFO:IPADDR,127.0.0.1".into(),
        format!("GETINFO:MODBUS_PORT,{}", device.port),
        "GETINFO:MODBUS_UNIT,1".into(),
        "GETINFO:MODBUS_TAGS,2/33 [tags.csv]".into(),
    ] {
        assert!(info.contains(&want), "{want} not in {info:?}");
    }
    // Nothing of EPSNET's: no EPSNET version, address or port, no
    // FIXED.pub.
    for epsnet in ["VERSION_EPSNET", "EPSADDR", "EPSPORT", "PUBFILE"] {
        let key = format!("GETINFO:{epsnet},");
        assert!(!info.iter().any(|l| l.starts_with(&key)), "{info:?}");
    }
    assert!(!info.iter().any(|l| l.contains("FIXED")), "{info:?}");
    // Asked by name, PUBFILE names the tag file, as SETCONF:pubfile does.
    c.ask("GETINFO:pubfile\r\n", "GETINFO:PUBFILE,2/33 [tags.csv]\r\n")
        .await;
}

/// What an S7-1200 user behind MB_SERVER found: `scale 0.1` printed 22.3
/// as 22.299999, and `Temperature,REAL,holding,40001` was refused with
/// "illegal data address" and no hint. Now: the value as written (or
/// with the tag file's decimals), and the hint at load and at the refusal.
#[tokio::test]
async fn scaled_values_print_as_meant_and_a_reference_is_explained() {
    let mut h = vec![223, 223, 1234];
    h.extend(words(&22.3f32.to_be_bytes()));
    let image = Image {
        holding: vec![(0, h)],
        ..Image::default()
    };
    let device = Pymodbus::start(free_port(), &image);
    let dir = tempfile::tempdir().unwrap();
    let tags = "name,type,table,address,scale,decimals\n\
                tenths,INT,holding,0,0.1\n\
                two,INT,holding,1,0.1,2\n\
                milli,INT,holding,2,0.001\n\
                real,REAL,holding,3,,1\n\
                Temperature,REAL,holding,40001\n";
    let server = modbus_server(dir.path(), device.port, tags, "");
    let mut c = Client::connect(server.addr).await;
    for (request, answer) in [
        ("GET:tenths", "GET:TENTHS,22.3"),
        ("GET:two", "GET:TWO,22.30"),
        ("GET:milli", "GET:MILLI,1.234"),
        ("GET:real", "GET:REAL,22.3"),
        ("LIST:tenths", "LIST:TENTHS,LREAL*\r\nLIST:"),
        ("LIST:real", "LIST:REAL,REAL*\r\nLIST:"),
        ("SET:tenths,22.4", "DIFF:TENTHS,22.4"),
        ("SET:two,-0.5", "DIFF:TWO,-0.50"),
        (
            "GET:temperature",
            "ERROR:80 Unable to get data from address: \
             'TEMPERATURE: Modbus exception 2 (illegal data address)'",
        ),
        (
            "SET:temperature,20",
            "ERROR:81 Unable to set data in to address: \
             'TEMPERATURE: Modbus exception 2 (illegal data address)'",
        ),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    // Polled: the DIFF carries the same text as GET.
    c.ask(
        "EN:tenths\r\n",
        "WARNING:252 Changed active variables in public file: '[3/7]'\r\n",
    )
    .await;
    c.expect(b"DIFF:TENTHS,22.4\r\n").await;
    c.ask(
        "EN:temperature\r\n",
        "WARNING:252 Changed active variables in public file: '[4/7]'\r\n",
    )
    .await;

    let hint = "holding 40001 looks like the 1-based reference 40001, which is holding 0 \
                (addresses are 0-based)";
    let log = server
        .log_with(&format!(
            "TEMPERATURE: the PLC refuses to read it (Modbus exception 2 (illegal data address)); \
             polled alone, the others go on; {hint}"
        ))
        .await;
    for want in [
        format!("tag file tags.csv: line 6, column 4: {hint}; the tag loads as written"),
        format!(
            "write of holding 40001 refused: Modbus exception 2 (illegal data address); {hint}"
        ),
        "tag file loaded: tags.csv".to_string(),
    ] {
        assert!(log.contains(&want), "{want:?} not in the log:\n{log}");
    }
    // A refusal that is not about an address like a reference has no hint.
    assert_eq!(log.matches("looks like").count(), 3, "{log}");
    for epsnet in ["public file", "FIXED.pub", "program"] {
        assert!(!log.contains(epsnet), "{epsnet:?} in the log:\n{log}");
    }
}

#[tokio::test]
async fn one_bad_tag_among_good_ones_is_left_out_and_the_rest_polls() {
    let device = Pymodbus::start(free_port(), &image());
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(dir.path(), device.port, TAGS, "");
    let mut watcher = Client::connect(server.addr).await;
    watcher
        .ask(
            "EN:*\r\n",
            "WARNING:252 Changed active variables in public file: '[33/33]'\r\n",
        )
        .await;
    // One DIFF per tag that reads, MISSING's neighbours included.
    let mut seen = std::collections::BTreeSet::new();
    while seen.len() < 32 {
        let line = String::from_utf8(watcher.line().await).unwrap();
        let name = line
            .strip_prefix("DIFF:")
            .and_then(|rest| rest.split(',').next())
            .unwrap_or_else(|| panic!("unexpected {line:?}"))
            .to_string();
        assert_ne!(name, "MISSING");
        if name == "AFTER" {
            assert_eq!(line, "DIFF:AFTER,77\r\n");
        }
        seen.insert(name);
    }
    // Polling goes on: another client's SET reaches the watcher.
    let mut writer = Client::connect(server.addr).await;
    writer.ask("SET:rw_int,7\r\n", "DIFF:RW_INT,7\r\n").await;
    let lines = watcher
        .wait_for_line(b"DIFF:RW_INT,7\r\n", Duration::from_secs(5))
        .await;
    assert!(lines.iter().all(|l| !l.starts_with(b"DIFF:MISSING")));
    let log = server.log();
    assert!(
        log.contains(
            "MISSING: the PLC refuses to read it (Modbus exception 2 (illegal data address)); \
             polled alone, the others go on"
        ),
        "{log}"
    );
    assert_eq!(
        log.matches("the PLC refuses to read it").count(),
        1,
        "{log}"
    );
}

#[tokio::test]
async fn the_device_killed_and_restarted() {
    let port = free_port();
    let small = Image {
        holding: vec![(0, vec![1234])],
        ..Image::default()
    };
    let device = Pymodbus::start(port, &small);
    let dir = tempfile::tempdir().unwrap();
    let tags = "name,type,table,address\nvalue,INT,holding,0\n";
    let server = modbus_server(dir.path(), port, tags, "MODBUS_TIMEOUT = 300");
    let mut c = Client::connect(server.addr).await;
    c.ask(
        "EN:value\r\n",
        "WARNING:252 Changed active variables in public file: '[3/3]'\r\n",
    )
    .await;
    c.expect(b"DIFF:VALUE,1234\r\n").await;

    drop(device);
    // Lost: requests are refused at once.
    until(
        &mut c,
        "GET:__plc_run",
        "ERROR:10 Unable to connect to PLC.",
        10,
    )
    .await;
    let _device = Pymodbus::start(port, &small);
    until(&mut c, "GET:value", "GET:VALUE,1234", 40).await;
    let log = server.log();
    assert_eq!(log.matches("PLC lost").count(), 1, "{log}");
    assert_eq!(log.matches("PLC connected again").count(), 1, "{log}");
}
