//! Every variable command over real TCP, with exact bytes on the wire.

mod common;

use common::{start, Client};
use plccoms_protocol::Area;

fn full_list(marks: &str) -> Vec<u8> {
    let mut out = b"LIST:__PLC_RUN,BOOL\r\nLIST:__PF_CRC,DWORD\r\n".to_vec();
    for (name, ty) in [
        ("TEST_1", "INT"),
        ("TEST_2", "REAL"),
        ("TEST_STRING", "STRING[20]"),
        ("TEST_BTN_UP", "BOOL"),
        ("TEST_BTN_DOWN", "BOOL"),
        ("V_LREAL", "LREAL"),
        ("V_BYTE", "BYTE"),
        ("V_WORD", "WORD"),
        ("V_DWORD", "DWORD"),
        ("V_LWORD", "LWORD"),
        ("V_SINT", "SINT"),
        ("V_DINT", "DINT"),
        ("V_LINT", "LINT"),
        ("V_USINT", "USINT"),
        ("V_UINT", "UINT"),
        ("V_UDINT", "UDINT"),
        ("V_ULINT", "ULINT"),
        ("V_DATE", "DATE"),
        ("V_TIME", "TIME"),
        ("V_TOD", "TOD"),
        ("V_DT", "DT"),
        ("METEO.WINDDIRECTION", "UINT"),
        ("T_ZONES_SET[0].TOPIT_TC", "BOOL"),
    ] {
        out.extend_from_slice(format!("LIST:{name},{ty}{marks}\r\n").as_bytes());
    }
    out.extend_from_slice(b"LIST:TEPLOTA_KUCHYN\xCC,REAL");
    out.extend_from_slice(marks.as_bytes());
    out.extend_from_slice(b"\r\nLIST:\r\n");
    out
}

#[tokio::test]
async fn list_marks_disabled_and_hidden() {
    let server = start("").await;
    let mut c = server.client().await;
    c.send(b"LIST:\r\n").await;
    c.expect(&full_list("*")).await;
    c.ask(
        "LIST:test_btn*\n",
        "LIST:TEST_BTN_UP,BOOL*\r\nLIST:TEST_BTN_DOWN,BOOL*\r\nLIST:\r\n",
    )
    .await;
    c.ask(
        "HIDE:test_btn_down\n",
        "WARNING:253 Changed hidden variables in public file: '[1]'\r\n",
    )
    .await;
    c.ask(
        "EN:test_btn_up\n",
        "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
    )
    .await;
    // The first poll after EN sends the value.
    c.expect(b"DIFF:TEST_BTN_UP,0\r\n").await;
    c.ask(
        "LIST:TEST_BTN*\n",
        "LIST:TEST_BTN_UP,BOOL\r\nLIST:TEST_BTN_DOWN,BOOL*~\r\nLIST:\r\n",
    )
    .await;
    c.ask("LIST:nothing*\n", "LIST:\r\n").await;
    c.ask("LIST:__PLC_RUN\n", "LIST:__PLC_RUN,BOOL\r\nLIST:\r\n")
        .await;
}

#[tokio::test]
async fn list_when_all_enabled_by_default() {
    let server = start("PF_VAR_DISABLED = No").await;
    let mut c = server.client().await;
    c.send(b"LIST:\n").await;
    c.expect(&full_list("")).await;
}

#[tokio::test]
async fn get_single_mask_unknown_and_direct() {
    let server = start("").await;
    server.poke(Area::R, 0, &123i16.to_le_bytes());
    server.poke(Area::R, 4, &1.2345f32.to_le_bytes());
    server.poke(Area::R, 8, b"Hello!\0");
    let mut c = server.client().await;
    c.ask("GET:test_1\n", "GET:TEST_1,123\r\n").await;
    c.ask("get:Test_2\n", "GET:TEST_2,1.234500\r\n").await;
    c.ask(
        "GET:test_*\n",
        "GET:TEST_1,123\r\nGET:TEST_2,1.234500\r\nGET:TEST_STRING,\"Hello!\"\r\nGET:TEST_BTN_UP,0\r\nGET:TEST_BTN_DOWN,0\r\nGET:\r\n",
    )
    .await;
    c.ask("GET:*_2\n", "GET:TEST_2,1.234500\r\nGET:\r\n").await;
    c.ask(
        "GET:test\n",
        "ERROR:33 Unknown variable name in request: 'GET:test'\r\n",
    )
    .await;
    c.ask("GET:nothing*\n", "GET:\r\n").await;
    c.ask("GET:%R0\n", "GET:%R0,123\r\n").await;
    c.ask("GET:%rw0\n", "GET:%RW0,123\r\n").await;
    c.ask(
        "GET:%R600000\n",
        "ERROR:80 Unable to get data from address: '%R600000'\r\n",
    )
    .await;
    c.ask(
        "GET:%Q5\n",
        "ERROR:80 Unable to get data from address: '%Q5'\r\n",
    )
    .await;
}

