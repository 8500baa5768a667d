//! The MQTT north side against a real Mosquitto broker (started here on a
//! loopback port), with its own `mosquitto_sub` and `mosquitto_pub` as the
//! other clients, and the built `plccoms` (and `plcsim`) as processes:
//! values (plain, json, retained, escaped names, cp1250), writes and their
//! refusals, Home Assistant discovery, the last will on kill -9, a broker
//! outage of 30 s with a server crash in it, TLS with a CA made here, a
//! wrong password, and two servers on one broker.
//!
//! Waits poll against generous deadlines; nothing here measures speed.

mod common;

use std::collections::BTreeSet;
use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use common::mqtt::{plcsim, signal, write, Broker, Received, Sub, DEADLINE};
use common::process::{free_port, free_udp_port, plcsim_bin, ChildGuard, ServerProcess};

/// A section served by the simulator inside the server.
fn sim_section(name: &str, port: u16, keys: &str) -> String {
    format!(
        "[{name}]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = idle\nSERVER_PORT = {port}\nPUBFILE = //demo.pub\n{keys}\n"
    )
}

fn config(broker: &Broker, global: &str, sections: &str) -> String {
    format!(
        "[*]\nCOMM_LOOP_DELAY = 50\nMQTT_URL = {}\n{global}\n{sections}",
        broker.url()
    )
}

/// A line-protocol client of the server.
struct Line {
    stream: BufReader<TcpStream>,
}

impl Line {
    fn connect(port: u16) -> Line {
        let stream = TcpStream::connect(("127.0.0.1", port)).expect("connect");
        stream
            .set_read_timeout(Some(DEADLINE))
            .expect("read timeout");
        Line {
            stream: BufReader::new(stream),
        }
    }

    /// Sends one request and returns the first answer line.
    fn ask(&mut self, request: &str) -> String {
        self.stream
            .get_mut()
            .write_all(format!("{request}\r\n").as_bytes())
            .expect("send");
        let mut line = Vec::new();
        self.stream.read_until(b'\n', &mut line).expect("answer");
        plccoms_protocol::cp1250::decode(&line)
            .trim_end()
            .to_string()
    }
}

fn in_secs(n: u64) -> Instant {
    Instant::now() + Duration::from_secs(n)
}

#[track_caller]
fn wait_until(what: &str, mut ready: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ready() {
        assert!(start.elapsed() < DEADLINE, "timed out waiting for {what}");
        thread::sleep(Duration::from_millis(20));
    }
}

// ------------------------------------------------------------------ values

#[test]
fn values_plain_and_json_retained_with_escaped_and_cp1250_names() {
    let broker = Broker::anonymous();
    let dir = tempfile::tempdir().unwrap();
    // Names MQTT gives a meaning in topics, and a cp1250 one (0xCC is Ě).
    let mut pubfile = b" A/B R B 0 INT PUB_INOUT\r\n C+D R B 2 INT PUB_INOUT\r\n E#F R B 4 INT PUB_INOUT\r\n G%H R B 6 INT PUB_INOUT\r\n TEXT R B 8 STRING[20] PUB_INOUT\r\n".to_vec();
    pubfile.extend_from_slice(b" TEPLOTA_KUCHYN\xcc R F 40 REAL PUB_INOUT\r\n");
    std::fs::write(dir.path().join("names.pub"), &pubfile).unwrap();
    let (plain, json) = (free_port(), free_port());
    let sections = format!(
        "{}{}",
        sim_section(
            "Plain",
            plain,
            &format!(
                "SIMULATOR_PUB = {}\nMQTT_PUBLISH = *\nMQTT_WRITE = A/B",
                dir.path().join("names.pub").display()
            )
        ),
        sim_section(
            "Json",
            json,
            "SIMULATOR_PROGRAM = demo\nMQTT_PUBLISH = text, counter, sinus\nMQTT_FORMAT = json"
        ),
    );
    let server = ServerProcess::with_config(&config(&broker, "", &sections), json);
    // A subscriber that comes after the values: it gets them retained.
    let sub = broker.subscribe(&["plccoms/#"]);
    let status = sub.wait_payload("plccoms/Plain/status", "online");
    assert!(status.retain);
    sub.wait_payload("plccoms/Plain/plc", "online");
    for topic in ["A%2FB", "C%2BD", "E%23F", "G%25H"] {
        let m = sub.wait(&format!("plccoms/Plain/{topic}"), |_| true);
        assert_eq!((m.payload.as_str(), m.retain), ("0", true), "{topic}");
    }
    // Values in the user's terms: a REAL as a number, not GET's text.
    sub.wait(&format!("plccoms/Plain/TEPLOTA_KUCHYN{}", 'Ě'), |m| {
        m.payload == "0"
    });
    // A write to an escaped name reaches the variable.
    broker.publish("plccoms/Plain/A%2FB/set", "-7", false);
    sub.wait_payload("plccoms/Plain/A%2FB", "-7");
    let mut line = Line::connect(plain);
    assert_eq!(line.ask("GET:a/b"), "GET:A/B,-7");
    // A STRING's text without the quotes GET prints.
    line.ask("SET:text,\"Hello\"");
    sub.wait_payload("plccoms/Plain/TEXT", "Hello");

    // json: value, the poll's time in UTC with milliseconds, quality.
    let text = sub.wait("plccoms/Json/TEXT", |_| true).json();
    assert_eq!(text["value"], "Have a nice day");
    assert_eq!(text["quality"], "good");
    let ts = text["ts"].as_str().unwrap();
    let parsed = chrono::DateTime::parse_from_rfc3339(ts).expect("ISO 8601");
    assert!(
        ts.ends_with('Z') && ts.len() == "2026-01-01T00:00:00.000Z".len(),
        "{ts}"
    );
    let age = chrono::Utc::now().signed_duration_since(parsed);
    assert!(age.num_seconds().abs() < 120, "{ts}");
    let sinus = sub.wait("plccoms/Json/SINUS", |m| !m.retain).json();
    assert!(sinus["value"].is_f64(), "{sinus}");
    assert_eq!(
        sub.wait("plccoms/Json/COUNTER", |_| true).json()["value"],
        0
    );
    drop(server);
}

