//! End to end: TCP client -> server section -> EPSNET backend -> simulated PLC,
//! over real UDP on 127.0.0.1, with exact bytes on the client's wire.

mod common;

use std::time::Duration;

use common::epsnet::{
    any_port, eventually, peek, poke, spawn_sim, start_server, watched_idle_plc, Link, FAST_LINK,
    SLOW,
};
use common::Client;
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_protocol::Area;
use plcsim::program::ProgramKind;
use plcsim::SimConfig;

fn date_bits(unix_seconds: f64) -> u64 {
    unix_seconds.to_bits()
}

/// `Příliš žluťoučký kůň` in cp1250.
const CZECH: &[u8] = b"P\xF8\xEDli\x9A \x9Elu\x9Dou\xE8k\xFD k\xF9\xF2";

#[tokio::test]
async fn set_get_every_type_through_epsnet() {
    let sim = spawn_sim(any_port(), ProgramKind::Idle).await;
    let server = start_server(sim.local_addr(), "", FAST_LINK).await;
    let mut c = Client::connect(server.local_addr).await;
    // (name, value sent, value shown, offset in R, bytes in PLC memory)
    let cases: Vec<(&str, String, String, u32, Vec<u8>)> = vec![
        ("SWITCH", "1".into(), "1".into(), 128, vec![0x01]),
        (
            "COUNTER",
            "-32768".into(),
            "-32768".into(),
            130,
            vec![0x00, 0x80],
        ),
        (
            "COUNTER",
            "32767".into(),
            "32767".into(),
            130,
            vec![0xFF, 0x7F],
        ),
        ("V_BYTE", "255".into(), "255".into(), 174, vec![0xFF]),
        ("V_BYTE", "0".into(), "0".into(), 174, vec![0x00]),
        ("V_WORD", "65535".into(), "65535".into(), 176, vec![0xFF; 2]),
        (
            "V_DWORD",
            "4294967295".into(),
            "4294967295".into(),
            180,
            vec![0xFF; 4],
        ),
        (
            "V_LWORD",
            "18446744073709551615".into(),
            "18446744073709551615".into(),
            184,
            vec![0xFF; 8],
        ),
        ("V_SINT", "-128".into(), "-128".into(), 192, vec![0x80]),
        ("V_SINT", "127".into(), "127".into(), 192, vec![0x7F]),
        (
            "V_DINT",
            "-2147483648".into(),
            "-2147483648".into(),
            196,
            i32::MIN.to_le_bytes().to_vec(),
        ),
        (
            "V_DINT",
            "2147483647".into(),
            "2147483647".into(),
            196,
            i32::MAX.to_le_bytes().to_vec(),
        ),
        (
            "V_LINT",
            "-9223372036854775808".into(),
            "-9223372036854775808".into(),
            200,
            i64::MIN.to_le_bytes().to_vec(),
        ),
        (
            "V_LINT",
            "9223372036854775807".into(),
            "9223372036854775807".into(),
            200,
            i64::MAX.to_le_bytes().to_vec(),
        ),
        ("V_USINT", "255".into(), "255".into(), 208, vec![0xFF]),
        ("V_UINT", "65535".into(), "65535".into(), 210, vec![0xFF; 2]),
        (
            "V_UDINT",
            "4294967295".into(),
            "4294967295".into(),
            212,
            vec![0xFF; 4],
        ),
        (
            "V_ULINT",
            "18446744073709551615".into(),
            "18446744073709551615".into(),
            216,
            vec![0xFF; 8],
        ),
        (
            "V_ULINT",
            "9007199254740993".into(),
            "9007199254740993".into(),
            216,
            9007199254740993u64.to_le_bytes().to_vec(),
        ),
        (
            "SETPOINT",
            "21.5".into(),
            "21.500000".into(),
            124,
            21.5f32.to_le_bytes().to_vec(),
        ),
        (
            "SETPOINT",
            "-0.1".into(),
            "-0.100000".into(),
            124,
            (-0.1f32).to_le_bytes().to_vec(),
        ),
        (
            "C",
            "1.23456789012345".into(),
            "1.2345678901".into(),
            32,
            1.23456789012345f64.to_le_bytes().to_vec(),
        ),
        (
            "C",
            "-1e-3".into(),
            "-0.0010000000".into(),
            32,
            (-1e-3f64).to_le_bytes().to_vec(),
        ),
        // DATE / DT: the f64 seconds since 1970 as its IEEE bits.
        (
            "DAT",
            date_bits(1_699_920_000.0).to_string(),
            date_bits(1_699_920_000.0).to_string(),
            0,
            1_699_920_000f64.to_le_bytes().to_vec(),
        ),
        (
            "V_DT",
            date_bits(1_700_000_000.5).to_string(),
            date_bits(1_700_000_000.5).to_string(),
            232,
            1_700_000_000.5f64.to_le_bytes().to_vec(),
        ),
        (
            "TIM",
            "4294967295".into(),
            "4294967295".into(),
            8,
            vec![0xFF; 4],
        ),
        (
            "V_TOD",
            "86399999".into(),
            "86399999".into(),
            224,
            86_399_999u32.to_le_bytes().to_vec(),
        ),
    ];
    for (name, value, shown, offset, bytes) in &cases {
        c.ask(
            &format!("SET:{name},{value}\n"),
            &format!("DIFF:{name},{shown}\r\n"),
        )
        .await;
        assert_eq!(
            peek(&sim, Area::R, *offset, bytes.len() as u32),
            *bytes,
            "{name} = {value} in PLC memory"
        );
        c.ask(&format!("GET:{name}\n"), &format!("GET:{name},{shown}\r\n"))
            .await;
    }
    // Out of range: refused before anything goes to the PLC.
    c.ask(
        "SET:v_sint,128\n",
        "ERROR:35 Wrong parameter value in request: 'SET:v_sint,128'\r\n",
    )
    .await;
    assert_eq!(peek(&sim, Area::R, 192, 1), [0x7F]);
}

