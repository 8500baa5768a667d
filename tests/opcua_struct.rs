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