/// A section that publishes no variable still says how it and its PLC are,
/// also when the PLC answered before the broker did.
#[test]
fn a_section_publishing_nothing_reports_its_plc() {
    let mut broker = Broker::anonymous();
    broker.stop();
    let port = free_port();
    // A local public file: no new table, so no batch of changes, after start.
    let dir = tempfile::tempdir().unwrap();
    let pubfile = dir.path().join("demo.pub");
    std::fs::write(&pubfile, include_bytes!("../conf/demo.pub")).unwrap();
    let section = format!(
        "[Bare]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = idle\nSIMULATOR_PUB = {p}\nSERVER_PORT = {port}\nPUBFILE = {p}\n",
        p = pubfile.display()
    );
    let server = ServerProcess::with_config(&config(&broker, "", &section), port);
    wait_until("the PLC", || server.log().contains("PLC connected"));
    thread::sleep(Duration::from_millis(500));
    broker.restart();
    let sub = broker.subscribe(&["plccoms/#"]);
    sub.wait_payload("plccoms/Bare/status", "online");
    sub.wait_payload("plccoms/Bare/plc", "online");
}

// ------------------------------------------------------------------ writes

#[test]
fn writes_round_trip_and_refusals_never_applied_later() {
    let broker = Broker::anonymous();
    // A retained write waiting at the broker before the server connects:
    // it must never be written.
    broker.publish("plccoms/Plc/NOTE/set", "stale", true);
    let udp = free_udp_port();
    let files = tempfile::tempdir().unwrap();
    let plc_process = plcsim(files.path(), udp);
    let (plc, ro) = (free_port(), free_port());
    let sections = format!(
        "[Plc]\nIPADDR = 127.0.0.1\nEPSPORT = {udp}\nEPSTOUT = 200\nEPSTOUT_STEP = 0\nSERVER_PORT = {plc}\nPUBFILE = //demo.pub\nMQTT_PUBLISH = counter, sinus, note\nMQTT_WRITE = counter, note, setpoint, v_dt, dat, v_tod, tim, switch\n{}",
        sim_section("Ro", ro, "READ_ONLY = Yes\nMQTT_PUBLISH = counter\nMQTT_WRITE = *")
    );
    let server = ServerProcess::with_config(&config(&broker, "", &sections), plc);
    let sub = broker.subscribe(&["plccoms/#"]);
    sub.wait_payload("plccoms/Plc/plc", "online");
    sub.wait_payload("plccoms/Plc/COUNTER", "0");

    // A write comes back confirmed on the value topic, once: also for a
    // variable not published, in cp1250 text, and for a value unchanged
    // (which the change stream does not publish).
    broker.publish("plccoms/Plc/COUNTER/set", "42", false);
    sub.wait_payload("plccoms/Plc/COUNTER", "42");
    broker.publish("plccoms/Plc/setpoint/set", "21.5", false);
    sub.wait_payload("plccoms/Plc/SETPOINT", "21.5");
    broker.publish("plccoms/Plc/NOTE/set", "Dobrý den", false);
    sub.wait_payload("plccoms/Plc/NOTE", "Dobrý den");
    broker.publish("plccoms/Plc/NOTE/set", "Dobrý den", false);
    let confirmations = |topic: &str, payload: &str| {
        sub.on(topic)
            .iter()
            .filter(|m| m.payload == payload)
            .count()
    };
    sub.wait_for("the unchanged NOTE confirmed", || {
        (confirmations("plccoms/Plc/NOTE", "Dobrý den") >= 2).then_some(())
    });

    // Times and BOOLs in the forms the value topics show: ISO 8601 read
    // back as the protocol's text, published as ISO again.
    for (name, value) in [
        ("V_DT", "2026-11-25T10:15:00.123Z"),
        ("DAT", "2026-11-25"),
        ("V_TOD", "10:15:00.123"),
        ("TIM", "PT1H2M3.456S"),
        ("SWITCH", "true"),
    ] {
        broker.publish(&format!("plccoms/Plc/{name}/set"), value, false);
        sub.wait_payload(&format!("plccoms/Plc/{name}"), value);
    }
    let mut line = Line::connect(plc);
    assert_eq!(line.ask("GET:tim"), "GET:TIM,3723456");
    // Another zone is the same instant; a form without one is refused,
    // naming the form expected, and nothing is written.
    broker.publish("plccoms/Plc/V_DT/set", "2026-11-25T12:00:00+01:00", false);
    sub.wait_payload("plccoms/Plc/V_DT", "2026-11-25T11:00:00.000Z");
    broker.publish("plccoms/Plc/V_DT/set", "2026-11-25 10:15", false);
    sub.wait_payload(
        "plccoms/Plc/V_DT/error",
        "ERROR:35 Wrong parameter value in request: 'SET:V_DT,2026-11-25 10:15' (expected a date and time in ISO 8601 with its zone, as 2026-11-25T10:15:00.123Z)",
    );
    broker.publish("plccoms/Plc/TIM/set", "3723456", false);
    sub.wait("plccoms/Plc/TIM/error", |m| {
        m.payload.contains("expected an ISO 8601 duration")
    });
    assert_eq!(line.ask("GET:tim"), "GET:TIM,3723456");

    // Refusals on <VAR>/error, with SET's error lines.
    broker.publish("plccoms/Plc/counter/set", "abc", false);
    sub.wait_payload(
        "plccoms/Plc/counter/error",
        "ERROR:35 Wrong parameter value in request: 'SET:counter,abc'",
    );
    broker.publish("plccoms/Plc/COUNTER/set", "70000", false);
    sub.wait("plccoms/Plc/COUNTER/error", |m| {
        m.payload.starts_with("ERROR:35")
    });
    broker.publish("plccoms/Plc/SINUS/set", "1", false);
    sub.wait_payload(
        "plccoms/Plc/SINUS/error",
        "ERROR:30 Bad client request: 'SET:SINUS,1' (not writable over MQTT: see MQTT_WRITE)",
    );
    broker.publish("plccoms/Ro/COUNTER/set", "5", false);
    sub.wait_payload(
        "plccoms/Ro/COUNTER/error",
        "ERROR:30 Bad client request: 'SET:COUNTER,5'",
    );
    assert_eq!(line.ask("GET:note"), "GET:NOTE,\"Dobrý den\"");
    // Each write published once, the refusals' time after.
    assert_eq!(confirmations("plccoms/Plc/COUNTER", "42"), 1);
    assert_eq!(confirmations("plccoms/Plc/SETPOINT", "21.5"), 1);
    assert_eq!(confirmations("plccoms/Plc/NOTE", "Dobrý den"), 2);
    let log = server.log();
    assert!(log.contains("write refused: ERROR:35"), "{log}");
    assert!(
        log.contains("a retained /set message is never written"),
        "{log}"
    );

    // A retained /set published while subscribed: refused too (MQTT 5
    // marks it retained), never written, with how to clear it.
    broker.publish("plccoms/Plc/COUNTER/set", "77", true);
    let retained = sub.wait("plccoms/Plc/COUNTER/error", |m| {
        m.payload.contains("'SET:COUNTER,77'")
    });
    assert!(
        retained.payload.contains("retained")
            && retained
                .payload
                .contains("clear it with an empty retained message"),
        "{}",
        retained.payload
    );
    // Clearing it is no write: no error, no log line. The write after it
    // comes after it (one subscription, in order), so by its confirmation
    // the clear was handled.
    broker.publish("plccoms/Plc/COUNTER/set", "", true);
    broker.publish("plccoms/Plc/COUNTER/set", "43", false);
    sub.wait_payload("plccoms/Plc/COUNTER", "43");
    assert_eq!(line.ask("GET:counter"), "GET:COUNTER,43");
    assert!(sub
        .on("plccoms/Plc/COUNTER")
        .iter()
        .all(|m| m.payload != "77"));
    let errors = sub.on("plccoms/Plc/COUNTER/error");
    assert!(
        errors.iter().all(|m| !m.payload.contains("'SET:COUNTER,'")),
        "{errors:?}"
    );
    assert!(!server.log().contains("'SET:COUNTER,'"));

    // The PLC goes away: a write is refused at once, and never made later.
    // Only an `offline` after the drop counts (one from before would let
    // the write race the loss).
    let before = sub.on("plccoms/Plc/plc").len();
    drop(plc_process);
    sub.wait_for("a new 'offline' on plccoms/Plc/plc", || {
        sub.on("plccoms/Plc/plc")
            .into_iter()
            .skip(before)
            .find(|m| m.payload == "offline")
    });
    broker.publish("plccoms/Plc/COUNTER/set", "99", false);
    sub.wait("plccoms/Plc/COUNTER/error", |m| {
        m.payload.starts_with("ERROR:10")
    });
    let _plcsim = plcsim(files.path(), udp);
    sub.wait("plccoms/Plc/plc", |m| m.payload == "online" && !m.retain);
    thread::sleep(Duration::from_millis(500));
    // A fresh PLC: memory zero; the refused 99 was not written.
    assert_eq!(line_after_reconnect(plc), "GET:COUNTER,0");
    assert!(sub
        .on("plccoms/Plc/COUNTER")
        .iter()
        .all(|m| m.payload != "99"));
}

