//! The OPC UA client backend (PROTOCOL = OPCUA) against this server's own
//! OPC UA server, in one process: section `Sim` is a simulated PLC served
//! over OPC UA (OPCUA_PORT), section `Via` reads it back through
//! OPCUA_BROWSE of `Sim`'s node. What a client of `Via` gets must be what
//! a client of `Sim` gets, and a change made on `Sim` reaches `Via`'s
//! DIFFs.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::{Ipv4Addr, TcpStream};
use std::thread;
use std::time::{Duration, Instant};

use common::process::{free_port, ServerProcess};

const DEADLINE: Duration = Duration::from_secs(30);

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

    fn send(&mut self, line: &str) {
        self.stream
            .write_all(format!("{line}\r\n").as_bytes())
            .unwrap();
    }

    fn line(&mut self) -> String {
        let mut line = String::new();
        self.reader.read_line(&mut line).unwrap();
        line.trim_end().to_string()
    }

    /// The answer to `line`, WARNING lines (a table loaded) passed over.
    fn ask(&mut self, line: &str) -> String {
        self.send(line);
        loop {
            let answer = self.line();
            if !answer.starts_with("WARNING:") {
                return answer;
            }
        }
    }
}

/// One plccoms: a simulated PLC `Sim` served over OPC UA (with `global`
/// keys added to [*]), read back by section `Via`; clients of both, once
/// Via serves Sim's SETPOINT.
fn sim_and_via(global: &str) -> (ServerProcess, Client, Client) {
    let (p_sim, p_via, p_ua) = (free_port(), free_port(), free_port());
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 100\nOPCUA_PORT = {p_ua}\n{global}\n\
         [Sim]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = idle\nSERVER_PORT = {p_sim}\nPUBFILE = //demo.pub\n\n\
         [Via]\nPROTOCOL = OPCUA\nOPCUA_URL = opc.tcp://127.0.0.1:{p_ua}/\n\
         OPCUA_BROWSE = nsu=urn:plccoms;s=Sim\nSERVER_PORT = {p_via}\n"
    );
    let server = ServerProcess::with_config(&ini, p_via);
    let sim = Client::connect(p_sim);
    let mut via = Client::connect(p_via);
    // Via's variables come once the OPC UA server answers.
    let start = Instant::now();
    while !via.ask("GET:setpoint").starts_with("GET:SETPOINT,") {
        assert!(
            start.elapsed() < DEADLINE,
            "Via has no SETPOINT; log:\n{}",
            server.log()
        );
        thread::sleep(Duration::from_millis(200));
    }
    (server, sim, via)
}

#[test]
fn a_section_read_through_our_own_opcua_server() {
    let (server, mut sim, mut via) = sim_and_via("");
    // The same values both ways, each type the line protocol prints alike.
    for name in [
        "TEXT", "SETPOINT", "SWITCH", "COUNTER", "V_DINT", "V_LINT", "V_SINT",
    ] {
        assert_eq!(
            via.ask(&format!("GET:{name}")),
            sim.ask(&format!("GET:{name}")),
            "{name}"
        );
    }
    // A change on the PLC side reaches Via's client as a DIFF.
    via.send("EN:setpoint");
    assert!(sim
        .ask("SET:setpoint,21.5")
        .starts_with("DIFF:SETPOINT,21.5"));
    let start = Instant::now();
    loop {
        let line = via.line();
        if line.starts_with("DIFF:SETPOINT,21.5") {
            break;
        }
        assert!(
            start.elapsed() < DEADLINE,
            "no DIFF:SETPOINT,21.5 at Via (last '{line}')"
        );
    }
    // Sim's own __PLC_RUN and __PF_CRC nodes are Via's fixed variables
    // already: left out quietly.
    let log = server.log();
    assert!(!log.contains("defined twice"), "{log}");
}

/// A server that takes 3 monitored items a subscription (our own, with
/// OPCUA_MAX_MONITORED_ITEMS = 3, answering BadTooManyMonitoredItems to a
/// CreateMonitoredItems beyond that): the client spreads the enabled
/// variables over more subscriptions, and every change still arrives.
#[test]
fn a_server_limiting_monitored_items_gets_more_subscriptions() {
    let (server, mut sim, mut via) = sim_and_via("OPCUA_MAX_MONITORED_ITEMS = 3\n");
    let changes = [
        ("SETPOINT", "33.5"),
        ("V_DINT", "123"),
        ("V_LINT", "-456"),
        ("V_SINT", "-7"),
        ("COUNTER", "99"),
    ];
    for (name, _) in changes {
        via.send(&format!("EN:{name}"));
    }
    // Polled a few cycles: the subscriptions made.
    thread::sleep(Duration::from_secs(2));
    for (name, value) in changes {
        assert!(
            sim.ask(&format!("SET:{name},{value}"))
                .starts_with(&format!("DIFF:{name},{value}")),
            "{name}"
        );
    }
    let mut missing: Vec<String> = changes
        .iter()
        .map(|(name, value)| format!("DIFF:{name},{value}"))
        .collect();
    let start = Instant::now();
    while !missing.is_empty() {
        let line = via.line();
        missing.retain(|want| !line.starts_with(want.as_str()));
        assert!(
            start.elapsed() < DEADLINE,
            "no {missing:?} at Via; log:\n{}",
            server.log()
        );
    }
    let log = server.log();
    assert!(
        log.contains("the server takes 3 monitored items a subscription"),
        "{log}"
    );
    assert!(!log.contains("PLC lost"), "{log}");
}