#[tokio::test]
async fn bools_sharing_a_byte_and_cp1250_strings() {
    let sim = spawn_sim(any_port(), ProgramKind::Idle).await;
    // A bit no variable names, in the same byte: a BOOL write must keep it.
    poke(&sim, Area::R, 240, &[0x80]);
    let server = start_server(sim.local_addr(), "", FAST_LINK).await;
    let mut c = Client::connect(server.local_addr).await;
    c.send(b"SET:flag_a,1\nSET:flag_b,1\n").await;
    c.expect(b"DIFF:FLAG_A,1\r\nDIFF:FLAG_B,1\r\n").await;
    assert_eq!(peek(&sim, Area::R, 240, 1), [0x83]);
    c.ask("SET:flag_a,0\n", "DIFF:FLAG_A,0\r\n").await;
    assert_eq!(peek(&sim, Area::R, 240, 1), [0x82]);
    c.ask("GET:flag_*\n", "GET:FLAG_A,0\r\nGET:FLAG_B,1\r\nGET:\r\n")
        .await;

    // STRING[40]: cp1250 bytes go to the PLC as they are, NUL-terminated.
    let mut set = b"SET:note,\"".to_vec();
    set.extend_from_slice(CZECH);
    set.extend_from_slice(b"\"\n");
    c.send(&set).await;
    let mut want = b"DIFF:NOTE,\"".to_vec();
    want.extend_from_slice(CZECH);
    want.extend_from_slice(b"\"\r\n");
    c.expect(&want).await;
    let mut memory = CZECH.to_vec();
    memory.push(0);
    assert_eq!(peek(&sim, Area::R, 132, memory.len() as u32), memory);
    c.send(b"GET:note\n").await;
    let mut want = b"GET:NOTE,\"".to_vec();
    want.extend_from_slice(CZECH);
    want.extend_from_slice(b"\"\r\n");
    c.expect(&want).await;
    // 40 characters fit, 41 do not.
    let forty = "x".repeat(40);
    c.ask(
        &format!("SET:note,\"{forty}\"\n"),
        &format!("DIFF:NOTE,\"{forty}\"\r\n"),
    )
    .await;
    c.ask(
        &format!("SET:note,\"{forty}y\"\n"),
        &format!("ERROR:35 Wrong parameter value in request: 'SET:note,\"{forty}y\"'\r\n"),
    )
    .await;
    c.ask("SET:note,\"\"\n", "DIFF:NOTE,\"\"\r\n").await;
    assert_eq!(peek(&sim, Area::R, 132, 1), [0]);

    // A Czech variable name, upper-cased in cp1250.
    c.send(b"SET:teplota_kuchyn\xEC,-12.25\n").await;
    c.expect(b"DIFF:TEPLOTA_KUCHYN\xCC,-12.250000\r\n").await;
    assert_eq!(peek(&sim, Area::R, 244, 4), (-12.25f32).to_le_bytes());

    // Direct addresses go through EPSNET too.
    c.ask("SET:%RW130,513\n", "DIFF:%RW130,513\r\n").await;
    c.ask("GET:counter\n", "GET:COUNTER,513\r\n").await;
    c.ask("GET:%R130.1\n", "GET:%R130.1,0\r\n").await;
    c.ask("GET:%R130.0\n", "GET:%R130.0,1\r\n").await;
}

