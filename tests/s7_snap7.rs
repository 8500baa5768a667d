//! The S7 backend against real S7 servers started by the test:
//! python-snap7 3.3's pure-Python server and the Snap7 C server of
//! python-snap7 1.4's wheel (`tests/common/s7.rs`), each behaviour against
//! the server that has it: every area and type, strings, arrays, bit
//! writes that keep the byte's other bits, writes read back, refusals named,
//! PDUs of 240, 480 and 960, the CPU's mode, a tag the server lacks among
//! good ones, and the server killed and restarted; all through the line
//! protocol of the real `plccoms` binary.

mod common;

use std::time::Duration;

use common::modbus::until;
use common::process::free_port;
use common::s7::{s7_server, Kind, Snap7};
use common::Client;

const TAGS: &str = "\
name,address,type,unit,description,access
x0_0,DB1.DBX0.0,BOOL
x0_1,DB1.DBX0.1
x0_7,DB1.DBX0.7,BOOL
int_a,DB1.DBW2,INT,rpm,\"speed, conveyor\"
dint_a,DB1.DBD4,DINT
real_a,DB1.DBD8,REAL
lreal_a,DB1.DBB12,LREAL
word_a,DB1.DBW20
byte_a,DB1.DBB22
sint_a,DB1.DBB23,SINT
udint_a,DB1.DBD24,UDINT
lint_a,DB1.DBB28,LINT
text,DB1.DBS36.10
dt_a,DB1.DBB48,DATE_AND_TIME
dtl_a,DB1.DBB56,DTL
s5_a,DB1.DBW68,S5TIME
time_a,DB1.DBD70,TIME
date_a,DB1.DBW74,DATE
tod_a,DB1.DBD76,TOD
wtext,DB1.DBB80,WSTRING[4]
levels,DB1.DBW92,ARRAY[0..3] OF INT
rw_int,DB1.DBW100,INT
rw_real,DB1.DBD102,REAL
rw_text,DB1.DBS106.8
rw_bit0,DB1.DBX116.0
rw_bit5,DB1.DBX116.5
missing,DB99.DBW0,INT
past,DB2.DBW10,INT
after,DB2.DBW0,INT
m_word,MW10,INT
m_bit,M0.1
in_word,IW0
in_bit,E2.3
out_byte,QB0
out_bit,A1.1
";

/// 2024-03-15 13:45:30.500 (a Friday), as DT's seconds.
const STAMP: f64 = 1_710_510_330.5;

fn db1() -> Vec<u8> {
    let mut b = vec![0u8; 128];
    b[0] = 0b1000_0101;
    b[2..4].copy_from_slice(&(-1234i16).to_be_bytes());
    b[4..8].copy_from_slice(&(-100_000i32).to_be_bytes());
    b[8..12].copy_from_slice(&1.5f32.to_be_bytes());
    b[12..20].copy_from_slice(&std::f64::consts::PI.to_be_bytes());
    b[20..22].copy_from_slice(&[0xBE, 0xEF]);
    b[22] = 200;
    b[23] = (-5i8) as u8;
    b[24..28].copy_from_slice(&4_000_000_000u32.to_be_bytes());
    b[28..36].copy_from_slice(&(-5_000_000_000i64).to_be_bytes());
    b[36..48].copy_from_slice(b"\x0A\x05Hello\0\0\0\0\0");
    b[48..56].copy_from_slice(&[0x24, 0x03, 0x15, 0x13, 0x45, 0x30, 0x50, 0x06]);
    b[56..68].copy_from_slice(&[0x07, 0xE8, 3, 15, 6, 13, 45, 30, 0x1D, 0xCD, 0x65, 0x00]);
    b[68..70].copy_from_slice(&[0x10, 0x25]);
    b[70..74].copy_from_slice(&123_456u32.to_be_bytes());
    // 2024-03-15: 12492 days after 1990-01-01.
    b[74..76].copy_from_slice(&12_492u16.to_be_bytes());
    b[76..80].copy_from_slice(&49_530_500u32.to_be_bytes());
    b[80..92].copy_from_slice(&[0, 4, 0, 2, 0, b'A', 0, b'b', 0, 0, 0, 0]);
    for (i, v) in [1i16, 2, 3, 4].iter().enumerate() {
        b[92 + 2 * i..94 + 2 * i].copy_from_slice(&v.to_be_bytes());
    }
    b[106] = 8;
    b[116] = 0b1010_0000;
    b
}

