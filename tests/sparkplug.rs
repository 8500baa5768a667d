//! Sparkplug B (spec 3.0) against a real Mosquitto broker and a
//! third-party decoder, pysparkplug (tests/sparkplug/spb.py, in a venv of
//! its own made by tests/sparkplug/venv.sh when missing), with the built
//! `plccoms` and `plcsim` as processes. The spec's assertion ids are cited
//! where they are checked.
//!
//! Waits poll against generous deadlines; nothing here measures speed.

mod common;

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use common::mqtt::{plcsim, Broker, DEADLINE};
use common::process::{free_port, free_udp_port, ChildGuard, ServerProcess};
use serde_json::{json, Value};

/// The venv's python, made when missing (a failure fails the test).
fn python() -> PathBuf {
    let root = env!("CARGO_MANIFEST_DIR");
    let out = Command::new("sh")
        .arg(format!("{root}/tests/sparkplug/venv.sh"))
        .arg(format!("{root}/target/sparkplug-venv"))
        .output()
        .expect("run tests/sparkplug/venv.sh");
    assert!(
        out.status.success(),
        "cannot make the pysparkplug venv: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    PathBuf::from(String::from_utf8(out.stdout).unwrap().trim())
}

fn script() -> String {
    format!("{}/tests/sparkplug/spb.py", env!("CARGO_MANIFEST_DIR"))
}

/// Every Sparkplug message the broker delivers, decoded by pysparkplug.
struct Host {
    lines: Arc<Mutex<Vec<Value>>>,
    _child: ChildGuard,
    port: u16,
}

impl Host {
    fn listen(broker: &Broker) -> Host {
        let mut child = ChildGuard::spawn(
            "spb.py listen",
            Command::new(python())
                .args([&script(), "listen", &broker.port.to_string()])
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit()),
        );
        let stdout = child.child().stdout.take().unwrap();
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = lines.clone();
        thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                let value: Value = serde_json::from_str(&line).expect("a JSON line");
                sink.lock().unwrap().push(value);
            }
        });
        let host = Host {
            lines,
            _child: child,
            port: broker.port,
        };
        host.wait("the listener subscribed", |m| m["type"] == "ready");
        host
    }

    fn all(&self) -> Vec<Value> {
        self.lines.lock().unwrap().clone()
    }

    fn count(&self) -> usize {
        self.lines.lock().unwrap().len()
    }

    /// The first message from `from` on that `want` accepts.
    #[track_caller]
    fn wait_from(&self, from: usize, what: &str, want: impl Fn(&Value) -> bool) -> Value {
        let start = Instant::now();
        loop {
            if let Some(m) = self.all().into_iter().skip(from).find(|m| want(m)) {
                assert!(m.get("error").is_none(), "pysparkplug could not read: {m}");
                return m;
            }
            assert!(
                start.elapsed() < DEADLINE,
                "timed out waiting for {what}; got {:#?}",
                self.all()
            );
            thread::sleep(Duration::from_millis(20));
        }
    }

    #[track_caller]
    fn wait(&self, what: &str, want: impl Fn(&Value) -> bool) -> Value {
        self.wait_from(0, what, want)
    }

    fn command(&self, topic: &str, metrics: Value) {
        let status = Command::new(python())
            .args([
                &script(),
                "cmd",
                &self.port.to_string(),
                topic,
                &metrics.to_string(),
            ])
            .status()
            .expect("spb.py cmd");
        assert!(status.success());
    }

    fn state(&self, host: &str, online: bool, timestamp: u64) {
        let status = Command::new(python())
            .arg(script())
            .args(["state", &self.port.to_string(), host])
            .args([
                if online { "true" } else { "false" },
                &timestamp.to_string(),
            ])
            .status()
            .expect("spb.py state");
        assert!(status.success());
    }
}

fn is(kind: &'static str) -> impl Fn(&Value) -> bool {
    move |m| m["type"] == kind
}

fn metric<'a>(message: &'a Value, name: &str) -> &'a Value {
    message["metrics"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == name)
        .unwrap_or_else(|| panic!("no metric {name} in {message}"))
}