/// The demo file's variables in table order, as LIST prints them.
const DEMO_VARS: [&str; 29] = [
    "__PLC_RUN",
    "__PF_CRC",
    "DAT",
    "TIM",
    "SINUS",
    "COSINUS",
    "C",
    "POSITIVE",
    "TEXT",
    "SETPOINT",
    "SWITCH",
    "COUNTER",
    "NOTE",
    "V_BYTE",
    "V_WORD",
    "V_DWORD",
    "V_LWORD",
    "V_SINT",
    "V_DINT",
    "V_LINT",
    "V_USINT",
    "V_UINT",
    "V_UDINT",
    "V_ULINT",
    "V_TOD",
    "V_DT",
    "FLAG_A",
    "FLAG_B",
    "TEPLOTA_KUCHYN\u{CC}",
];

fn diff_line(name: &str, value: &str) -> Vec<u8> {
    // Names are ASCII but one; Ì stands for the cp1250 byte 0xCC.
    let mut line = b"DIFF:".to_vec();
    for ch in name.chars() {
        line.push(if ch == '\u{CC}' { 0xCC } else { ch as u8 });
    }
    line.push(b',');
    line.extend_from_slice(value.as_bytes());
    line.extend_from_slice(b"\r\n");
    line
}

#[tokio::test]
async fn en_all_then_every_type_diffs_from_plc_memory() {
    let sim = spawn_sim(any_port(), ProgramKind::Idle).await;
    let server = start_server(sim.local_addr(), "", FAST_LINK).await;
    let mut c = Client::connect(server.local_addr).await;
    c.ask(
        "EN:*\n",
        "WARNING:252 Changed active variables in public file: '[29/29]'\r\n",
    )
    .await;
    // The first poll sends every value, in table order.
    let mut first = Vec::new();
    for name in DEMO_VARS {
        let value = match name {
            "__PLC_RUN" => "1",
            "__PF_CRC" => "357882496", // 0x1554DA80, the file's CRC trailer
            "SINUS" | "COSINUS" | "C" => "0.0000000000",
            "TEXT" | "NOTE" => "\"\"",
            "SETPOINT" | "TEPLOTA_KUCHYN\u{CC}" => "0.000000",
            _ => "0",
        };
        first.extend_from_slice(&diff_line(name, value));
    }
    c.expect(&first).await;

    // Each change the PLC makes arrives as exactly one DIFF line.
    let r = Area::R;
    let steps: Vec<(u32, Vec<u8>, &str, String)> = vec![
        (128, vec![0x01], "SWITCH", "1".into()),
        (
            130,
            (-32768i16).to_le_bytes().to_vec(),
            "COUNTER",
            "-32768".into(),
        ),
        (
            130,
            32767i16.to_le_bytes().to_vec(),
            "COUNTER",
            "32767".into(),
        ),
        (174, vec![0xFF], "V_BYTE", "255".into()),
        (176, vec![0xFF; 2], "V_WORD", "65535".into()),
        (180, vec![0xFF; 4], "V_DWORD", "4294967295".into()),
        (184, vec![0xFF; 8], "V_LWORD", "18446744073709551615".into()),
        (192, vec![0x80], "V_SINT", "-128".into()),
        (192, vec![0x7F], "V_SINT", "127".into()),
        (
            196,
            i32::MIN.to_le_bytes().to_vec(),
            "V_DINT",
            "-2147483648".into(),
        ),
        (
            196,
            i32::MAX.to_le_bytes().to_vec(),
            "V_DINT",
            "2147483647".into(),
        ),
        (
            200,
            i64::MIN.to_le_bytes().to_vec(),
            "V_LINT",
            "-9223372036854775808".into(),
        ),
        (
            200,
            i64::MAX.to_le_bytes().to_vec(),
            "V_LINT",
            "9223372036854775807".into(),
        ),
        (208, vec![0xFF], "V_USINT", "255".into()),
        (210, vec![0xFF; 2], "V_UINT", "65535".into()),
        (212, vec![0xFF; 4], "V_UDINT", "4294967295".into()),
        (216, vec![0xFF; 8], "V_ULINT", "18446744073709551615".into()),
        // One below: a change a double could not see.
        (
            216,
            (u64::MAX - 1).to_le_bytes().to_vec(),
            "V_ULINT",
            "18446744073709551614".into(),
        ),
        (
            124,
            21.5f32.to_le_bytes().to_vec(),
            "SETPOINT",
            "21.500000".into(),
        ),
        (
            124,
            f32::MIN_POSITIVE.to_le_bytes().to_vec(),
            "SETPOINT",
            "0.000000".into(),
        ),
        (
            32,
            (-2.5f64).to_le_bytes().to_vec(),
            "C",
            "-2.5000000000".into(),
        ),
        (
            16,
            0.5f64.to_le_bytes().to_vec(),
            "SINUS",
            "0.5000000000".into(),
        ),
        (
            0,
            1_699_920_000f64.to_le_bytes().to_vec(),
            "DAT",
            date_bits(1_699_920_000.0).to_string(),
        ),
        (
            232,
            1_700_000_000.5f64.to_le_bytes().to_vec(),
            "V_DT",
            date_bits(1_700_000_000.5).to_string(),
        ),
        (
            8,
            86_399_999u32.to_le_bytes().to_vec(),
            "TIM",
            "86399999".into(),
        ),
        (
            8,
            u32::MAX.to_le_bytes().to_vec(),
            "TIM",
            "4294967295".into(),
        ),
        (
            224,
            3_600_000u32.to_le_bytes().to_vec(),
            "V_TOD",
            "3600000".into(),
        ),
        (
            41,
            b"Have a nice day\0".to_vec(),
            "TEXT",
            "\"Have a nice day\"".into(),
        ),
        (40, vec![0x01], "POSITIVE", "1".into()),
        (240, vec![0x01], "FLAG_A", "1".into()),
        (240, vec![0x03], "FLAG_B", "1".into()),
        (240, vec![0x02], "FLAG_A", "0".into()),
        (
            244,
            36.6f32.to_le_bytes().to_vec(),
            "TEPLOTA_KUCHYN\u{CC}",
            "36.599998".into(),
        ),
    ];
    for (offset, bytes, name, shown) in &steps {
        poke(&sim, r, *offset, bytes);
        c.expect(&diff_line(name, shown)).await;
    }
    // A cp1250 STRING[40].
    let mut note = CZECH.to_vec();
    note.push(0);
    poke(&sim, r, 132, &note);
    let mut want = b"DIFF:NOTE,\"".to_vec();
    want.extend_from_slice(CZECH);
    want.extend_from_slice(b"\"\r\n");
    c.expect(&want).await;

    // A bit no variable names changes in the byte FLAG_A and FLAG_B share:
    // no DIFF. TEPLOTA_KUCHYNĚ comes after both flags in table order, so a
    // flag DIFF of the same or an earlier poll would arrive before it.
    poke(&sim, r, 240, &[0x06]);
    poke(&sim, r, 244, 1.0f32.to_le_bytes().as_ref());
    c.expect(&diff_line("TEPLOTA_KUCHYN\u{CC}", "1.000000"))
        .await;
    assert!(c.buffered().is_empty());
}

