//! The OPC UA client backend's structures and arrays against asyncua's
//! server (tests/opcua_client/structs.py): structures with no field child
//! nodes served field by field from their DataTypeDefinition (nested, with
//! array fields, an enumeration, an array of structures), a two-dimensional
//! array element by element; LIST, GET, EN with the server's changes, SET
//! of one field or element (a read-modify-write of the node, checked on the
//! server's side), and a structure whose definition cannot be served
//! skipped with one log line.

mod common;

use std::io::Write;
use std::process::{ChildStdin, Command, Stdio};
use std::time::{Duration, Instant};

use common::process::{free_port, which, ChildGuard, ServerProcess};
use common::Client;

const SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/opcua_client/structs.py");

struct Structs {
    port: u16,
    _child: ChildGuard,
    stdin: ChildStdin,
    lines: std::sync::mpsc::Receiver<String>,
}

impl Structs {
    fn start() -> Structs {
        let python = which("python3")
            .unwrap_or_else(|| panic!("python3 is not installed: this test runs asyncua's server"));
        let port = free_port();
        let mut child = ChildGuard::spawn(
            "asyncua",
            Command::new(python)
                .arg(SCRIPT)
                .arg(port.to_string())
                .stdin(Stdio::piped())
                .stdout(Stdio::piped())
                .stderr(Stdio::null()),
        );
        let (stdin, lines) = child.command_lines();
        let mut server = Structs {
            port,
            _child: child,
            stdin,
            lines,
        };
        // asyncua missing: no "ready" (.ci/run installs asyncua==2.1.0).
        server.until("ready", Duration::from_secs(60));
        server
    }

    /// Lines up to `want`, which ends them.
    fn until(&mut self, want: &str, within: Duration) -> Vec<String> {
        let deadline = Instant::now() + within;
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) if line == want => return seen,
                Ok(line) => seen.push(line),
                Err(_) => panic!(
                    "structs.py: no '{want}' within {within:?} (is asyncua 2.1.0 installed?)"
                ),
            }
        }
    }

    /// A command of structs.py; what it printed.
    fn command(&mut self, line: &str) -> String {
        writeln!(self.stdin, "{line}").expect("command to asyncua");
        self.until("done", Duration::from_secs(10)).join("\n")
    }
}

/// The variables, in browse order: BAD is skipped.
const LIST: &str = "\
LIST:__PLC_RUN,BOOL
LIST:__PF_CRC,DWORD
LIST:MOTOR.SPEED,LREAL*
LIST:MOTOR.RUNNING,BOOL*
LIST:MOTOR.NAME,STRING[255]*
LIST:MOTOR.STEPS[0],UINT*
LIST:MOTOR.STEPS[1],UINT*
LIST:MOTOR.STEPS[2],UINT*
LIST:MOTOR.POS.X,INT*
LIST:MOTOR.POS.Y,INT*
LIST:MOTOR.MODE,DINT*
LIST:POINTS[0].X,INT*
LIST:POINTS[0].Y,INT*
LIST:POINTS[1].X,INT*
LIST:POINTS[1].Y,INT*
LIST:MATRIX[0][0],DINT*
LIST:MATRIX[0][1],DINT*
LIST:MATRIX[0][2],DINT*
LIST:MATRIX[1][0],DINT*
LIST:MATRIX[1][1],DINT*
LIST:MATRIX[1][2],DINT*
LIST:
";