fn config(broker: &Broker, global: &str, sections: &str) -> String {
    format!(
        "[*]\nCOMM_LOOP_DELAY = 50\nMQTT_URL = {}\nSPARKPLUG_GROUP = Plant\nSPARKPLUG_NODE = gw1\n{global}\n{sections}",
        broker.url()
    )
}

fn sim_section(name: &str, port: u16, keys: &str) -> String {
    format!(
        "[{name}]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = idle\nSERVER_PORT = {port}\nPUBFILE = //demo.pub\nSPARKPLUG = Yes\n{keys}\n"
    )
}

/// A broker, the listening host, and a server whose simulated section
/// `Demo` has `keys`.
fn start(global: &str, keys: &str) -> (Broker, Host, ServerProcess) {
    let broker = Broker::anonymous();
    let host = Host::listen(&broker);
    let port = free_port();
    let ini = config(&broker, global, &sim_section("Demo", port, keys));
    let server = ServerProcess::with_config(&ini, port);
    (broker, host, server)
}

/// A line-protocol client's one request and answer.
fn ask(port: u16, request: &str) -> String {
    use std::io::Write;
    let stream = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    stream.set_read_timeout(Some(DEADLINE)).unwrap();
    let mut reader = BufReader::new(stream);
    reader
        .get_mut()
        .write_all(format!("{request}\r\n").as_bytes())
        .unwrap();
    let mut line = String::new();
    reader.read_line(&mut line).unwrap();
    line.trim_end().to_string()
}

/// seq goes 0..255 and round again across every message of the node
/// after `nbirth` (its position), NDEATH aside
/// ([tck-id-payloads-sequence-num-always-included],
/// [tck-id-payloads-sequence-num-incrementing]).
#[track_caller]
fn assert_seq_runs(messages: &[Value]) {
    let mut expected = None;
    for m in messages {
        // The host's commands and the node's death carry none.
        if !["NBIRTH", "NDATA", "DBIRTH", "DDATA", "DDEATH"]
            .contains(&m["type"].as_str().unwrap_or(""))
        {
            continue;
        }
        let seq = m["seq"].as_u64().unwrap_or_else(|| panic!("no seq in {m}"));
        if m["type"] == "NBIRTH" {
            assert_eq!(seq, 0, "[tck-id-payloads-nbirth-seq] {m}");
        } else if let Some(want) = expected {
            assert_eq!(seq, want, "seq after {want}: {m}");
        }
        expected = Some((seq + 1) % 256);
    }
}

const PUBLISH: &str = "MQTT_PUBLISH = counter, sinus, setpoint, switch, note, dat, tim, v_dt, v_sint, v_ulint, v_word";

