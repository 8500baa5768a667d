//! What any client of the broker can send the MQTT north side: floods of
//! Home Assistant `online`s, oversized retained `/set`s, thousands of
//! refused writes. A real Mosquitto broker (its `mosquitto_pub` and
//! `mosquitto_sub` as the other clients) and the server in this process,
//! so its memory (VmRSS) and its log lines can be read. One test at a time
//! (memory and log lines are the process's), each counting only what its
//! own run added.
//!
//! Waits poll against generous deadlines; nothing here measures speed.

mod common;

use std::collections::BTreeSet;
use std::io::Write as _;
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use common::logs::Logs;
use common::mqtt::{Broker, DEADLINE};
use common::{rss_kib, simulated};

static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

fn logs() -> &'static Logs {
    static LOGS: OnceLock<Logs> = OnceLock::new();
    LOGS.get_or_init(Logs::install)
}

/// `mosquitto_pub -l`: each of `lines` a message (QoS 1) on `topic`.
fn publish_lines(broker: &Broker, topic: &str, lines: usize, payload: &str) {
    let mut child = Command::new("mosquitto_pub")
        .args(["-h", "127.0.0.1", "-p", &broker.port.to_string()])
        .args(["-q", "1", "-t", topic, "-l"])
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .expect("run mosquitto_pub");
    let mut stdin = child.stdin.take().expect("stdin");
    stdin
        .write_all(format!("{payload}\n").repeat(lines).as_bytes())
        .expect("write mosquitto_pub's stdin");
    drop(stdin);
    assert!(child.wait().expect("mosquitto_pub").success());
}

/// `mosquitto_pub -r -s` of `bytes` on `topic`, retained.
fn publish_retained_bytes(broker: &Broker, topic: &str, bytes: &[u8]) {
    let mut child = Command::new("mosquitto_pub")
        .args(["-h", "127.0.0.1", "-p", &broker.port.to_string()])
        .args(["-q", "1", "-r", "-t", topic, "-s"])
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .expect("run mosquitto_pub");
    let mut stdin = child.stdin.take().expect("stdin");
    stdin.write_all(bytes).expect("write mosquitto_pub's stdin");
    drop(stdin);
    assert!(child.wait().expect("mosquitto_pub").success());
}

/// The value of `family{section="PLC"}` in `/metrics`.
fn metric(server: &plccoms::startup::Server, family: &str) -> u64 {
    let text = server.metrics.render();
    let prefix = format!("{family}{{section=\"PLC\"}} ");
    text.lines()
        .find_map(|l| l.strip_prefix(&prefix))
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{family} not in /metrics"))
}

/// The log text written since `from` (a byte offset of the log).
fn log_since(from: usize) -> String {
    logs().text()[from..].to_string()
}

/// A discovery config of one of the project's `VAR_nnnnn`.
fn is_var_config(topic: &str) -> bool {
    topic.contains("/plccoms_PLC_VAR_") && topic.ends_with("/config")
}