fn line_after_reconnect(port: u16) -> String {
    let mut line = Line::connect(port);
    let start = Instant::now();
    loop {
        let answer = line.ask("GET:counter");
        if answer.starts_with("GET:") || start.elapsed() > DEADLINE {
            return answer;
        }
        thread::sleep(Duration::from_millis(100));
    }
}

/// MQTT_DELTA: a change is published once it moved more than the deadband
/// from the value last published.
#[test]
fn deadband() {
    let broker = Broker::anonymous();
    let port = free_port();
    let ini = config(
        &broker,
        "",
        &sim_section("Demo", port, "MQTT_PUBLISH = counter\nMQTT_DELTA = 5"),
    );
    let _server = ServerProcess::with_config(&ini, port);
    let sub = broker.subscribe(&["plccoms/Demo/COUNTER"]);
    sub.wait_payload("plccoms/Demo/COUNTER", "0");
    let mut line = Line::connect(port);
    for value in [3, 5, 6, 8, 11, 12, -1] {
        assert_eq!(
            line.ask(&format!("SET:counter,{value}")),
            format!("DIFF:COUNTER,{value}")
        );
        thread::sleep(Duration::from_millis(150));
    }
    sub.wait_payload("plccoms/Demo/COUNTER", "-1");
    let seen: Vec<String> = sub
        .on("plccoms/Demo/COUNTER")
        .into_iter()
        .map(|m| m.payload)
        .collect();
    assert_eq!(seen, ["0", "6", "12", "-1"]);
}

// --------------------------------------------------------------- discovery

#[test]
fn home_assistant_discovery_stable_ids_and_removed_configs_cleared() {
    let broker = Broker::anonymous();
    let port = free_port();
    let section = |publish: &str| {
        sim_section(
            "Hala",
            port,
            &format!(
                "MQTT_PUBLISH = {publish}\nMQTT_WRITE = switch, counter, note\nMQTT_HA_DISCOVERY = Yes"
            ),
        )
    };
    let dir = tempfile::tempdir().unwrap();
    let ini = dir.path().join("plccoms.ini");
    let sub = broker.subscribe(&["homeassistant/#"]);
    let run = |publish: &str| {
        write(&ini, &config(&broker, "", &section(publish)));
        let mut child = ChildGuard::spawn(
            "plccoms",
            Command::new(common::process::PLCCOMS)
                .args(["-c", "plccoms.ini"])
                .current_dir(dir.path())
                .env_remove("RUST_LOG")
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::null()),
        );
        assert!(child.exited().is_none());
        child
    };
    let server = run("switch, positive, counter, sinus, note, text");
    let config_of = |component: &str, name: &str| -> (Received, serde_json::Value) {
        let m = sub.wait_for(&format!("the {component} config of {name}"), || {
            // Once the PLC's identification is in it: configs sent before
            // it was known are sent again with it.
            sub.messages().into_iter().rev().find(|m| {
                m.topic.starts_with(&format!("homeassistant/{component}/"))
                    && m.payload.contains(&format!("\"name\":\"{name}\""))
                    && m.payload.contains("\"hw_version\"")
            })
        });
        let json = m.json();
        (m, json)
    };
    let mut ids = Vec::new();
    for (component, name, writable) in [
        ("switch", "SWITCH", true),
        ("binary_sensor", "POSITIVE", false),
        ("number", "COUNTER", true),
        ("sensor", "SINUS", false),
        ("text", "NOTE", true),
        ("sensor", "TEXT", false),
    ] {
        let (m, c) = config_of(component, name);
        let id = c["unique_id"].as_str().expect("unique_id").to_string();
        assert_eq!(m.topic, format!("homeassistant/{component}/{id}/config"));
        assert_eq!(c["state_topic"], format!("plccoms/Hala/{name}"));
        assert_eq!(
            c["command_topic"].as_str(),
            writable
                .then(|| format!("plccoms/Hala/{name}/set"))
                .as_deref(),
            "{name}"
        );
        assert_eq!(c["availability"][0]["topic"], "plccoms/Hala/status");
        assert_eq!(c["availability"][1]["topic"], "plccoms/Hala/plc");
        assert_eq!(c["availability_mode"], "all");
        assert_eq!(c["device"]["identifiers"][0], "plccoms_Hala");
        assert_eq!(c["device"]["name"], "Hala");
        ids.push((m.topic.clone(), m.payload.clone()));
    }
    let (_, number) = config_of("number", "COUNTER");
    assert_eq!(
        (number["min"].as_f64(), number["max"].as_f64()),
        (Some(-32768.0), Some(32767.0))
    );
    let (_, switch) = config_of("switch", "SWITCH");
    assert_eq!(
        (switch["payload_on"].as_str(), switch["state_off"].as_str()),
        (Some("true"), Some("false"))
    );
    // Home Assistant restarting asks for the configs again.
    let before = sub.messages().len();
    broker.publish("homeassistant/status", "online", false);
    sub.wait_for("configs sent again", || {
        (sub.messages()[before..]
            .iter()
            .filter(|m| m.topic.ends_with("/config"))
            .count()
            >= 6)
            .then_some(())
    });

    // Restarted without SINUS and TEXT: same ids for the others, and the
    // two configs cleared (an empty retained message).
    drop(server);
    let before = sub.messages().len();
    let _server = run("switch, positive, counter, note");
    let (sinus_topic, text_topic) = (&ids[3].0, &ids[5].0);
    for gone in [sinus_topic, text_topic] {
        sub.wait_for(&format!("{gone} cleared"), || {
            sub.messages()[before..]
                .iter()
                .find(|m| &m.topic == gone && m.payload.is_empty())
                .cloned()
        });
    }
    for (topic, payload) in [&ids[0], &ids[1], &ids[2], &ids[4]] {
        sub.wait_for(&format!("{topic} again, unchanged"), || {
            sub.messages()[before..]
                .iter()
                .find(|m| &m.topic == topic && &m.payload == payload)
                .cloned()
        });
    }
    // What stays retained at the broker: only the four.
    let late = broker.subscribe(&["homeassistant/#"]);
    thread::sleep(Duration::from_secs(1));
    let retained: Vec<String> = late.messages().into_iter().map(|m| m.topic).collect();
    assert_eq!(retained.len(), 4, "{retained:?}");
}