#[tokio::test]
async fn set_answers_with_the_value_read_back() {
    let server = start("").await;
    let mut c = server.client().await;
    c.ask("SET:test_1,123\n", "DIFF:TEST_1,123\r\n").await;
    assert_eq!(server.peek(Area::R, 0, 2), 123i16.to_le_bytes());
    c.ask("SET:test_1,-32768\n", "DIFF:TEST_1,-32768\r\n").await;
    c.ask(
        "SET:test_1,32768\n",
        "ERROR:35 Wrong parameter value in request: 'SET:test_1,32768'\r\n",
    )
    .await;
    assert_eq!(server.peek(Area::R, 0, 2), (-32768i16).to_le_bytes());
    c.ask(
        "SET:test_string,\"Hello, world: yes\"\n",
        "DIFF:TEST_STRING,\"Hello, world: yes\"\r\n",
    )
    .await;
    c.ask("SET:test_string,\"123456789012345678901\"\n", "ERROR:35 Wrong parameter value in request: 'SET:test_string,\"123456789012345678901\"'\r\n").await;
    c.ask("SET:test_2,2.5\n", "DIFF:TEST_2,2.500000\r\n").await;
    c.ask(
        "SET:v_lreal,3.14159265358979\n",
        "DIFF:V_LREAL,3.1415926536\r\n",
    )
    .await;
    c.ask(
        "SET:nothing,1\n",
        "ERROR:33 Unknown variable name in request: 'SET:nothing,1'\r\n",
    )
    .await;
    c.ask("SET:test_1\n", "ERROR:31 Incomplete client request.\r\n")
        .await;
    c.ask("SET:%RW200,513\n", "DIFF:%RW200,513\r\n").await;
    assert_eq!(server.peek(Area::R, 200, 2), [1, 2]);
}

#[tokio::test]
async fn two_bools_in_one_byte_both_stick() {
    let server = start("").await;
    let mut c = server.client().await;
    c.send(b"SET:test_btn_up,true\nSET:test_btn_down,TRUE\n")
        .await;
    c.expect(b"DIFF:TEST_BTN_UP,1\r\nDIFF:TEST_BTN_DOWN,1\r\n")
        .await;
    assert_eq!(server.peek(Area::R, 30, 1), [0b11]);
    c.ask("SET:test_btn_up,false\n", "DIFF:TEST_BTN_UP,0\r\n")
        .await;
    assert_eq!(server.peek(Area::R, 30, 1), [0b10]);
    c.ask(
        "SET:test_btn_up,2\n",
        "ERROR:35 Wrong parameter value in request: 'SET:test_btn_up,2'\r\n",
    )
    .await;
}

#[tokio::test]
async fn every_type_formats_and_round_trips() {
    let server = start("").await;
    let mut c = server.client().await;
    for (name, value, shown) in [
        ("V_BYTE", "255", "255"),
        ("V_WORD", "65535", "65535"),
        ("V_DWORD", "4294967295", "4294967295"),
        ("V_LWORD", "18446744073709551615", "18446744073709551615"),
        ("V_SINT", "-128", "-128"),
        ("V_DINT", "-2147483648", "-2147483648"),
        ("V_LINT", "-9223372036854775808", "-9223372036854775808"),
        ("V_USINT", "200", "200"),
        ("V_UINT", "40000", "40000"),
        ("V_UDINT", "3000000000", "3000000000"),
        ("V_ULINT", "9007199254740993", "9007199254740993"),
        ("V_TIME", "86399999", "86399999"),
        ("V_TOD", "3600000", "3600000"),
        ("V_DATE", "4743316646144000000", "4743316646144000000"),
        ("V_DT", "4743316646144000000", "4743316646144000000"),
        ("METEO.WINDDIRECTION", "270", "270"),
        ("T_ZONES_SET[0].TOPIT_TC", "1", "1"),
    ] {
        c.ask(
            &format!("SET:{name},{value}\n"),
            &format!("DIFF:{name},{shown}\r\n"),
        )
        .await;
        c.ask(&format!("GET:{name}\n"), &format!("GET:{name},{shown}\r\n"))
            .await;
    }
    c.ask(
        "SET:V_BYTE,-1\n",
        "ERROR:35 Wrong parameter value in request: 'SET:V_BYTE,-1'\r\n",
    )
    .await;
}