fn areas() -> Vec<common::s7::Area> {
    let mut mk = vec![0u8; 32];
    mk[0] = 0x02;
    mk[10..12].copy_from_slice(&777i16.to_be_bytes());
    let mut pe = vec![0u8; 8];
    pe[0..2].copy_from_slice(&[0x12, 0x34]);
    pe[2] = 0x08;
    let mut pa = vec![0u8; 8];
    pa[0] = 0x55;
    pa[1] = 0x02;
    vec![
        ("DB", 1, db1()),
        ("DB", 2, vec![0, 42, 0, 0]),
        ("MK", 0, mk),
        ("PE", 0, pe),
        ("PA", 0, pa),
    ]
}

/// Every line of GETINFO.
async fn getinfo(c: &mut Client) -> Vec<String> {
    c.send(b"GETINFO:\r\n").await;
    let mut info = Vec::new();
    loop {
        let line = String::from_utf8(c.line().await).unwrap();
        if line == "GETINFO:\r\n" {
            return info;
        }
        info.push(line.trim_end().to_string());
    }
}

/// What every server reads alike: every area and type.
async fn reads_every_area_and_type(c: &mut Client) {
    let stamp = STAMP.to_bits();
    let date = 1_710_460_800f64.to_bits();
    for (request, answer) in [
        ("GET:x0_0", "GET:X0_0,1".to_string()),
        ("GET:x0_1", "GET:X0_1,0".into()),
        ("GET:x0_7", "GET:X0_7,1".into()),
        ("GET:int_a", "GET:INT_A,-1234".into()),
        ("GET:dint_a", "GET:DINT_A,-100000".into()),
        ("GET:real_a", "GET:REAL_A,1.500000".into()),
        ("GET:lreal_a", "GET:LREAL_A,3.1415926536".into()),
        ("GET:word_a", "GET:WORD_A,48879".into()),
        ("GET:byte_a", "GET:BYTE_A,200".into()),
        ("GET:sint_a", "GET:SINT_A,-5".into()),
        ("GET:udint_a", "GET:UDINT_A,4000000000".into()),
        ("GET:lint_a", "GET:LINT_A,-5000000000".into()),
        ("GET:text", "GET:TEXT,\"Hello\"".into()),
        ("GET:dt_a", format!("GET:DT_A,{stamp}")),
        ("GET:dtl_a", format!("GET:DTL_A,{stamp}")),
        ("GET:s5_a", "GET:S5_A,2500".into()),
        ("GET:time_a", "GET:TIME_A,123456".into()),
        ("GET:date_a", format!("GET:DATE_A,{date}")),
        ("GET:tod_a", "GET:TOD_A,49530500".into()),
        ("GET:wtext", "GET:WTEXT,\"Ab\"".into()),
        ("GET:levels[0]", "GET:LEVELS[0],1".into()),
        ("GET:levels[3]", "GET:LEVELS[3],4".into()),
        ("GET:after", "GET:AFTER,42".into()),
        ("GET:m_word", "GET:M_WORD,777".into()),
        ("GET:m_bit", "GET:M_BIT,1".into()),
        ("GET:in_word", "GET:IN_WORD,4660".into()),
        ("GET:in_bit", "GET:IN_BIT,1".into()),
        ("GET:out_byte", "GET:OUT_BYTE,85".into()),
        ("GET:out_bit", "GET:OUT_BIT,1".into()),
        ("LIST:dtl_a", "LIST:DTL_A,DT*\r\nLIST:".into()),
        ("LIST:wtext", "LIST:WTEXT,STRING[4]*\r\nLIST:".into()),
        ("LIST:in_word", "LIST:IN_WORD,WORD*\r\nLIST:".into()),
        (
            "GET:missing",
            "ERROR:80 Unable to get data from address: \
             'MISSING: S7 object does not exist (0x0A)'"
                .into(),
        ),
        (
            "GET:past",
            "ERROR:80 Unable to get data from address: \
             'PAST: S7 address out of range (0x05)'"
                .into(),
        ),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
}

#[tokio::test]
async fn c_server_every_area_type_write_and_refusal() {
    let mut device = Snap7::start(Kind::C, free_port(), &areas());
    let dir = tempfile::tempdir().unwrap();
    let server = s7_server(dir.path(), device.port, TAGS, "");
    let mut c = Client::connect(server.addr).await;
    reads_every_area_and_type(&mut c).await;

    for (request, answer) in [
        ("SET:rw_int,-42", "DIFF:RW_INT,-42"),
        ("SET:rw_real,12.25", "DIFF:RW_REAL,12.250000"),
        ("SET:rw_text,\"Hi\"", "DIFF:RW_TEXT,\"Hi\""),
        ("SET:levels[2],-7", "DIFF:LEVELS[2],-7"),
        (
            "SET:dt_a,0",
            "ERROR:35 Wrong parameter value in request: 'SET:dt_a,0'",
        ),
        ("SET:rw_bit0,1", "DIFF:RW_BIT0,1"),
        ("SET:out_bit,0", "DIFF:OUT_BIT,0"),
        ("SET:m_bit,0", "DIFF:M_BIT,0"),
        (
            "SET:in_word,5",
            "ERROR:30 Bad client request: 'SET:in_word,5'",
        ),
        (
            "SET:missing,1",
            "ERROR:81 Unable to set data in to address: \
             'MISSING: S7 object does not exist (0x0A)'",
        ),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    // What the server holds: the bit items kept each byte's other bits.
    assert_eq!(device.peek("DB", 1, 100, 2), (-42i16).to_be_bytes());
    assert_eq!(device.peek("DB", 1, 102, 4), 12.25f32.to_be_bytes());
    assert_eq!(device.peek("DB", 1, 106, 4), [8, 2, b'H', b'i']);
    assert_eq!(device.peek("DB", 1, 96, 2), (-7i16).to_be_bytes());
    assert_eq!(device.peek("DB", 1, 116, 1), [0b1010_0001]);
    assert_eq!(device.peek("PA", 0, 0, 2), [0x55, 0x00]);
    assert_eq!(device.peek("MK", 0, 0, 1), [0x00]);
    c.ask("SET:rw_bit5,0\r\n", "DIFF:RW_BIT5,0\r\n").await;
    assert_eq!(device.peek("DB", 1, 116, 1), [0b1000_0001]);

    let info = getinfo(&mut c).await;
    for want in [
        "GETINFO:PROTOCOL,S7".to_string(),
        format!("GETINFO:S7_PORT,{}", device.port),
        "GETINFO:VERSION_PLC,S7 TSAP 0100/0101, PDU 960 (asked 960), 8 parallel job(s)".into(),
        "GETINFO:S7_TAGS,2/40 [tags.csv]".into(),
    ] {
        assert!(info.contains(&want), "{want} not in {info:?}");
    }
    for epsnet in ["VERSION_EPSNET", "EPSADDR", "EPSPORT", "PUBFILE"] {
        let key = format!("GETINFO:{epsnet},");
        assert!(!info.iter().any(|l| l.starts_with(&key)), "{info:?}");
    }

    // The CPU's mode is __PLC_RUN.
    c.ask("GET:__PLC_RUN\r\n", "GET:__PLC_RUN,1\r\n").await;
    device.set_run(false);
    until(&mut c, "GET:__PLC_RUN", "GET:__PLC_RUN,0", 5).await;
    device.set_run(true);
    until(&mut c, "GET:__PLC_RUN", "GET:__PLC_RUN,1", 5).await;
}

/// One tag the server lacks among good ones: polled alone, named once in
/// the log with its address and what to check, and the rest keeps polling.
#[tokio::test]
async fn a_missing_tag_among_good_ones_is_split_out() {
    let device = Snap7::start(Kind::C, free_port(), &areas());
    let dir = tempfile::tempdir().unwrap();
    let server = s7_server(dir.path(), device.port, TAGS, "");
    let mut watcher = Client::connect(server.addr).await;
    watcher
        .ask(
            "EN:*\r\n",
            "WARNING:252 Changed active variables in public file: '[40/40]'\r\n",
        )
        .await;
    let mut seen = std::collections::BTreeSet::new();
    while seen.len() < 38 {
        let line = String::from_utf8(watcher.line().await).unwrap();
        let name = line
            .strip_prefix("DIFF:")
            .and_then(|rest| rest.split(',').next())
            .unwrap_or_else(|| panic!("unexpected {line:?}"))
            .to_string();
        assert!(name != "MISSING" && name != "PAST", "{line}");
        seen.insert(name);
    }
    let log = server.log_with("MISSING: the PLC refuses to read it").await;
    assert!(log.contains("DB99 does not exist in the CPU"), "{log}");
    let log = server.log_with("PAST: the PLC refuses to read it").await;
    assert!(log.contains("past the end of DB2"), "{log}");
    tokio::time::sleep(Duration::from_secs(2)).await;
    let log = server.log();
    assert_eq!(log.matches("MISSING: the PLC refuses").count(), 1, "{log}");
}

/// PDUs of 240 and 480 asked of the C server: granted, shown, and a block
/// longer than one answer (an array of 200 INTs) read and written in pieces.
#[tokio::test]
async fn c_server_pdus_240_and_480() {
    let mut big = vec![0u8; 600];
    for i in 0..200u16 {
        big[2 * usize::from(i)..2 * usize::from(i) + 2].copy_from_slice(&(i * 3).to_be_bytes());
    }
    let mut areas = areas();
    areas.push(("DB", 3, big));
    let tags = format!("{TAGS}series,DB3.DBW0,ARRAY[0..199] OF INT\nlong,DB3.DBS400.180\n");
    for pdu in [240, 480] {
        let mut device = Snap7::start(Kind::C, free_port(), &areas);
        let dir = tempfile::tempdir().unwrap();
        let server = s7_server(dir.path(), device.port, &tags, &format!("S7_PDU = {pdu}"));
        let mut c = Client::connect(server.addr).await;
        let info = getinfo(&mut c).await;
        let want = format!(
            "GETINFO:VERSION_PLC,S7 TSAP 0100/0101, PDU {pdu} (asked {pdu}), 8 parallel job(s)"
        );
        assert!(info.contains(&want), "{want} not in {info:?}");
        reads_every_area_and_type(&mut c).await;
        c.send(b"GET:series*\r\n").await;
        for i in 0..200 {
            let line = String::from_utf8(c.line().await).unwrap();
            assert_eq!(line, format!("GET:SERIES[{i}],{}\r\n", i * 3), "PDU {pdu}");
        }
        c.expect(b"GET:\r\n").await;
        // 182 bytes: more than one write item at PDU 240.
        let text: String = (0..180)
            .map(|i| char::from(b'a' + (i % 26) as u8))
            .collect();
        c.ask(
            &format!("SET:long,\"{text}\"\r\n"),
            &format!("DIFF:LONG,\"{text}\"\r\n"),
        )
        .await;
        let held = device.peek("DB", 3, 400, 182);
        assert_eq!(&held[..2], [180, 180]);
        assert_eq!(&held[2..], text.as_bytes());
    }
}

/// python-snap7 3.3's server: grants at most 480, tells no CPU mode (so
/// __PLC_RUN is 1 while it answers), and writes (and answers) only the
/// first item of a multi-item write: the rest is written again.
#[tokio::test]
async fn python_server_pdu_480_writes_and_no_cpu_mode() {
    let mut device = Snap7::start(Kind::Python, free_port(), &areas());
    let dir = tempfile::tempdir().unwrap();
    let server = s7_server(dir.path(), device.port, TAGS, "S7_PDU = 960");
    let mut c = Client::connect(server.addr).await;
    let info = getinfo(&mut c).await;
    let want = "GETINFO:VERSION_PLC,S7 TSAP 0100/0101, PDU 480 (asked 960), 1 parallel job(s)";
    assert!(info.iter().any(|l| l == want), "{want} not in {info:?}");
    reads_every_area_and_type(&mut c).await;
    c.ask("GET:__PLC_RUN\r\n", "GET:__PLC_RUN,1\r\n").await;
    for (request, answer) in [
        ("SET:rw_int,-42", "DIFF:RW_INT,-42"),
        ("SET:rw_real,12.25", "DIFF:RW_REAL,12.250000"),
        ("SET:rw_text,\"Hi\"", "DIFF:RW_TEXT,\"Hi\""),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    assert_eq!(device.peek("DB", 1, 100, 6), [0xFF, 0xD6, 0x41, 0x44, 0, 0]);

    // Writes of several clients at once go in one batch, and so in one
    // multi-item job: the server writes and answers its first item only;
    // the backend writes the rest again, one item a job.
    let writes: [(&str, &str, &str, u32, Vec<u8>); 4] = [
        (
            "rw_int",
            "7",
            "DIFF:RW_INT,7",
            100,
            7i16.to_be_bytes().to_vec(),
        ),
        (
            "levels[1]",
            "-9",
            "DIFF:LEVELS[1],-9",
            94,
            (-9i16).to_be_bytes().to_vec(),
        ),
        (
            "levels[2]",
            "11",
            "DIFF:LEVELS[2],11",
            96,
            11i16.to_be_bytes().to_vec(),
        ),
        (
            "rw_real",
            "0.5",
            "DIFF:RW_REAL,0.500000",
            102,
            0.5f32.to_be_bytes().to_vec(),
        ),
    ];
    let mut clients = Vec::new();
    for _ in &writes {
        clients.push(Client::connect(server.addr).await);
    }
    let mut round = 0;
    loop {
        round += 1;
        let sets =
            clients
                .iter_mut()
                .zip(&writes)
                .map(|(c, (name, value, diff, _, _))| async move {
                    let value = if round % 2 == 0 { "0" } else { value };
                    let diff = if round % 2 == 0 {
                        format!(
                            "{},{}",
                            diff.split(',').next().unwrap(),
                            if name.contains("real") {
                                "0.000000"
                            } else {
                                "0"
                            }
                        )
                    } else {
                        diff.to_string()
                    };
                    c.ask(&format!("SET:{name},{value}\r\n"), &format!("{diff}\r\n"))
                        .await;
                });
        futures::future::join_all(sets).await;
        for (name, _, _, at, bytes) in &writes {
            let want = if round % 2 == 0 {
                vec![0; bytes.len()]
            } else {
                bytes.clone()
            };
            assert_eq!(
                device.peek("DB", 1, *at, bytes.len() as u32),
                want,
                "{name}, round {round}"
            );
        }
        if server
            .log()
            .contains("writing one item a request from now on")
        {
            break;
        }
        assert!(
            round < 30,
            "no multi-item write in {round} rounds:\n{}",
            server.log()
        );
    }
}

/// The server killed: the link is declared lost (GET answers ERROR); the
/// server started again on its port: values again. The section names its
/// TSAPs (S7_TSAP) rather than rack and slot.
#[tokio::test]
async fn server_killed_and_restarted() {
    let device = Snap7::start(Kind::C, free_port(), &areas());
    let port = device.port;
    let dir = tempfile::tempdir().unwrap();
    // The TSAPs given as TIA Portal shows them (a LOGO!'s), instead of
    // rack and slot.
    let server = s7_server(
        dir.path(),
        port,
        TAGS,
        "S7_TIMEOUT = 500\nS7_TSAP = 01.00/02.00",
    );
    let mut c = Client::connect(server.addr).await;
    c.ask("GET:int_a\r\n", "GET:INT_A,-1234\r\n").await;
    drop(device);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    loop {
        c.send(b"GET:int_a\r\n").await;
        let line = String::from_utf8(c.line().await).unwrap();
        if line.starts_with("ERROR:") {
            break;
        }
        assert!(tokio::time::Instant::now() < deadline, "still {line:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let mut areas = areas();
    areas[0].2[2..4].copy_from_slice(&99i16.to_be_bytes());
    let _device = Snap7::start(Kind::C, port, &areas);
    until(&mut c, "GET:int_a", "GET:INT_A,99", 10).await;
    let log = server.log_with("PLC connected again").await;
    assert!(log.contains("ident=S7 TSAP 0100/0200, PDU 960"), "{log}");
}