#[tokio::test]
async fn set_read_back_is_the_answer_and_the_other_clients_diff() {
    let sim = spawn_sim(any_port(), ProgramKind::Idle).await;
    let server = start_server(sim.local_addr(), "", FAST_LINK).await;
    let mut writer = Client::connect(server.local_addr).await;
    let mut watcher = Client::connect(server.local_addr).await;
    for c in [&mut writer, &mut watcher] {
        c.ask(
            "EN:counter\nEN:v_tod\n",
            "WARNING:252 Changed active variables in public file: '[3/29]'\r\n\
             WARNING:252 Changed active variables in public file: '[4/29]'\r\n",
        )
        .await;
        // The second client's EN may come after the first poll of COUNTER.
        c.wait_for_line(b"DIFF:V_TOD,0\r\n", SLOW).await;
    }
    writer.ask("SET:counter,42\n", "DIFF:COUNTER,42\r\n").await;
    watcher.expect(b"DIFF:COUNTER,42\r\n").await;
    assert_eq!(peek(&sim, Area::R, 130, 2), 42i16.to_le_bytes());
    // The writer is not told twice: the next line it gets is the next change.
    poke(&sim, Area::R, 224, &5u32.to_le_bytes());
    writer.expect(b"DIFF:V_TOD,5\r\n").await;
    watcher.expect(b"DIFF:V_TOD,5\r\n").await;

    // The answer is the value read back from the PLC: 2^24 + 1 is no REAL.
    writer
        .ask(
            "SET:setpoint,16777217\n",
            "DIFF:SETPOINT,16777216.000000\r\n",
        )
        .await;
    assert_eq!(peek(&sim, Area::R, 124, 4), 16_777_216f32.to_le_bytes());
    // A GET right behind a SET sees the SET, also through EPSNET.
    writer
        .ask(
            "SET:v_lint,-1\nGET:v_lint\n",
            "DIFF:V_LINT,-1\r\nGET:V_LINT,-1\r\n",
        )
        .await;
}