/// A new public file (SETCONF:pubfile) re-sends the configs of the
/// variables that stay, under the same ids, and clears the others.
#[test]
fn discovery_follows_a_new_public_file() {
    let broker = Broker::anonymous();
    let files = tempfile::tempdir().unwrap();
    let udp = free_udp_port();
    let _plcsim = plcsim(files.path(), udp);
    std::fs::write(
        files.path().join("small.pub"),
        " switch R B 128 .0 BOOL PUB_INOUT\r\n counter R B 130 INT PUB_INOUT\r\n",
    )
    .unwrap();
    let port = free_port();
    let section = format!(
        "[Plc]\nIPADDR = 127.0.0.1\nEPSPORT = {udp}\nSERVER_PORT = {port}\nPUBFILE = //demo.pub\nMQTT_PUBLISH = counter, sinus, switch\nMQTT_WRITE = switch\nMQTT_HA_DISCOVERY = Yes\n"
    );
    let sub = broker.subscribe(&["homeassistant/#"]);
    let _server = ServerProcess::with_config(&config(&broker, "", &section), port);
    let config_of = |name: &str, from: usize| {
        sub.wait_for(&format!("the config of {name}"), || {
            sub.messages()[from..]
                .iter()
                .find(|m| m.payload.contains(&format!("\"name\":\"{name}\"")))
                .cloned()
        })
    };
    let (counter, sinus, switch) = (
        config_of("COUNTER", 0),
        config_of("SINUS", 0),
        config_of("SWITCH", 0),
    );
    assert!(switch.topic.starts_with("homeassistant/switch/"));
    let before = sub.messages().len();
    let mut line = Line::connect(port);
    assert_eq!(
        line.ask("SETCONF:pubfile,//small.pub"),
        "WARNING:250 Changed public file: 'small.pub'"
    );
    sub.wait_for("SINUS cleared", || {
        sub.messages()[before..]
            .iter()
            .find(|m| m.topic == sinus.topic && m.payload.is_empty())
            .cloned()
    });
    for kept in [&counter, &switch] {
        let again = config_of(kept.json()["name"].as_str().unwrap(), before);
        assert_eq!(
            (&again.topic, again.json()["unique_id"].clone()),
            (&kept.topic, kept.json()["unique_id"].clone())
        );
    }
}

/// Keys Home Assistant's MQTT platforms take (its discovery schemas; any
/// other key is refused or dropped), per platform.
fn allowed_keys(platform: &str) -> Vec<&'static str> {
    let mut keys = vec![
        "name",
        "unique_id",
        "state_topic",
        "qos",
        "value_template",
        "availability",
        "availability_mode",
        "device",
        "origin",
        "entity_category",
        "icon",
        "enabled_by_default",
        "json_attributes_topic",
        "json_attributes_template",
        "encoding",
    ];
    keys.extend_from_slice(match platform {
        "sensor" => &[
            "device_class",
            "unit_of_measurement",
            "state_class",
            "suggested_display_precision",
            "expire_after",
            "force_update",
        ][..],
        "binary_sensor" => &[
            "device_class",
            "payload_on",
            "payload_off",
            "expire_after",
            "force_update",
            "off_delay",
        ],
        "number" => &[
            "device_class",
            "command_topic",
            "command_template",
            "min",
            "max",
            "step",
            "mode",
            "unit_of_measurement",
            "optimistic",
            "retain",
        ],
        "switch" => &[
            "device_class",
            "command_topic",
            "command_template",
            "payload_on",
            "payload_off",
            "state_on",
            "state_off",
            "optimistic",
            "retain",
        ],
        "text" => &[
            "command_topic",
            "command_template",
            "min",
            "max",
            "mode",
            "pattern",
            "optimistic",
            "retain",
        ],
        other => panic!("a platform not announced: {other}"),
    });
    keys
}

/// The units Home Assistant takes for a device class (the classes this
/// server announces).
fn units_of(class: &str) -> Option<&'static [&'static str]> {
    Some(match class {
        "temperature" => &["°C", "°F", "K"],
        "power" => &["W", "kW"],
        "energy" => &["Wh", "kWh", "MWh"],
        "voltage" => &["V"],
        "current" => &["A"],
        "pressure" => &["Pa", "hPa", "bar"],
        "frequency" => &["Hz"],
        _ => return None,
    })
}

