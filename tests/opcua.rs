//! The OPC UA server against a real third-party client: asyncua (PyPI),
//! driven through tests/opcua/client.py, on loopback, with the simulated
//! PLC in-process (EPSNET) so the tests set values, lose the link and
//! bring it back. `.ci/run` installs asyncua; without it these tests fail.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::Client;
use plcsim::{SimConfig, SimHandle};
use serde_json::Value;
use tokio::io::{AsyncBufReadExt, BufReader};

const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/opcua/client.py");

/// Users of every test: `hmi` may write, `scada` only reads.
fn users_file(dir: &Path) -> PathBuf {
    let path = dir.join("opcua-users");
    let text = [
        plccoms_opcua::users::hash_line("hmi", "write", "hmi-pass", b"tests-salt-1", 1000),
        plccoms_opcua::users::hash_line("scada", "read", "scada-pass", b"tests-salt-2", 1000),
    ]
    .join("\n");
    std::fs::write(&path, text).unwrap();
    path
}

struct Ua {
    server: plccoms::startup::Server,
    sim: SimHandle,
    port: u16,
    url: String,
    conf: tempfile::TempDir,
    _files: tempfile::TempDir,
}

impl Ua {
    async fn start(global: &str, section: &str) -> Ua {
        let ua = Ua::start_with(global, section).await;
        ua.wait_table(&[]).await;
        ua
    }

    /// Starts; [`Ua::wait_table`] waits for the PLC's table.
    async fn start_with(global: &str, section: &str) -> Ua {
        Ua::start_pub(global, section, plcsim::DEMO_PUB).await
    }

    /// Starts with `public` as the PLC's public file.
    async fn start_pub(global: &str, section: &str, public: &[u8]) -> Ua {
        Ua::start_animated(global, section, public, &[], SimConfig::default().cycle).await
    }

    /// [`Ua::start_pub`] with the variables matching `animate` counting
    /// the PLC's cycles of `cycle`.
    async fn start_animated(
        global: &str,
        section: &str,
        public: &[u8],
        animate: &[&str],
        cycle: Duration,
    ) -> Ua {
        let files = tempfile::tempdir().unwrap();
        std::fs::write(files.path().join("demo.pub"), public).unwrap();
        let users = users_file(files.path());
        let sim = plcsim::spawn(SimConfig {
            bind: "127.0.0.1:0".parse().unwrap(),
            files: Some(files.path().to_path_buf()),
            program: "idle".parse().unwrap(),
            // Its memory and what it animates are laid out by the same
            // project it serves.
            pubfile: plcsim::PubSource::Bytes(public.to_vec()),
            animate: animate.iter().map(|m| m.to_string()).collect(),
            cycle,
            ..SimConfig::default()
        })
        .await
        .unwrap();
        let epsport = sim.local_addr().port();
        let (server, port, conf) = common::start_on_free_port(|port| {
            let opc = common::process::free_port();
            format!(
                "[*]\nCOMM_LOOP_DELAY = 20\nOPCUA_PORT = {opc}\nOPCUA_USERS = {}\n{global}\n\
                 [PLC]\nIPADDR = 127.0.0.1\nEPSPORT = {epsport}\nEPSTOUT = 100\nEPSTOUT_STEP = 0\n\
                 IPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {port}\nPUBFILE_CRC = No\nPUBFILE = //demo.pub\n\
                 OPCUA_WRITE = SETPOINT, COUNTER, NOTE, V_*, DAT, TIM\n{section}\n",
                users.display()
            )
        })
        .await;
        let opcua = server.opcua.as_ref().expect("OPC UA running");
        let url = format!("opc.tcp://127.0.0.1:{}/", opcua.local_addr.port());
        Ua {
            server,
            sim,
            port,
            url,
            conf,
            _files: files,
        }
    }

    async fn telnet(&self) -> Client {
        Client::connect(([127, 0, 0, 1], self.port).into()).await
    }

