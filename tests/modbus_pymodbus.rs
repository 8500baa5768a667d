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

const TAGS: &str = "\
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

fn image() -> Image {
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

#[tokio::test]
async fn every_type_order_and_table() {
    let device = Pymodbus::start(free_port(), &image());
    let dir = tempfile::tempdir().unwrap();
    let server = modbus_server(dir.path(), device.port, TAGS, "MODBUS_TIMEOUT = 2000");
    let mut c = Client::connect(server.addr).await;
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

/// The log, once it has `want` (lines are written as the server goes).
async fn log_with(server: &common::process::ServerProcess, want: &str) -> String {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let log = server.log();
        if log.contains(want) {
            return log;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{want:?} not in the log:\n{log}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
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
    let log = log_with(
        &server,
        &format!(
            "TEMPERATURE: the PLC refuses to read it (Modbus exception 2 (illegal data address)); \
             polled alone, the others go on; {hint}"
        ),
    )
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