/// Every config announced for a section with every IEC type (all
/// writable), a READ_ONLY one, and a Modbus device whose tags have units,
/// descriptions, ranges, decimals, read-only tables and `access ro`, system
/// variables in each: checked against what Home Assistant's platforms
/// accept, and against the values actually published on their state
/// topics.
#[test]
fn every_announced_config_is_one_home_assistant_accepts() {
    let broker = Broker::anonymous();
    let dir = tempfile::tempdir().unwrap();
    let tags =
        "name,type,table,address,bit,order,scale,offset,access,unit,description,min,max,decimals\n\
        t_room,REAL,holding,0,,,,,,°C,Room temperature,5,30,1\n\
        power,REAL,holding,2,,,,,,kW,,,,2\n\
        energy,LREAL,holding,4,,,,,,kWh,Energy meter,,,\n\
        current,UINT,holding,8,,,,,ro,A,,,,\n\
        pressure,INT,holding,9,,,,,,hPa,,900,1100,\n\
        freq,UINT,holding,10,,,,,,Hz,,,,\n\
        humidity,UINT,holding,11,,,,,,%,Humidity,0,100,\n\
        stamp,TS48,holding,12,,,,,,,Last event,,,\n\
        day,DATE,holding,16,,,,,,,,,,\n\
        label,STRING[16],holding,20,,,,,,,,,,\n\
        kelvin,REAL,holding,30,,,,,,K,,,,\n\
        voltage,INT,input,0,,,0.1,,,V,Mains voltage,,,1\n\
        running,BOOL,coil,0,,,,,,,Pump running,,,\n\
        alarm,BOOL,discrete,0,,,,,,,,,,\n";
    let tags_path = dir.path().join("tags.csv");
    write(&tags_path, tags);
    let device_port = free_port();
    let _device = ChildGuard::spawn(
        "plcsim",
        Command::new(plcsim_bin())
            .args(["--modbus", &format!("127.0.0.1:{device_port}")])
            .arg("--tags")
            .arg(&tags_path)
            .args(["--program", "idle"])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null()),
    );
    let (all, ro, mb) = (free_port(), free_port(), free_port());
    let keys = "MQTT_FORMAT = json\nMQTT_HA_DISCOVERY = Yes\nMQTT_WRITE = *, __*";
    let sections = format!(
        "{}{}[Mb]\nPROTOCOL = MODBUS_TCP\nIPADDR = 127.0.0.1\nMODBUS_PORT = {device_port}\nMODBUS_UNIT = 7\nMODBUS_TAGS = {}\nSERVER_PORT = {mb}\nMQTT_PUBLISH = *, __*\n{keys}\n",
        sim_section("All", all, &format!("MQTT_PUBLISH = *, __*\n{keys}")),
        sim_section("Ro", ro, &format!("READ_ONLY = Yes\nMQTT_PUBLISH = counter, switch, setpoint, note, __*\n{keys}")),
        tags_path.display()
    );
    let sub = broker.subscribe(&["homeassistant/#", "plccoms/#"]);
    let _server = ServerProcess::with_config(&config(&broker, "", &sections), all);
    let names =
        |list: &str| -> Vec<String> { list.split_whitespace().map(str::to_uppercase).collect() };
    let expected = [
        ("All", names("dat tim sinus cosinus c positive text setpoint switch counter note v_byte v_word v_dword v_lword v_sint v_dint v_lint v_usint v_uint v_udint v_ulint v_tod v_dt flag_a flag_b __PLC_RUN __PF_CRC")),
        ("Ro", names("counter switch setpoint note __PLC_RUN")),
        ("Mb", names("t_room power energy current pressure freq humidity stamp day label kelvin voltage running alarm __PLC_RUN __PF_CRC")),
    ];
    // Every expected variable has its config and its value.
    let configs = sub.wait_for("every config and value", || {
        let messages = sub.messages();
        let configs: Vec<Received> = messages
            .iter()
            .filter(|m| m.topic.starts_with("homeassistant/") && !m.payload.is_empty())
            .cloned()
            .collect();
        let complete = expected.iter().all(|(section, names)| {
            names.iter().all(|name| {
                let state = format!("plccoms/{section}/{name}");
                configs
                    .iter()
                    .any(|c| c.json()["state_topic"] == state.as_str())
                    && messages.iter().any(|m| m.topic == state)
            })
        });
        complete.then_some(configs)
    });
    let messages = sub.messages();
    let value_of = |state: &str| -> serde_json::Value {
        let m = messages
            .iter()
            .rev()
            .find(|m| m.topic == state)
            .unwrap_or_else(|| panic!("no value on {state}"));
        m.json()["value"].clone()
    };
    let mut ids = BTreeSet::new();
    let mut seen = BTreeSet::new();
    for m in &configs {
        let c = m.json();
        let object = c.as_object().expect("a JSON object");
        let parts: Vec<&str> = m.topic.split('/').collect();
        let [_, platform, id, "config"] = parts[..] else {
            panic!("{}: not homeassistant/<platform>/<id>/config", m.topic)
        };
        let what = format!("{}: {c}", m.topic);
        // Keys, ids, topics.
        let allowed = allowed_keys(platform);
        for key in object.keys() {
            assert!(
                allowed.contains(&key.as_str()),
                "{key} not a {platform} key: {what}"
            );
        }
        assert_eq!(c["unique_id"], id, "{what}");
        assert!(id
            .chars()
            .all(|ch| ch.is_ascii_alphanumeric() || ch == '_' || ch == '-'));
        if !ids.insert((platform.to_string(), id.to_string())) {
            // Sent again (Home Assistant online, a new connection): the same.
            continue;
        }
        assert!(c["name"].as_str().is_some_and(|n| !n.is_empty()), "{what}");
        let state = c["state_topic"].as_str().expect("state_topic");
        assert!(!state.contains(['+', '#']), "{what}");
        let (section, name) = state
            .strip_prefix("plccoms/")
            .and_then(|rest| rest.split_once('/'))
            .expect("plccoms/<section>/<name>");
        seen.insert((section.to_string(), name.to_string()));
        assert!(matches!(c["qos"].as_u64(), Some(0..=2)), "{what}");
        assert_eq!(
            c["value_template"]
                .as_str()
                .map(|t| t.contains("value_json.value")),
            Some(true),
            "{what}"
        );
        assert_eq!(c["availability_mode"], "all", "{what}");
        assert_eq!(
            c["availability"].as_array().map(Vec::len),
            Some(2),
            "{what}"
        );
        // The device, by its backend.
        let device = &c["device"];
        assert_eq!(device["name"], section, "{what}");
        assert!(device["identifiers"]
            .as_array()
            .is_some_and(|a| !a.is_empty()));
        if section == "Mb" {
            assert_eq!(device["manufacturer"], "Modbus TCP device", "{what}");
            assert_eq!(
                device["model"],
                format!("127.0.0.1:{device_port} unit 7"),
                "{what}"
            );
            assert!(!device.to_string().contains("Teco"), "{what}");
        } else {
            assert_eq!(
                (device["manufacturer"].as_str(), device["model"].as_str()),
                (Some("Teco"), Some("Tecomat PLC")),
                "{what}"
            );
        }
        // Writable entities only where a write can succeed.
        let writable = matches!(platform, "number" | "switch" | "text");
        assert_eq!(c.get("command_topic").is_some(), writable, "{what}");
        if writable {
            assert_eq!(c["command_topic"], format!("{state}/set"), "{what}");
            assert!(section == "All" || section == "Mb", "READ_ONLY: {what}");
            assert!(!name.starts_with("__"), "system variable: {what}");
            assert!(
                !["CURRENT", "VOLTAGE", "ALARM"].contains(&name),
                "a read-only tag: {what}"
            );
        }
        // System variables: diagnostic, no state class.
        if name.starts_with("__") {
            assert_eq!(c["entity_category"], "diagnostic", "{what}");
            assert!(c.get("state_class").is_none(), "{what}");
        } else {
            assert!(c.get("entity_category").is_none(), "{what}");
        }
        if name == "__PLC_RUN" {
            assert_eq!(
                (platform, c["device_class"].as_str()),
                ("binary_sensor", Some("running"))
            );
        }
        // What the state will be, as the template renders the value.
        let value = value_of(state);
        let class = c["device_class"].as_str();
        match platform {
            "binary_sensor" | "switch" => {
                assert!(value.is_boolean(), "{what}: {value}");
                assert_eq!(
                    (c["payload_on"].as_str(), c["payload_off"].as_str()),
                    (Some("true"), Some("false"))
                );
                assert!(
                    c["value_template"].as_str().unwrap().contains("'true'"),
                    "a JSON boolean renders as True without it: {what}"
                );
                if platform == "switch" {
                    assert_eq!(
                        (c["state_on"].as_str(), c["state_off"].as_str()),
                        (Some("true"), Some("false"))
                    );
                    assert!(class.is_none());
                } else {
                    assert!(class.is_none() || class == Some("running"), "{what}");
                }
            }
            "number" => {
                assert!(value.is_number(), "{what}: {value}");
                let (min, max, step) = (
                    c["min"].as_f64().unwrap(),
                    c["max"].as_f64().unwrap(),
                    c["step"].as_f64().unwrap(),
                );
                assert!(min < max, "{what}");
                assert!(step >= 0.001, "{what}");
                assert!(
                    max.abs() < 1e30 && min.abs() < 1e30,
                    "an absurd range: {what}"
                );
                assert!(
                    ["auto", "box", "slider"].contains(&c["mode"].as_str().unwrap()),
                    "{what}"
                );
            }
            "text" => {
                assert!(value.is_string(), "{what}: {value}");
                let max = c["max"].as_u64().unwrap_or(255);
                assert!(max <= 255, "{what}");
            }
            "sensor" => match class {
                Some("timestamp") => {
                    let text = value.as_str().expect("a timestamp is text");
                    assert!(
                        chrono::DateTime::parse_from_rfc3339(text).is_ok(),
                        "{what}: {text}"
                    );
                    assert!(
                        c.get("state_class").is_none() && c.get("unit_of_measurement").is_none()
                    );
                }
                Some("date") => {
                    let text = value.as_str().expect("a date is text");
                    assert!(
                        chrono::NaiveDate::parse_from_str(text, "%Y-%m-%d").is_ok(),
                        "{what}"
                    );
                    assert!(
                        c.get("state_class").is_none() && c.get("unit_of_measurement").is_none()
                    );
                }
                _ => {
                    let numeric = c.get("state_class").is_some()
                        || c.get("unit_of_measurement").is_some()
                        || class.is_some();
                    if numeric {
                        assert!(value.is_number(), "numeric sensor, value {value}: {what}");
                    }
                    if let Some(state_class) = c["state_class"].as_str() {
                        let allowed: &[&str] = if class == Some("energy") {
                            &["total", "total_increasing"]
                        } else {
                            &["measurement", "total", "total_increasing"]
                        };
                        assert!(allowed.contains(&state_class), "{what}");
                        assert!(!name.contains("CRC"), "{what}");
                    }
                }
            },
            _ => unreachable!(),
        }
        if let Some(class) = class.filter(|c| !["timestamp", "date", "running"].contains(c)) {
            let units = units_of(class).unwrap_or_else(|| panic!("device class {class}: {what}"));
            assert!(
                units.contains(&c["unit_of_measurement"].as_str().unwrap_or("")),
                "{what}"
            );
        }
    }
    // Everything expected was announced, and a few in particular.
    let total: usize = expected.iter().map(|(_, names)| names.len()).sum();
    assert!(seen.len() >= total, "{} of {total}: {seen:?}", seen.len());
    for (section, names) in &expected {
        for name in names {
            assert!(
                seen.contains(&(section.to_string(), name.clone())),
                "{section}/{name}"
            );
        }
    }
    let config = |section: &str, name: &str| -> (String, serde_json::Value) {
        let state = format!("plccoms/{section}/{name}");
        let m = configs
            .iter()
            .find(|m| m.json()["state_topic"] == state.as_str())
            .unwrap();
        (m.topic.split('/').nth(1).unwrap().to_string(), m.json())
    };
    let (platform, c) = config("All", "V_DT");
    assert_eq!(
        (platform.as_str(), c["device_class"].as_str()),
        ("sensor", Some("timestamp"))
    );
    let (platform, c) = config("All", "DAT");
    assert_eq!(
        (platform.as_str(), c["device_class"].as_str()),
        ("sensor", Some("date"))
    );
    for name in ["TIM", "V_TOD"] {
        let (platform, c) = config("All", name);
        assert_eq!(
            (platform.as_str(), c.get("device_class")),
            ("sensor", None),
            "{name}"
        );
    }
    let (platform, c) = config("All", "SETPOINT");
    assert_eq!(platform, "number");
    assert_eq!(
        (c["min"].as_f64(), c["max"].as_f64(), c["mode"].as_str()),
        (Some(-1e9), Some(1e9), Some("box"))
    );
    let (platform, c) = config("Ro", "SETPOINT");
    assert_eq!(
        (platform.as_str(), c["state_class"].as_str()),
        ("sensor", Some("measurement"))
    );
    let (platform, c) = config("Mb", "T_ROOM");
    assert_eq!(platform, "number");
    assert_eq!(
        (
            c["name"].as_str(),
            c["unit_of_measurement"].as_str(),
            c["device_class"].as_str()
        ),
        (Some("Room temperature"), Some("°C"), Some("temperature"))
    );
    assert_eq!(
        (c["min"].as_f64(), c["max"].as_f64(), c["step"].as_f64()),
        (Some(5.0), Some(30.0), Some(0.1))
    );
    let (_, c) = config("Mb", "HUMIDITY");
    assert_eq!(
        (c["unit_of_measurement"].as_str(), c.get("device_class")),
        (Some("%"), None)
    );
    let (platform, c) = config("Mb", "VOLTAGE");
    assert_eq!(
        (
            platform.as_str(),
            c["device_class"].as_str(),
            c["state_class"].as_str()
        ),
        ("sensor", Some("voltage"), Some("measurement"))
    );
    assert_eq!(c["suggested_display_precision"].as_u64(), Some(1));
    let (platform, c) = config("Mb", "CURRENT");
    assert_eq!(
        (platform.as_str(), c["device_class"].as_str()),
        ("sensor", Some("current"))
    );
    let (platform, _) = config("Mb", "ALARM");
    assert_eq!(platform, "binary_sensor");
    let (platform, c) = config("Mb", "STAMP");
    assert_eq!(
        (
            platform.as_str(),
            c["name"].as_str(),
            c["device_class"].as_str()
        ),
        ("sensor", Some("Last event"), Some("timestamp"))
    );
    let (_, c) = config("Mb", "__PF_CRC");
    assert!(c.get("state_class").is_none());
}

