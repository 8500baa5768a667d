//! The OPC UA client backend (PROTOCOL = OPCUA) against a third-party
//! server: asyncua's (PyPI), started by the test with a small S7-like model
//! (tests/opcua_client/server.py). Browse naming and types, LIST, GET of
//! every scalar type, SET with the confirmed value, EN with DIFFs, the
//! server's refusals by StatusCode name, a tag file, a user, the server
//! restarted mid-subscription, nodes added while running, Uncertain values
//! shown as stale; in both modes (subscribe, read). All through the line
//! protocol of the real binary (and its web API where quality shows).

mod common;

use std::io::Write;
use std::process::{ChildStdin, Command, Stdio};
use std::time::{Duration, Instant};

use common::modbus::until;
use common::process::{free_port, which, ChildGuard, ServerProcess};
use common::Client;

const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/opcua_client/server.py");

/// asyncua's server on 127.0.0.1:`port`; killed when dropped.
struct OpcServer {
    port: u16,
    child: ChildGuard,
    stdin: ChildStdin,
    lines: std::sync::mpsc::Receiver<String>,
}

impl OpcServer {
    /// Starts it (with a user `user:password` when given); returns once it
    /// listens.
    fn start(port: u16, user: Option<&str>) -> OpcServer {
        OpcServer::start_with(port, user, None)
    }

    /// With `secure`: SignAndEncrypt only, certificates made in that folder
    /// (see server.py).
    fn start_with(port: u16, user: Option<&str>, secure: Option<&std::path::Path>) -> OpcServer {
        OpcServer::start_args(port, user, secure, None)
    }

    /// With `max_sessions`: more sessions than that are refused.
    fn start_args(
        port: u16,
        user: Option<&str>,
        secure: Option<&std::path::Path>,
        max_sessions: Option<usize>,
    ) -> OpcServer {
        let python = which("python3")
            .unwrap_or_else(|| panic!("python3 is not installed: this test runs asyncua's server"));
        let probe = Command::new(&python)
            .args(["-c", "import asyncua"])
            .stderr(Stdio::null())
            .status()
            .expect("run python3");
        assert!(
            probe.success(),
            "asyncua is not installed: this test runs its OPC UA server. \
             Install it with `python3 -m pip install asyncua==2.1.0` (.ci/run installs it)."
        );
        let mut command = Command::new(python);
        command.arg(SCRIPT).arg(port.to_string());
        if let Some(user) = user {
            command.args(["--user", user]);
        }
        if let Some(dir) = secure {
            command.arg("--secure").arg(dir);
        }
        if let Some(n) = max_sessions {
            command.args(["--max-sessions", &n.to_string()]);
        }
        let mut child = ChildGuard::spawn(
            "asyncua",
            command
                .stdin(Stdio::piped())
                .stdout(Stdio::piped())
                .stderr(Stdio::null()),
        );
        let (stdin, lines) = child.command_lines();
        let mut server = OpcServer {
            port,
            child,
            stdin,
            lines,
        };
        server.wait_for("ready", Duration::from_secs(60));
        server
    }

    fn wait_for(&mut self, want: &str, within: Duration) {
        let deadline = Instant::now() + within;
        loop {
            if let Ok(line) = self.lines.recv_timeout(Duration::from_millis(100)) {
                if line == want {
                    return;
                }
            }
            if let Some(status) = self.child.exited() {
                panic!(
                    "asyncua exited ({status}) before '{want}' on port {}",
                    self.port
                );
            }
            assert!(
                Instant::now() < deadline,
                "asyncua: no '{want}' within {within:?}"
            );
        }
    }

    /// A command of server.py (`add NAME`, `set NAME V`), done when it returns.
    fn command(&mut self, line: &str) {
        writeln!(self.stdin, "{line}").expect("command to asyncua");
        self.wait_for("done", Duration::from_secs(10));
    }

    /// A command's one line of answer (`wrote`).
    fn answer(&mut self, line: &str) -> String {
        writeln!(self.stdin, "{line}").expect("command to asyncua");
        let answer = self
            .lines
            .recv_timeout(Duration::from_secs(10))
            .unwrap_or_else(|_| panic!("asyncua: no answer to '{line}'"));
        self.wait_for("done", Duration::from_secs(10));
        answer
    }