fn text(line: &[u8]) -> String {
    String::from_utf8_lossy(line).into_owned()
}

/// The value of a `DIFF:<name>,<value>\r\n` line.
fn diff_value<'a>(line: &'a str, name: &str) -> Option<&'a str> {
    line.strip_prefix("DIFF:")?
        .strip_prefix(name)?
        .strip_prefix(',')?
        .strip_suffix("\r\n")
}

#[tokio::test]
async fn halt_then_run_diffs_plc_run_and_polling_goes_on() {
    let sim = spawn_sim(any_port(), ProgramKind::Demo).await;
    let server = start_server(sim.local_addr(), "", FAST_LINK).await;
    let mut c = Client::connect(server.local_addr).await;
    c.ask(
        "EN:__plc_run\nEN:tim\nEN:counter\n",
        "WARNING:252 Changed active variables in public file: '[2/29]'\r\n\
         WARNING:252 Changed active variables in public file: '[3/29]'\r\n\
         WARNING:252 Changed active variables in public file: '[4/29]'\r\n",
    )
    .await;
    // Both values, from whichever polls they come in.
    c.wait_for_lines(&[b"DIFF:__PLC_RUN,1\r\n", b"DIFF:COUNTER,0\r\n"], SLOW)
        .await;

    sim.halt();
    for line in c.wait_for_line(b"DIFF:__PLC_RUN,0\r\n", SLOW).await {
        assert!(text(&line).starts_with("DIFF:TIM,"), "{}", text(&line));
    }
    // Still polled in HALT; the program is frozen: two polls later no TIM
    // has changed.
    poke(&sim, Area::R, 130, &7i16.to_le_bytes());
    c.wait_for_line(b"DIFF:COUNTER,7\r\n", SLOW).await;
    poke(&sim, Area::R, 130, &8i16.to_le_bytes());
    c.expect(b"DIFF:COUNTER,8\r\n").await;
    c.ask("GET:counter\n", "GET:COUNTER,8\r\n").await;

    sim.run();
    // HALT -> RUN re-initialises the link; DIFFs go on without the client
    // doing anything.
    for line in c.wait_for_line(b"DIFF:__PLC_RUN,1\r\n", SLOW).await {
        assert!(text(&line).starts_with("DIFF:TIM,"), "{}", text(&line));
    }
    let line = text(&c.line_within(SLOW).await.expect("TIM runs again"));
    assert!(diff_value(&line, "TIM").is_some(), "{line}");
    poke(&sim, Area::R, 130, &9i16.to_le_bytes());
    for line in c.wait_for_line(b"DIFF:COUNTER,9\r\n", SLOW).await {
        assert!(text(&line).starts_with("DIFF:TIM,"), "{}", text(&line));
    }
}