#[tokio::test]
async fn czech_names_and_strings_round_trip_in_cp1250() {
    let server = start("").await;
    let mut c = server.client().await;
    // "teplota_kuchyně" in lower case cp1250, answered in upper case.
    c.send(b"SET:teplota_kuchyn\xEC,21.5\n").await;
    c.expect(b"DIFF:TEPLOTA_KUCHYN\xCC,21.500000\r\n").await;
    c.send(b"SET:test_string,\"\xE8erven\xFD \xBE\xEDv\xFD\"\n")
        .await;
    c.expect(b"DIFF:TEST_STRING,\"\xE8erven\xFD \xBE\xEDv\xFD\"\r\n")
        .await;
    c.send(b"GET:TEST_STRING\n").await;
    c.expect(b"GET:TEST_STRING,\"\xE8erven\xFD \xBE\xEDv\xFD\"\r\n")
        .await;
}

#[tokio::test]
async fn en_di_counts_and_diffs() {
    let server = start("").await;
    let mut c = server.client().await;
    c.ask(
        "EN:test_1\n",
        "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
    )
    .await;
    // The first poll sends the current value.
    c.expect(b"DIFF:TEST_1,0\r\n").await;
    server.poke(Area::R, 0, &7i16.to_le_bytes());
    c.expect(b"DIFF:TEST_1,7\r\n").await;
    c.ask(
        "EN:\n",
        "WARNING:252 Changed active variables in public file: '[26/26]'\r\n",
    )
    .await;
    c.ask(
        "DI:\n",
        "WARNING:252 Changed active variables in public file: '[2/26]'\r\n",
    )
    .await;
    c.ask(
        "DI:test_1 a\n",
        "ERROR:35 Wrong parameter value in request: 'DI:test_1 a'\r\n",
    )
    .await;
    c.ask(
        "EN:temp a\n",
        "ERROR:35 Wrong parameter value in request: 'EN:temp a'\r\n",
    )
    .await;
    c.ask(
        "EN:temp\n",
        "ERROR:33 Unknown variable name in request: 'EN:temp'\r\n",
    )
    .await;
    c.ask(
        "EN:v_*int 0\n",
        "WARNING:252 Changed active variables in public file: '[9/26]'\r\n",
    )
    .await;
}

#[tokio::test]
async fn diff_respects_delta_exactly_for_64_bit_integers() {
    let server = start("").await;
    server.poke(Area::R, 80, &9007199254740992u64.to_le_bytes());
    server.poke(Area::R, 0, &100i16.to_le_bytes());
    let mut c = server.client().await;
    c.ask(
        "EN:v_ulint 0\n",
        "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
    )
    .await;
    c.expect(b"DIFF:V_ULINT,9007199254740992\r\n").await;
    // One more than 2^53: a double would see no change.
    server.poke(Area::R, 80, &9007199254740993u64.to_le_bytes());
    c.expect(b"DIFF:V_ULINT,9007199254740993\r\n").await;
    c.ask(
        "EN:test_1 5\n",
        "WARNING:252 Changed active variables in public file: '[4/26]'\r\n",
    )
    .await;
    c.expect(b"DIFF:TEST_1,100\r\n").await;
    server.poke(Area::R, 0, &105i16.to_le_bytes());
    c.silent(400).await;
    server.poke(Area::R, 0, &106i16.to_le_bytes());
    c.expect(b"DIFF:TEST_1,106\r\n").await;
}

#[tokio::test]
async fn set_of_an_enabled_variable_is_answered_once() {
    let server = start("").await;
    let mut c = server.client().await;
    let mut other = server.client().await;
    c.ask(
        "EN:test_1\n",
        "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
    )
    .await;
    c.expect(b"DIFF:TEST_1,0\r\n").await;
    other
        .ask(
            "EN:test_1\n",
            "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
        )
        .await;
    other.expect(b"DIFF:TEST_1,0\r\n").await;
    c.ask("SET:test_1,42\n", "DIFF:TEST_1,42\r\n").await;
    other.expect(b"DIFF:TEST_1,42\r\n").await;
    c.silent(300).await;
    // A GET right after a SET sees the new value.
    c.ask(
        "SET:test_1,43\nGET:test_1\n",
        "DIFF:TEST_1,43\r\nGET:TEST_1,43\r\n",
    )
    .await;
}

