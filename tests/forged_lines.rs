//! No STRING value can forge a line for the line-protocol clients: a write
//! with a control character is refused from every writer (the telnet port
//! and the web API here; MQTT `/set` takes the same write path), and a
//! string that a PLC program put in memory with CR/LF prints escaped
//! (`\x0D\x0A`), so every byte of a DIFF stays on its line.

mod common;

use std::io::{Read, Write};
use std::time::Duration;

use common::Client;
use plccoms_protocol::Area;

/// `POST path` with a JSON body and the bearer token; the status and body.
fn post(port: u16, path: &str, body: &str) -> (u16, String) {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAuthorization: Bearer secret-token\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut answer = String::new();
    s.read_to_string(&mut answer).unwrap();
    let status = answer[9..12].parse().unwrap();
    let body = answer.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    (status, body.to_string())
}

#[tokio::test]
async fn strings_with_line_ends_are_refused_from_every_writer_and_printed_escaped() {
    let http = common::process::free_port();
    let (server, addr, _dir) = common::simulated(
        &format!("HTTP_PORT = {http}\nHTTP_TOKEN = secret-token\n"),
        "",
        None,
    )
    .await;
    let mut watcher = Client::connect(addr).await;
    watcher.send(b"EN:setpoint\nEN:note\n").await;
    watcher
        .wait_for_line(b"DIFF:NOTE,\"\"\r\n", Duration::from_secs(10))
        .await;

    // The web API: refused, nothing written.
    let forged = r#"{"name":"note","value":"0\r\nDIFF:SETPOINT,99.000000"}"#;
    let (status, body) =
        tokio::task::spawn_blocking(move || post(http, "/api/sections/PLC/set", forged))
            .await
            .unwrap();
    assert_eq!(status, 400, "{body}");
    assert!(
        body.contains("contains the control character 0x0D") && body.contains("bad_value"),
        "{body}"
    );

    // The telnet port: a TAB is a control character too.
    let mut writer = Client::connect(addr).await;
    writer
        .ask(
            "SET:note,\"a\tb\"\n",
            "ERROR:35 Wrong parameter value in request: 'SET:note,\"a\tb\"'\r\n",
        )
        .await;

    // The watcher saw no forged line, and NOTE is still empty.
    watcher.silent(300).await;
    writer.ask("GET:note\n", "GET:NOTE,\"\"\r\n").await;

    // A PLC program that puts CR/LF in a string: printed escaped, one line.
    let sim = &server.simulators()[0];
    common::epsnet::poke(sim, Area::R, 132, b"0\r\nDIFF:SETPOINT,99.000000\0");
    let lines = watcher
        .wait_for_line(
            b"DIFF:NOTE,\"0\\x0D\\x0ADIFF:SETPOINT,99.000000\"\r\n",
            Duration::from_secs(10),
        )
        .await;
    assert!(
        lines.iter().all(|l| !l.starts_with(b"DIFF:SETPOINT,99")),
        "{lines:?}"
    );
    writer
        .ask(
            "GET:note\n",
            "GET:NOTE,\"0\\x0D\\x0ADIFF:SETPOINT,99.000000\"\r\n",
        )
        .await;
    drop((watcher, writer));
    server.shutdown().await;
}