#[test]
fn births_data_commands_and_seq() {
    let broker = Broker::anonymous();
    let host = Host::listen(&broker);
    let port = free_port();
    let ini = config(
        &broker,
        "",
        &sim_section(
            "Hala 1",
            port,
            &format!("{PUBLISH}\nMQTT_WRITE = counter, setpoint, switch, note, v_dt"),
        ),
    );
    let server = ServerProcess::with_config(&ini, port);

    // NBIRTH: seq 0, bdSeq, Node Control/Rebirth ([tck-id-payloads-nbirth-bdseq],
    // [tck-id-message-flow-edge-node-birth-publish-nbirth-payload-seq]).
    let nbirth = host.wait("NBIRTH", is("NBIRTH"));
    assert_eq!(nbirth["topic"], "spBv1.0/Plant/NBIRTH/gw1");
    assert_eq!(nbirth["seq"], 0);
    assert!(
        nbirth["timestamp"].as_u64().is_some(),
        "[tck-id-payloads-timestamp-in-UTC]"
    );
    assert_eq!(metric(&nbirth, "bdSeq")["datatype"], 8);
    assert_eq!(metric(&nbirth, "Node Control/Rebirth")["value"], false);
    assert_eq!(metric(&nbirth, "Node Control/Rebirth")["datatype"], 11);

    // DBIRTH: every published metric with name, alias, datatype, value,
    // timestamp and the Quality property ([tck-id-payloads-dbirth-seq],
    // [tck-id-payloads-alias-birth-requirement]).
    let dbirth = host.wait("DBIRTH", is("DBIRTH"));
    assert_eq!(dbirth["topic"], "spBv1.0/Plant/DBIRTH/gw1/Hala 1");
    assert_eq!(dbirth["seq"], 1);
    let metrics = dbirth["metrics"].as_array().unwrap();
    assert_eq!(metrics.len(), 11, "{dbirth}\n{}", server.log());
    let mut aliases: Vec<u64> = metrics
        .iter()
        .map(|m| m["alias"].as_u64().unwrap())
        .collect();
    aliases.extend([1, 2, 3, 4]); // the node's
    let unique: std::collections::BTreeSet<_> = aliases.iter().collect();
    assert_eq!(
        unique.len(),
        aliases.len(),
        "[tck-id-payloads-alias-uniqueness] {aliases:?}"
    );
    for (name, datatype) in [
        ("COUNTER", 2),
        ("SINUS", 10),
        ("SETPOINT", 9),
        ("SWITCH", 11),
        ("NOTE", 12),
        ("DAT", 13),
        ("TIM", 12),
        ("V_DT", 13),
        ("V_SINT", 1),
        ("V_ULINT", 8),
        ("V_WORD", 6),
    ] {
        let m = metric(&dbirth, name);
        assert_eq!(m["datatype"], datatype, "{m}");
        assert!(m["timestamp"].as_u64().unwrap() > 1_600_000_000_000, "{m}");
        assert_eq!(m["properties"]["Quality"], "good", "{m}");
    }
    assert_eq!(metric(&dbirth, "COUNTER")["value"], 0);
    let counter = metric(&dbirth, "COUNTER")["alias"].as_u64().unwrap();

    // A change comes as DDATA, by alias only ([tck-id-payloads-alias-data-cmd-requirement]).
    let from = host.count();
    assert_eq!(ask(port, "SET:counter,-5"), "DIFF:COUNTER,-5");
    let ddata = host.wait_from(from, "DDATA of COUNTER", is("DDATA"));
    assert_eq!(ddata["topic"], "spBv1.0/Plant/DDATA/gw1/Hala 1");
    let m = &ddata["metrics"][0];
    assert_eq!(
        (m["alias"].as_u64(), &m["value"], &m["name"]),
        (Some(counter), &json!(-5), &json!("COUNTER")),
        "pysparkplug names it from the birth: {ddata}"
    );

    // DCMD by alias and by name, through the write path: the value read
    // back comes as DDATA, and the PLC holds it.
    let from = host.count();
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Hala 1",
        json!([{"alias": counter, "datatype": 2, "value": 42}]),
    );
    host.wait_from(from, "DDATA of the written COUNTER", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == 42
    });
    assert_eq!(ask(port, "GET:counter"), "GET:COUNTER,42");
    let from = host.count();
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Hala 1",
        json!([{"name": "SETPOINT", "datatype": 9, "value": 21.5}]),
    );
    host.wait_from(from, "DDATA of SETPOINT", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == 21.5
    });
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Hala 1",
        json!([{"name": "V_DT", "datatype": 13, "value": null}]),
    );
    let from = host.count();
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Hala 1",
        json!([{"name": "SWITCH", "datatype": 11, "value": true}]),
    );
    host.wait_from(from, "DDATA of SWITCH", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == true
    });

    // Refusals change nothing and are counted in the node's metric: not
    // in MQTT_WRITE, out of the type's range, no such metric.
    let from = host.count();
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Hala 1",
        json!([{"name": "SINUS", "datatype": 10, "value": 3.0}]),
    );
    let refused = host.wait_from(from, "NDATA of refusals", is("NDATA"));
    assert_eq!(refused["metrics"][0]["name"], "Node Info/Write Refusals");
    let before = refused["metrics"][0]["value"].as_u64().unwrap();
    assert!(before >= 2, "the null V_DT and SINUS: {refused}");
    let from = host.count();
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Hala 1",
        json!([{"name": "COUNTER", "datatype": 3, "value": 100000}]),
    );
    host.wait_from(from, "the range refusal", |m| {
        m["type"] == "NDATA" && m["metrics"][0]["value"] == before + 1
    });
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Hala 1",
        json!([{"alias": 999_999, "datatype": 2, "value": 1}]),
    );
    host.wait_from(from, "the alias refusal", |m| {
        m["type"] == "NDATA" && m["metrics"][0]["value"].as_u64() >= Some(before + 2)
    });
    assert_eq!(ask(port, "GET:counter"), "GET:COUNTER,42");
    assert!(
        server.log().contains("Sparkplug: DCMD to Hala 1 refused"),
        "{}",
        server.log()
    );

    // NCMD Rebirth: NBIRTH (seq 0) and DBIRTH again, same bdSeq
    // ([tck-id-operational-behavior-data-commands-rebirth-action-2]).
    let from = host.count();
    host.command(
        "spBv1.0/Plant/NCMD/gw1",
        json!([{"name": "Node Control/Rebirth", "datatype": 11, "value": true}]),
    );
    let again = host.wait_from(from, "NBIRTH again", is("NBIRTH"));
    assert_eq!(
        metric(&again, "bdSeq")["value"],
        metric(&nbirth, "bdSeq")["value"]
    );
    let dbirth = host.wait_from(from, "DBIRTH again", is("DBIRTH"));
    assert_eq!(metric(&dbirth, "COUNTER")["value"], 42);

    // 300 changes: seq wraps from 255 to 0 with no gap.
    let from = host.count();
    for n in 1..=300 {
        assert_eq!(
            ask(port, &format!("SET:counter,{n}")),
            format!("DIFF:COUNTER,{n}")
        );
    }
    host.wait_from(from, "the 300th change", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == 300
    });
    let all = host.all();
    assert!(all.iter().skip(1).filter(|m| m["type"] == "DDATA").count() > 256);
    assert_seq_runs(&all[1..]);
    assert!(
        all.iter().any(|m| m["seq"] == 255) && all.iter().filter(|m| m["seq"] == 0).count() >= 3
    );
}