#[tokio::test]
async fn hidden_variables_skip_the_all_forms_only() {
    let server = start("").await;
    let mut c = server.client().await;
    // Only the answers matter here, not the DIFF lines EN causes.
    c.ask("SETCONF:diff,no\n", "SETCONF:DIFF,NO\r\n").await;
    c.ask(
        "HIDE:v_*\n",
        "WARNING:253 Changed hidden variables in public file: '[16]'\r\n",
    )
    .await;
    c.ask(
        "UNHIDE:v_byte\n",
        "WARNING:253 Changed hidden variables in public file: '[15]'\r\n",
    )
    .await;
    c.ask(
        "EN:*\n",
        "WARNING:252 Changed active variables in public file: '[11/26]'\r\n",
    )
    .await;
    c.ask(
        "EN:v_word\n",
        "WARNING:252 Changed active variables in public file: '[12/26]'\r\n",
    )
    .await;
    c.ask(
        "HIDE:nope\n",
        "ERROR:33 Unknown variable name in request: 'HIDE:nope'\r\n",
    )
    .await;
    c.ask(
        "UNHIDE:*\n",
        "WARNING:253 Changed hidden variables in public file: '[0]'\r\n",
    )
    .await;
}

#[tokio::test]
async fn continuation_lines_repeat_the_command() {
    let server = start("").await;
    server.poke(Area::R, 0, &5i16.to_le_bytes());
    let mut c = server.client().await;
    c.ask(
        "GET:test_1\ntest_2\nv_byte\n",
        "GET:TEST_1,5\r\nGET:TEST_2,0.000000\r\nGET:V_BYTE,0\r\n",
    )
    .await;
    c.ask(
        "SET:v_byte,1\nv_usint,2\n",
        "DIFF:V_BYTE,1\r\nDIFF:V_USINT,2\r\n",
    )
    .await;
    c.ask(
        "GET:test_1\nnope\n",
        "GET:TEST_1,5\r\nERROR:33 Unknown variable name in request: 'GET:nope'\r\n",
    )
    .await;
    c.ask("GETINFO:version_plc\nv_byte\n", "GETINFO:VERSION_PLC,CP1000    SIM 1.0 1.0\r\nERROR:32 Unknown command name in request: 'v_byte'\r\n").await;
}

/// HELP is `HELP:`, as in the vendor's manual (`HELP:\n`): every command
/// ends in its colon. A bare `HELP` is a line without one, which continues
/// the command before it (after `GET:a`, `GET:HELP`: a variable may be
/// called HELP) and is an unknown command when none came before.
#[tokio::test]
async fn help_is_answered_with_its_colon_and_a_bare_help_is_a_continuation() {
    let server = start("").await;
    let mut c = server.client().await;
    c.send(b"help:\n").await;
    let mut lines = Vec::new();
    loop {
        let line = String::from_utf8(c.line().await).unwrap();
        if line == "HELP:\r\n" {
            break;
        }
        assert!(line.starts_with("HELP:"), "{line:?}");
        lines.push(line);
    }
    assert_eq!(lines.len(), 15, "{lines:?}");
    assert!(lines[0].starts_with("HELP:LIST:[mask]"), "{lines:?}");
    assert!(lines[14].starts_with("HELP:HELP: "), "{lines:?}");
    c.ask(
        "HELP\n",
        "ERROR:32 Unknown command name in request: 'HELP'\r\n",
    )
    .await;
    c.ask(
        "GET:test_1\nHELP\n",
        "GET:TEST_1,0\r\nERROR:33 Unknown variable name in request: 'GET:HELP'\r\n",
    )
    .await;
}

#[tokio::test]
async fn unknown_commands_bad_lines_and_empty_lines() {
    let server = start("").await;
    let mut c = server.client().await;
    c.ask(
        "FOO:bar\n",
        "ERROR:32 Unknown command name in request: 'FOO:bar'\r\n",
    )
    .await;
    c.ask(
        "\n\r\n  \nhello\n",
        "ERROR:32 Unknown command name in request: 'hello'\r\n",
    )
    .await;
    let mut long = b"GET:".to_vec();
    long.extend(std::iter::repeat_n(b'A', 20_000));
    long.push(b'\n');
    c.send(&long).await;
    c.expect(b"ERROR:30 Bad client request: 'GET:AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA...'\r\n").await;
    c.ask("GET:test_1\n", "GET:TEST_1,0\r\n").await;
}