/// Seconds since 1970 of a UTC civil time.
fn unix(year: i32, month: u32, day: u32, h: u32, m: u32, s: u32) -> i64 {
    chrono::NaiveDate::from_ymd_opt(year, month, day)
        .unwrap()
        .and_hms_opt(h, m, s)
        .unwrap()
        .and_utc()
        .timestamp()
}

#[tokio::test]
async fn demo_program_values_arrive_as_diffs() {
    let sim = spawn_sim(any_port(), ProgramKind::Demo).await;
    let server = start_server(sim.local_addr(), "", FAST_LINK).await;
    let mut c = Client::connect(server.local_addr).await;
    c.send(b"EN:dat\nEN:tim\nEN:sinus\nEN:cosinus\nEN:c\nEN:positive\nEN:text\n")
        .await;
    for n in 3..=9 {
        c.expect(
            format!("WARNING:252 Changed active variables in public file: '[{n}/29]'\r\n")
                .as_bytes(),
        )
        .await;
    }
    let (mut sinus, mut cosinus, mut tims, mut cs) = (vec![], vec![], vec![], vec![]);
    let (mut dat, mut positive, mut greeting) = (None, false, false);
    let deadline = tokio::time::Instant::now() + SLOW;
    while sinus.len() < 5 || cosinus.len() < 5 || tims.len() < 5 || !positive || !greeting {
        assert!(tokio::time::Instant::now() < deadline, "demo values");
        let line = text(&c.line_within(SLOW).await.expect("demo DIFFs"));
        let host_ms = chrono::Utc::now().timestamp_millis();
        if let Some(v) = diff_value(&line, "SINUS") {
            let v: f64 = v.parse().unwrap();
            assert!((-1.0..=1.0).contains(&v), "{line}");
            sinus.push(v);
        } else if let Some(v) = diff_value(&line, "COSINUS") {
            let v: f64 = v.parse().unwrap();
            assert!((-1.0..=1.0).contains(&v), "{line}");
            cosinus.push(v);
        } else if let Some(v) = diff_value(&line, "C") {
            cs.push(v.parse::<f64>().unwrap());
        } else if let Some(v) = diff_value(&line, "TIM") {
            // Milliseconds of the (UTC) day, as the host sees it.
            let v: i64 = v.parse().unwrap();
            let host = host_ms.rem_euclid(86_400_000);
            let off = (host - v).rem_euclid(86_400_000);
            assert!(
                !(10_000..86_390_000).contains(&off),
                "TIM {v} vs host {host}"
            );
            tims.push(v);
        } else if let Some(v) = diff_value(&line, "DAT") {
            dat = Some(v.parse::<u64>().unwrap());
        } else if line == "DIFF:POSITIVE,1\r\n" {
            positive = true;
        } else if line == "DIFF:TEXT,\"Have a nice day\"\r\n" {
            greeting = true;
        } else {
            panic!("unexpected {line}");
        }
    }
    // c := c + 0.001 every cycle: it only grows.
    assert!(
        cs.len() >= 2 && cs.windows(2).all(|w| w[0] < w[1]),
        "{cs:?}"
    );
    let today = (chrono::Utc::now().timestamp() / 86_400 * 86_400) as f64;
    let dat = dat.expect("DAT arrives");
    assert!(
        dat == date_bits(today) || dat == date_bits(today - 86_400.0),
        "DAT {dat}"
    );

    // Another EPSNET station sets the PLC clock (SETTID): DAT follows.
    let mut eps = EpsnetConfig::new(sim.local_addr());
    eps.local_ip = "127.0.0.1".parse().unwrap();
    let mut other = EpsnetBackend::new(eps);
    let set = plccoms_plc::epsnet::service::PlcTime {
        year: 2030,
        month: 1,
        day: 2,
        hour: 3,
        minute: 4,
        second: 5,
        weekday: 3,
    };
    other.set_time(set).await.unwrap().unwrap();
    let day = unix(2030, 1, 2, 0, 0, 0) as f64;
    let want = diff_line("DAT", &date_bits(day).to_string());
    for line in c.wait_for_line(&want, SLOW).await {
        let line = text(&line);
        assert!(
            ["SINUS", "COSINUS", "C", "TIM", "POSITIVE"]
                .iter()
                .any(|n| diff_value(&line, n).is_some()),
            "{line}"
        );
    }
}

