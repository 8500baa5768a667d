//! Child processes for tests that run programs: the built `plccoms` binary
//! and real client programs. Every child is killed when its guard drops, on
//! every path, panics included.

use std::io::Read;
use std::net::{Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

/// The binary under test, as cargo built it for this test run.
pub const PLCCOMS: &str = env!("CARGO_BIN_EXE_plccoms");

/// The `plcsim` binary of this build.
pub fn plcsim_bin() -> std::path::PathBuf {
    artifact("plcsim", &["-p", "plcsim", "--bin", "plcsim"])
}

/// A backend plugin of this build: `demo` or `bad` (the workspace's
/// `plugins/*-plugin` cdylibs).
pub fn plugin_lib(name: &str) -> std::path::PathBuf {
    let package = format!("plccoms-{name}-plugin");
    artifact(&format!("libplccoms_{name}_plugin.so"), &["-p", &package])
}

/// A file another workspace crate builds: cargo does not hand its path to
/// these tests, but it sits beside `plccoms` (target/<profile>/). It is
/// brought up to date (`cargo build <args>`) once per test process: `cargo
/// test` leaves it out with `-p plccoms`, and never builds a cdylib at all,
/// so a file already there may be stale.
fn artifact(file: &str, args: &[&str]) -> std::path::PathBuf {
    static BUILT: Mutex<Vec<String>> = Mutex::new(Vec::new());
    let dir = std::path::Path::new(PLCCOMS).parent().expect("bin dir");
    let path = dir.join(file);
    let mut built = BUILT.lock().unwrap_or_else(|e| e.into_inner());
    if !built.iter().any(|f| f == file) {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let profile = if dir.ends_with("release") {
            vec!["--release"]
        } else {
            vec![]
        };
        let status = std::process::Command::new(cargo)
            .arg("build")
            .arg("--quiet")
            .args(args)
            .args(profile)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .status()
            .expect("run cargo build");
        assert!(status.success(), "cargo build {args:?} failed");
        built.push(file.to_string());
    }
    path
}

/// How long a server gets from spawn to accepting connections.
pub const START_TIMEOUT: Duration = Duration::from_secs(10);

/// A child process that is killed and reaped when dropped.
pub struct ChildGuard {
    child: Child,
    name: String,
}

impl ChildGuard {
    pub fn spawn(name: &str, command: &mut Command) -> ChildGuard {
        let child = command
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
        ChildGuard {
            child,
            name: name.to_string(),
        }
    }

    pub fn child(&mut self) -> &mut Child {
        &mut self.child
    }

    /// The child's stdin, and its stdout as lines on a channel (a thread
    /// reads them): for a helper process driven by commands (spawned with
    /// both piped).
    pub fn command_lines(
        &mut self,
    ) -> (std::process::ChildStdin, std::sync::mpsc::Receiver<String>) {
        use std::io::{BufRead, BufReader};
        let stdin = self.child.stdin.take().expect("stdin piped");
        let stdout = self.child.stdout.take().expect("stdout piped");
        let (tx, lines) = std::sync::mpsc::channel();
        thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        (stdin, lines)
    }

    /// The exit status, if it has exited.
    pub fn exited(&mut self) -> Option<ExitStatus> {
        self.child
            .try_wait()
            .unwrap_or_else(|e| panic!("waiting for {}: {e}", self.name))
    }

    /// Waits up to `timeout` for the child to exit by itself.
    pub fn wait_timeout(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.exited() {
                return Some(status);
            }
            if Instant::now() >= deadline {
                return None;
            }
            thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
        }
        let _ = self.child.wait();
    }
}

/// Collects everything a child writes on one pipe, on a thread.
pub struct Capture {
    bytes: Arc<Mutex<Vec<u8>>>,
    thread: Option<JoinHandle<()>>,
}

impl Capture {
    pub fn start(mut pipe: impl Read + Send + 'static) -> Capture {
        let bytes = Arc::new(Mutex::new(Vec::new()));
        let sink = bytes.clone();
        let thread = thread::spawn(move || {
            let mut chunk = [0u8; 8192];
            while let Ok(n) = pipe.read(&mut chunk) {
                if n == 0 {
                    break;
                }
                sink.lock().unwrap().extend_from_slice(&chunk[..n]);
            }
        });
        Capture {
            bytes,
            thread: Some(thread),
        }
    }