#[track_caller]
fn wait_until(what: &str, mut ready: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ready() {
        assert!(start.elapsed() < DEADLINE, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// 300 `online`s on `homeassistant/status` with 2,000 variables published
/// used to queue 600,000 config messages in memory; they are coalesced into
/// one announcement, and discovery still ends complete.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_home_assistant_onlines_keeps_memory_bounded() {
    let _serial = SERIAL.lock().await;
    logs();
    // Subscribers here take thousands of messages at once: none dropped.
    let broker = Broker::start("allow_anonymous true\nmax_queued_messages 0\n");
    let project = plcsim::genpub::plain(2000);
    let (server, _addr, _dir) = simulated(
        &format!("MQTT_URL = {}", broker.url()),
        "PUBFILE = //project.pub\nMQTT_PUBLISH = *\nMQTT_WRITE = VAR_00001\nMQTT_HA_DISCOVERY = Yes",
        Some(&project),
    )
    .await;
    let configs = |sub: &common::mqtt::Sub| -> usize {
        sub.messages()
            .into_iter()
            .filter(|m| is_var_config(&m.topic) && !m.payload.is_empty())
            .map(|m| m.topic)
            .collect::<BTreeSet<_>>()
            .len()
    };
    // The first announcement, whole (retained at the broker).
    let first = broker.subscribe(&["homeassistant/#"]);
    first.wait_for("2000 configs", || (configs(&first) == 2000).then_some(()));
    drop(first);
    let before = rss_kib();
    let start = logs().len();

    let live = broker.subscribe(&["homeassistant/#"]);
    let live_before = live.messages().len();
    publish_lines(&broker, "homeassistant/status", 300, "online");
    // A refused write after the onlines: its log line says every online
    // before it was taken.
    broker.publish("plccoms/PLC/VAR_00002/set", "after-the-flood", false);
    let mut peak = before;
    wait_until("the write after the flood", || {
        peak = peak.max(rss_kib());
        log_since(start).contains("after-the-flood")
    });
    for _ in 0..20 {
        peak = peak.max(rss_kib());
        std::thread::sleep(Duration::from_millis(100));
    }
    let grown_mib = peak.saturating_sub(before) / 1024;
    assert!(
        grown_mib < 48,
        "RSS grew by {grown_mib} MiB ({before} KiB before)"
    );
    // Discovery is sent again, complete: every config after the flood.
    live.wait_for("2000 configs sent again", || {
        let again: BTreeSet<String> = live.messages()[live_before..]
            .iter()
            .filter(|m| is_var_config(&m.topic) && !m.payload.is_empty())
            .map(|m| m.topic.clone())
            .collect();
        (again.len() == 2000).then_some(())
    });
    let late = broker.subscribe(&["homeassistant/#"]);
    late.wait_for("2000 retained configs", || {
        (configs(&late) == 2000).then_some(())
    });
    server.shutdown().await;
}

/// A simulated section publishing to `broker` with the section `keys`, and
/// a subscriber to `filter` that saw it come online.
async fn online(
    broker: &Broker,
    keys: &str,
    filter: &str,
) -> (
    plccoms::startup::Server,
    std::net::SocketAddr,
    tempfile::TempDir,
    common::mqtt::Sub,
) {
    let (server, addr, dir) = simulated(&format!("MQTT_URL = {}", broker.url()), keys, None).await;
    let sub = broker.subscribe(&[filter]);
    sub.wait_payload("plccoms/PLC/status", "online");
    (server, addr, dir, sub)
}

/// A retained `/set` over rumqttc's old 1 MiB limit made every connection
/// fail at its subscription: reconnections without end, queued changes
/// sent again each time, a log line each. It is refused like any retained
/// write, the connection stays, and a change goes out once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_retained_set_keeps_the_connection() {
    let _serial = SERIAL.lock().await;
    logs();
    let broker = Broker::anonymous();
    let (server, addr, _dir, sub) = online(
        &broker,
        "MQTT_PUBLISH = counter\nMQTT_WRITE = counter, note",
        "plccoms/PLC/#",
    )
    .await;
    let start = logs().len();
    assert_eq!(metric(&server, "plccoms_mqtt_connects_total"), 1);

    publish_retained_bytes(&broker, "plccoms/PLC/NOTE/set", &vec![b'x'; 3 << 20]);
    wait_until("the oversized write refused", || {
        metric(&server, "plccoms_mqtt_write_refusals_total") >= 1
    });
    // Ten seconds: the connection stays.
    std::thread::sleep(Duration::from_secs(10));
    assert_eq!(
        metric(&server, "plccoms_mqtt_connects_total"),
        1,
        "{}",
        log_since(start)
    );
    let log = log_since(start);
    assert!(log.lines().count() <= 3, "{log}");

    // A later change (a line-protocol client's SET) arrives exactly once.
    let mut client = common::Client::connect(addr).await;
    client.send(b"SET:counter,4321\n").await;
    sub.wait_payload("plccoms/PLC/COUNTER", "4321");
    std::thread::sleep(Duration::from_secs(3));
    let seen = sub
        .on("plccoms/PLC/COUNTER")
        .into_iter()
        .filter(|m| m.payload == "4321")
        .count();
    assert_eq!(seen, 1);
    assert_eq!(metric(&server, "plccoms_mqtt_connects_total"), 1);
    // Cleared, so the broker's folder does not keep it.
    broker.publish("plccoms/PLC/NOTE/set", "", true);
    server.shutdown().await;
}

/// A retained `/set` too big for any client of this server (over the
/// incoming limit) used to make every connection fail at its
/// subscription. The limit is now MQTT 5's maximum packet size, which the
/// broker honours: it drops the message for this client, the connection
/// stays, nothing is logged, and writes after it go through.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_retained_set_over_the_limit_never_reaches_the_server() {
    let _serial = SERIAL.lock().await;
    logs();
    let broker = Broker::anonymous();
    let (server, _addr, _dir, sub) = online(
        &broker,
        "MQTT_PUBLISH = counter\nMQTT_WRITE = counter, note",
        "plccoms/PLC/#",
    )
    .await;
    let start = logs().len();
    publish_retained_bytes(&broker, "plccoms/PLC/NOTE/set", &vec![b'x'; 20 << 20]);
    // Messages to one subscriber keep their order: once this write is
    // confirmed, the big one was dropped or sent before it.
    broker.publish("plccoms/PLC/COUNTER/set", "12", false);
    sub.wait_payload("plccoms/PLC/COUNTER", "12");
    assert_eq!(metric(&server, "plccoms_mqtt_connects_total"), 1);
    assert_eq!(metric(&server, "plccoms_mqtt_write_refusals_total"), 0);
    let log = log_since(start);
    assert!(log.is_empty(), "{log}");
    broker.publish("plccoms/PLC/NOTE/set", "", true);
    server.shutdown().await;
}