/// bdSeq survives kill -9: the will the broker delivers holds the NBIRTH's
/// bdSeq, and the next start's NBIRTH the one after
/// ([tck-id-payloads-ndeath-bdseq], [tck-id-payloads-nbirth-bdseq-repeat]).
#[test]
fn bdseq_across_kill_9_and_restart() {
    let (_broker, host, mut server) = start("", "MQTT_PUBLISH = counter");
    let port = server.port();
    let first = metric(&host.wait("NBIRTH", is("NBIRTH")), "bdSeq")["value"]
        .as_u64()
        .unwrap();
    host.wait("DBIRTH", is("DBIRTH"));
    server.child.child().kill().expect("SIGKILL");
    let _ = server.child.child().wait();
    let death = host.wait("NDEATH, the will", is("NDEATH"));
    assert_eq!(death["topic"], "spBv1.0/Plant/NDEATH/gw1");
    assert_eq!(metric(&death, "bdSeq")["value"], first);
    let from = host.count();
    let mut server = ServerProcess::with_config_in(server.dir, port);
    let second = metric(
        &host.wait_from(from, "NBIRTH after restart", is("NBIRTH")),
        "bdSeq",
    )["value"]
        .as_u64()
        .unwrap();
    assert_eq!(second, (first + 1) % 256);
    // A clean stop sends NDEATH itself, with the same bdSeq.
    common::mqtt::signal(server.child.child().id(), libc::SIGTERM);
    assert!(server.child.wait_timeout(DEADLINE).is_some());
    let death = host.wait_from(from, "NDEATH on a clean stop", is("NDEATH"));
    assert_eq!(metric(&death, "bdSeq")["value"], second);
}