    /// What arrived so far.
    pub fn bytes(&self) -> Vec<u8> {
        self.bytes.lock().unwrap().clone()
    }

    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.bytes()).into_owned()
    }

    /// Waits for the pipe's end (the writer exited), then everything.
    pub fn finish(mut self) -> Vec<u8> {
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        self.bytes()
    }
}

/// A TCP port that was free a moment ago on every interface (servers
/// bind 0.0.0.0, which a listener on any one address blocks).
pub fn free_port() -> u16 {
    free_ports(1)
}

/// `n` consecutive TCP ports that were free a moment ago; the first.
pub fn free_ports(n: u16) -> u16 {
    // A listener on 127.0.0.1 (or any address) blocks a bind of 0.0.0.0
    // too: one bind tells both.
    unused_ports(n, port_is_free)
}

/// A UDP port on 127.0.0.1 that was free a moment ago.
pub fn free_udp_port() -> u16 {
    unused_ports(1, |port| {
        std::net::UdpSocket::bind((Ipv4Addr::LOCALHOST, port)).is_ok()
    })
}

/// The first of `n` random consecutive ports below Linux's ephemeral range
/// (32768-60999) that `free` accepts and that this process has not handed
/// out before. The tests' own connections and `:0` binds draw from the
/// ephemeral range, so a port found free there could be taken before the
/// server binds it. Down here only another pick can take it, and a pick is
/// never repeated: a test that restarts its server or broker on the same
/// port leaves it free for a while, and another test must not pick it then
/// (a CI failure: a Sparkplug test's server found its port taken).
fn unused_ports(n: u16, free: impl Fn(u16) -> bool) -> u16 {
    use std::hash::{BuildHasher, Hasher};
    static PICKS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    static HANDED_OUT: Mutex<std::collections::BTreeSet<u16>> =
        Mutex::new(std::collections::BTreeSet::new());
    for _ in 0..5000 {
        let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
        hasher.write_u64(PICKS.fetch_add(1, std::sync::atomic::Ordering::Relaxed));
        hasher.write_u32(std::process::id());
        // 23000..32000: clear of bench/run's and the soak's default ports.
        let first = 23_000 + (hasher.finish() % u64::from(9_000 - n)) as u16;
        let ports = first..first + n;
        let mut handed_out = HANDED_OUT.lock().unwrap_or_else(|e| e.into_inner());
        if ports.clone().all(|p| !handed_out.contains(&p) && free(p)) {
            handed_out.extend(ports);
            return first;
        }
    }
    panic!("no {n} free ports in 23000..32000");
}

/// Whether a server could listen on `port` on all interfaces now.
pub fn port_is_free(port: u16) -> bool {
    TcpListener::bind((Ipv4Addr::UNSPECIFIED, port)).is_ok()
}

/// The `plccoms` binary running in its own empty temporary directory, its log
/// (stderr) in a file there.
pub struct ServerProcess {
    pub child: ChildGuard,
    pub addr: SocketAddr,
    pub dir: tempfile::TempDir,
}