#[tokio::test]
async fn pipelined_burst_of_250_gets_answered_in_order() {
    let server = start("").await;
    let mut c = server.client().await;
    let mut burst = Vec::new();
    let mut want = Vec::new();
    for i in 0..250u32 {
        let name = ["TEST_1", "V_BYTE", "%R0", "V_UINT", "TEST_BTN_UP"][i as usize % 5];
        burst.extend_from_slice(format!("GET:{name}\r\n").as_bytes());
        want.extend_from_slice(format!("GET:{name},0\r\n").as_bytes());
        if i == 100 {
            burst.extend_from_slice(b"SET:v_uint,0\r\n");
            want.extend_from_slice(b"DIFF:V_UINT,0\r\n");
        }
    }
    c.send(&burst).await;
    c.expect(&want).await;
}

#[tokio::test]
async fn line_ends_follow_the_setting_and_setconf() {
    let server = start("END_LINE_CRLF = No").await;
    let mut c = server.client().await;
    c.ask("GET:test_1\r\n", "GET:TEST_1,0\n").await;
    c.ask("SETCONF:crlf,yes\n", "SETCONF:CRLF,YES\r\n").await;
    c.ask("GET:test_1\n", "GET:TEST_1,0\r\n").await;
    c.ask("SETCONF: crlf , no\n", "SETCONF:CRLF,NO\n").await;
    // The booleans of the ini file.
    c.ask("SETCONF:crlf,On\n", "SETCONF:CRLF,YES\r\n").await;
    c.ask("SETCONF:CRLF,off\n", "SETCONF:CRLF,NO\n").await;
    c.ask("SETCONF:crlf,TRUE\n", "SETCONF:CRLF,YES\r\n").await;
    c.ask("SETCONF:crlf,0\n", "SETCONF:CRLF,NO\n").await;
    c.ask(
        "SETCONF:crlf,maybe\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:crlf,maybe'\n",
    )
    .await;
    c.ask(
        "SETCONF:nothing,1\n",
        "ERROR:50 Unknown name in request: 'SETCONF:nothing,1'\n",
    )
    .await;
}

#[tokio::test]
async fn setconf_diff_switches_diffs_off_for_this_client_only() {
    let server = start("").await;
    let mut quiet = server.client().await;
    let mut loud = server.client().await;
    quiet.ask("SETCONF:diff,no\n", "SETCONF:DIFF,NO\r\n").await;
    quiet
        .ask(
            "EN:test_1\n",
            "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
        )
        .await;
    loud.ask(
        "EN:test_1\n",
        "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
    )
    .await;
    loud.expect(b"DIFF:TEST_1,0\r\n").await;
    server.poke(Area::R, 0, &9i16.to_le_bytes());
    loud.expect(b"DIFF:TEST_1,9\r\n").await;
    quiet.silent(300).await;
    // SET is not answered when DIFF lines are off.
    quiet
        .ask("SET:test_1,3\nGET:test_1\n", "GET:TEST_1,3\r\n")
        .await;
}

#[tokio::test]
async fn telnet_negotiation_is_skipped_and_ctrl_d_closes() {
    let server = start("").await;
    let mut c = server.client().await;
    c.send(b"\xff\xfd\x03\xff\xfb\x18\xff\xfb\x1f\xff\xfa\x1f\x00\x50\x00\x18\xff\xf0GET:te\xff\xfb\x01st_1\r\n").await;
    c.expect(b"GET:TEST_1,0\r\n").await;
    c.send(b"\x04").await;
    c.closed().await;
}

#[tokio::test]
async fn half_closing_client_gets_its_answers() {
    let server = start("").await;
    let mut c = server.client().await;
    c.send(b"GET:test_1\nSET:v_byte,4\nGET:v_byte").await;
    c.stream.shutdown().await.unwrap();
    c.expect(b"GET:TEST_1,0\r\nDIFF:V_BYTE,4\r\nGET:V_BYTE,4\r\n")
        .await;
    c.closed().await;
}