    /// `line`'s answer once `done` accepts it, asked again every 200 ms
    /// for up to 10 s (the link acts at its next polls); `plc`'s log in
    /// the failure.
    async fn answer_until(
        &mut self,
        line: &str,
        plc: &ServerProcess,
        done: impl Fn(&str) -> bool,
    ) -> String {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let answer = self.answer(line);
            if done(&answer) {
                return answer;
            }
            assert!(
                Instant::now() < deadline,
                "'{line}' answered {answer}; the log:\n{}",
                plc.log()
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    fn url(&self) -> String {
        format!("opc.tcp://127.0.0.1:{}/plc", self.port)
    }
}

/// plccoms with one OPC UA section `[P]` on `url`, and `extra` keys.
fn plccoms(url: &str, extra: &str) -> ServerProcess {
    let port = free_port();
    let ini =
        format!("[*]\n[P]\nPROTOCOL = OPCUA\nOPCUA_URL = {url}\nSERVER_PORT = {port}\n{extra}\n");
    ServerProcess::with_config(&ini, port)
}

/// The variables browsed from the Objects folder, in browse order.
const LIST: &str = "\
LIST:__PLC_RUN,BOOL
LIST:__PF_CRC,DWORD
LIST:ARRAY_V[0],INT*
LIST:ARRAY_V[1],INT*
LIST:ARRAY_V[2],INT*
LIST:TYPES.BOOL_V,BOOL*
LIST:TYPES.SBYTE_V,SINT*
LIST:TYPES.BYTE_V,USINT*
LIST:TYPES.INT16_V,INT*
LIST:TYPES.UINT16_V,UINT*
LIST:TYPES.INT32_V,DINT*
LIST:TYPES.UINT32_V,UDINT*
LIST:TYPES.INT64_V,LINT*
LIST:TYPES.UINT64_V,ULINT*
LIST:TYPES.FLOAT_V,REAL*
LIST:TYPES.DOUBLE_V,LREAL*
LIST:TYPES.STRING_V,STRING[255]*
LIST:TYPES.DATETIME_V,DT*
LIST:TYPES.DURATION_V,TIME*
LIST:RECIPE.TEMP,LREAL*
LIST:RECIPE.TIME,UDINT*
LIST:DB_LINE1.MOTOR.SPEED,LREAL*
LIST:DB_LINE1.MOTOR.RUNNING,BOOL*
LIST:DB_LINE1.MOTOR.COUNT,UDINT*
LIST:
";

/// Waits until the section has its variables (the list is built once the
/// server answers).
async fn listed(c: &mut Client, name: &str) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        c.send(format!("GET:{name}\r\n").as_bytes()).await;
        let line = String::from_utf8(c.line().await).unwrap();
        if line.starts_with("GET:") {
            return;
        }
        assert!(Instant::now() < deadline, "{name} never served: {line:?}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// EN of DB_LINE1.MOTOR.SPEED, and its first DIFF.
async fn enable_speed(c: &mut Client) {
    c.ask(
        "EN:db_line1.motor.speed\r\n",
        "WARNING:252 Changed active variables in public file: '[3/24]'\r\n",
    )
    .await;
    c.expect(b"DIFF:DB_LINE1.MOTOR.SPEED,1450.5000000000\r\n")
        .await;
}

/// EN of DB_LINE1.MOTOR.RUNNING, and its first DIFF.
async fn enable_running(c: &mut Client) {
    c.ask(
        "EN:db_line1.motor.running\r\n",
        "WARNING:252 Changed active variables in public file: '[3/24]'\r\n",
    )
    .await;
    c.expect(b"DIFF:DB_LINE1.MOTOR.RUNNING,1\r\n").await;
}

/// Asks `request` until it is answered with a link error, within `secs`.
async fn until_lost(c: &mut Client, request: &str, secs: u64) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        c.send(format!("{request}\r\n").as_bytes()).await;
        let line = String::from_utf8(c.line().await).unwrap();
        if common::health::is_link_error(&line) {
            return;
        }
        assert!(Instant::now() < deadline, "still served: {line:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn browse_get_set(mode: &str) {
    let server = OpcServer::start(free_port(), None);
    let plc = plccoms(&server.url(), &format!("OPCUA_MODE = {mode}"));
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "DB_LINE1.MOTOR.SPEED").await;
    c.send(b"LIST:\r\n").await;
    let mut list = String::new();
    loop {
        let line = String::from_utf8(c.line().await).unwrap();
        list.push_str(line.trim_end());
        list.push('\n');
        if line == "LIST:\r\n" {
            break;
        }
    }
    assert_eq!(list, LIST);
    let stamp = 1_710_510_330.5f64.to_bits();
    for (request, answer) in [
        ("GET:__PLC_RUN", "GET:__PLC_RUN,1".to_string()),
        ("GET:types.bool_v", "GET:TYPES.BOOL_V,0".into()),
        ("GET:types.sbyte_v", "GET:TYPES.SBYTE_V,-5".into()),
        ("GET:types.byte_v", "GET:TYPES.BYTE_V,200".into()),
        ("GET:types.int16_v", "GET:TYPES.INT16_V,-1234".into()),
        ("GET:types.uint16_v", "GET:TYPES.UINT16_V,54321".into()),
        ("GET:types.int32_v", "GET:TYPES.INT32_V,-100000".into()),
        ("GET:types.uint32_v", "GET:TYPES.UINT32_V,4000000000".into()),
        ("GET:types.int64_v", "GET:TYPES.INT64_V,-5000000000".into()),
        (
            "GET:types.uint64_v",
            "GET:TYPES.UINT64_V,12345678901234567890".into(),
        ),
        ("GET:types.float_v", "GET:TYPES.FLOAT_V,1.500000".into()),
        (
            "GET:types.double_v",
            "GET:TYPES.DOUBLE_V,-2.2500000000".into(),
        ),
        ("GET:types.string_v", "GET:TYPES.STRING_V,\"Hello\"".into()),
        (
            "GET:types.datetime_v",
            format!("GET:TYPES.DATETIME_V,{stamp}"),
        ),
        ("GET:types.duration_v", "GET:TYPES.DURATION_V,1500".into()),
        (
            "GET:db_line1.motor.count",
            "GET:DB_LINE1.MOTOR.COUNT,7".into(),
        ),
        ("GET:array_v[1]", "GET:ARRAY_V[1],2".into()),
        // A structure's fields, shown by the server as child variables.
        ("GET:recipe.time", "GET:RECIPE.TIME,30".into()),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    // Writes: the DIFF is the server's value, read back.
    for (request, answer) in [
        ("SET:types.bool_v,1", "DIFF:TYPES.BOOL_V,1"),
        ("SET:types.sbyte_v,-100", "DIFF:TYPES.SBYTE_V,-100"),
        ("SET:types.byte_v,7", "DIFF:TYPES.BYTE_V,7"),
        ("SET:types.int16_v,-2", "DIFF:TYPES.INT16_V,-2"),
        ("SET:types.uint16_v,65535", "DIFF:TYPES.UINT16_V,65535"),
        ("SET:types.int32_v,123456", "DIFF:TYPES.INT32_V,123456"),
        ("SET:types.uint32_v,1", "DIFF:TYPES.UINT32_V,1"),
        ("SET:types.int64_v,-1", "DIFF:TYPES.INT64_V,-1"),
        ("SET:types.uint64_v,42", "DIFF:TYPES.UINT64_V,42"),
        ("SET:types.float_v,0.25", "DIFF:TYPES.FLOAT_V,0.250000"),
        (
            "SET:types.double_v,1e3",
            "DIFF:TYPES.DOUBLE_V,1000.0000000000",
        ),
        (
            "SET:types.string_v,\"Žluťoučký\"",
            "DIFF:TYPES.STRING_V,\"Žluťoučký\"",
        ),
        ("SET:types.duration_v,2500", "DIFF:TYPES.DURATION_V,2500"),
        ("SET:array_v[2],-9", "DIFF:ARRAY_V[2],-9"),
        ("GET:array_v[0]", "GET:ARRAY_V[0],1"),
        (
            "SET:db_line1.motor.count,3",
            "ERROR:30 Bad client request: 'SET:db_line1.motor.count,3'",
        ),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    c.ask(
        "GET:types.string_v\r\n",
        "GET:TYPES.STRING_V,\"Žluťoučký\"\r\n",
    )
    .await;
    let info = c.getinfo().await;
    for want in [
        "GETINFO:PROTOCOL,OPCUA".to_string(),
        format!("GETINFO:OPCUA_URL,{}", server.url()),
        "GETINFO:PUBFILE,2/24 [OPCUA_VARS.csv]".into(),
        "GETINFO:VERSION_PLC,OPC UA FreeOpcUa Python Server 1.0pre".into(),
    ] {
        assert!(info.contains(&want), "{want} not in {info:?}");
    }
    for epsnet in [
        "VERSION_EPSNET",
        "EPSADDR",
        "EPSPORT",
        "IPADDR",
        "MODBUS_TAGS",
    ] {
        let key = format!("GETINFO:{epsnet},");
        assert!(!info.iter().any(|l| l.starts_with(&key)), "{info:?}");
    }
    // EN: the server's own changes come as DIFFs.
    enable_speed(&mut c).await;
    let mut server = server;
    server.command("set SPEED 99.5");
    c.wait_for_line(
        b"DIFF:DB_LINE1.MOTOR.SPEED,99.5000000000\r\n",
        Duration::from_secs(5),
    )
    .await;
    // The structure itself is skipped, said once.
    let log = plc.log();
    assert_eq!(
        log.matches("1 structured variables skipped").count(),
        1,
        "{log}"
    );
}

#[tokio::test]
async fn browse_get_set_en_subscribed() {
    browse_get_set("subscribe").await;
}

#[tokio::test]
async fn browse_get_set_en_read() {
    browse_get_set("read").await;
}

#[tokio::test]
async fn tag_file_user_and_refusals() {
    let server = OpcServer::start(free_port(), Some("op:secret"));
    // A node that does not exist, a read-only node declared rw (the
    // server refuses the write), a type the tag file gives.
    let tags = "name,node,type,access,unit,description\n\
                speed,nsu=http://plccoms.test/s7like;s=DB_LINE1.MOTOR.SPEED,,,rpm,Main drive\n\
                count,ns=2;s=DB_LINE1.MOTOR.COUNT,,rw\n\
                ghost,ns=2;s=NOPE,INT\n\
                level,ns=2;s=TYPES.INT16_V,DINT\n";
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tags.csv");
    std::fs::write(&path, tags).unwrap();
    let plc = plccoms(
        &server.url(),
        &format!(
            "OPCUA_TAGS = {}\nOPCUA_USER = op\nOPCUA_PASSWORD = secret",
            path.display()
        ),
    );
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "speed").await;
    for (request, answer) in [
        ("GET:speed", "GET:SPEED,1450.5000000000"),
        ("GET:count", "GET:COUNT,7"),
        ("GET:level", "GET:LEVEL,-1234"),
        (
            "GET:ghost",
            "ERROR:80 Unable to get data from address: 'GHOST: OPC UA BadNodeIdUnknown (0x80340000)'",
        ),
        (
            "SET:count,3",
            "ERROR:81 Unable to set data in to address: 'COUNT: OPC UA BadUserAccessDenied (0x801F0000)'",
        ),
        ("SET:level,-7", "DIFF:LEVEL,-7"),
        ("GET:level", "GET:LEVEL,-7"),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }

    // A wrong password: the server is never reached, and the log says why.
    let wrong = plccoms(
        &server.url(),
        &format!(
            "OPCUA_TAGS = {}\nOPCUA_USER = op\nOPCUA_PASSWORD = wrong",
            path.display()
        ),
    );
    let mut c = Client::connect(wrong.addr).await;
    tokio::time::sleep(Duration::from_secs(3)).await;
    c.ask(
        "GET:__PLC_RUN\r\n",
        "ERROR:10 Unable to connect to PLC.\r\n",
    )
    .await;
    let log = wrong.log();
    assert!(
        log.contains("BadUserAccessDenied") || log.contains("BadIdentityTokenRejected"),
        "{log}"
    );
}

/// The rebrowse found the server's variables changed: the table reloaded.
async fn reloaded(c: &mut Client) {
    reloaded_within(c, Duration::from_secs(10)).await;
}

/// As [`reloaded`], waiting up to `wait`.
async fn reloaded_within(c: &mut Client, wait: Duration) {
    c.wait_for_line(
        b"WARNING:250 Changed public file: 'OPCUA_VARS.csv'\r\n",
        wait,
    )
    .await;
}

#[tokio::test]
async fn server_restart_mid_subscription_and_nodes_added() {
    let port = free_port();
    let mut server = OpcServer::start(port, None);
    let plc = plccoms(&server.url(), "OPCUA_REBROWSE = 1");
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "DB_LINE1.MOTOR.SPEED").await;
    enable_running(&mut c).await;

    // Nodes added while running: the table is reloaded.
    server.command("add TORQUE");
    reloaded(&mut c).await;
    c.ask(
        "GET:db_line1.motor.torque\r\n",
        "GET:DB_LINE1.MOTOR.TORQUE,1.5000000000\r\n",
    )
    .await;
    // And removed: the rebrowse that only compares sees it go.
    server.command("remove TORQUE");
    reloaded(&mut c).await;
    c.ask(
        "GET:db_line1.motor.torque\r\n",
        "ERROR:33 Unknown variable name in request: 'GET:db_line1.motor.torque'\r\n",
    )
    .await;

    // The server goes away: no value is served as live.
    drop(server);
    until_lost(&mut c, "GET:db_line1.motor.speed", 5).await;
    // It returns (a new process, no TORQUE): values again within 2 s of
    // its listening, the subscription made anew.
    let server = OpcServer::start(port, None);
    let back = Instant::now();
    until(
        &mut c,
        "GET:db_line1.motor.speed",
        "GET:DB_LINE1.MOTOR.SPEED,1450.5000000000",
        10,
    )
    .await;
    let took = back.elapsed();
    assert!(
        took <= Duration::from_secs(2),
        "values again after {took:?}"
    );
    let mut server = server;
    server.command("set RUNNING 0");
    c.wait_for_line(
        b"DIFF:DB_LINE1.MOTOR.RUNNING,0\r\n",
        Duration::from_secs(10),
    )
    .await;
    let log = plc.log();
    assert_eq!(log.matches("PLC lost").count(), 1, "{log}");
}

/// A look that only compares browses the folders and the variables that
/// had children (RECIPE's fields), not every variable: at 10,000 variables
/// the Browse of each every 10 s tipped node-opcua's server over. A field
/// added to a structure is found by such a look; a variable that had no
/// children and gains one, by the full look every tenth.
#[tokio::test]
async fn a_look_browses_folders_and_structures_only() {
    let port = free_port();
    let mut server = OpcServer::start(port, None);
    let plc = plccoms(&server.url(), "OPCUA_REBROWSE = 1");
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "TYPES.INT16_V").await;
    server.answer("browsed");
    // The nodes browsed by the next looks (a look every 1 s or more).
    let mut browsed = std::collections::BTreeSet::new();
    let deadline = Instant::now() + Duration::from_secs(10);
    while !(browsed.contains("DB_LINE1.MOTOR") && browsed.contains("RECIPE")) {
        assert!(Instant::now() < deadline, "no look: {browsed:?}");
        tokio::time::sleep(Duration::from_millis(300)).await;
        let answer = server.answer("browsed");
        browsed.extend(answer.split_whitespace().skip(1).map(str::to_owned));
    }
    for childless in [
        "TYPES.INT16_V",
        "DB_LINE1.MOTOR.SPEED",
        "ARRAY_V",
        "RECIPE.TEMP",
    ] {
        assert!(
            !browsed.contains(childless),
            "{childless} browsed: {browsed:?}"
        );
    }
    assert!(browsed.contains("TYPES"), "{browsed:?}");

    // A structure's new field: found by the next look.
    server.command("addto RECIPE PRESSURE");
    reloaded(&mut c).await;
    c.ask(
        "GET:recipe.pressure\r\n",
        "GET:RECIPE.PRESSURE,1.5000000000\r\n",
    )
    .await;
    // A child of a variable that had none: found by a full look, one in
    // ten (looks every 1 s or more: well within 60 s).
    server.command("addto INT16_V EXTRA");
    reloaded_within(&mut c, Duration::from_secs(60)).await;
    c.ask(
        "GET:types.int16_v.extra\r\n",
        "GET:TYPES.INT16_V.EXTRA,1.5000000000\r\n",
    )
    .await;
}

#[tokio::test]
async fn a_slow_server() {
    let mut server = OpcServer::start(free_port(), None);
    let plc = plccoms(&server.url(), "OPCUA_MODE = read\nOPCUA_TIMEOUT = 1000");
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "DB_LINE1.MOTOR.SPEED").await;
    // Slow, within the timeout: values as ever.
    server.command("slow 300");
    for _ in 0..3 {
        c.ask(
            "GET:db_line1.motor.count\r\n",
            "GET:DB_LINE1.MOTOR.COUNT,7\r\n",
        )
        .await;
    }
    // Slower than OPCUA_TIMEOUT: the link is lost, errors answer.
    server.command("slow 2500");
    until_lost(&mut c, "GET:db_line1.motor.count", 10).await;
    // Fast again: values again.
    server.command("slow 0");
    until(
        &mut c,
        "GET:db_line1.motor.count",
        "GET:DB_LINE1.MOTOR.COUNT,7",
        10,
    )
    .await;
    let log = plc.log();
    assert_eq!(log.matches("PLC lost").count(), 1, "{log}");
}