// ---------------------------------------------------------------- the will

#[test]
fn last_will_on_kill_9_and_offline_on_a_clean_stop() {
    let broker = Broker::anonymous();
    let port = free_port();
    let ini = config(
        &broker,
        "",
        &sim_section("Demo", port, "MQTT_PUBLISH = counter"),
    );
    let sub = broker.subscribe(&["plccoms/Demo/status"]);
    let mut server = ServerProcess::with_config(&ini, port);
    sub.wait_payload("plccoms/Demo/status", "online");
    // kill -9: the broker sends the will.
    server.child.child().kill().expect("SIGKILL");
    let _ = server.child.child().wait();
    let will = sub.wait("plccoms/Demo/status", |m| m.payload == "offline");
    assert!(!will.retain, "delivered live");
    let late = broker.subscribe(&["plccoms/Demo/status"]);
    late.wait("plccoms/Demo/status", |m| {
        m.payload == "offline" && m.retain
    });

    // A clean stop says offline itself.
    let before = sub.on("plccoms/Demo/status").len();
    let mut server = ServerProcess::with_config(&ini, port);
    sub.wait_for("online again", || {
        sub.on("plccoms/Demo/status")[before..]
            .iter()
            .find(|m| m.payload == "online")
            .cloned()
    });
    signal(server.child.child().id(), libc::SIGTERM);
    assert!(server.child.wait_timeout(DEADLINE).is_some());
    sub.wait_for("offline after SIGTERM", || {
        sub.on("plccoms/Demo/status")[before..]
            .iter()
            .find(|m| m.payload == "offline")
            .cloned()
    });
    assert!(server.log().contains("MQTT: connected"), "{}", server.log());
}