/// 5,000 refused writes: counted each, logged a few times, not 5,000.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refused_writes_are_counted_but_their_log_is_rate_limited() {
    let _serial = SERIAL.lock().await;
    logs();
    // Every one of the 5,000 reaches the server, however slow it is.
    let broker = Broker::start("allow_anonymous true\nmax_queued_messages 0\n");
    let (server, _addr, _dir, _sub) = online(
        &broker,
        "MQTT_PUBLISH = counter\nMQTT_WRITE = counter",
        "plccoms/PLC/status",
    )
    .await;
    let start = logs().len();
    let began = Instant::now();
    publish_lines(&broker, "plccoms/PLC/SINUS/set", 5000, "1");
    wait_until("5000 refusals", || {
        metric(&server, "plccoms_mqtt_write_refusals_total") == 5000
    });
    let log = log_since(start);
    let refused = log.matches("write refused").count();
    // At most one line a second.
    let most = began.elapsed().as_secs() as usize + 2;
    assert!((1..=most).contains(&refused), "{refused} lines in {most} s");
    assert!(log.contains("SET:SINUS,1"), "{log}");
    server.shutdown().await;
}

/// `*` in MQTT_PUBLISH and MQTT_WRITE means the project's variables: no
/// system variable (`__...`) is published or written, and no direct
/// address (`%...`) written, unless a mask begins with `__` or `%`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_star_means_the_project_s_variables() {
    let _serial = SERIAL.lock().await;
    logs();
    let broker = Broker::anonymous();
    let (server, _addr, _dir) = simulated(
        &format!("MQTT_URL = {}", broker.url()),
        "MQTT_PUBLISH = *\nMQTT_WRITE = *",
        None,
    )
    .await;
    let sub = broker.subscribe(&["plccoms/PLC/#"]);
    sub.wait_payload("plccoms/PLC/COUNTER", "0");
    broker.publish("plccoms/PLC/%25R0/set", "1", false);
    broker.publish("plccoms/PLC/__PLC_RUN/set", "0", false);
    for level in ["%25R0", "__PLC_RUN"] {
        sub.wait(&format!("plccoms/PLC/{level}/error"), |m| {
            m.payload.contains("not writable over MQTT")
        });
    }
    let system: Vec<String> = sub
        .messages()
        .into_iter()
        .map(|m| m.topic)
        .filter(|t| {
            t.starts_with("plccoms/PLC/__") && !t.ends_with("/error") && !t.ends_with("/set")
        })
        .collect();
    assert!(system.is_empty(), "{system:?}");
    server.shutdown().await;
}

/// A STRING with CR/LF written over MQTT is refused like any bad value: the
/// line clients that enabled the variable see no forged DIFF line.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_string_with_line_ends_over_mqtt_forges_no_line() {
    let _serial = SERIAL.lock().await;
    logs();
    let broker = Broker::anonymous();
    let (server, addr, _dir) = simulated(
        &format!("MQTT_URL = {}", broker.url()),
        "MQTT_PUBLISH = note\nMQTT_WRITE = note",
        None,
    )
    .await;
    let mut watcher = common::Client::connect(addr).await;
    watcher.send(b"EN:setpoint\nEN:note\n").await;
    // Both first values, in whichever publishes they come: a late one
    // would break the silence below.
    watcher
        .wait_for_lines(
            &[b"DIFF:NOTE,\"\"\r\n", b"DIFF:SETPOINT,0.000000\r\n"],
            DEADLINE,
        )
        .await;
    let sub = broker.subscribe(&["plccoms/PLC/#"]);
    // An empty STRING is an empty message, which clears the retained one:
    // the subscriber sees no value, only the connection.
    sub.wait_payload("plccoms/PLC/status", "online");
    let mut child = Command::new("mosquitto_pub")
        .args(["-h", "127.0.0.1", "-p", &broker.port.to_string()])
        .args(["-q", "1", "-t", "plccoms/PLC/NOTE/set", "-s"])
        .stdin(Stdio::piped())
        .spawn()
        .expect("run mosquitto_pub");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(b"0\r\nDIFF:SETPOINT,99.000000")
        .unwrap();
    assert!(child.wait().unwrap().success());
    sub.wait("plccoms/PLC/NOTE/error", |m| m.payload.contains("ERROR:35"));
    watcher.silent(300).await;
    watcher.ask("GET:note\n", "GET:NOTE,\"\"\r\n").await;
    drop(watcher);
    server.shutdown().await;
}