/// The PLC lost: DDEATH; back: DBIRTH with its values
/// ([tck-id-operational-behavior-device-ddeath]).
#[test]
fn plc_lost_is_ddeath_and_its_return_a_dbirth() {
    let broker = Broker::anonymous();
    let host = Host::listen(&broker);
    let udp = free_udp_port();
    let files = tempfile::tempdir().unwrap();
    let mut plc = plcsim(files.path(), udp);
    let port = free_port();
    let section = format!(
        "[Plc]\nIPADDR = 127.0.0.1\nEPSPORT = {udp}\nEPSTOUT = 200\nEPSTOUT_STEP = 0\nSERVER_PORT = {port}\nPUBFILE = //demo.pub\nSPARKPLUG = Yes\nMQTT_PUBLISH = counter\n"
    );
    let _server = ServerProcess::with_config(&config(&broker, "", &section), port);
    host.wait("DBIRTH", is("DBIRTH"));
    drop(plc.child().kill());
    let death = host.wait("DDEATH", is("DDEATH"));
    assert_eq!(death["topic"], "spBv1.0/Plant/DDEATH/gw1/Plc");
    assert!(death["seq"].as_u64().is_some());
    drop(plc);
    let from = host.count();
    let _plc = plcsim(files.path(), udp);
    let birth = host.wait_from(from, "DBIRTH on return", is("DBIRTH"));
    assert_eq!(metric(&birth, "COUNTER")["properties"]["Quality"], "good");
    assert_seq_runs(&host.all()[1..]);
}

/// With SPARKPLUG_HOST: nothing is born before the host's STATE says
/// online; its offline is NDEATH and a new session that waits for it
/// ([tck-id-operational-behavior-edge-node-birth-sequence-wait],
/// [tck-id-message-flow-edge-node-birth-publish-phid-offline]).
#[test]
fn primary_host_state() {
    let (_broker, host, server) = start("SPARKPLUG_HOST = scada", "MQTT_PUBLISH = counter");
    let port = server.port();
    let start = Instant::now();
    while !server
        .log()
        .contains("Sparkplug: edge node Plant/gw1 connected")
    {
        assert!(start.elapsed() < DEADLINE, "{}", server.log());
        thread::sleep(Duration::from_millis(20));
    }
    thread::sleep(Duration::from_millis(500));
    assert!(
        !host.all().iter().any(is("NBIRTH")),
        "born before the host: {:?}",
        host.all()
    );
    host.state("scada", true, 1000);
    let first = host.wait("NBIRTH once the host is online", is("NBIRTH"));
    host.wait("DBIRTH", is("DBIRTH"));
    let from = host.count();
    host.state("scada", false, 2000);
    let death = host.wait_from(from, "NDEATH on the host's offline", is("NDEATH"));
    assert_eq!(
        metric(&death, "bdSeq")["value"],
        metric(&first, "bdSeq")["value"]
    );
    // Changes while the host is away are held, then sent after the births
    // as historical metrics, in order, with their poll times
    // ((spec 3.0, Payloads: the metric's is_historical)).
    let from = host.count();
    while !server.log().contains("waiting for it") {
        assert!(start.elapsed() < DEADLINE, "{}", server.log());
        thread::sleep(Duration::from_millis(20));
    }
    for n in 1..=5 {
        assert_eq!(
            ask(port, &format!("SET:counter,{n}")),
            format!("DIFF:COUNTER,{n}")
        );
        thread::sleep(Duration::from_millis(150));
    }
    thread::sleep(Duration::from_millis(500));
    let later = &host.all()[from..];
    assert!(
        !later.iter().any(is("NBIRTH")),
        "born while the host is offline"
    );
    assert!(
        !later.iter().any(is("DDATA")),
        "data while the host is offline"
    );
    host.state("scada", true, 3000);
    let second = host.wait_from(from, "NBIRTH when the host is back", is("NBIRTH"));
    assert_eq!(
        metric(&second, "bdSeq")["value"].as_u64().unwrap(),
        (metric(&first, "bdSeq")["value"].as_u64().unwrap() + 1) % 256,
        "a new session"
    );
    let birth = host.wait_from(from, "DBIRTH when the host is back", is("DBIRTH"));
    assert_eq!(metric(&birth, "COUNTER")["value"], 5);
    host.wait_from(from, "the last held change", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == 5
    });
    let all = host.all();
    let held: Vec<&Value> = all[from..]
        .iter()
        .filter(|m| m["type"] == "DDATA")
        .flat_map(|m| m["metrics"].as_array().unwrap())
        .collect();
    let values: Vec<i64> = held.iter().map(|m| m["value"].as_i64().unwrap()).collect();
    assert_eq!(values, [1, 2, 3, 4, 5], "{held:?}");
    assert!(
        held.iter()
            .all(|m| m["is_historical"] == true && m["name"] == "COUNTER"),
        "{held:?}"
    );
    let stamps: Vec<u64> = held
        .iter()
        .map(|m| m["timestamp"].as_u64().unwrap())
        .collect();
    assert!(
        stamps.windows(2).all(|w| w[0] < w[1]),
        "poll times in order: {stamps:?}"
    );
    let reborn = all.iter().position(|m| m == &second).unwrap();
    assert_seq_runs(&all[reborn..]);
}