// ------------------------------------------------------------------ outage

/// The broker is stopped for 30 s while a counter keeps rising, and the
/// server is killed (-9) and started again in the middle of it: every value
/// arrives, in order, once the broker is back.
#[test]
fn broker_outage_of_30_s_with_a_crash_loses_nothing() {
    let mut broker = Broker::anonymous();
    let udp = free_udp_port();
    // The PLC outlives the server, so the counter is what the test wrote.
    let files = tempfile::tempdir().unwrap();
    let _plcsim = plcsim(files.path(), udp);
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let ini = config(
        &broker,
        &format!("MQTT_SPOOL = {}", dir.path().join("spool").display()),
        &format!(
            "[Plc]\nIPADDR = 127.0.0.1\nEPSPORT = {udp}\nSERVER_PORT = {port}\nPUBFILE = //demo.pub\nMQTT_PUBLISH = counter\n"
        ),
    );
    let topic = "plccoms/Plc/COUNTER";
    // A persistent subscriber: the broker keeps its messages while it is
    // itself away, and it reconnects by itself.
    let sub = Sub::start(broker.port, &[topic], Some("outage-test"));
    let mut server = ServerProcess::with_config(&ini, port);
    sub.wait_payload(topic, "0");
    let mut line = Line::connect(port);
    let mut next = 1;
    let write_until = |line: &mut Line, until: Instant, next: &mut i32| {
        while Instant::now() < until {
            assert_eq!(
                line.ask(&format!("SET:counter,{next}")),
                format!("DIFF:COUNTER,{next}")
            );
            *next += 1;
            thread::sleep(Duration::from_millis(100));
        }
    };
    write_until(&mut line, in_secs(2), &mut next);
    let before_outage = next - 1;
    sub.wait_payload(topic, &before_outage.to_string());

    broker.stop();
    let back_at = in_secs(30);
    write_until(&mut line, in_secs(10), &mut next);
    // A crash in the middle of the outage: the queue is on disk.
    server.child.child().kill().expect("SIGKILL");
    let _ = server.child.child().wait();
    drop(line);
    let queued_at_crash = next - 1;
    let mut server = ServerProcess::with_config_in(server.dir, port);
    let log = server.log();
    assert!(log.contains("queued from before"), "{log}");
    let mut line = Line::connect(port);
    write_until(&mut line, back_at, &mut next);
    broker.restart();
    write_until(&mut line, in_secs(2), &mut next);
    let last = next - 1;
    sub.wait_payload(topic, &last.to_string());

    // Every value from 0 to the last, in order; a value may come twice (a
    // message the broker took but did not acknowledge before it stopped,
    // or the restarted server publishing its first value again) but never
    // after a later one.
    let values: Vec<i32> = sub
        .on(topic)
        .iter()
        .map(|m| m.payload.parse().expect("a number"))
        .collect();
    let mut firsts = Vec::new();
    for &v in &values {
        if !firsts.contains(&v) {
            assert!(firsts.last().is_none_or(|&l| v > l), "{v} after {firsts:?}");
            firsts.push(v);
        } else {
            assert!(
                firsts.iter().rev().take(256).any(|&f| f == v),
                "{v} long after"
            );
        }
    }
    assert_eq!(
        firsts,
        (0..=last).collect::<Vec<_>>(),
        "queued at the crash: {queued_at_crash}"
    );
    let metrics = server.log();
    assert!(metrics.contains("connected to"), "{metrics}");
    drop(line);
    signal(server.child.child().id(), libc::SIGTERM);
    assert!(server.child.wait_timeout(DEADLINE).is_some());
}

// --------------------------------------------------------------------- TLS