impl ServerProcess {
    /// Writes `ini` to `plccoms.ini` in a new temporary directory and runs
    /// `plccoms -c plccoms.ini` there; returns once `port` accepts.
    pub fn with_config(ini: &str, port: u16) -> ServerProcess {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("plccoms.ini"), ini).expect("write ini");
        ServerProcess::start(dir, &["-c", "plccoms.ini"], port)
    }

    /// Runs `plccoms -c plccoms.ini` again in the directory of an earlier
    /// run (whatever it left there stays).
    pub fn with_config_in(dir: tempfile::TempDir, port: u16) -> ServerProcess {
        ServerProcess::start(dir, &["-c", "plccoms.ini"], port)
    }

    /// Runs `plccoms` with no arguments in an empty temporary directory: the
    /// built-in configuration. Returns once `port` accepts.
    pub fn built_in(port: u16) -> ServerProcess {
        let dir = tempfile::tempdir().expect("tempdir");
        ServerProcess::start(dir, &[], port)
    }

    fn start(dir: tempfile::TempDir, args: &[&str], port: u16) -> ServerProcess {
        let log = std::fs::File::create(dir.path().join("plccoms.log")).expect("log file");
        let child = ChildGuard::spawn(
            "plccoms",
            Command::new(PLCCOMS)
                .args(args)
                .current_dir(dir.path())
                .env_remove("RUST_LOG")
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(log),
        );
        let mut server = ServerProcess {
            child,
            addr: SocketAddr::from((Ipv4Addr::LOCALHOST, port)),
            dir,
        };
        server.wait_ready();
        server
    }

    /// Waits until the port accepts, and checks that the listener is this
    /// child's: a server that failed to bind exits at once.
    fn wait_ready(&mut self) {
        let deadline = Instant::now() + START_TIMEOUT;
        loop {
            if let Some(status) = self.child.exited() {
                panic!(
                    "plccoms exited ({status}) before accepting on {}; its log:\n{}",
                    self.addr,
                    self.log()
                );
            }
            if TcpStream::connect_timeout(&self.addr, Duration::from_millis(200)).is_ok() {
                break;
            }
            if Instant::now() >= deadline {
                panic!(
                    "plccoms did not accept on {} within {START_TIMEOUT:?}; its log:\n{}",
                    self.addr,
                    self.log()
                );
            }
            thread::sleep(Duration::from_millis(50));
        }
        thread::sleep(Duration::from_millis(200));
        if let Some(status) = self.child.exited() {
            panic!(
                "plccoms exited ({status}) although {} accepts: another program holds the port; its log:\n{}",
                self.addr,
                self.log()
            );
        }
    }

    pub fn port(&self) -> u16 {
        self.addr.port()
    }

    /// The server's log so far.
    /// The log, once it has `want` (lines are written as the server goes);
    /// fails after 30 s.
    pub async fn log_with(&self, want: &str) -> String {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        loop {
            let log = self.log();
            if log.contains(want) {
                return log;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{want:?} not in the log:\n{log}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    pub fn log(&self) -> String {
        std::fs::read(self.dir.path().join("plccoms.log"))
            .map(|b| String::from_utf8_lossy(&b).into_owned())
            .unwrap_or_else(|e| format!("(no log: {e})"))
    }
}

/// A program's full path from `PATH`, like `which`.
pub fn which(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(program))
        .find(|candidate| is_executable(candidate))
}

fn is_executable(path: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(path)
        .map(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
        .unwrap_or(false)
}

/// A TCP relay on 127.0.0.1 in front of a server, for one connection: it
/// records the bytes each way, so a test can see what a client program puts
/// on the wire. A close on one side is passed on as a half-close.
pub struct Relay {
    pub addr: SocketAddr,
    upstream: Arc<Mutex<Vec<u8>>>,
    downstream: Arc<Mutex<Vec<u8>>>,
}

impl Relay {
    pub fn start(server: SocketAddr) -> Relay {
        let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).expect("relay bind");
        let addr = listener.local_addr().expect("relay addr");
        let upstream = Arc::new(Mutex::new(Vec::new()));
        let downstream = Arc::new(Mutex::new(Vec::new()));
        let (up, down) = (upstream.clone(), downstream.clone());
        thread::spawn(move || {
            let Ok((client, _)) = listener.accept() else {
                return;
            };
            let Ok(server) = TcpStream::connect(server) else {
                return;
            };
            let _ = client.set_nodelay(true);
            let _ = server.set_nodelay(true);
            let (Ok(client2), Ok(server2)) = (client.try_clone(), server.try_clone()) else {
                return;
            };
            let to_server = thread::spawn(move || pump(client2, server2, up));
            pump(server, client, down);
            let _ = to_server.join();
        });
        Relay {
            addr,
            upstream,
            downstream,
        }
    }

    /// Bytes the client sent.
    pub fn upstream(&self) -> Vec<u8> {
        self.upstream.lock().unwrap().clone()
    }

    /// Bytes the server sent.
    pub fn downstream(&self) -> Vec<u8> {
        self.downstream.lock().unwrap().clone()
    }
}

fn pump(mut from: TcpStream, mut to: TcpStream, record: Arc<Mutex<Vec<u8>>>) {
    use std::io::Write;
    let mut chunk = [0u8; 8192];
    loop {
        match from.read(&mut chunk) {
            Ok(0) | Err(_) => break,
            Ok(n) => {
                record.lock().unwrap().extend_from_slice(&chunk[..n]);
                if to.write_all(&chunk[..n]).is_err() {
                    break;
                }
            }
        }
    }
    let _ = to.shutdown(std::net::Shutdown::Write);
}