/// A section whose MQTT_PUBLISH names none of its variables is a device
/// all the same: born without metrics once the wait for them ends.
#[test]
fn a_device_without_metrics_is_born_all_the_same() {
    let (_broker, host, _server) = start("", "MQTT_PUBLISH = no_such_variable");
    let birth = host.wait("DBIRTH", is("DBIRTH"));
    assert_eq!(birth["topic"], "spBv1.0/Plant/DBIRTH/gw1/Demo");
    assert_eq!(birth["metrics"].as_array().unwrap().len(), 0, "{birth}");
}

/// A metric's time is the PLC's own where HISTORY_STAMP pairs one, and a
/// new PLC time is a new event of its value even when the value is the
/// same ([tck-id-payloads-metric-timestamp-in-UTC]).
#[test]
fn plc_time_of_a_paired_metric() {
    let (_broker, host, server) =
        start("", "MQTT_PUBLISH = counter\nHISTORY_STAMP = counter:v_lint");
    let port = server.port();
    // A device online before its public file is read waits for it (2 s at
    // most: longer, under load, it is born with no metrics, and again with
    // the new table's).
    let birth = host.wait("DBIRTH with COUNTER", |m| {
        m["type"] == "DBIRTH" && !m["metrics"].as_array().unwrap().is_empty()
    });
    assert_eq!(
        birth["metrics"].as_array().unwrap().len(),
        1,
        "the stamp is no metric: {birth}"
    );
    let from = host.count();
    assert_eq!(
        ask(port, "SET:v_lint,1795601700123"),
        "DIFF:V_LINT,1795601700123"
    );
    assert_eq!(ask(port, "SET:counter,7"), "DIFF:COUNTER,7");
    let data = host.wait_from(from, "COUNTER = 7", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == 7
    });
    assert_eq!(data["metrics"][0]["timestamp"], 1_795_601_700_123_u64);
    let from = host.count();
    assert_eq!(
        ask(port, "SET:v_lint,1795601800000"),
        "DIFF:V_LINT,1795601800000"
    );
    let data = host.wait_from(from, "COUNTER stamped again", is("DDATA"));
    assert_eq!(data["metrics"][0]["value"], 7);
    assert_eq!(data["metrics"][0]["timestamp"], 1_795_601_800_000_u64);
}

/// MQTT_DELTA holds back changes within the deadband; a confirmed DCMD
/// write is sent whatever its size.
#[test]
fn deadband_and_confirmed_writes() {
    let (_broker, host, server) = start(
        "",
        "MQTT_PUBLISH = counter\nMQTT_WRITE = counter\nMQTT_DELTA = 5",
    );
    let port = server.port();
    host.wait("DBIRTH", is("DBIRTH"));
    let from = host.count();
    for n in [3, 9, 12, 20] {
        assert_eq!(
            ask(port, &format!("SET:counter,{n}")),
            format!("DIFF:COUNTER,{n}")
        );
    }
    host.wait_from(from, "COUNTER = 20", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == 20
    });
    let sent: Vec<i64> = host.all()[from..]
        .iter()
        .filter(|m| m["type"] == "DDATA")
        .map(|m| m["metrics"][0]["value"].as_i64().unwrap())
        .collect();
    assert_eq!(sent, [9, 20], "moves over 5 from the last sent");
    let from = host.count();
    host.command(
        "spBv1.0/Plant/DCMD/gw1/Demo",
        json!([{"name": "COUNTER", "datatype": 2, "value": 21}]),
    );
    host.wait_from(from, "the confirmed write", |m| {
        m["type"] == "DDATA" && m["metrics"][0]["value"] == 21
    });
}