/// A server slow to browse (slower than OPCUA_TIMEOUT, as a PLC with a
/// large address space): the rebrowse runs beside the link on a session of
/// its own, so SETs are answered meanwhile (asyncua answers a session's
/// requests one after another: a Write behind a Browse on the link's
/// session would wait past the timeout), the link is never lost, and the
/// nodes added are found all the same.
#[tokio::test]
async fn a_slow_browse_holds_no_set_up() {
    let mut server = OpcServer::start(free_port(), None);
    let plc = plccoms(&server.url(), "OPCUA_REBROWSE = 1\nOPCUA_TIMEOUT = 500");
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "DB_LINE1.MOTOR.SPEED").await;
    // (A changed list is told to clients with variables enabled.)
    enable_running(&mut c).await;
    server.command("slowbrowse 800");
    server.command("add TORQUE");
    for i in 0..12 {
        c.ask(
            &format!("SET:types.int16_v,{i}\r\n"),
            &format!("DIFF:TYPES.INT16_V,{i}\r\n"),
        )
        .await;
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    c.wait_for_line(
        b"WARNING:250 Changed public file: 'OPCUA_VARS.csv'\r\n",
        Duration::from_secs(40),
    )
    .await;
    until(
        &mut c,
        "GET:db_line1.motor.torque",
        "GET:DB_LINE1.MOTOR.TORQUE,1.5000000000",
        5,
    )
    .await;
    let log = plc.log();
    assert!(!log.contains("PLC lost"), "{log}");
}

