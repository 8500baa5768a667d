//! A section's frame trace: `SETCONF:trace,Yes` (or `TRACE = Yes`) puts the
//! section's PLC requests and answers and its clients' lines in the log at
//! trace level, for that section only, while the server logs at info; `No`
//! stops it. The built `plccoms` as a process, its simulated PLC, a raw TCP
//! client.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::{Ipv4Addr, TcpStream};
use std::thread;
use std::time::{Duration, Instant};

use common::process::{free_port, ServerProcess};

const DEADLINE: Duration = Duration::from_secs(20);

fn section(name: &str, port: u16, keys: &str) -> String {
    format!("[{name}]\nSIMULATOR = Yes\nSERVER_PORT = {port}\nPUBFILE = //demo.pub\n{keys}\n")
}

struct Client {
    stream: TcpStream,
    reader: BufReader<TcpStream>,
}

impl Client {
    fn connect(port: u16) -> Client {
        let stream = TcpStream::connect((Ipv4Addr::LOCALHOST, port)).unwrap();
        stream.set_read_timeout(Some(DEADLINE)).unwrap();
        let reader = BufReader::new(stream.try_clone().unwrap());
        Client { stream, reader }
    }

    fn ask(&mut self, line: &str) -> String {
        self.stream
            .write_all(format!("{line}\r\n").as_bytes())
            .unwrap();
        let mut answer = String::new();
        self.reader.read_line(&mut answer).unwrap();
        answer.trim_end().to_string()
    }
}

/// The frame lines of the log (level TRACE).
fn frames(server: &ServerProcess) -> Vec<String> {
    server
        .log()
        .lines()
        .filter(|l| l.contains("TRACE"))
        .map(str::to_string)
        .collect()
}

#[track_caller]
fn wait_frame(server: &ServerProcess, what: &str, found: impl Fn(&str) -> bool) {
    let start = Instant::now();
    while !frames(server).iter().any(|l| found(l)) {
        assert!(
            start.elapsed() < DEADLINE,
            "no frame line with {what}; log:\n{}",
            server.log()
        );
        thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn setconf_trace_logs_one_sections_frames_and_stops() {
    let (pa, pb, pc) = (free_port(), free_port(), free_port());
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 100\n{}{}{}",
        section("A", pa, ""),
        section("B", pb, ""),
        section("C", pc, "READ_ONLY = Yes")
    );
    let server = ServerProcess::with_config(&ini, pa);
    let mut a = Client::connect(pa);
    let mut b = Client::connect(pb);
    // Nothing is traced before it is asked for.
    assert_eq!(b.ask("GET:tim").split(',').next(), Some("GET:TIM"));
    assert!(frames(&server).is_empty(), "{}", server.log());

    assert_eq!(a.ask("SETCONF:trace,Yes"), "SETCONF:TRACE,YES");
    assert!(a.ask("GET:tim").starts_with("GET:TIM,"));
    wait_frame(&server, "A's client line", |l| {
        l.contains("-> GET:tim") && l.contains("section=A")
    });
    wait_frame(&server, "its answer", |l| {
        l.contains("<- GET:TIM,") && l.contains("section=A")
    });
    wait_frame(&server, "a PLC request", |l| {
        l.contains("PLC -> read ") && l.contains("section=A")
    });
    wait_frame(&server, "a PLC answer in hex", |l| {
        l.contains("PLC <- ") && l.contains(" ms)") && l.contains("section=A")
    });
    b.ask("GET:tim");
    thread::sleep(Duration::from_millis(300));
    assert!(
        !frames(&server).iter().any(|l| l.contains("section=B")),
        "B is traced: {}",
        server.log()
    );
    assert!(
        server.log().contains("SETCONF: trace on"),
        "{}",
        server.log()
    );

    // Off again: no more frame lines.
    assert_eq!(a.ask("SETCONF:trace,No"), "SETCONF:TRACE,NO");
    thread::sleep(Duration::from_millis(300));
    let after = frames(&server).len();
    a.ask("GET:tim");
    thread::sleep(Duration::from_millis(500));
    assert_eq!(frames(&server).len(), after, "{}", server.log());

    // A READ_ONLY section's clients cannot switch it.
    let mut c = Client::connect(pc);
    assert!(c.ask("SETCONF:trace,Yes").starts_with("ERROR:30"));
}

#[test]
fn trace_key_traces_from_the_start() {
    let port = free_port();
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 100\n{}",
        section("T", port, "TRACE = Yes")
    );
    let server = ServerProcess::with_config(&ini, port);
    wait_frame(&server, "the connection to the PLC", |l| {
        l.contains("PLC -> probe ") || l.contains("PLC -> connect ")
    });
    wait_frame(&server, "the PLC's identification", |l| {
        l.contains("identified: ")
    });
}