#[test]
fn tls_with_a_test_ca() {
    let dir = tempfile::tempdir().unwrap();
    let (ca_pem, cert_pem, key_pem) = test_ca();
    write(&dir.path().join("ca.pem"), &ca_pem);
    write(&dir.path().join("cert.pem"), &cert_pem);
    write(&dir.path().join("key.pem"), &key_pem);
    let tls_port = free_port();
    let broker = Broker::start(&format!(
        "allow_anonymous true\nlistener {tls_port} 127.0.0.1\ncafile {d}/ca.pem\ncertfile {d}/cert.pem\nkeyfile {d}/key.pem\n",
        d = dir.path().display()
    ));
    let sub = broker.subscribe(&["plccoms/#"]);
    // A server on the TLS listener, checking the broker against `ca`.
    let server_with_ca = |section: &str, ca: &str, keys: &str| {
        let port = free_port();
        let ini = format!(
            "[*]\nMQTT_URL = mqtts://127.0.0.1:{tls_port}\nMQTT_CA = {}\n{}",
            dir.path().join(ca).display(),
            sim_section(section, port, keys)
        );
        ServerProcess::with_config(&ini, port)
    };
    let server = server_with_ca(
        "Tls",
        "ca.pem",
        "MQTT_PUBLISH = text\nSIMULATOR_PROGRAM = demo",
    );
    sub.wait_payload("plccoms/Tls/status", "online");
    sub.wait_payload("plccoms/Tls/TEXT", "Have a nice day");
    drop(server);

    // A CA that did not sign the broker's certificate: refused, and said.
    let (other_ca, _, _) = test_ca();
    write(&dir.path().join("other.pem"), &other_ca);
    let server = server_with_ca("Tls2", "other.pem", "MQTT_PUBLISH = text");
    wait_until("a TLS log line", || server.log().contains("cannot connect"));
    let log = server.log();
    assert!(log.contains("TLS") && log.contains("MQTT_CA"), "{log}");
    assert!(sub.on("plccoms/Tls2/status").is_empty());
}

/// A CA, and a certificate for 127.0.0.1 and localhost it signed (PEM).
fn test_ca() -> (String, String, String) {
    use rcgen::{BasicConstraints, CertificateParams, IsCa, KeyPair, SanType};
    let ca_key = KeyPair::generate().unwrap();
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name
        .push(rcgen::DnType::CommonName, "plccoms test CA");
    let ca_cert = ca.self_signed(&ca_key).unwrap();
    let issuer = rcgen::Issuer::new(ca, ca_key);
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::new(vec!["localhost".to_string()]).unwrap();
    params
        .subject_alt_names
        .push(SanType::IpAddress("127.0.0.1".parse().unwrap()));
    let cert = params.signed_by(&key, &issuer).unwrap();
    (ca_cert.pem(), cert.pem(), key.serialize_pem())
}

// ------------------------------------------------------------- credentials

#[test]
fn a_wrong_password_is_a_clear_log_line_and_the_right_one_connects() {
    let dir = tempfile::tempdir().unwrap();
    let passwords = dir.path().join("passwords");
    let status = Command::new("mosquitto_passwd")
        .args(["-b", "-c"])
        .arg(&passwords)
        .args(["plc", "right"])
        .status()
        .expect("run mosquitto_passwd");
    assert!(status.success());
    let broker = Broker::start(&format!(
        "allow_anonymous false\npassword_file {}\n",
        passwords.display()
    ));
    let port = free_port();
    let section = sim_section("Auth", port, "MQTT_PUBLISH = counter");
    let ini = config(&broker, "MQTT_USER = plc\nMQTT_PASSWORD = wrong", &section);
    let server = ServerProcess::with_config(&ini, port);
    wait_until("the refusal in the log", || {
        server.log().contains("refused the connection")
    });
    let log = server.log();
    let refusal = log
        .lines()
        .find(|l| l.contains("refused the connection"))
        .unwrap();
    assert!(refusal.contains("MQTT_PASSWORD"), "{refusal}");
    assert!(
        !log.contains("wrong"),
        "the password is never logged: {log}"
    );
    // Retrying does not repeat the line.
    thread::sleep(Duration::from_secs(2));
    assert_eq!(server.log().matches("refused the connection").count(), 1);
    drop(server);

    write(&dir.path().join("pass"), "right\n");
    let port = free_port();
    let ini = config(
        &broker,
        &format!(
            "MQTT_USER = plc\nMQTT_PASSWORD_FILE = {}",
            dir.path().join("pass").display()
        ),
        &sim_section("Auth", port, "MQTT_PUBLISH = counter"),
    );
    let server = ServerProcess::with_config(&ini, port);
    wait_until("connected", || server.log().contains("MQTT: connected"));
}

// ------------------------------------------------------------ two servers

#[test]
fn two_servers_on_one_broker_never_clash() {
    let broker = Broker::anonymous();
    let sub = broker.subscribe(&["#"]);
    // The same section name in both, told apart by MQTT_PREFIX; client ids
    // differ by default (the configuration's path).
    let (p1, p2) = (free_port(), free_port());
    let one = ServerProcess::with_config(
        &config(
            &broker,
            "MQTT_PREFIX = site1",
            &sim_section("Demo", p1, "MQTT_PUBLISH = counter\nMQTT_WRITE = counter"),
        ),
        p1,
    );
    let two = ServerProcess::with_config(
        &config(
            &broker,
            "MQTT_PREFIX = site2",
            &sim_section("Demo", p2, "MQTT_PUBLISH = counter\nMQTT_WRITE = counter"),
        ),
        p2,
    );
    sub.wait_payload("site1/Demo/status", "online");
    sub.wait_payload("site2/Demo/status", "online");
    broker.publish("site1/Demo/COUNTER/set", "1", false);
    broker.publish("site2/Demo/COUNTER/set", "2", false);
    sub.wait_payload("site1/Demo/COUNTER", "1");
    sub.wait_payload("site2/Demo/COUNTER", "2");
    assert!(sub
        .on("site1/Demo/COUNTER")
        .iter()
        .all(|m| m.payload != "2"));
    let id = |log: &str| {
        log.lines()
            .find_map(|l| {
                l.split(" as ")
                    .nth(1)
                    .map(|s| s.split_whitespace().next().unwrap_or("").to_string())
            })
            .unwrap()
    };
    let (id1, id2) = (id(&one.log()), id(&two.log()));
    assert_ne!(id1, id2);
    // Neither was thrown off by the other.
    assert!(!one.log().contains("lost") && !two.log().contains("lost"));
    // One stops: only its status says so.
    drop(one);
    sub.wait_payload("site1/Demo/status", "offline");
    thread::sleep(Duration::from_millis(500));
    assert!(sub
        .on("site2/Demo/status")
        .iter()
        .all(|m| m.payload == "online"));
    broker.publish("site2/Demo/COUNTER/set", "3", false);
    sub.wait_payload("site2/Demo/COUNTER", "3");
}