#[tokio::test]
async fn security_first_contact_and_a_user() {
    let dir = tempfile::tempdir().unwrap();
    let server = OpcServer::start_with(free_port(), Some("op:secret"), Some(dir.path()));
    let pki = dir.path().join("client-pki");
    let plc = plccoms(
        &server.url(),
        &format!(
            "OPCUA_SECURITY = SignAndEncrypt:Basic256Sha256\nOPCUA_PKI = {}\n\
             OPCUA_USER = op\nOPCUA_PASSWORD = secret",
            pki.display()
        ),
    );
    // First contact: the server's certificate is refused and stored in
    // rejected/, and the log says where to move it.
    let rejected = pki.join("rejected");
    let deadline = Instant::now() + Duration::from_secs(30);
    let stored = loop {
        let found: Vec<_> = std::fs::read_dir(&rejected)
            .map(|d| d.flatten().map(|e| e.path()).collect())
            .unwrap_or_default();
        if let Some(file) = found.into_iter().next() {
            break file;
        }
        assert!(
            Instant::now() < deadline,
            "nothing in {}: {}",
            rejected.display(),
            plc.log()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let mut c = Client::connect(plc.addr).await;
    c.ask(
        "GET:__PLC_RUN\r\n",
        "ERROR:10 Unable to connect to PLC.\r\n",
    )
    .await;
    let log = plc.log();
    // The file and its thumbprint, and where it goes.
    let said = format!("as {}, thumbprint ", stored.display());
    assert!(
        log.contains("not trusted") && log.contains(&said) && log.contains("/trusted to trust it"),
        "{log}"
    );
    // Trusted by hand: values within the next probes.
    let trusted = pki.join("trusted");
    std::fs::create_dir_all(&trusted).unwrap();
    std::fs::rename(&stored, trusted.join(stored.file_name().unwrap())).unwrap();
    until(
        &mut c,
        "GET:db_line1.motor.count",
        "GET:DB_LINE1.MOTOR.COUNT,7",
        30,
    )
    .await;
    // A new session: the one above may have answers still on the way.
    let mut c = Client::connect(plc.addr).await;
    c.ask(
        "SET:db_line1.motor.speed,3.5\r\n",
        "DIFF:DB_LINE1.MOTOR.SPEED,3.5000000000\r\n",
    )
    .await;
    drop(server);
}

/// Subscribed values reach DIFFs and the history with the server's
/// SourceTimestamp, not the time plccoms received them.
#[tokio::test]
async fn source_timestamps_are_the_historys_time() {
    // 2024-03-15T13:45:30.000Z: far from now, so no poll's time matches.
    const MS0: i64 = 1_710_510_330_000;
    let mut server = OpcServer::start(free_port(), None);
    let (port, http) = (free_port(), free_port());
    let ini = format!(
        "[*]\nHTTP_PORT = {http}\nHISTORY_SYNC = 1\nCOMM_LOOP_DELAY = 100\n\
         [P]\nPROTOCOL = OPCUA\nOPCUA_URL = {}\nSERVER_PORT = {port}\n\
         HISTORY = DB_LINE1.MOTOR.SPEED\n",
        server.url()
    );
    let plc = ServerProcess::with_config(&ini, port);
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "DB_LINE1.MOTOR.SPEED").await;
    enable_speed(&mut c).await;
    // The subscription is made once the poll's period is known.
    tokio::time::sleep(Duration::from_secs(1)).await;
    for k in 1..=5i64 {
        server.command(&format!("stamp SPEED {k} {}", MS0 + k * 1000));
        c.wait_for_line(
            format!("DIFF:DB_LINE1.MOTOR.SPEED,{k}.0000000000\r\n").as_bytes(),
            Duration::from_secs(5),
        )
        .await;
    }
    let path = format!(
        "/api/history?section=P&vars=DB_LINE1.MOTOR.SPEED&from={}&to={}&format=csv",
        MS0 - 1000,
        MS0 + 10_000
    );
    let csv = common::http::get_until(http, &path, Duration::from_secs(10), |answer| {
        answer.matches(",DB_LINE1.MOTOR.SPEED,").count() >= 5
    });
    assert_eq!(csv.matches(",DB_LINE1.MOTOR.SPEED,").count(), 5, "{csv}");
    for k in 1..=5i64 {
        let at = chrono::DateTime::from_timestamp_millis(MS0 + 1000 * k)
            .unwrap()
            .format("%Y-%m-%dT%H:%M:%S%.3fZ")
            .to_string();
        assert!(
            csv.lines()
                .any(|l| l.contains(&at) && l.contains(&format!(",{k},"))
                    || l.contains(&at) && l.contains(&format!(",{k}.0,"))),
            "no sample {k} at {at} in:\n{csv}"
        );
    }
}

/// The value of `name` in section P as the web API shows it: (quality, text).
fn web_value(http: u16, name: &str) -> (String, String) {
    let answer = common::http::get(http, &format!("/api/sections/P/values?vars={name}"));
    let body = &answer[answer.find("\r\n\r\n").expect("an HTTP answer") + 4..];
    let json: serde_json::Value =
        serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {answer}"));
    let value = &json["values"][0];
    let field = |key: &str| value[key].as_str().unwrap_or_default().to_string();
    (field("quality"), field("text"))
}

/// Waits until the web API shows `name` with `quality` and `text`.
fn web_until(http: u16, name: &str, quality: &str, text: &str) {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let shown = web_value(http, name);
        if shown == (quality.to_string(), text.to_string()) {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{name}: {shown:?}, not ({quality}, {text})"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// An Uncertain status is served as a value (GET, DIFF: the line protocol
/// has no quality) and shown as stale where quality is shown (web API,
/// history); Good again is good. A change of status alone sends no DIFF.
async fn uncertain_is_stale(mode: &str) {
    const SPEED: &str = "DB_LINE1.MOTOR.SPEED";
    let mut server = OpcServer::start(free_port(), None);
    let (port, http) = (free_port(), free_port());
    let ini = format!(
        "[*]\nHTTP_PORT = {http}\nHISTORY_SYNC = 1\nCOMM_LOOP_DELAY = 100\n\
         [P]\nPROTOCOL = OPCUA\nOPCUA_URL = {}\nOPCUA_MODE = {mode}\nSERVER_PORT = {port}\n\
         HISTORY = {SPEED}\n",
        server.url()
    );
    let from = chrono::Utc::now().timestamp_millis() - 1000;
    let plc = ServerProcess::with_config(&ini, port);
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, SPEED).await;
    enable_speed(&mut c).await;
    web_until(http, SPEED, "good", "1450.5");
    // Subscribe mode: the subscription is made once the poll's period is known.
    tokio::time::sleep(Duration::from_secs(1)).await;

    // Uncertain, the same value: stale on the web, as it was on telnet.
    server.command("status SPEED uncertain");
    web_until(http, SPEED, "stale", "1450.5");
    c.ask(
        "GET:DB_LINE1.MOTOR.SPEED\r\n",
        "GET:DB_LINE1.MOTOR.SPEED,1450.5000000000\r\n",
    )
    .await;
    c.silent(300).await;
    // Uncertain with a new value: the DIFF, still stale.
    server.command("status SPEED uncertain 12.5");
    c.wait_for_line(
        b"DIFF:DB_LINE1.MOTOR.SPEED,12.5000000000\r\n",
        Duration::from_secs(5),
    )
    .await;
    web_until(http, SPEED, "stale", "12.5");
    // Good again, the same value: good, no DIFF.
    server.command("status SPEED good");
    web_until(http, SPEED, "good", "12.5");
    c.silent(300).await;

    // The history: the stale samples, and the good one after them.
    let path = format!(
        "/api/history?section=P&vars={SPEED}&from={from}&to={}&format=csv",
        chrono::Utc::now().timestamp_millis() + 60_000
    );
    let deadline = Instant::now() + Duration::from_secs(10);
    let want = ["1450.5,good", "1450.5,stale", "12.5,stale", "12.5,good"];
    let mut rows;
    loop {
        let csv = common::http::get(http, &path);
        rows = csv
            .lines()
            .filter(|l| l.contains(&format!(",{SPEED},")))
            // time,name,value,text,quality: the value and the quality.
            .map(|l| l.rsplitn(4, ',').collect::<Vec<_>>())
            .map(|f| format!("{},{}", f[2], f[0]))
            .collect::<Vec<_>>();
        rows.dedup();
        if rows == want || Instant::now() > deadline {
            break;
        }
        std::thread::sleep(Duration::from_millis(300));
    }
    assert_eq!(rows, want);
    drop(plc);
}

#[tokio::test]
async fn uncertain_is_stale_subscribed() {
    uncertain_is_stale("subscribe").await;
}

#[tokio::test]
async fn uncertain_is_stale_read() {
    uncertain_is_stale("read").await;
}

/// SETs of the subscribed variable, their DIFFs, and which of the server's
/// sessions their Writes came on: `want`, asked again for up to 10 s (a
/// session lost and made anew under load has its subscription again at the
/// link's next poll).
async fn sets_wrote(server: &mut OpcServer, extra: &str, want: &str) -> ServerProcess {
    // Room for a loaded machine: a timeout would make the sessions anew.
    let plc = plccoms(
        &server.url(),
        &format!("OPCUA_REBROWSE = 0\nOPCUA_TIMEOUT = 5000\n{extra}"),
    );
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "db_line1.motor.speed").await;
    enable_speed(&mut c).await;
    for (set, diff) in [
        (
            "SET:db_line1.motor.speed,3.5\r\n",
            "DIFF:DB_LINE1.MOTOR.SPEED,3.5000000000\r\n",
        ),
        (
            "SET:db_line1.motor.speed,-1\r\n",
            "DIFF:DB_LINE1.MOTOR.SPEED,-1.0000000000\r\n",
        ),
    ] {
        c.send(set.as_bytes()).await;
        c.wait_for_line(diff.as_bytes(), Duration::from_secs(5))
            .await;
    }
    server
        .answer_until("wrote", &plc, |wrote| wrote == want)
        .await;
    plc
}

/// SETs go on a session of their own (OPCUA_WRITE_SESSION, default Yes),
/// not the one whose publishes carry the subscription's notifications; on
/// that one with `No`, or where the server refuses a second session (said
/// in the log), and they are confirmed all the same.
#[tokio::test]
async fn sets_on_a_session_of_their_own() {
    let mut server = OpcServer::start(free_port(), None);
    sets_wrote(&mut server, "", "wrote apart").await;

    let mut server = OpcServer::start(free_port(), None);
    sets_wrote(&mut server, "OPCUA_WRITE_SESSION = No", "wrote together").await;

    let mut server = OpcServer::start_args(free_port(), None, None, Some(1));
    let plc = sets_wrote(&mut server, "", "wrote together").await;
    let log = plc.log();
    assert!(log.contains("no session of its own for SETs"), "{log}");
    assert!(log.contains("BadMaxConnectionsReached"), "{log}");
}

/// The monitored items each session of the section made, from the server
/// (`items N1 N2 ...`), once `total` are made (asked again for up to 10 s:
/// the link subscribes at its next polls).
async fn items_by_session(server: &mut OpcServer, total: usize, plc: &ServerProcess) -> Vec<usize> {
    let counts = |answer: &str| -> Vec<usize> {
        answer
            .split_whitespace()
            .skip(1)
            .map(|n| n.parse().expect("a count"))
            .collect()
    };
    let answer = server
        .answer_until("items", plc, |a| counts(a).iter().sum::<usize>() == total)
        .await;
    counts(&answer)
}

/// EN:* and the server's own changes of variables monitored on the first
/// session and on the last, as DIFFs; a SET confirmed.
async fn every_session_notifies(server: &mut OpcServer, plc: &ServerProcess) {
    let mut c = Client::connect(plc.addr).await;
    listed(&mut c, "db_line1.motor.speed").await;
    c.send(b"EN:*\r\n").await;
    c.wait_for_line(
        b"DIFF:DB_LINE1.MOTOR.SPEED,1450.5000000000\r\n",
        Duration::from_secs(10),
    )
    .await;
    // 20 nodes (the array and the structure's fields each one) and the
    // server's state.
    let items = items_by_session(server, 21, plc).await;
    for (set, diff) in [
        ("set INT16_V 77", "DIFF:TYPES.INT16_V,77\r\n"),
        (
            "set SPEED 12.25",
            "DIFF:DB_LINE1.MOTOR.SPEED,12.2500000000\r\n",
        ),
    ] {
        server.command(set);
        c.wait_for_line(diff.as_bytes(), Duration::from_secs(5))
            .await;
    }
    c.send(b"SET:types.int32_v,-42\r\n").await;
    c.wait_for_line(b"DIFF:TYPES.INT32_V,-42\r\n", Duration::from_secs(5))
        .await;
    assert!(items.len() > 1, "{items:?}");
}

/// OPCUA_SESSION_ITEMS: the monitored items are spread over sessions of
/// at most that many (and a small rest), each notifying its own; where the
/// server grants no more sessions, the rest go on the sessions there are
/// (said in the log).
#[tokio::test]
async fn monitored_items_spread_over_sessions() {
    let keys = "OPCUA_REBROWSE = 0\nOPCUA_TIMEOUT = 5000\nOPCUA_SESSION_ITEMS = 4";
    let mut server = OpcServer::start(free_port(), None);
    let mut plc = plccoms(&server.url(), keys);
    every_session_notifies(&mut server, &plc).await;
    let items = items_by_session(&mut server, 21, &plc).await;
    assert_eq!(items, [4, 4, 4, 4, 4, 1], "{}", plc.log());
    // The sessions carrying values run on threads of their own.
    let pid = plc.child.child().id();
    let threads: Vec<String> = std::fs::read_dir(format!("/proc/{pid}/task"))
        .expect("the process's threads")
        .filter_map(|task| std::fs::read_to_string(task.ok()?.path().join("comm")).ok())
        .map(|name| name.trim().to_string())
        .collect();
    assert!(threads.iter().any(|t| t == "opcua-values"), "{threads:?}");

    // A rest of no more than a tenth of OPCUA_SESSION_ITEMS goes on the
    // last session, not on a session of its own.
    let keys_of_ten = keys.replace("SESSION_ITEMS = 4", "SESSION_ITEMS = 10");
    let mut server = OpcServer::start(free_port(), None);
    let plc = plccoms(&server.url(), &keys_of_ten);
    every_session_notifies(&mut server, &plc).await;
    let items = items_by_session(&mut server, 21, &plc).await;
    assert_eq!(items, [10, 11], "{}", plc.log());

    // The link's session, the SETs' and one more.
    let mut server = OpcServer::start_args(free_port(), None, None, Some(3));
    let plc = plccoms(&server.url(), keys);
    every_session_notifies(&mut server, &plc).await;
    let items = items_by_session(&mut server, 21, &plc).await;
    assert_eq!(items, [4, 17], "{}", plc.log());
    let log = plc.log();
    assert!(
        log.contains("no further session for monitored items"),
        "{log}"
    );
    assert!(log.contains("BadMaxConnectionsReached"), "{log}");
}
