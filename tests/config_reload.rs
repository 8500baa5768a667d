//! SIGHUP re-reads the configuration: sections added start, removed ones
//! stop (their clients' connections closed), changed ones restart alone,
//! unchanged ones keep their clients, links and MQTT sessions; a file with
//! errors is refused whole; `[*]` keys are named for the next restart. The
//! built `plccoms` as a process, a real Mosquitto broker on loopback, raw
//! TCP clients.

mod common;

use std::io::{Read, Write};
use std::net::{Ipv4Addr, SocketAddr, TcpStream};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use common::mqtt::{signal, Broker, DEADLINE};
use common::process::{free_port, ServerProcess};

fn section(name: &str, port: u16, keys: &str) -> String {
    format!("[{name}]\nSIMULATOR = Yes\nSERVER_PORT = {port}\nPUBFILE = //demo.pub\n{keys}\n")
}

/// A client that keeps every byte it receives, and whether the server
/// closed the connection.
struct Watched {
    stream: TcpStream,
    received: Arc<Mutex<Vec<u8>>>,
    closed: Arc<Mutex<bool>>,
}

impl Watched {
    fn connect(port: u16, first: &str) -> Watched {
        let mut stream = TcpStream::connect((Ipv4Addr::LOCALHOST, port)).unwrap();
        stream.write_all(first.as_bytes()).unwrap();
        let received = Arc::new(Mutex::new(Vec::new()));
        let closed = Arc::new(Mutex::new(false));
        let mut reader = stream.try_clone().unwrap();
        let (r, c) = (received.clone(), closed.clone());
        thread::spawn(move || {
            let mut buf = [0u8; 4096];
            loop {
                match reader.read(&mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => r.lock().unwrap().extend_from_slice(&buf[..n]),
                }
            }
            *c.lock().unwrap() = true;
        });
        Watched {
            stream,
            received,
            closed,
        }
    }

    fn text(&self) -> String {
        String::from_utf8_lossy(&self.received.lock().unwrap()).into_owned()
    }

    fn closed(&self) -> bool {
        *self.closed.lock().unwrap()
    }

    #[track_caller]
    fn wait(&self, what: &str, done: impl Fn(&Watched) -> bool) {
        let start = Instant::now();
        while !done(self) {
            assert!(
                start.elapsed() < DEADLINE,
                "client: {what} not seen within {DEADLINE:?}; received:\n{}",
                self.text()
            );
            thread::sleep(Duration::from_millis(20));
        }
    }
}

fn accepts(port: u16) -> bool {
    TcpStream::connect_timeout(
        &SocketAddr::from((Ipv4Addr::LOCALHOST, port)),
        Duration::from_millis(500),
    )
    .is_ok()
}

#[track_caller]
fn wait_log(server: &ServerProcess, needle: &str) {
    let start = Instant::now();
    while !server.log().contains(needle) {
        assert!(
            start.elapsed() < DEADLINE,
            "log: '{needle}' not seen within {DEADLINE:?}; log:\n{}",
            server.log()
        );
        thread::sleep(Duration::from_millis(20));
    }
}

fn hangup(server: &mut ServerProcess) {
    signal(server.child.child().id(), libc::SIGHUP);
}

fn write(server: &ServerProcess, ini: &str) {
    std::fs::write(server.dir.path().join("plccoms.ini"), ini).unwrap();
}

/// Counts `needle` in the log.
fn count(server: &ServerProcess, needle: &str) -> usize {
    server.log().matches(needle).count()
}