/// A reload (SIGHUP) that adds a Sparkplug section is a new session of
/// the node: NDEATH, then NBIRTH with the next bdSeq and a DBIRTH per
/// device, the new one included.
#[test]
fn a_reload_that_adds_a_device_is_a_new_session() {
    let (broker, host, server) = start("", "MQTT_PUBLISH = counter");
    let first = host.wait("NBIRTH", is("NBIRTH"));
    host.wait("DBIRTH", is("DBIRTH"));
    let from = host.count();
    let two = free_port();
    let ini = config(
        &broker,
        "",
        &(sim_section("Demo", server.port(), "MQTT_PUBLISH = counter")
            + &sim_section("Two", two, "MQTT_PUBLISH = sinus")),
    );
    std::fs::write(server.dir.path().join("plccoms.ini"), ini).unwrap();
    let mut server = server;
    common::mqtt::signal(server.child.child().id(), libc::SIGHUP);
    let death = host.wait_from(from, "NDEATH of the old session", is("NDEATH"));
    assert_eq!(
        metric(&death, "bdSeq")["value"],
        metric(&first, "bdSeq")["value"]
    );
    let second = host.wait_from(from, "NBIRTH of the new session", is("NBIRTH"));
    assert_eq!(
        metric(&second, "bdSeq")["value"].as_u64().unwrap(),
        (metric(&first, "bdSeq")["value"].as_u64().unwrap() + 1) % 256
    );
    let births = |device: &str| {
        host.wait_from(from, device, |m| {
            m["type"] == "DBIRTH" && m["device"] == device
        })
    };
    assert_eq!(births("Two")["metrics"][0]["name"], "SINUS");
    assert_eq!(births("Demo")["metrics"][0]["name"], "COUNTER");
}

/// MQTT_URL with a primary and a standby (issue 36): the primary gone, the
/// edge node moves to the standby with the next bdSeq (NBIRTH, DBIRTH), a
/// plain section's `status` and Home Assistant discovery are announced
/// there again, and the wills are the standby's: a kill -9 of the server
/// delivers NDEATH and `status` = `offline` there.
#[test]
fn moves_to_the_next_broker_with_births_discovery_and_wills() {
    let mut primary = Broker::anonymous();
    let standby = Broker::anonymous();
    let on_primary = Host::listen(&primary);
    let on_standby = Host::listen(&standby);
    let sub = standby.subscribe(&["plccoms/#", "homeassistant/#"]);
    let (spb, plain) = (free_port(), free_port());
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 50\nMQTT_URL = {}, {}\nSPARKPLUG_GROUP = Plant\nSPARKPLUG_NODE = gw1\n{}\
         [Plain]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = idle\nSERVER_PORT = {plain}\nPUBFILE = //demo.pub\n\
         MQTT_PUBLISH = counter\nMQTT_HA_DISCOVERY = Yes\n",
        primary.url(),
        standby.url(),
        sim_section("Demo", spb, "MQTT_PUBLISH = counter"),
    );
    let mut server = ServerProcess::with_config(&ini, plain);
    let first = metric(&on_primary.wait("NBIRTH", is("NBIRTH")), "bdSeq")["value"]
        .as_u64()
        .unwrap();
    on_primary.wait("DBIRTH", is("DBIRTH"));
    assert_eq!(on_standby.count(), 1, "only the listener's ready line");

    primary.stop();
    let birth = on_standby.wait("NBIRTH on the standby", is("NBIRTH"));
    assert_eq!(metric(&birth, "bdSeq")["value"], (first + 1) % 256);
    on_standby.wait("DBIRTH on the standby", is("DBIRTH"));
    sub.wait_payload("plccoms/Plain/status", "online");
    sub.wait_for("a discovery config on the standby", || {
        sub.messages()
            .into_iter()
            .find(|m| m.topic.starts_with("homeassistant/") && m.topic.ends_with("/config"))
    });
    let log = server.log();
    assert!(
        log.contains("moving to 127.0.0.1:") && log.contains("(broker 2 of 2)"),
        "{log}"
    );

    server.child.child().kill().expect("SIGKILL");
    let _ = server.child.child().wait();
    let death = on_standby.wait("NDEATH, the will, on the standby", is("NDEATH"));
    assert_eq!(metric(&death, "bdSeq")["value"], (first + 1) % 256);
    sub.wait_payload("plccoms/Plain/status", "offline");
}