/// plccoms with one OPC UA section on `server` and `extra` keys, and a
/// client once `first` is served.
async fn plccoms(server: &Structs, extra: &str, first: &str) -> (ServerProcess, Client) {
    let port = free_port();
    let ini = format!(
        "[*]\n[P]\nPROTOCOL = OPCUA\nOPCUA_URL = opc.tcp://127.0.0.1:{}/plc\nSERVER_PORT = {port}\n{extra}\n",
        server.port
    );
    let plc = ServerProcess::with_config(&ini, port);
    let mut c = Client::connect(plc.addr).await;
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        c.send(format!("GET:{first}\r\n").as_bytes()).await;
        let line = String::from_utf8(c.line().await).unwrap();
        if line.starts_with("GET:") {
            return (plc, c);
        }
        assert!(Instant::now() < deadline, "{first} never served: {line:?}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

async fn structures(mode: &str) {
    let mut server = Structs::start();
    let (plc, mut c) = plccoms(&server, &format!("OPCUA_MODE = {mode}"), "MOTOR.SPEED").await;
    assert_eq!(c.list().await, LIST);
    for (request, answer) in [
        ("GET:motor.speed", "GET:MOTOR.SPEED,1450.5000000000"),
        ("GET:motor.running", "GET:MOTOR.RUNNING,1"),
        ("GET:motor.name", "GET:MOTOR.NAME,\"Pump\""),
        ("GET:motor.steps[2]", "GET:MOTOR.STEPS[2],30"),
        ("GET:motor.pos.y", "GET:MOTOR.POS.Y,-4"),
        ("GET:motor.mode", "GET:MOTOR.MODE,1"),
        ("GET:points[1].x", "GET:POINTS[1].X,5"),
        ("GET:matrix[1][2]", "GET:MATRIX[1][2],6"),
        ("GET:matrix[0][1]", "GET:MATRIX[0][1],2"),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    // One field written: the rest of the structure stays as it was.
    for (request, answer) in [
        ("SET:motor.pos.y,-7", "DIFF:MOTOR.POS.Y,-7"),
        (
            "SET:motor.name,\"Main pump\"",
            "DIFF:MOTOR.NAME,\"Main pump\"",
        ),
        ("SET:motor.steps[1],21", "DIFF:MOTOR.STEPS[1],21"),
        ("SET:points[0].y,-2", "DIFF:POINTS[0].Y,-2"),
        ("SET:matrix[1][0],40", "DIFF:MATRIX[1][0],40"),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    let motor = server.command("show MOTOR");
    assert_eq!(
        motor,
        "MotorT(SPEED=1450.5, RUNNING=True, NAME='Main pump', STEPS=[10, 21, 30], \
         POS=PointT(X=3, Y=-7), MODE=<ModeE.Auto: 1>, \
         ID=UUID('72962b91-fa75-4ae6-8d28-b404dc7daf63'))"
    );
    assert_eq!(
        server.command("show POINTS"),
        "[PointT(X=1, Y=-2), PointT(X=5, Y=6)]"
    );
    assert_eq!(server.command("show MATRIX"), "[[1, 2, 3], [40, 5, 6]]");
    c.ask("GET:motor.speed\r\n", "GET:MOTOR.SPEED,1450.5000000000\r\n")
        .await;
    // EN: the server's changes of the structure come as DIFFs of its field.
    c.send(b"EN:motor.speed\r\n").await;
    c.wait_for_line(
        b"DIFF:MOTOR.SPEED,1450.5000000000\r\n",
        Duration::from_secs(5),
    )
    .await;
    server.command("speed 99.5");
    c.wait_for_line(
        b"DIFF:MOTOR.SPEED,99.5000000000\r\n",
        Duration::from_secs(5),
    )
    .await;
    let log = plc.log();
    assert_eq!(
        log.matches("structured variables of DataType ns=2;i=")
            .count(),
        1,
        "{log}"
    );
    assert!(
        log.contains("BaseDataType") || log.contains("i=24"),
        "{log}"
    );
}

#[tokio::test]
async fn structures_and_arrays_subscribed() {
    structures("subscribe").await;
}

#[tokio::test]
async fn structures_and_arrays_read() {
    structures("read").await;
}

/// A tag file names fields of structures by their path (`field`), of an
/// array of structures with `index`; a field the definition lacks is
/// skipped with a warning.
#[tokio::test]
async fn tag_file_fields() {
    let mut server = Structs::start();
    let tags = "name,node,index,field\n\
                posx,nsu=http://plccoms.test/structs;s=MOTOR,,pos.x\n\
                p1y,nsu=http://plccoms.test/structs;s=POINTS,1,Y\n\
                nope,nsu=http://plccoms.test/structs;s=MOTOR,,NOPE\n\
                grid,nsu=http://plccoms.test/structs;s=MATRIX,4\n";
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tags.csv");
    std::fs::write(&path, tags).unwrap();
    let (plc, mut c) = plccoms(&server, &format!("OPCUA_TAGS = {}", path.display()), "posx").await;
    for (request, answer) in [
        ("GET:posx", "GET:POSX,3"),
        ("GET:p1y", "GET:P1Y,6"),
        ("GET:grid", "GET:GRID,5"),
        ("SET:p1y,9", "DIFF:P1Y,9"),
        ("SET:grid,-5", "DIFF:GRID,-5"),
        (
            "GET:nope",
            "ERROR:33 Unknown variable name in request: 'GET:nope'",
        ),
    ] {
        c.ask(&format!("{request}\r\n"), &format!("{answer}\r\n"))
            .await;
    }
    assert_eq!(
        server.command("show POINTS"),
        "[PointT(X=1, Y=2), PointT(X=5, Y=9)]"
    );
    assert_eq!(server.command("show MATRIX"), "[[1, 2, 3], [4, -5, 6]]");
    let log = plc.log();
    assert!(log.contains("no field NOPE in its DataType"), "{log}");
}

/// plccoms's own OPC UA server as the PLC (loopback, one process): it shows
/// a public file's array elements as scalar nodes (`ARR[1]`), so a SET of
/// an element through the OPC UA section is a plain write of that node,
/// the neighbours untouched; no read-modify-write is involved.
#[tokio::test]
async fn array_elements_through_our_own_server() {
    let (p_sim, p_via, p_ua) = (free_port(), free_port(), free_port());
    let dir = tempfile::tempdir().unwrap();
    let pubfile = dir.path().join("arr.pub");
    std::fs::write(
        &pubfile,
        " ARR[0] R B 0 INT PUB_INOUT\r\n ARR[1] R B 2 INT PUB_INOUT\r\n ARR[2] R B 4 INT PUB_INOUT\r\n",
    )
    .unwrap();
    // A user who may write ARR* (password "secret").
    let users = dir.path().join("users");
    std::fs::write(
        &users,
        "hmi write pbkdf2-sha256:1000:00112233445566778899aabbccddeeff:\
         588372775fb38b5711b6f36b465e293dc7b793e008550ee8a10bb26a8e7f85b8\n",
    )
    .unwrap();
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 100\nOPCUA_PORT = {p_ua}\nOPCUA_USERS = {u}\n\n\
         [Sim]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = idle\nSIMULATOR_PUB = {p}\nSERVER_PORT = {p_sim}\nPUBFILE = {p}\nOPCUA_WRITE = ARR*\n\n\
         [Via]\nPROTOCOL = OPCUA\nOPCUA_URL = opc.tcp://127.0.0.1:{p_ua}/\nOPCUA_USER = hmi\nOPCUA_PASSWORD = secret\n\
         OPCUA_BROWSE = nsu=urn:plccoms;s=Sim\nSERVER_PORT = {p_via}\n",
        p = pubfile.display(),
        u = users.display()
    );
    let server = ServerProcess::with_config(&ini, p_via);
    let mut sim = Client::connect(std::net::SocketAddr::from(([127, 0, 0, 1], p_sim))).await;
    for (i, v) in [(0, 11), (1, 12), (2, 13)] {
        sim.ask(
            &format!("SET:arr[{i}],{v}\r\n"),
            &format!("DIFF:ARR[{i}],{v}\r\n"),
        )
        .await;
    }
    let mut via = Client::connect(server.addr).await;
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        via.send(b"GET:arr[1]\r\n").await;
        let line = String::from_utf8(via.line().await).unwrap();
        if line == "GET:ARR[1],12\r\n" {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "Via has no ARR[1]: {line:?}; log:\n{}",
            server.log()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    // A new client: the table's reload may have said more than the GETs
    // above were answered with.
    let mut via = Client::connect(server.addr).await;
    via.ask("SET:arr[1],-5\r\n", "DIFF:ARR[1],-5\r\n").await;
    for (name, value) in [("ARR[0]", 11), ("ARR[1]", -5), ("ARR[2]", 13)] {
        sim.ask(
            &format!("GET:{name}\r\n"),
            &format!("GET:{name},{value}\r\n"),
        )
        .await;
    }
}