#[tokio::test]
async fn net_connect_max_refuses_with_error_11() {
    let server = start("NET_CONNECT_MAX = 2").await;
    let mut a = server.client().await;
    let mut b = server.client().await;
    a.ask("GET:test_1\n", "GET:TEST_1,0\r\n").await;
    b.ask("GET:test_1\n", "GET:TEST_1,0\r\n").await;
    let mut refused = server.client().await;
    refused
        .expect(b"ERROR:11 Maximum connections reached.\r\n")
        .await;
    refused.closed().await;
    a.ask("GET:test_1\n", "GET:TEST_1,0\r\n").await;
    drop(b);
    // The slot frees once the server notices the close.
    let mut again = None;
    for _ in 0..50 {
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        let mut c = server.client().await;
        c.send(b"GET:test_1\n").await;
        let line = c.line().await;
        if line == b"GET:TEST_1,0\r\n" {
            again = Some(c);
            break;
        }
    }
    assert!(again.is_some(), "a slot never freed");
}

#[tokio::test]
async fn getinfo_lists_keys_and_clients() {
    let server = start("").await;
    let mut c = server.client().await;
    let _other = server.client().await;
    c.send(b"GETINFO:\n").await;
    let mut lines = Vec::new();
    loop {
        let line = c.line().await;
        let done = line == b"GETINFO:\r\n";
        lines.push(String::from_utf8(line).unwrap());
        if done {
            break;
        }
    }
    let keys: Vec<&str> = lines.iter().map(|l| l.split(',').next().unwrap()).collect();
    assert_eq!(
        keys,
        [
            "GETINFO:VERSION",
            "GETINFO:VERSION_EPSNET",
            "GETINFO:VERSION_INI",
            "GETINFO:VERSION_PLC",
            "GETINFO:IPADDR",
            "GETINFO:EPSADDR",
            "GETINFO:EPSPORT",
            "GETINFO:PUBFILE",
            "GETINFO:NETWORK",
            "GETINFO:NETWORK",
            "GETINFO:\r\n"
        ]
    );
    assert_eq!(lines[7], "GETINFO:PUBFILE,2/26 [FIXED.pub,test.pub]\r\n");
    assert!(
        lines[8].starts_with("GETINFO:NETWORK,1/128 [127.0.0.1       20"),
        "{}",
        lines[8]
    );
    c.ask("GETINFO:epsport\n", "GETINFO:EPSPORT,61682\r\n")
        .await;
    c.ask(
        "GETINFO:bogus\n",
        "ERROR:60 Unknown name in request: 'GETINFO:bogus'\r\n",
    )
    .await;
}

use tokio::io::AsyncWriteExt;

#[allow(dead_code)]
async fn unused(_: Client) {}

/// Clients that enabled everything get the poll's shared DIFF block; it must
/// say exactly what per-client selection says, and a SET's answer must not
/// come twice.
#[tokio::test]
async fn shared_diff_block_matches_per_client_diffs() {
    let server = start("").await;
    let mut all = server.client().await;
    let mut lf = server.client().await;
    all.ask(
        "EN:*\n",
        "WARNING:252 Changed active variables in public file: '[26/26]'\r\n",
    )
    .await;
    lf.ask("SETCONF:crlf,no\n", "SETCONF:CRLF,NO\n").await;
    lf.ask(
        "EN:*\n",
        "WARNING:252 Changed active variables in public file: '[26/26]'\n",
    )
    .await;
    // Both get the 26 first values, then wait for the next change.
    for c in [&mut all, &mut lf] {
        for _ in 0..26 {
            let line = c.line().await;
            assert!(line.starts_with(b"DIFF:"), "{line:?}");
        }
    }
    server.poke(Area::R, 0, &11i16.to_le_bytes());
    server.poke(Area::R, 40, &[7]);
    let mut got_all = vec![all.line().await, all.line().await];
    let mut got_lf = vec![lf.line().await, lf.line().await];
    got_all.sort();
    got_lf.sort();
    assert_eq!(
        got_all,
        [
            b"DIFF:TEST_1,11\r\n".to_vec(),
            b"DIFF:V_BYTE,7\r\n".to_vec()
        ]
    );
    assert_eq!(
        got_lf,
        [b"DIFF:TEST_1,11\n".to_vec(), b"DIFF:V_BYTE,7\n".to_vec()]
    );
    all.ask("SET:v_byte,8\n", "DIFF:V_BYTE,8\r\n").await;
    lf.expect(b"DIFF:V_BYTE,8\n").await;
    all.silent(300).await;
    server.poke(Area::R, 40, &[9]);
    all.expect(b"DIFF:V_BYTE,9\r\n").await;
    lf.expect(b"DIFF:V_BYTE,9\n").await;
}