#[test]
fn sighup_adds_removes_and_restarts_sections_and_leaves_the_others_alone() {
    let broker = Broker::anonymous();
    let sub = broker.subscribe(&["plccoms/#"]);
    let (pa, pb, pc) = (free_port(), free_port(), free_port());
    let global = |delay: u32, extra: &str| {
        format!(
            "[*]\nCOMM_LOOP_DELAY = {delay}\nMQTT_URL = {}\n{extra}\n",
            broker.url()
        )
    };
    let a = section("A", pa, "MQTT_PUBLISH = tim");
    let ini = global(50, "") + &a + &section("B", pb, "MQTT_PUBLISH = tim");
    let mut server = ServerProcess::with_config(&ini, pa);
    assert!(accepts(pb));
    sub.wait_payload("plccoms/A/status", "online");
    sub.wait_payload("plccoms/B/status", "online");
    let client_a = Watched::connect(pa, "EN:tim\r\n");
    let client_b = Watched::connect(pb, "EN:tim\r\n");
    client_a.wait("a DIFF", |c| c.text().contains("DIFF:TIM,"));
    client_b.wait("a DIFF", |c| c.text().contains("DIFF:TIM,"));

    // What A's client sees from here on is checked at the end (a client
    // that connects before the PLC's public file arrived is warned of it).
    let a_before = client_a.text().len();

    // B removed, C added, a [*] key changed.
    write(
        &server,
        &(global(70, "") + &a + &section("C", pc, "MQTT_PUBLISH = tim")),
    );
    hangup(&mut server);
    wait_log(
        &server,
        "configuration reloaded: added [C], removed [B], 1 unchanged",
    );
    assert!(
        server
            .log()
            .contains("[*] COMM_LOOP_DELAY changed: [*] keys take effect at the next restart"),
        "{}",
        server.log()
    );
    client_b.wait("the connection closed", Watched::closed);
    assert!(!accepts(pb), "B's port still accepts");
    sub.wait_payload("plccoms/B/status", "offline");
    sub.wait_payload("plccoms/C/status", "online");
    let client_c = Watched::connect(pc, "EN:tim\r\n");
    client_c.wait("a DIFF", |c| c.text().contains("DIFF:TIM,"));

    // A file with an error: refused whole, nothing changes.
    write(
        &server,
        &(global(70, "") + &a + &section("C", pc, "EPSTOUT = soon")),
    );
    hangup(&mut server);
    wait_log(&server, "error(s) above; the running configuration stays");
    thread::sleep(Duration::from_millis(300));
    assert!(
        !client_c.closed(),
        "C's client was closed by a refused file"
    );
    assert!(accepts(pc));

    // C changed: it restarts alone, its clients closed; A untouched.
    write(
        &server,
        &(global(70, "") + &a + &section("C", pc, "MQTT_PUBLISH = tim\nEPSTOUT = 1500")),
    );
    hangup(&mut server);
    wait_log(
        &server,
        "configuration reloaded: restarted [C] (EPSTOUT), 1 unchanged",
    );
    client_c.wait("the connection closed", Watched::closed);
    let again = Watched::connect(pc, "GET:tim\r\n");
    again.wait("GET's answer", |c| c.text().contains("GET:TIM,"));

    // Through all of it A's client saw only its own traffic: EN's answer
    // and DIFF lines, the connection open; and A's MQTT session was never
    // taken down (one `online`, no `offline`).
    thread::sleep(Duration::from_millis(300));
    assert!(!client_a.closed(), "A's client was disconnected");
    let before = client_a.text().len();
    client_a.wait("more DIFFs", |c| c.text().len() > before);
    let text = client_a.text();
    let from = text[..a_before].rfind("\r\n").map_or(0, |at| at + 2);
    for line in text[from..].split_terminator("\r\n") {
        assert!(line.starts_with("DIFF:TIM,"), "A's client got '{line}'");
    }
    let statuses: Vec<String> = sub
        .on("plccoms/A/status")
        .into_iter()
        .map(|m| m.payload)
        .collect();
    assert_eq!(statuses, ["online"], "A's MQTT session was restarted");
    assert_eq!(count(&server, "section=A"), count_at_start(&server));
    drop(client_a.stream);
}

/// Log lines about section A written before the first SIGHUP: a reload
/// adds none (A is neither stopped, restarted nor reconnected).
fn count_at_start(server: &ServerProcess) -> usize {
    let log = server.log();
    let start = log.find("SIGHUP").unwrap_or(log.len());
    log[..start].matches("section=A").count()
}