    /// Until the demo table (from the PLC) is in the address space.
    async fn wait_table(&self, options: &[&str]) {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let names = browse(&self.url, options).await;
            if names.iter().any(|v| v["name"] == "SETPOINT") {
                return;
            }
            assert!(Instant::now() < deadline, "no demo table: {names:?}");
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    fn pki(&self) -> PathBuf {
        self.conf.path().join("opcua-pki")
    }

    /// A client certificate (made in a new folder) that the server first
    /// refuses, storing it in rejected/, then trusts once it is moved to
    /// trusted/ as an administrator does; the client options that use it
    /// with Basic256Sha256 SignAndEncrypt, and the folder.
    async fn trusted_client(&self, options: &[&str]) -> (Vec<String>, tempfile::TempDir) {
        let certs = tempfile::tempdir().unwrap();
        let mut secure: Vec<String> = [
            "--security",
            "Basic256Sha256,SignAndEncrypt",
            "--cert",
            certs.path().to_str().unwrap(),
        ]
        .iter()
        .chain(options)
        .map(|s| s.to_string())
        .collect();
        let refused = run(args_of(&secure, "browse", &self.url, &[])).await;
        assert_eq!(
            refused[0]["error"], "BadCertificateUntrusted",
            "{refused:?}"
        );
        self.trust_rejected();
        secure.truncate(4);
        (secure, certs)
    }

    /// Trusts the one client certificate in rejected/.
    fn trust_rejected(&self) {
        let rejected: Vec<_> = std::fs::read_dir(self.pki().join("rejected"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert_eq!(rejected.len(), 1, "{rejected:?}");
        let name = rejected[0].file_name().unwrap();
        std::fs::rename(&rejected[0], self.pki().join("trusted").join(name)).unwrap();
    }
}

/// Runs the client to its end: its JSON lines.
async fn run(args: Vec<String>) -> Vec<Value> {
    let output = tokio::task::spawn_blocking(move || {
        Command::new("python3")
            .arg(SCRIPT)
            .args(&args)
            .stdin(Stdio::null())
            .output()
            .expect("python3")
    })
    .await
    .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let lines: Vec<Value> = stdout
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    assert!(
        output.status.success() || lines.iter().any(|l| l.get("error").is_some()),
        "client.py failed ({}): {}\n{}",
        output.status,
        stdout,
        String::from_utf8_lossy(&output.stderr)
    );
    lines
}

fn args_of(options: &[String], command: &str, url: &str, rest: &[&str]) -> Vec<String> {
    let options: Vec<&str> = options.iter().map(String::as_str).collect();
    args(&options, command, url, rest)
}

fn args(options: &[&str], command: &str, url: &str, rest: &[&str]) -> Vec<String> {
    options
        .iter()
        .chain([command, url].iter())
        .chain(rest.iter())
        .map(|s| s.to_string())
        .collect()
}

async fn browse(url: &str, options: &[&str]) -> Vec<Value> {
    run(args(options, "browse", url, &[])).await
}

async fn write(url: &str, options: &[&str], node: &str, ty: &str, value: &str) -> String {
    let lines = run(args(options, "write", url, &[node, ty, value])).await;
    lines[0]["status"]
        .as_str()
        .or(lines[0]["error"].as_str())
        .unwrap()
        .to_string()
}

const HMI: &[&str] = &["--user", "hmi", "--password", "hmi-pass"];
const SCADA: &[&str] = &["--user", "scada", "--password", "scada-pass"];

/// SET through the telnet port; SET answers with the value read back.
async fn set(c: &mut Client, name: &str, value: &str) {
    // The line protocol speaks cp1250.
    let request = format!("SET:{name},{value}\n");
    c.send(&plccoms_protocol::cp1250::encode(&request)).await;
    let line = String::from_utf8_lossy(&c.line().await).into_owned();
    assert!(line.starts_with(&format!("DIFF:{name},")), "{line}");
}

/// GET through the telnet port: the value's text.
async fn get(c: &mut Client, name: &str) -> String {
    c.send(format!("GET:{name}\n").as_bytes()).await;
    let line = String::from_utf8_lossy(&c.line().await).into_owned();
    line.strip_prefix(&format!("GET:{name},"))
        .unwrap_or_else(|| panic!("{line}"))
        .trim_end()
        .to_string()
}

async fn get_f64(c: &mut Client, name: &str) -> f64 {
    get(c, name).await.parse().unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn browse_and_read_every_type() {
    let ua = Ua::start("", "").await;
    let mut c = ua.telnet().await;
    set(&mut c, "SETPOINT", "21.5").await;
    set(&mut c, "COUNTER", "-7").await;
    set(&mut c, "V_ULINT", "18446744073709551615").await;
    set(&mut c, "V_SINT", "-128").await;
    set(&mut c, "NOTE", "\"Žluťoučký kůň\"").await;
    let tree = browse(&ua.url, &[]).await;
    let var = |name: &str| {
        tree.iter()
            .find(|v| v["name"] == name)
            .unwrap_or_else(|| panic!("{name} not browsed: {tree:?}"))
            .clone()
    };
    // The table of types.
    for (name, ty) in [
        ("POSITIVE", "Boolean"),
        ("V_SINT", "SByte"),
        ("V_USINT", "Byte"),
        ("V_BYTE", "Byte"),
        ("COUNTER", "Int16"),
        ("V_UINT", "UInt16"),
        ("V_WORD", "UInt16"),
        ("V_DINT", "Int32"),
        ("V_UDINT", "UInt32"),
        ("V_DWORD", "UInt32"),
        ("V_LINT", "Int64"),
        ("V_ULINT", "UInt64"),
        ("V_LWORD", "UInt64"),
        ("SETPOINT", "Float"),
        ("SINUS", "Double"),
        ("TEXT", "String"),
        ("NOTE", "String"),
        ("DAT", "DateTime"),
        ("V_DT", "DateTime"),
        ("TIM", "Duration"),
    ] {
        let v = var(name);
        assert_eq!(v["type"], ty, "{name}: {v}");
        assert_eq!(v["status"], "Good", "{name}: {v}");
        assert_eq!(v["id"], format!("PLC.{name}"), "{name}: {v}");
        assert!(v["source_ts"].is_string(), "{name}: {v}");
    }
    assert_eq!(var("SETPOINT")["value"], 21.5);
    assert_eq!(var("COUNTER")["value"], -7);
    assert_eq!(var("V_ULINT")["value"], u64::MAX);
    assert_eq!(var("V_SINT")["value"], -128);
    assert_eq!(var("NOTE")["value"], "Žluťoučký kůň");
    assert_eq!(var("TIM")["variant"], "Double");
    // AccessLevel: CurrentRead (1), CurrentWrite (2) where OPCUA_WRITE
    // allows it.
    assert_eq!(var("SETPOINT")["access"], 3);
    assert_eq!(var("SINUS")["access"], 1);
    // The section object's properties.
    assert_eq!(var("LinkState")["value"], "online");
    assert_eq!(var("Backend")["value"], "EPSNET");
    // TranslateBrowsePaths, and Browse 5 references a call with BrowseNext.
    let paths = run(args(&[], "paths", &ua.url, &["PLC", "SETPOINT", "5"])).await;
    assert_eq!(paths[0]["translated"], "PLC.SETPOINT");
    let names: Vec<&str> = paths[1]["names"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|n| n.as_str())
        .collect();
    let browsed: Vec<&str> = tree.iter().filter_map(|v| v["name"].as_str()).collect();
    assert_eq!(names.len(), browsed.len(), "{names:?}");
    assert!(browsed.iter().all(|b| names.contains(b)), "{names:?}");
    assert!(paths[1]["calls"].as_u64().unwrap() >= 6, "{}", paths[1]);
    ua.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn writes_go_through_the_core_and_refusals_say_why() {
    let ua = Ua::start("", "").await;
    let mut c = ua.telnet().await;
    assert_eq!(
        write(&ua.url, HMI, "PLC.SETPOINT", "Float", "21.5").await,
        "Good"
    );
    assert_eq!(get_f64(&mut c, "SETPOINT").await, 21.5);
    assert_eq!(
        write(&ua.url, HMI, "PLC.COUNTER", "Int16", "-300").await,
        "Good"
    );
    assert_eq!(get(&mut c, "COUNTER").await, "-300");
    assert_eq!(
        write(
            &ua.url,
            HMI,
            "PLC.DAT",
            "DateTime",
            "2026-11-25T00:00:00+00:00"
        )
        .await,
        "Good"
    );
    // Not in OPCUA_WRITE.
    assert_eq!(
        write(&ua.url, HMI, "PLC.SINUS", "Double", "1.0").await,
        "BadNotWritable"
    );
    // An Int32 to a REAL.
    assert_eq!(
        write(&ua.url, HMI, "PLC.SETPOINT", "Int32", "5").await,
        "BadTypeMismatch"
    );
    // 60 characters into a STRING[40].
    let long = "x".repeat(60);
    assert_eq!(
        write(&ua.url, HMI, "PLC.NOTE", "String", &long).await,
        "BadOutOfRange"
    );
    // A reader, and an anonymous session, may not write.
    assert_eq!(
        write(&ua.url, SCADA, "PLC.SETPOINT", "Float", "1").await,
        "BadUserAccessDenied"
    );
    assert_eq!(
        write(&ua.url, &[], "PLC.SETPOINT", "Float", "1").await,
        "BadUserAccessDenied"
    );
    assert_eq!(get_f64(&mut c, "SETPOINT").await, 21.5);

    // The link lost: refused at once, and never applied later.
    ua.sim.set_loss(1.0);
    let lost = Instant::now();
    loop {
        let tree = browse(&ua.url, &[]).await;
        let setpoint = tree.iter().find(|v| v["name"] == "SETPOINT").unwrap();
        if setpoint["status"] == "BadNoCommunication" {
            // The last value stays, with its bad quality.
            assert_eq!(setpoint["value"], 21.5);
            break;
        }
        assert!(lost.elapsed() < Duration::from_secs(10), "{setpoint}");
    }
    assert_eq!(
        write(&ua.url, HMI, "PLC.SETPOINT", "Float", "99").await,
        "BadCommunicationError"
    );
    ua.sim.set_loss(0.0);
    let back = Instant::now();
    loop {
        let (line, _) = common::health::answer(&mut c, "GET:SETPOINT\n").await;
        if line.starts_with("GET:") {
            assert!(line.starts_with("GET:SETPOINT,21.5"), "{line}");
            break;
        }
        assert!(back.elapsed() < Duration::from_secs(10), "{line}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(get_f64(&mut c, "SETPOINT").await, 21.5);
    ua.server.shutdown().await;
}

/// A running subscription: its JSON lines as they come.
struct Subscription {
    child: tokio::process::Child,
    lines: tokio::io::Lines<BufReader<tokio::process::ChildStdout>>,
}

impl Subscription {
    async fn start(
        url: &str,
        options: &[&str],
        command: &str,
        rest: &[&str],
    ) -> (Subscription, Value) {
        let mut child = tokio::process::Command::new("python3")
            .arg(SCRIPT)
            .args(args(options, command, url, rest))
            .stdout(Stdio::piped())
            .stdin(Stdio::null())
            .kill_on_drop(true)
            .spawn()
            .expect("python3");
        let lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let mut sub = Subscription { child, lines };
        let ready = sub.next().await.expect("ready line");
        assert!(ready.get("ready").is_some(), "{ready}");
        (sub, ready)
    }

    async fn next(&mut self) -> Option<Value> {
        let line = tokio::time::timeout(Duration::from_secs(20), self.lines.next_line())
            .await
            .expect("a line within 20 s")
            .ok()??;
        Some(serde_json::from_str(&line).unwrap())
    }

    /// Values until `done`.
    async fn values(&mut self) -> Vec<Value> {
        let mut values = Vec::new();
        while let Some(line) = self.next().await {
            if line.get("done").is_some() {
                break;
            }
            values.push(line);
        }
        values
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn subscriptions_get_every_change_once_and_deadbands() {
    let ua = Ua::start("", "").await;
    let mut c = ua.telnet().await;
    set(&mut c, "COUNTER", "0").await;
    set(&mut c, "V_DINT", "0").await;
    // A DataChangeFilter of deadband 0 (trigger StatusValue): every change
    // of value or quality. (async-opcua 0.19 compares only the value for
    // an item without a filter.)
    let (mut every, ready) = Subscription::start(
        &ua.url,
        &[],
        "subscribe",
        &["PLC.COUNTER", "absolute", "0", "6", "10"],
    )
    .await;
    // Sampling interval 0 (the fastest practical): every poll's change,
    // revised to 0 (the stack's own sampling would drop a value of a poll
    // that came a hair early).
    assert_eq!(ready["status"], "Good");
    assert_eq!(ready["revised_sampling"], 0.0, "{ready}");
    assert_eq!(ready["revised_queue"], 1000);
    // Publishing as asked (10 ms), below COMM_LOOP_DELAY (20): a change
    // need not wait a whole poll interval after its poll.
    assert_eq!(ready["revised_publishing"], 10.0, "{ready}");
    let (mut absolute, _) = Subscription::start(
        &ua.url,
        &[],
        "subscribe",
        &["PLC.V_DINT", "absolute", "2", "6"],
    )
    .await;
    // One change per poll or slower: every one must arrive, once.
    for n in 1..=20 {
        set(&mut c, "COUNTER", &n.to_string()).await;
        tokio::time::sleep(Duration::from_millis(60)).await;
    }
    for n in [1, 2, 4, 5, 8] {
        set(&mut c, "V_DINT", &n.to_string()).await;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let all = every.values().await;
    // The value SET left (not polled yet: stale), then polled (good).
    assert_eq!(all[0]["status"], "UncertainLastUsableValue", "{all:?}");
    let got: Vec<i64> = all
        .iter()
        .filter(|v| v["status"] == "Good")
        .map(|v| v["value"].as_i64().unwrap())
        .collect();
    assert_eq!(got, (0..=20).collect::<Vec<_>>());
    let got: Vec<i64> = absolute
        .values()
        .await
        .iter()
        .filter(|v| v["status"] == "Good")
        .map(|v| v["value"].as_i64().unwrap())
        .collect();
    // |change| > 2 from the last value reported.
    assert_eq!(got, [0, 4, 8]);
    ua.server.shutdown().await;
}

/// The server gives a section's changes to the stack a slice of variables
/// at a time (a Read or Write waits for one slice, not for 100,000): with
/// 5,000 monitored variables, several slices, each still gets every change
/// once and in order.
#[tokio::test(flavor = "multi_thread")]
async fn every_change_of_5000_monitored_variables_arrives_once_in_order() {
    const N: usize = 5_000;
    let public = plcsim::genpub::generate(&plcsim::genpub::Layout {
        vars: N,
        animated: N,
        setvars: 0,
    });
    let ua = Ua::start_animated("", "", &public, &["ANIM_*"], Duration::from_millis(400)).await;
    let nodes: Vec<String> = (0..N).map(|i| format!("PLC.ANIM_{i:05}")).collect();
    let deadline = Instant::now() + Duration::from_secs(30);
    let (mut watch, ready) = loop {
        let (watch, ready) = Subscription::start(&ua.url, &[], "watch", &[&nodes.join(",")]).await;
        // Created once the PLC's table is served.
        if ready["created"]
            .as_array()
            .unwrap()
            .iter()
            .all(|c| c == true)
        {
            break (watch, ready);
        }
        assert!(Instant::now() < deadline, "items not created: {ready}");
        tokio::time::sleep(Duration::from_millis(300)).await;
    };
    assert_eq!(ready["created"].as_array().unwrap().len(), N);
    // Each variable holds the PLC's cycle counter: six cycles of it.
    let mut values: std::collections::HashMap<String, Vec<u64>> = Default::default();
    let mut complete = 0;
    let mut lines = 0;
    let deadline = Instant::now() + Duration::from_secs(60);
    while complete < N {
        assert!(
            Instant::now() < deadline,
            "{complete} of {N} variables with 6 values after {lines} lines ({} seen at all); one: {:?}",
            values.len(),
            values.iter().find(|(_, got)| got.len() < 6)
        );
        let v = watch.next().await.expect("the client ended");
        lines += 1;
        if v["status"] == "Good" {
            let got = values
                .entry(v["node"].as_str().unwrap().to_string())
                .or_default();
            got.push(v["value"].as_u64().unwrap());
            if got.len() == 6 {
                complete += 1;
            }
        }
    }
    assert_eq!(values.len(), N);
    for (node, got) in &values {
        let expected: Vec<u64> = (got[0]..got[0] + got.len() as u64).collect();
        assert_eq!(got, &expected, "{node}: every cycle's value once, in order");
    }
    ua.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_client_killed_mid_subscription_leaves_the_server_serving() {
    let ua = Ua::start("", "").await;
    let mut c = ua.telnet().await;
    let (mut held, _) = Subscription::start(&ua.url, &[], "hold", &["PLC.COUNTER"]).await;
    set(&mut c, "COUNTER", "5").await;
    loop {
        let v = held.next().await.expect("a value");
        if v["value"] == 5 {
            break;
        }
    }
    held.child.kill().await.unwrap();
    let (mut other, _) = Subscription::start(
        &ua.url,
        &[],
        "subscribe",
        &["PLC.COUNTER", "none", "0", "2"],
    )
    .await;
    set(&mut c, "COUNTER", "6").await;
    let got: Vec<Value> = other.values().await;
    assert!(got.iter().any(|v| v["value"] == 6), "{got:?}");
    assert_eq!(
        write(&ua.url, HMI, "PLC.COUNTER", "Int16", "7").await,
        "Good"
    );
    assert_eq!(get(&mut c, "COUNTER").await, "7");
    ua.server.shutdown().await;
}

/// A change that comes sooner after the last one reported than its item's
/// sampling interval is held back by the stack to that interval's end; it
/// must still arrive when no change follows it (async-opcua 0.19 looked at
/// the item again only on its next change: the last value never came).
#[tokio::test(flavor = "multi_thread")]
async fn a_change_held_back_by_the_sampling_interval_still_arrives() {
    let ua = Ua::start("", "").await;
    let mut c = ua.telnet().await;
    // Publishing every 20 ms (the poll's rate), sampling every 1000 ms: as
    // made, and as modified from 0 (on V_DINT, so that the first item's
    // interval does not stand in for the second's).
    for (node, name, sampling) in [
        ("PLC.COUNTER", "COUNTER", ["1000", "-"]),
        ("PLC.V_DINT", "V_DINT", ["0", "1000"]),
    ] {
        set(&mut c, name, "1").await;
        let mut rest = vec![node, "none", "0", "5", "20", "10", sampling[0]];
        if sampling[1] != "-" {
            rest.push(sampling[1]);
        }
        let (mut sub, ready) = Subscription::start(&ua.url, &[], "subscribe", &rest).await;
        assert_eq!(ready["revised_sampling"], 1000.0, "{ready}");
        // The first change soon after the first value (its time): held back,
        // and the next after it too.
        set(&mut c, name, "2").await;
        set(&mut c, name, "3").await;
        let got: Vec<Value> = sub.values().await;
        let values: Vec<&Value> = got.iter().map(|v| &v["value"]).collect();
        assert_eq!(values.last(), Some(&&Value::from(3)), "{name}: {got:?}");
    }
    ua.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn an_untrusted_certificate_is_rejected_then_signandencrypt_with_a_user() {
    let ua = Ua::start("", "").await;
    let (secure, _certs) = ua.trusted_client(HMI).await;
    let secure: Vec<&str> = secure.iter().map(String::as_str).collect();
    let with_user: Vec<&str> = secure.iter().chain(HMI).copied().collect();
    assert_eq!(
        write(&ua.url, &with_user, "PLC.SETPOINT", "Float", "3.5").await,
        "Good"
    );
    let mut c = ua.telnet().await;
    assert_eq!(get_f64(&mut c, "SETPOINT").await, 3.5);
    // A wrong password is refused.
    let wrong: Vec<&str> = secure
        .iter()
        .chain(&["--user", "hmi", "--password", "nope"])
        .copied()
        .collect();
    let lines = run(args(&wrong, "browse", &ua.url, &[])).await;
    assert!(lines[0].get("error").is_some(), "{lines:?}");
    ua.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn anonymous_is_refused_off_loopback() {
    // Bound to every address: not loopback, although the test connects
    // through 127.0.0.1.
    let ua = Ua::start_with("OPCUA_HOST = 0.0.0.0", "").await;
    let (secure, _certs) = ua.trusted_client(HMI).await;
    let secure: Vec<&str> = secure.iter().map(String::as_str).collect();
    let with_user: Vec<&str> = secure.iter().chain(HMI).copied().collect();
    ua.wait_table(&with_user).await;
    // Anonymous: refused on the secure endpoint, and there is no None
    // endpoint.
    let lines = run(args(&secure, "browse", &ua.url, &[])).await;
    assert!(lines[0].get("error").is_some(), "{lines:?}");
    let lines = run(args(&[], "browse", &ua.url, &[])).await;
    assert!(lines[0].get("error").is_some(), "{lines:?}");
    assert_eq!(
        write(&ua.url, &with_user, "PLC.COUNTER", "Int16", "9").await,
        "Good"
    );
    ua.server.shutdown().await;
}

/// Until the link state shown on the section object is `state`.
async fn until_link(ua: &Ua, state: &str) {
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        let tree = browse(&ua.url, &[]).await;
        if tree
            .iter()
            .any(|v| v["name"] == "LinkState" && v["value"] == state)
        {
            return;
        }
        assert!(Instant::now() < deadline, "link never {state}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Every value of a HistoryRead of `node` over the last hour, read in
/// pages of `per_page`: (pages, values).
async fn history(ua: &Ua, node: &str, per_page: usize) -> (usize, Vec<Value>) {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as i64;
    let pages = run(args(
        &[],
        "history",
        &ua.url,
        &[
            node,
            &(now - 3_600_000).to_string(),
            &(now + 60_000).to_string(),
            &per_page.to_string(),
        ],
    ))
    .await;
    let values = pages
        .iter()
        .flat_map(|p| p["values"].as_array().unwrap().clone())
        .collect();
    for page in &pages[..pages.len() - 1] {
        assert_eq!(page["values"].as_array().unwrap().len(), per_page, "{page}");
        assert_eq!(page["more"], true, "{page}");
    }
    (pages.len(), values)
}

#[tokio::test(flavor = "multi_thread")]
async fn history_read_pages_with_continuation_points_and_shows_outages() {
    let ua = Ua::start("HISTORY_SYNC = 1", "HISTORY = COUNTER").await;
    let tree = browse(&ua.url, &[]).await;
    let counter = tree.iter().find(|v| v["name"] == "COUNTER").unwrap();
    assert_eq!(counter["historizing"], true, "{counter}");
    // AccessLevel: read, write and HistoryRead (4).
    assert_eq!(counter["access"], 7, "{counter}");
    let mut c = ua.telnet().await;
    for n in 1..=25 {
        set(&mut c, "COUNTER", &n.to_string()).await;
        tokio::time::sleep(Duration::from_millis(40)).await;
    }
    // Recorded within HISTORY_SYNC.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let (pages, values) = history(&ua, "PLC.COUNTER", 7).await;
    let good: Vec<i64> = values
        .iter()
        .filter(|v| v["status"] == "Good")
        .map(|v| v["value"].as_i64().unwrap())
        .collect();
    assert!(pages >= 4, "{pages} pages: {values:?}");
    let from = good.iter().position(|&v| v == 1).expect("1 recorded");
    assert_eq!(good[from..], (1..=25).collect::<Vec<_>>()[..], "{values:?}");

    // Bounds: the values just outside the range, at its ends.
    let ms = |v: &Value| {
        chrono::DateTime::parse_from_rfc3339(v["ts"].as_str().unwrap())
            .unwrap()
            .timestamp_millis()
    };
    let at = |n: i64| values.iter().find(|v| v["value"] == n).unwrap();
    let (after_5, before_7) = (ms(at(5)) + 1, ms(at(7)) - 1);
    let bounded = run(args(
        &["--bounds"],
        "history",
        &ua.url,
        &[
            "PLC.COUNTER",
            &after_5.to_string(),
            &before_7.to_string(),
            "0",
        ],
    ))
    .await;
    let got: Vec<(Value, Value)> = bounded[0]["values"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| (v["value"].clone(), v["status"].clone()))
        .collect();
    assert_eq!(
        got,
        [
            (Value::from(5), Value::from("Good")),
            (Value::from(6), Value::from("Good")),
            (Value::from(7), Value::from("Good")),
        ]
    );

    // An outage comes back as Bad samples, not as silence.
    ua.sim.set_loss(1.0);
    until_link(&ua, "lost").await;
    ua.sim.set_loss(0.0);
    until_link(&ua, "online").await;
    set(&mut c, "COUNTER", "26").await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let (_, values) = history(&ua, "PLC.COUNTER", 5).await;
    let at_25 = values.iter().position(|v| v["value"] == 25).unwrap();
    let at_26 = values.iter().position(|v| v["value"] == 26).unwrap();
    assert!(
        values[at_25..at_26]
            .iter()
            .any(|v| v["status"] == "BadNoCommunication"),
        "{:?}",
        &values[at_25..=at_26]
    );
    ua.server.shutdown().await;
}

const TAGS: &str =
    "name,type,table,address,bit,order,scale,offset,access,unit,description,min,max\n\
                    level,REAL,holding,0,,,,,,%,tank level,0,200\n\
                    count,INT,holding,2,,,,,,,a counter,,\n";

/// A Modbus section on the embedded simulated device, its tag file in
/// `dir` (edited by the test).
async fn modbus(dir: &Path) -> (plccoms::startup::Server, String, u16, tempfile::TempDir) {
    let tags = dir.join("tags.csv");
    std::fs::write(&tags, TAGS).unwrap();
    let users = users_file(dir);
    let (server, port, conf) = common::start_on_free_port(|port| {
        let opc = common::process::free_port();
        format!(
            "[*]\nCOMM_LOOP_DELAY = 20\nOPCUA_PORT = {opc}\nOPCUA_USERS = {}\n[M]\nPROTOCOL = MODBUS_TCP\n\
             SIMULATOR = Yes\nMODBUS_TAGS = {}\nSERVER_PORT = {port}\nIPADDR_LOCAL = 127.0.0.1\n\
             OPCUA_WRITE = LEVEL\n",
            users.display(),
            tags.display()
        )
    })
    .await;
    let url = format!(
        "opc.tcp://127.0.0.1:{}/",
        server.opcua.as_ref().unwrap().local_addr.port()
    );
    (server, url, port, conf)
}

/// Browses until `check` holds for the variables of the tree.
async fn until_tree(url: &str, what: &str, check: impl Fn(&[Value]) -> bool) -> Vec<Value> {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let tree = browse(url, &[]).await;
        if check(&tree) {
            return tree;
        }
        assert!(Instant::now() < deadline, "never {what}: {tree:?}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

fn names(tree: &[Value]) -> Vec<&str> {
    tree.iter().filter_map(|v| v["name"].as_str()).collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn tag_file_units_ranges_percent_deadband_and_a_live_edit() {
    let files = tempfile::tempdir().unwrap();
    let (server, url, port, _conf) = modbus(files.path()).await;
    let tree = until_tree(&url, "LEVEL shown", |t| names(t).contains(&"LEVEL")).await;
    let level = tree.iter().find(|v| v["name"] == "LEVEL").unwrap();
    assert_eq!(level["type"], "Float", "{level}");
    assert_eq!(level["description"], "tank level", "{level}");
    assert_eq!(level["EngineeringUnits"]["unit"], "%", "{level}");
    assert_eq!(level["EURange"]["low"], 0.0, "{level}");
    assert_eq!(level["EURange"]["high"], 200.0, "{level}");
    let count = tree.iter().find(|v| v["name"] == "COUNT").unwrap();
    assert!(count.get("EURange").is_none(), "{count}");

    // 10 % of the range 0-200: a change must exceed 20 from the last value
    // reported.
    let mut c = Client::connect(([127, 0, 0, 1], port).into()).await;
    set(&mut c, "LEVEL", "0").await;
    let (mut percent, _) =
        Subscription::start(&url, &[], "subscribe", &["M.LEVEL", "percent", "10", "4"]).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    for level in ["5", "15", "25", "30", "50"] {
        set(&mut c, "LEVEL", level).await;
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    let got: Vec<f64> = percent
        .values()
        .await
        .iter()
        .filter(|v| v["status"] == "Good")
        .map(|v| v["value"].as_f64().unwrap())
        .collect();
    assert_eq!(got, [0.0, 25.0, 50.0]);
    // Writes stay within the range.
    assert_eq!(
        write(&url, HMI, "M.LEVEL", "Float", "250").await,
        "BadOutOfRange"
    );
    assert_eq!(
        write(&url, HMI, "M.LEVEL", "Float", "-1").await,
        "BadOutOfRange"
    );
    assert_eq!(write(&url, HMI, "M.LEVEL", "Float", "120").await, "Good");
    assert_eq!(get_f64(&mut c, "LEVEL").await, 120.0);

    // The tag file edited: COUNT goes, EXTRA comes; LEVEL keeps its id;
    // a client of model change events hears of it.
    let (mut events, _) = Subscription::start(&url, &[], "events", &["20"]).await;
    let edited = TAGS.replace(
        "count,INT,holding,2,,,,,,,a counter,,\n",
        "extra,DINT,holding,4,,,,,,,added later,,\n",
    );
    std::fs::write(files.path().join("tags.csv"), edited).unwrap();
    let tree = until_tree(&url, "the edit", |t| {
        names(t).contains(&"EXTRA") && !names(t).contains(&"COUNT")
    })
    .await;
    let level = tree.iter().find(|v| v["name"] == "LEVEL").unwrap();
    assert_eq!(level["id"], "M.LEVEL");
    let extra = tree.iter().find(|v| v["name"] == "EXTRA").unwrap();
    assert_eq!(extra["type"], "Int32", "{extra}");
    let event = events.next().await.expect("a model change event");
    assert_eq!(event["source"], "M", "{event}");
    assert!(
        event["event_type"].as_str().unwrap().contains("2133"),
        "{event}"
    );
    server.shutdown().await;
}

/// An overloaded subscription says so, and holds no other back: one that
/// publishes every 2 s with a queue of 3 sees the Overflow bit and the last
/// value; another on the same variable, publishing every 20 ms, gets every
/// value, once.
#[tokio::test(flavor = "multi_thread")]
async fn an_overflowing_queue_says_so_and_holds_no_other_subscription_back() {
    let ua = Ua::start("", "").await;
    let mut c = ua.telnet().await;
    set(&mut c, "COUNTER", "0").await;
    let (mut slow, ready) = Subscription::start(
        &ua.url,
        &[],
        "subscribe",
        &["PLC.COUNTER", "absolute", "0", "8", "2000", "3"],
    )
    .await;
    assert_eq!(ready["revised_queue"], 3, "{ready}");
    let (mut fast, _) = Subscription::start(
        &ua.url,
        &[],
        "subscribe",
        &["PLC.COUNTER", "absolute", "0", "8"],
    )
    .await;
    for n in 1..=30 {
        set(&mut c, "COUNTER", &n.to_string()).await;
        tokio::time::sleep(Duration::from_millis(60)).await;
    }
    let fast = fast.values().await;
    let slow = slow.values().await;
    let good = |values: &[Value]| -> Vec<i64> {
        values
            .iter()
            .filter(|v| v["status"] == "Good")
            .map(|v| v["value"].as_i64().unwrap())
            .collect()
    };
    assert_eq!(good(&fast), (0..=30).collect::<Vec<_>>(), "{fast:?}");
    assert!(fast.iter().all(|v| v["overflow"] == false), "{fast:?}");
    assert!(slow.iter().any(|v| v["overflow"] == true), "{slow:?}");
    assert_eq!(good(&slow).last(), Some(&30), "{slow:?}");
    assert!(slow.len() < fast.len(), "{slow:?}");
    ua.server.shutdown().await;
}

/// Part 4: an item without a DataChangeFilter reports changes of value or
/// status. A lost link (status only, the value unchanged at the PLC)
/// reaches it as BadNoCommunication (the value null, as Part 4 has a Bad
/// DataValue's), and the value comes back with the link.
#[tokio::test(flavor = "multi_thread")]
async fn a_lost_link_reaches_a_subscriber_without_a_filter() {
    let ua = Ua::start("", "").await;
    let mut c = ua.telnet().await;
    set(&mut c, "V_DINT", "7").await;
    let (mut sub, ready) = Subscription::start(
        &ua.url,
        &[],
        "subscribe",
        &["PLC.V_DINT", "none", "0", "12"],
    )
    .await;
    assert_eq!(ready["status"], "Good");
    tokio::time::sleep(Duration::from_millis(500)).await;
    ua.sim.set_loss(1.0);
    until_link(&ua, "lost").await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    ua.sim.set_loss(0.0);
    until_link(&ua, "online").await;
    let values = sub.values().await;
    // 7 (stale until a poll reads it, then Good), Bad, 7 Good again.
    let bad = values
        .iter()
        .position(|v| v["status"] == "BadNoCommunication")
        .unwrap_or_else(|| panic!("no BadNoCommunication: {values:?}"));
    assert!(bad > 0 && values[bad - 1]["value"] == 7, "{values:?}");
    assert_eq!(values[bad]["value"], Value::Null, "{values:?}");
    let good = |v: &Value| v["status"] == "Good" && v["value"] == 7;
    assert!(values[bad..].iter().any(good), "not back: {values:?}");
    ua.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_history_stamp_pair_gives_the_plcs_time_as_source_timestamp() {
    let ua = Ua::start("", "HISTORY_STAMP = V_DINT:V_LINT").await;
    let mut c = ua.telnet().await;
    // Milliseconds since 1970, as the PLC's program writes them.
    set(&mut c, "V_LINT", "1700000000123").await;
    set(&mut c, "V_DINT", "5").await;
    let (mut sub, _) = Subscription::start(
        &ua.url,
        &[],
        "subscribe",
        &["PLC.V_DINT", "absolute", "0", "2"],
    )
    .await;
    let values = sub.values().await;
    // The first value.
    assert_eq!(values[0]["value"], 5, "{values:?}");
    assert_eq!(
        values[0]["source_ts"], "2023-11-14T22:13:20.123000+00:00",
        "{values:?}"
    );
    ua.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn history_read_continues_across_a_day_file_boundary() {
    use plccoms_historian::sample::{Sample, Stored};
    use plccoms_historian::store::{day_of, DayFile, DAY_MS};
    let ua = Ua::start("HISTORY_SYNC = 1", "HISTORY = COUNTER").await;
    // Yesterday's day file: COUNTER 100..=109 in its last ten seconds.
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as i64;
    let yesterday = day_of(now) - 1;
    let table = std::sync::Arc::new(plccoms_core::vars::table_of(&[("COUNTER", "INT")]));
    let counter = table.lookup(b"COUNTER").unwrap();
    let end = (yesterday + 1) * DAY_MS;
    let samples: Vec<Sample> = (0..10)
        .map(|i| Sample {
            t: end - 10_000 + i * 1000,
            var: counter,
            value: Stored::Int(100 + i),
            quality: plccoms_core::changes::Quality::Good,
            plc_time: None,
        })
        .collect();
    let mut file = DayFile::open(&ua.conf.path().join("history"), "PLC", yesterday).unwrap();
    file.write(&[(&table, &samples)], &[]).unwrap();
    file.close();
    // Today's, recorded live.
    let mut c = ua.telnet().await;
    for n in 1..=5 {
        set(&mut c, "COUNTER", &n.to_string()).await;
        tokio::time::sleep(Duration::from_millis(40)).await;
    }
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let pages = run(args(
        &[],
        "history",
        &ua.url,
        &[
            "PLC.COUNTER",
            &(end - 60_000).to_string(),
            &(now + 60_000).to_string(),
            "3",
        ],
    ))
    .await;
    let good: Vec<i64> = pages
        .iter()
        .flat_map(|p| p["values"].as_array().unwrap().clone())
        .filter(|v| v["status"] == "Good")
        .map(|v| v["value"].as_i64().unwrap())
        .collect();
    let expected: Vec<i64> = (100..=109).chain(1..=5).collect();
    let today: Vec<i64> = good.iter().copied().filter(|&v| v != 0).collect();
    assert_eq!(today, expected, "{pages:?}");
    // Three values a page: yesterday's ten end in the middle of a page.
    assert!(pages.len() >= 5, "{pages:?}");
    ua.server.shutdown().await;
}

/// Lines of `sub` until `done` holds for one; all of them.
async fn lines_until(sub: &mut Subscription, mut done: impl FnMut(&Value) -> bool) -> Vec<Value> {
    let mut lines = Vec::new();
    while let Some(line) = sub.next().await {
        let end = done(&line);
        lines.push(line);
        if end {
            return lines;
        }
    }
    panic!("the client ended first: {lines:?}");
}

/// SIGHUP to the real binary under subscribed clients: [B] removed, [C]
/// restarted (a key changed), [D] added, [A] unchanged and changing
/// throughout.
#[tokio::test(flavor = "multi_thread")]
async fn sighup_adds_removes_and_restarts_sections_under_subscribed_clients() {
    use common::process::{free_port, ServerProcess};
    let files = tempfile::tempdir().unwrap();
    let tags = files.path().join("tags.csv");
    std::fs::write(&tags, TAGS).unwrap();
    let opc = free_port();
    let (pa, pb, pc, pd) = (free_port(), free_port(), free_port(), free_port());
    let section = |name: &str, port: u16, keys: &str| {
        format!(
            "[{name}]\nPROTOCOL = MODBUS_TCP\nSIMULATOR = Yes\nMODBUS_TAGS = {}\n\
             SERVER_PORT = {port}\nIPADDR_LOCAL = 127.0.0.1\n{keys}\n",
            tags.display()
        )
    };
    let users = users_file(files.path());
    let global = format!(
        "[*]\nCOMM_LOOP_DELAY = 20\nOPCUA_PORT = {opc}\nOPCUA_USERS = {}\n",
        users.display()
    );
    let before = global.clone() + &section("A", pa, "") + &section("B", pb, "");
    let before = before + &section("C", pc, "");
    let after = global + &section("A", pa, "") + &section("C", pc, "OPCUA_WRITE = COUNT");
    let after = after + &section("D", pd, "");
    let mut server = ServerProcess::with_config(&before, pa);
    let url = format!("opc.tcp://127.0.0.1:{opc}/");
    let has = |tree: &[Value], section: &str| {
        tree.iter()
            .any(|v| v["section"] == section && v["name"] == "COUNT")
    };
    until_tree(&url, "A, B and C", |t| {
        has(t, "A") && has(t, "B") && has(t, "C")
    })
    .await;
    let mut a = Client::connect(([127, 0, 0, 1], pa).into()).await;
    set(&mut a, "COUNT", "0").await;
    let mut b = Client::connect(([127, 0, 0, 1], pb).into()).await;
    set(&mut b, "COUNT", "5").await;
    let (mut watch_a, _) = Subscription::start(&url, &[], "watch", &["A.COUNT"]).await;
    let (mut watch_bc, _) = Subscription::start(&url, &[], "watch", &["B.COUNT,C.COUNT"]).await;
    let (mut events, _) = Subscription::start(&url, &[], "events", &["60"]).await;
    // Both items of B and C have a value before the reload.
    let mut seen = std::collections::HashSet::new();
    lines_until(&mut watch_bc, |v| {
        if v["status"] == "Good" {
            seen.insert(v["node"].as_str().unwrap_or("").to_string());
        }
        seen.len() == 2
    })
    .await;

    // A changes every 100 ms, through the reload.
    for n in 1..=40 {
        if n == 10 {
            std::fs::write(server.dir.path().join("plccoms.ini"), &after).unwrap();
            common::mqtt::signal(server.child.child().id(), libc::SIGHUP);
        }
        set(&mut a, "COUNT", &n.to_string()).await;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let deadline = Instant::now() + Duration::from_secs(20);
    while !server.log().contains("configuration reloaded") {
        assert!(Instant::now() < deadline, "no reload: {}", server.log());
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let log = server.log();
    assert!(log.contains("restarted [C]"), "{log}");

    // A: every change once, in order, never Bad.
    let a_lines = lines_until(&mut watch_a, |v| v["status"] == "Good" && v["value"] == 40).await;
    let first_good = a_lines.iter().position(|v| v["status"] == "Good").unwrap();
    let after_first = &a_lines[first_good..];
    assert!(
        after_first
            .iter()
            .all(|v| !v["status"].as_str().unwrap().starts_with("Bad")),
        "{a_lines:?}"
    );
    let good: Vec<i64> = after_first
        .iter()
        .filter(|v| v["status"] == "Good")
        .map(|v| v["value"].as_i64().unwrap())
        .collect();
    assert_eq!(good, (0..=40).collect::<Vec<_>>(), "{a_lines:?}");

    // B: its item told its node went; reads of it refused.
    let mut bc_lines = lines_until(&mut watch_bc, |v| {
        v["node"] == "B.COUNT" && v["status"] == "BadNodeIdUnknown"
    })
    .await;
    let read = run(args(&[], "read", &url, &["B.COUNT"])).await;
    assert_eq!(read[0]["status"], "BadNodeIdUnknown", "{read:?}");
    // C: the same item, Bad while the new section connects, then values
    // of the new section.
    let mut c = Client::connect(([127, 0, 0, 1], pc).into()).await;
    set(&mut c, "COUNT", "7").await;
    bc_lines.extend(
        lines_until(&mut watch_bc, |v| {
            v["node"] == "C.COUNT" && v["status"] == "Good" && v["value"] == 7
        })
        .await,
    );
    let c_lines = bc_lines;
    // (The binary publishes the sections without C, then with the new C:
    // between, C's nodes are unknown; a follower may see either list.)
    let c_lines: Vec<&Value> = c_lines.iter().filter(|v| v["node"] == "C.COUNT").collect();
    let restart = c_lines
        .iter()
        .position(|v| v["status"].as_str().unwrap().starts_with("Bad"))
        .unwrap_or_else(|| panic!("C never told of its restart: {c_lines:?}"));
    // Never a Good without a value (a variable not read yet).
    assert!(
        c_lines
            .iter()
            .all(|v| v["status"] != "Good" || !v["value"].is_null()),
        "{c_lines:?}"
    );
    assert!(c_lines[restart..].iter().any(|v| v["value"] == 7));
    // The restart took OPCUA_WRITE: C.COUNT is writable now.
    assert_eq!(write(&url, HMI, "C.COUNT", "Int16", "8").await, "Good");
    // D: browsed, subscribed, fed.
    let tree = until_tree(&url, "D added, B removed", |t| {
        has(t, "D") && !has(t, "B") && has(t, "A") && has(t, "C")
    })
    .await;
    let count = tree
        .iter()
        .find(|v| v["section"] == "D" && v["name"] == "COUNT")
        .unwrap();
    assert_eq!(count["id"], "D.COUNT");
    let (mut watch_d, _) = Subscription::start(&url, &[], "watch", &["D.COUNT"]).await;
    let mut d = Client::connect(([127, 0, 0, 1], pd).into()).await;
    set(&mut d, "COUNT", "3").await;
    lines_until(&mut watch_d, |v| v["status"] == "Good" && v["value"] == 3).await;
    // A model change event of each section that changed, none of A.
    let mut sources = std::collections::BTreeSet::new();
    let changes = lines_until(&mut events, |v| {
        assert!(v["event_type"].as_str().unwrap().contains("2133"), "{v}");
        sources.insert(v["source"].as_str().unwrap().to_string());
        sources.len() == 3
    })
    .await;
    assert_eq!(
        sources.into_iter().collect::<Vec<_>>(),
        ["B", "C", "D"],
        "{changes:?}"
    );

    // B added back: the item its client kept gets values again.
    let again = after + &section("B", pb, "");
    std::fs::write(server.dir.path().join("plccoms.ini"), &again).unwrap();
    common::mqtt::signal(server.child.child().id(), libc::SIGHUP);
    let deadline = Instant::now() + Duration::from_secs(20);
    while server.log().matches("configuration reloaded").count() < 2 {
        assert!(Instant::now() < deadline, "no reload: {}", server.log());
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut b = Client::connect(([127, 0, 0, 1], pb).into()).await;
    set(&mut b, "COUNT", "9").await;
    lines_until(&mut watch_bc, |v| {
        v["node"] == "B.COUNT" && v["status"] == "Good" && v["value"] == 9
    })
    .await;
    drop(server);
}

/// BrowseNext pages through a section of 1,500 variables, 100 references
/// a call: each variable once, in the table's order, every page Good and
/// within the client's maximum; TranslateBrowsePaths finds the last one.
#[tokio::test(flavor = "multi_thread")]
async fn browse_next_pages_through_a_section_of_1500_variables() {
    let ua = Ua::start_pub("", "", &plcsim::genpub::plain(1500)).await;
    let deadline = Instant::now() + Duration::from_secs(20);
    let paths = loop {
        let paths = run(args(&[], "paths", &ua.url, &["PLC", "VAR_01499", "100"])).await;
        if paths.len() == 2 {
            break paths;
        }
        assert!(Instant::now() < deadline, "no table: {paths:?}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(paths[0]["translated"], "PLC.VAR_01499");
    let page = &paths[1];
    assert_eq!(page["statuses"], serde_json::json!(["Good"]), "{page}");
    assert_eq!(page["most"], 100, "{page}");
    let names: Vec<&str> = page["names"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|n| n.as_str())
        .collect();
    let vars: Vec<&str> = names
        .iter()
        .copied()
        .filter(|n| n.starts_with("VAR_"))
        .collect();
    let expected: Vec<String> = (0..1500).map(|i| format!("VAR_{i:05}")).collect();
    assert_eq!(vars, expected);
    // The section object's own properties come after its variables.
    for property in ["LinkState", "LastPoll", "Backend"] {
        assert_eq!(
            names.iter().filter(|n| **n == property).count(),
            1,
            "{property}"
        );
    }
    assert!(page["calls"].as_u64().unwrap() >= 16, "{page}");
    ua.server.shutdown().await;
}

/// Every attribute of a variable node and of its property nodes, as a
/// client reads them, with their references; UserAccessLevel per user.
#[tokio::test(flavor = "multi_thread")]
async fn every_attribute_of_a_variable_and_of_its_properties() {
    let files = tempfile::tempdir().unwrap();
    let (server, url, _port, _conf) = modbus(files.path()).await;
    until_tree(&url, "LEVEL shown", |t| names(t).contains(&"LEVEL")).await;
    let lines = run(args(HMI, "attrs", &url, &["M.LEVEL"])).await;
    let (nodes, paths): (Vec<Value>, Vec<Value>) =
        lines.into_iter().partition(|l| l.get("node").is_some());
    assert_eq!(nodes.len(), 3, "{nodes:?}");
    // TranslateBrowsePaths to each property and back (inverse HasProperty).
    let mut translated: Vec<&str> = paths
        .iter()
        .filter_map(|p| p["translated"].as_str())
        .collect();
    translated.sort();
    assert_eq!(
        translated,
        ["M.LEVEL#EURange", "M.LEVEL#EngineeringUnits"],
        "{paths:?}"
    );
    assert!(
        paths
            .iter()
            .all(|p| p["back"] == serde_json::json!(["M.LEVEL"])),
        "{paths:?}"
    );
    let ns = nodes[0]["attrs"]["BrowseName"]
        .as_str()
        .unwrap()
        .split(':')
        .next()
        .unwrap()
        .to_string();
    let level = &nodes[0];
    let attrs = &level["attrs"];
    assert_eq!(level["node"], "M.LEVEL");
    assert_eq!(attrs["NodeId"], format!("ns={ns};s=M.LEVEL"));
    assert_eq!(attrs["NodeClass"], 2, "{attrs}");
    assert_eq!(attrs["BrowseName"], format!("{ns}:LEVEL"));
    assert_eq!(attrs["DisplayName"], "LEVEL");
    assert_eq!(attrs["Description"], "tank level");
    assert_eq!(attrs["DataType"], "i=10", "Float: {attrs}");
    assert_eq!(attrs["ValueRank"], -1);
    assert_eq!(attrs["ArrayDimensions"], "BadAttributeIdInvalid");
    // CurrentRead | CurrentWrite (OPCUA_WRITE = LEVEL); hmi may write.
    assert_eq!(attrs["AccessLevel"], 3);
    assert_eq!(attrs["UserAccessLevel"], 3);
    assert_eq!(attrs["MinimumSamplingInterval"], 20.0);
    assert_eq!(attrs["Historizing"], false);
    assert!(attrs["Value"].is_number(), "{attrs}");
    assert_eq!(attrs["WriteMask"], 0);
    // Object-only and type-only attributes are not a variable's.
    for attr in ["EventNotifier", "IsAbstract", "Symmetric", "Executable"] {
        assert_eq!(attrs[attr], "BadAttributeIdInvalid", "{attr}: {attrs}");
    }
    let refs = level["refs"].as_array().unwrap();
    let has = |refs: &[Value], ty: &str, forward: bool, node: &str| {
        refs.iter()
            .any(|r| r["type"] == ty && r["forward"] == forward && r["node"] == node)
    };
    // HasComponent (i=47) from the section object, HasTypeDefinition
    // (i=40) AnalogItemType (i=2368), HasProperty (i=46) to both.
    assert!(
        has(refs, "i=47", false, &format!("ns={ns};s=M")),
        "{refs:?}"
    );
    assert!(has(refs, "i=40", true, "i=2368"), "{refs:?}");
    assert!(
        has(
            refs,
            "i=46",
            true,
            &format!("ns={ns};s=M.LEVEL#EngineeringUnits")
        ),
        "{refs:?}"
    );
    assert!(
        has(refs, "i=46", true, &format!("ns={ns};s=M.LEVEL#EURange")),
        "{refs:?}"
    );
    assert_eq!(refs.len(), 4, "{refs:?}");
    for (property, ty) in [("EngineeringUnits", "i=887"), ("EURange", "i=884")] {
        let node = nodes
            .iter()
            .find(|n| n["node"] == format!("M.LEVEL#{property}"))
            .unwrap_or_else(|| panic!("{property}: {nodes:?}"));
        let attrs = &node["attrs"];
        assert_eq!(attrs["NodeClass"], 2, "{attrs}");
        assert_eq!(attrs["BrowseName"], format!("0:{property}"));
        assert_eq!(attrs["DisplayName"], property);
        assert_eq!(attrs["DataType"], ty, "{attrs}");
        assert_eq!(attrs["ValueRank"], -1);
        assert_eq!(attrs["AccessLevel"], 1);
        assert_eq!(attrs["UserAccessLevel"], 1);
        assert_eq!(attrs["Historizing"], false);
        let refs = node["refs"].as_array().unwrap();
        assert!(
            has(refs, "i=46", false, &format!("ns={ns};s=M.LEVEL")),
            "{refs:?}"
        );
        // PropertyType (i=68).
        assert!(has(refs, "i=40", true, "i=68"), "{refs:?}");
        assert_eq!(refs.len(), 2, "{refs:?}");
    }
    let units = nodes
        .iter()
        .find(|n| n["node"] == "M.LEVEL#EngineeringUnits")
        .unwrap();
    assert_eq!(units["attrs"]["Value"]["unit"], "%");
    let range = nodes
        .iter()
        .find(|n| n["node"] == "M.LEVEL#EURange")
        .unwrap();
    assert_eq!(range["attrs"]["Value"]["high"], 200.0);
    // A reader's UserAccessLevel lacks CurrentWrite.
    let nodes = run(args(SCADA, "attrs", &url, &["M.LEVEL"])).await;
    assert_eq!(nodes[0]["attrs"]["AccessLevel"], 3);
    assert_eq!(nodes[0]["attrs"]["UserAccessLevel"], 1);
    // COUNT: no range, no unit: BaseDataVariableType (i=63), no property.
    let nodes = run(args(HMI, "attrs", &url, &["M.COUNT"])).await;
    assert_eq!(nodes.len(), 1, "{nodes:?}");
    let refs = nodes[0]["refs"].as_array().unwrap();
    assert!(has(refs, "i=40", true, "i=63"), "{refs:?}");
    assert_eq!(refs.len(), 2, "{refs:?}");
    assert_eq!(nodes[0]["attrs"]["AccessLevel"], 1);
    server.shutdown().await;
}