#[tokio::test]
async fn plc_stopped_then_restarted_on_the_same_port() {
    let (sim, server, mut watcher) = watched_idle_plc().await;
    let plc = sim.local_addr();
    let mut c = Client::connect(server.local_addr).await;
    c.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;

    sim.stop().await;
    // Straight after the loss the poller may still count the PLC as online:
    // then the read itself fails (ERROR:20); else ERROR:10. Either way the
    // answer comes, after the link's retries, not never.
    let started = tokio::time::Instant::now();
    c.send(b"GET:counter\n").await;
    let first = c
        .line_within(SLOW)
        .await
        .expect("GET answered during outage");
    assert!(
        first == b"ERROR:10 Unable to connect to PLC.\r\n"
            || first == b"ERROR:20 Unable to get data from PLC.\r\n",
        "{}",
        text(&first)
    );
    assert!(started.elapsed() < Duration::from_secs(10));
    eventually("the poller notices", SLOW, || {
        server.section.link_state() != plccoms_core::link::LinkState::Online
    })
    .await;
    // Once the PLC is known lost: ERROR:10 for reads and writes, also of a
    // polled variable (no stale value passed off as current).
    c.ask("GET:counter\n", "ERROR:10 Unable to connect to PLC.\r\n")
        .await;
    c.ask("GET:setpoint\n", "ERROR:10 Unable to connect to PLC.\r\n")
        .await;
    c.ask("GET:%RW130\n", "ERROR:10 Unable to connect to PLC.\r\n")
        .await;
    c.ask("SET:counter,77\n", "ERROR:10 Unable to connect to PLC.\r\n")
        .await;
    c.ask("SET:%RW130,78\n", "ERROR:10 Unable to connect to PLC.\r\n")
        .await;
    // What needs no PLC still works.
    c.ask("LIST:counter\n", "LIST:COUNTER,INT*\r\nLIST:\r\n")
        .await;

    // The PLC comes back on the same address with fresh memory. It drops
    // everything until its memory is set, so the first poll sees 2.5.
    let sim = plcsim::spawn(SimConfig {
        bind: plc,
        program: ProgramKind::Idle,
        loss: 1.0,
        ..SimConfig::default()
    })
    .await
    .expect("the same port again");
    poke(&sim, Area::R, 124, &2.5f32.to_le_bytes());
    sim.set_loss(0.0);
    // Without reconnecting, the watcher gets the new value, and nothing
    // else happened on its connection meanwhile.
    let skipped = watcher
        .wait_for_line(b"DIFF:SETPOINT,2.500000\r\n", SLOW)
        .await;
    assert!(skipped.is_empty(), "{skipped:?}");
    assert!(server.section.link_state() == plccoms_core::link::LinkState::Online);
    // The SETs refused during the outage were not kept for later.
    c.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;
    assert_eq!(peek(&sim, Area::R, 130, 2), [0, 0]);
    c.ask("SET:counter,5\n", "DIFF:COUNTER,5\r\n").await;
    poke(&sim, Area::R, 124, &3.5f32.to_le_bytes());
    watcher.expect(b"DIFF:SETPOINT,3.500000\r\n").await;
}

