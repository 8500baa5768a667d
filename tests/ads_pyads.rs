//! The ADS backend against pyads's test server (tests/ads/fixture.py, its
//! advanced handler extended where pyads falls short of a TwinCAT PLC):
//! symbol upload with structures and arrays, every type, sum reads by
//! handle, writes read back and refused, a symbol removed by a new program,
//! and the server restarted; all through the line protocol of the real
//! `plccoms` binary.

mod common;
#[path = "ads/fixture.rs"]
mod fixture;

use std::time::Duration;

use common::modbus::until;
use common::process::{free_port, ServerProcess};
use common::Client;
use fixture::{ads_ini, Fixture};

/// Past whatever lines a reload left (its WARNING:250, answers `until`
/// did not wait for).
async fn sync(c: &mut Client) {
    c.send(b"GET:__PLC_RUN\r\n").await;
    c.wait_for_line(b"GET:__PLC_RUN,1\r\n", Duration::from_secs(5))
        .await;
}

#[tokio::test]
async fn symbols_types_sums_writes_and_a_new_program() {
    let mut device = Fixture::start(0);
    let port = free_port();
    let server =
        ServerProcess::with_config(&ads_ini(device.port, port, "ADS_TIMEOUT = 2000"), port);
    let mut c = Client::connect(server.addr).await;
    until(&mut c, "GET:MAIN.vint", "GET:MAIN.VINT,-1234", 15).await;
    for (request, answer) in [
        ("GET:MAIN.vbool", "GET:MAIN.VBOOL,1"),
        ("GET:MAIN.vbyte", "GET:MAIN.VBYTE,18"),
        ("GET:MAIN.vword", "GET:MAIN.VWORD,48879"),
        ("GET:MAIN.vdword", "GET:MAIN.VDWORD,3735928559"),
        ("GET:MAIN.vlword", "GET:MAIN.VLWORD,1099511627776"),
        ("GET:MAIN.vsint", "GET:MAIN.VSINT,-5"),
        ("GET:MAIN.vusint", "GET:MAIN.VUSINT,250"),
        ("GET:MAIN.vuint", "GET:MAIN.VUINT,54321"),
        ("GET:MAIN.vdint", "GET:MAIN.VDINT,-123456"),
        ("GET:MAIN.vudint", "GET:MAIN.VUDINT,4000000000"),
        ("GET:MAIN.vlint", "GET:MAIN.VLINT,-1099511627776"),
        ("GET:MAIN.vulint", "GET:MAIN.VULINT,9223372036854775808"),
        ("GET:MAIN.vreal", "GET:MAIN.VREAL,1.500000"),
        ("GET:MAIN.vlreal", "GET:MAIN.VLREAL,-2.2500000000"),
        ("GET:MAIN.vstring", "GET:MAIN.VSTRING,\"Hello ADS\""),
        ("GET:MAIN.vtime", "GET:MAIN.VTIME,1500"),
        ("GET:MAIN.vtod", "GET:MAIN.VTOD,3723000"),
        ("GET:MAIN.vdate", "GET:MAIN.VDATE,1710460800"),
        ("GET:MAIN.vdt", "GET:MAIN.VDT,1710510330"),
        // A structure's fields, an array field's elements, an array.
        ("GET:MAIN.st.on", "GET:MAIN.ST.ON,1"),
        ("GET:MAIN.st.n[0]", "GET:MAIN.ST.N[0],10"),
        ("GET:MAIN.st.n[2]", "GET:MAIN.ST.N[2],30"),
        ("GET:MAIN.arr[1]", "GET:MAIN.ARR[1],7"),
        ("GET:MAIN.arr[3]", "GET:MAIN.ARR[3],9"),
        ("LIST:MAIN.st.n[1]", "LIST:MAIN.ST.N[1],WORD*\r\nLIST:"),
        (
            "LIST:MAIN.vstring",
            "LIST:MAIN.VSTRING,STRING[80]*\r\nLIST:",
        ),
        ("GETINFO:PROTOCOL", "GETINFO:PROTOCOL,ADS"),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    // Many symbols in one GET: one sum read.
    c.send(b"GET:MAIN.arr[*]\r\n").await;
    for want in [
        "GET:MAIN.ARR[1],7",
        "GET:MAIN.ARR[2],-8",
        "GET:MAIN.ARR[3],9",
        "GET:",
    ] {
        assert_eq!(String::from_utf8(c.line().await).unwrap().trim_end(), want);
    }

    // Writes by handle, read back; the fixture holds the new bytes.
    c.ask("SET:MAIN.vint,42\r\n", "DIFF:MAIN.VINT,42\r\n").await;
    assert_eq!(device.ask("get MAIN.vint"), "2a00");
    c.ask("SET:MAIN.st.n[1],513\r\n", "DIFF:MAIN.ST.N[1],513\r\n")
        .await;
    assert_eq!(device.ask("get MAIN.st"), "010a0001021e00");
    c.ask("SET:MAIN.vbool,0\r\n", "DIFF:MAIN.VBOOL,0\r\n").await;
    assert_eq!(device.ask("get MAIN.vbool"), "00");
    // A change the PLC program makes is polled.
    device.ask("set MAIN.vdint 01000000");
    until(&mut c, "GET:MAIN.vdint", "GET:MAIN.VDINT,1", 5).await;

    // A new program without MAIN.vword: the symbol version changes and the
    // table is reloaded live.
    device.ask("remove MAIN.vword");
    until(
        &mut c,
        "GET:MAIN.vword",
        "ERROR:33 Unknown variable name in request: 'GET:MAIN.vword'",
        10,
    )
    .await;
    sync(&mut c).await;
    c.ask("GET:MAIN.vint\r\n", "GET:MAIN.VINT,42\r\n").await;
    // A program with a new symbol.
    device.ask("add MAIN.fresh INT 0700");
    until(&mut c, "GET:MAIN.fresh", "GET:MAIN.FRESH,7", 10).await;
    sync(&mut c).await;

    // Handles: one per symbol read, none leaked by the reload.
    let held = device.ask("count");
    let handles: usize = held.split_whitespace().nth(1).unwrap().parse().unwrap();
    assert!(handles <= 40, "{held}");
    let log = server.log();
    assert!(log.contains("symbols uploaded"), "{log}");
}

#[tokio::test]
async fn refusals_are_named_and_the_restarted_server_is_found_again() {
    let mut device = Fixture::start(0);
    let device_port = device.port;
    let port = free_port();
    let server = ServerProcess::with_config(&ads_ini(device_port, port, ""), port);
    let mut c = Client::connect(server.addr).await;
    until(&mut c, "GET:MAIN.counter", "GET:MAIN.COUNTER,0", 15).await;
    // The symbol is gone from the PLC but the program's version is the
    // same: the device's own answer, named, with the symbol's name.
    device.ask("forget MAIN.counter");
    c.ask(
        "GET:MAIN.counter\r\n",
        "ERROR:80 Unable to get data from address: 'MAIN.COUNTER: ADS error 0x710 (symbol not found)'\r\n",
    )
    .await;
    let log = server.log();
    drop(device);
    // The server restarted on its port: values again.
    let mut device = Fixture::start(device_port);
    until(&mut c, "GET:MAIN.counter", "GET:MAIN.COUNTER,0", 10).await;
    device.ask("set MAIN.counter 05000000");
    until(&mut c, "GET:MAIN.counter", "GET:MAIN.COUNTER,5", 5).await;
    let _ = log;
}

#[tokio::test]
async fn a_tag_file_names_symbols_and_index_groups() {
    let mut device = Fixture::start(0);
    let port = free_port();
    // MAIN.vint is the eighth symbol: index group 0x4040, offset 0x8000.
    let tags = "name,address,type,unit,description\n\
                temp,MAIN.vint,INT,°C,\"kitchen, north\"\n\
                raw,0x4040:0x8000,INT\n\
                flag,MAIN.vbool,BOOL\n\
                missing,MAIN.nothere,INT\n\
                bad,MAIN.vint,FOO\n";
    let ini = ads_ini(device.port, port, "ADS_TAGS = tags.csv");
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("plccoms.ini"), ini).unwrap();
    std::fs::write(dir.path().join("tags.csv"), tags).unwrap();
    let server = ServerProcess::with_config_in(dir, port);
    let mut c = Client::connect(server.addr).await;
    until(&mut c, "GET:temp", "GET:TEMP,-1234", 15).await;
    c.ask("GET:raw\r\n", "GET:RAW,-1234\r\n").await;
    c.ask("GET:flag\r\n", "GET:FLAG,1\r\n").await;
    c.ask(
        "GET:missing\r\n",
        "ERROR:80 Unable to get data from address: 'MISSING: ADS error 0x710 (symbol not found)'\r\n",
    )
    .await;
    c.ask("LIST:\r\n", "LIST:__PLC_RUN,BOOL\r\n").await;
    for want in [
        "LIST:__PF_CRC,DWORD",
        "LIST:TEMP,INT*",
        "LIST:RAW,INT*",
        "LIST:FLAG,BOOL*",
        "LIST:MISSING,INT*",
        "LIST:",
    ] {
        assert_eq!(String::from_utf8(c.line().await).unwrap().trim_end(), want);
    }
    // Written at the index group, read back by handle.
    c.ask("SET:raw,77\r\n", "DIFF:RAW,77\r\n").await;
    assert_eq!(device.ask("get MAIN.vint"), "4d00");
    until(&mut c, "GET:temp", "GET:TEMP,77", 5).await;
    let log = server.log();
    assert!(log.contains("line 6: unknown type 'FOO'"), "{log}");

    // An edited tag file is loaded again.
    std::fs::write(
        server.dir.path().join("tags.csv"),
        format!("{tags}extra,MAIN.vdint,DINT\n"),
    )
    .unwrap();
    until(&mut c, "GET:extra", "GET:EXTRA,-123456", 10).await;
}

/// The fixture is an ADS device pyads's own client accepts: its script
/// (tests/ads/pyads_client.py) reads, writes, uploads, sum-reads, is
/// notified and refused. pyads's router always dials 48898.
#[test]
fn pyads_own_client_works_against_the_fixture() {
    assert!(
        common::process::port_is_free(48898),
        "TCP 48898 is taken: pyads's client can only reach the fixture there"
    );
    let _device = Fixture::start(48898);
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/ads/pyads_client.py");
    let out = std::process::Command::new("python3")
        .arg(script)
        .output()
        .expect("run python3");
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