#[tokio::test]
async fn twenty_percent_packet_loss() {
    let sim = spawn_sim(any_port(), ProgramKind::Idle).await;
    sim.set_loss(0.2);
    // Each datagram is lost with p = 0.2 and tried 1 + 8 times: a batch
    // fails with p = 0.2^9 = 5e-7 (with the default 3 retries, 1.6e-3).
    let link = Link {
        timeout_ms: 100,
        step_ms: 50,
        retries: 8,
    };
    let server = start_server(sim.local_addr(), "", link).await;
    let mut watcher = Client::connect(server.local_addr).await;
    watcher
        .ask(
            "EN:v_udint\n",
            "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
        )
        .await;
    watcher.expect(b"DIFF:V_UDINT,0\r\n").await;
    let mut c = Client::connect(server.local_addr).await;
    // A SET that waited longer than EPSTOUT (here 100 ms: any poll that lost
    // a datagram) is refused with ERROR:21 and never sent; every other
    // answer is exact, whole and in order.
    let (mut counter, mut lint, mut flag, mut refused) = (0i64, 0i64, 0i64, 0);
    let set = async |c: &mut Client, name: &str, value: i64, now: &mut i64| {
        let line = c.line().await;
        if line == format!("DIFF:{name},{value}\r\n").as_bytes() {
            *now = value;
            0
        } else {
            assert_eq!(
                String::from_utf8_lossy(&line),
                "ERROR:21 Unable to send data to PLC.\r\n"
            );
            1
        }
    };
    for round in 0..50i64 {
        let big = -round * 1_000_000_000_007;
        c.send(
            format!(
                "SET:counter,{round}\nGET:counter\nSET:v_lint,{big}\nGET:%RW130\n\
                 GET:v_lint\nSET:flag_b,{}\nGET:flag_*\n",
                round % 2
            )
            .as_bytes(),
        )
        .await;
        refused += set(&mut c, "COUNTER", round, &mut counter).await;
        c.expect(format!("GET:COUNTER,{counter}\r\n").as_bytes())
            .await;
        refused += set(&mut c, "V_LINT", big, &mut lint).await;
        c.expect(format!("GET:%RW130,{counter}\r\nGET:V_LINT,{lint}\r\n").as_bytes())
            .await;
        refused += set(&mut c, "FLAG_B", round % 2, &mut flag).await;
        c.expect(format!("GET:FLAG_A,0\r\nGET:FLAG_B,{flag}\r\nGET:\r\n").as_bytes())
            .await;
        assert_eq!(peek(&sim, Area::R, 200, 8), lint.to_le_bytes());
        if round % 5 == 0 {
            // DIFFs keep flowing: each change arrives, exactly once.
            let value = round as u32 + 1;
            poke(&sim, Area::R, 212, &value.to_le_bytes());
            watcher
                .expect(format!("DIFF:V_UDINT,{value}\r\n").as_bytes())
                .await;
        }
    }
    eprintln!(
        "{refused} of 150 SETs refused (waited over EPSTOUT behind a poll that lost datagrams)"
    );
    assert!(refused < 120, "{refused} of 150 SETs refused");
    assert!(server.section.link_state() == plccoms_core::link::LinkState::Online);
}

#[tokio::test]
async fn shutdown_answers_every_request_already_received() {
    let sim = spawn_sim(any_port(), ProgramKind::Idle).await;
    let slow = Link {
        timeout_ms: 5000,
        step_ms: 0,
        retries: 0,
    };
    let server = start_server(sim.local_addr(), "", slow).await;
    let mut c = Client::connect(server.local_addr).await;
    c.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;
    // Every PLC answer now takes 300 ms: the GET and the SETCONF are under
    // way, the 50 GETs behind the SETCONF received but not yet handled, when
    // the server is told to stop.
    sim.set_latency(Duration::from_millis(300));
    let mut requests = b"LIST:counter\nGET:%RW130\nSETCONF:pubfile,//x.pub\n".to_vec();
    for _ in 0..50 {
        requests.extend_from_slice(b"GET:%RW130\n");
    }
    c.send(&requests).await;
    c.expect(b"LIST:COUNTER,INT*\r\nLIST:\r\n").await;
    server.stop_accepting();
    c.expect(b"GET:%RW130,0\r\n").await;
    c.expect(b"ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,//x.pub'\r\n")
        .await;
    for _ in 0..50 {
        c.expect(b"GET:%RW130,0\r\n").await;
    }
    c.closed().await;
}
