//! The built binaries as processes: `plccoms` (daemon, log file, start-up
//! errors, `-t`, signals, SETCONF, GETINFO, outages) and `plcsim` as the PLC.
//!
//! Everything listens on 127.0.0.1 ports found free below the ephemeral
//! range (`common::process::free_port`); every
//! child is killed on every path (the guards' `Drop`); waits poll against a
//! generous deadline instead of sleeping a fixed time (the one exception:
//! the outage test watches the log for two seconds to see that a lost PLC
//! is logged once, not once per cycle).
//!
//! Daemon tests make this process a child subreaper, so a detached server
//! becomes our child (found in /proc/self/task/*/children, never by scanning
//! other processes) and its exit status can be checked.
//!
//! Not covered yet: SIGTERM during a WRITEFILE (the file commands are not on
//! main).

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use common::process::{free_port, free_ports, free_udp_port};

const PLCCOMS: &str = env!("CARGO_BIN_EXE_plccoms");

/// Longest wait for anything: the machine is shared and may be slow.
const DEADLINE: Duration = Duration::from_secs(20);
const DEMO_PUB: &[u8] = include_bytes!("../conf/demo.pub");

// ---------------------------------------------------------------- helpers --

/// Polls `ready` until it holds; panics with `what` after [`DEADLINE`].
#[track_caller]
fn wait_for(what: &str, mut ready: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ready() {
        assert!(start.elapsed() < DEADLINE, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn read(path: &Path) -> String {
    String::from_utf8_lossy(&std::fs::read(path).unwrap_or_default()).into_owned()
}

fn count(text: &str, needle: &str) -> usize {
    text.lines().filter(|l| l.contains(needle)).count()
}

fn signal(pid: u32, sig: libc::c_int) {
    // SAFETY: plain syscall; the pid is a process this test started.
    unsafe {
        libc::kill(pid as libc::pid_t, sig);
    }
}

/// A child process, killed and reaped when dropped.
struct Proc {
    child: Child,
}

impl Proc {
    fn spawn(command: &mut Command) -> Proc {
        let child = command
            .env_remove("RUST_LOG")
            .stdin(Stdio::null())
            .spawn()
            .expect("spawn");
        Proc { child }
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    fn running(&mut self) -> bool {
        self.child.try_wait().unwrap().is_none()
    }

    /// Waits for the process to end by itself.
    #[track_caller]
    fn exit(&mut self) -> ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                start.elapsed() < DEADLINE,
                "process {} did not exit",
                self.pid()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Makes this test process the reaper of orphaned descendants, so a
/// detached server becomes our child when its parent exits (and its exit
/// status can be checked) instead of being handed to PID 1.
fn become_subreaper() {
    // SAFETY: plain syscall with constant arguments.
    let rc = unsafe { libc::prctl(libc::PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) };
    assert_eq!(rc, 0, "PR_SET_CHILD_SUBREAPER");
}

/// A detached server, found through /proc. With [`become_subreaper`] it is
/// our child once its parent has exited; SIGKILLed and reaped when dropped
/// unless it has ended already.
struct Daemon {
    pid: u32,
    reaped: bool,
}

impl Daemon {
    /// The running plccoms process whose command line names `config`,
    /// among this process's children (only ever look at our own processes).
    fn find(config: &Path) -> Option<Daemon> {
        let config = config.to_str().unwrap();
        let tasks = std::fs::read_dir("/proc/self/task").ok()?;
        let children: Vec<u32> = tasks
            .filter_map(|task| std::fs::read_to_string(task.ok()?.path().join("children")).ok())
            .flat_map(|list| {
                list.split_whitespace()
                    .filter_map(|pid| pid.parse().ok())
                    .collect::<Vec<u32>>()
            })
            .collect();
        children.into_iter().find_map(|pid| {
            let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
            let args: Vec<&[u8]> = cmdline.split(|&b| b == 0).collect();
            let ours =
                args.first() == Some(&PLCCOMS.as_bytes()) && args.contains(&config.as_bytes());
            // Built only for the match: dropping a Daemon kills its pid.
            (ours && alive(pid)).then(|| Daemon { pid, reaped: false })
        })
    }

    /// The exit status once the process has ended (it must be our child).
    fn try_reap(&mut self) -> Option<libc::c_int> {
        let mut status = 0;
        // SAFETY: waits for one specific child of ours.
        let rc = unsafe { libc::waitpid(self.pid as libc::pid_t, &mut status, libc::WNOHANG) };
        assert!(rc >= 0, "waitpid {}: not our child", self.pid);
        if rc == 0 {
            return None;
        }
        self.reaped = true;
        Some(status)
    }

    /// SIGTERM; returns the exit code.
    #[track_caller]
    fn terminate(mut self) -> i32 {
        signal(self.pid, libc::SIGTERM);
        let mut status = None;
        wait_for("the daemon to exit", || {
            status = self.try_reap();
            status.is_some()
        });
        let status = status.unwrap();
        assert!(libc::WIFEXITED(status), "killed by a signal: {status:#x}");
        libc::WEXITSTATUS(status)
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if !self.reaped {
            signal(self.pid, libc::SIGKILL);
            let mut status = 0;
            // SAFETY: waits for one specific child of ours (an error when
            // it is not ours is ignored).
            unsafe { libc::waitpid(self.pid as libc::pid_t, &mut status, 0) };
        }
    }
}

/// Exists and is not a zombie.
fn alive(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => !stat
            .rsplit_once(')')
            .is_some_and(|(_, rest)| rest.trim_start().starts_with('Z')),
        Err(_) => false,
    }
}

/// A temporary folder with a configuration file and a log file in it.
struct Site {
    dir: tempfile::TempDir,
    port: u16,
}

impl Site {
    fn new() -> Site {
        Site {
            dir: tempfile::tempdir().unwrap(),
            port: free_port(),
        }
    }

    fn ini(&self) -> PathBuf {
        self.dir.path().join("PLCComS.ini")
    }

    fn log(&self) -> PathBuf {
        self.dir.path().join("plccoms.log")
    }

    fn log_text(&self) -> String {
        read(&self.log())
    }

    fn write_ini(&self, text: &str) {
        std::fs::write(self.ini(), text).unwrap();
    }

    /// `[*]` plus one section with a simulated PLC inside the server.
    fn simulated(&self) {
        self.write_ini(&format!(
            "[*]\nCOMM_LOOP_DELAY = 20\n[Demo]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = demo\n\
             IPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {}\nPUBFILE = //demo.pub\n",
            self.port
        ));
    }

    /// `[*]` plus one section on the PLC at 127.0.0.1:`epsport`, its public
    /// file fetched from the PLC.
    fn external(&self, epsport: u16) {
        self.write_ini(&format!(
            "[*]\nCOMM_LOOP_DELAY = 20\n[PLC]\nIPADDR = 127.0.0.1\nEPSPORT = {epsport}\n\
             EPSTOUT = 100\nEPSTOUT_STEP = 0\nIPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {}\n\
             PUBFILE_CRC = Yes\nPUBFILE_WRITE = No\nPUBFILE = //demo.pub\n",
            self.port
        ));
    }

    fn command(&self, args: &[&str]) -> Command {
        let mut command = Command::new(PLCCOMS);
        command
            .args(args)
            .arg("-c")
            .arg(self.ini())
            .arg("-l")
            .arg(self.log())
            .current_dir(self.dir.path());
        command
    }

    /// The server in the foreground, logging to the site's log; returns
    /// once it accepts clients.
    fn run(&self, args: &[&str]) -> Proc {
        let mut server = Proc::spawn(
            self.command(args)
                .stdout(Stdio::null())
                .stderr(Stdio::null()),
        );
        wait_for("the server to listen", || {
            assert!(server.running(), "server exited:\n{}", self.log_text());
            TcpStream::connect(("127.0.0.1", self.port)).is_ok()
        });
        server
    }

    /// Waits until the log has a line containing `needle`.
    #[track_caller]
    fn wait_log(&self, needle: &str) {
        let start = Instant::now();
        while !self.log_text().contains(needle) {
            assert!(
                start.elapsed() < DEADLINE,
                "no {needle:?} in the log:\n{}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn client(&self) -> Client {
        Client::connect(self.port)
    }
}

/// `plcsim` as a process: EPSNET on a UDP port, a control port, and a
/// folder as its file system holding `demo.pub`.
struct Plcsim {
    proc: Proc,
    udp: u16,
    control: u16,
    files: tempfile::TempDir,
    program: &'static str,
}

impl Plcsim {
    fn start(program: &'static str) -> Plcsim {
        let files = tempfile::tempdir().unwrap();
        std::fs::write(files.path().join("demo.pub"), DEMO_PUB).unwrap();
        // Ports are picked at random below the ephemeral range, so another
        // test may take one between the pick and the bind: pick again.
        let mut attempts = 0;
        let (proc, udp, control) = loop {
            let (udp, control) = (free_udp_port(), free_port());
            match Plcsim::try_spawn(files.path(), udp, control, program) {
                Ok(proc) => break (proc, udp, control),
                Err(log) if attempts < 5 && log.contains("Address already in use") => attempts += 1,
                Err(log) => panic!("plcsim exited: {log}"),
            }
        };
        Plcsim {
            proc,
            udp,
            control,
            files,
            program,
        }
    }

    fn spawn(files: &Path, udp: u16, control: u16, program: &str) -> Proc {
        Plcsim::try_spawn(files, udp, control, program)
            .unwrap_or_else(|log| panic!("plcsim exited: {log}"))
    }

    /// Starts plcsim and waits for its control port; its log if it exits first.
    fn try_spawn(files: &Path, udp: u16, control: u16, program: &str) -> Result<Proc, String> {
        let log = std::fs::File::create(files.join("plcsim.log")).unwrap();
        let mut proc = Proc::spawn(
            Command::new(common::process::plcsim_bin())
                .arg("--bind")
                .arg(format!("127.0.0.1:{udp}"))
                .arg("--control")
                .arg(format!("127.0.0.1:{control}"))
                .arg("--files")
                .arg(files)
                .arg("--pub")
                .arg(files.join("demo.pub"))
                .args(["--program", program])
                .stdout(Stdio::null())
                .stderr(log),
        );
        let mut exited = false;
        wait_for("plcsim's control port", || {
            exited = !proc.running();
            exited || TcpStream::connect(("127.0.0.1", control)).is_ok()
        });
        if exited {
            return Err(read(&files.join("plcsim.log")));
        }
        Ok(proc)
    }

    /// Sends one control command; returns its answer line.
    #[track_caller]
    fn control(&self, command: &str) -> String {
        let mut stream = TcpStream::connect(("127.0.0.1", self.control)).unwrap();
        stream.set_read_timeout(Some(DEADLINE)).unwrap();
        stream.write_all(format!("{command}\n").as_bytes()).unwrap();
        let mut answer = String::new();
        BufReader::new(stream).read_line(&mut answer).unwrap();
        assert!(answer.starts_with("OK"), "{command}: {answer}");
        answer.trim_end().to_string()
    }

    #[track_caller]
    fn kill(&mut self) {
        self.proc.child.kill().expect("kill plcsim");
        let status = self.proc.child.wait().expect("wait plcsim");
        assert!(!status.success(), "{status}");
    }

    /// A new plcsim process on the same ports and files.
    fn restart(&mut self) {
        self.proc = Plcsim::spawn(self.files.path(), self.udp, self.control, self.program);
    }
}

/// A client on a server port, reading lines against a deadline.
struct Client {
    stream: TcpStream,
    buf: Vec<u8>,
}

impl Client {
    fn connect(port: u16) -> Client {
        let addr = SocketAddr::from(([127, 0, 0, 1], port));
        let stream = TcpStream::connect_timeout(&addr, DEADLINE).expect("connect");
        Client {
            stream,
            buf: Vec::new(),
        }
    }

    fn send(&mut self, text: &str) {
        self.stream.write_all(text.as_bytes()).unwrap();
    }

    /// Reads more bytes; 0 at EOF.
    #[track_caller]
    fn fill(&mut self, until: Instant) -> usize {
        let left = until.saturating_duration_since(Instant::now());
        assert!(
            !left.is_zero(),
            "timed out; received so far: {:?}",
            String::from_utf8_lossy(&self.buf)
        );
        self.stream.set_read_timeout(Some(left)).unwrap();
        let mut chunk = [0u8; 65536];
        match self.stream.read(&mut chunk) {
            Ok(n) => {
                self.buf.extend_from_slice(&chunk[..n]);
                n
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                self.fill(until)
            }
            Err(e) => panic!("read: {e}"),
        }
    }

    /// The next line with its line end (which must be CRLF) removed.
    #[track_caller]
    fn line(&mut self) -> String {
        let until = Instant::now() + DEADLINE;
        loop {
            if let Some(pos) = self.buf.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.buf.drain(..=pos).collect();
                let text = String::from_utf8_lossy(&line).into_owned();
                return match text.strip_suffix("\r\n") {
                    Some(text) => text.to_string(),
                    None => panic!("line without CRLF: {text:?}"),
                };
            }
            if self.fill(until) == 0 {
                panic!(
                    "connection closed; partial: {:?}",
                    String::from_utf8_lossy(&self.buf)
                );
            }
        }
    }

    /// The next line, raw, with its line end.
    #[track_caller]
    fn raw_line(&mut self) -> Vec<u8> {
        let until = Instant::now() + DEADLINE;
        loop {
            if let Some(pos) = self.buf.iter().position(|&b| b == b'\n') {
                return self.buf.drain(..=pos).collect();
            }
            assert!(self.fill(until) > 0, "connection closed");
        }
    }

    /// Reads lines until one equals `want`; returns the lines before it.
    #[track_caller]
    fn until(&mut self, want: &str) -> Vec<String> {
        let mut before = Vec::new();
        loop {
            let line = self.line();
            if line == want {
                return before;
            }
            before.push(line);
            assert!(before.len() < 100_000, "never got {want:?}");
        }
    }

    /// Reads lines until one satisfies `pred`, which it returns.
    #[track_caller]
    fn until_match(&mut self, what: &str, pred: impl Fn(&str) -> bool) -> String {
        let until = Instant::now() + DEADLINE;
        loop {
            assert!(Instant::now() < until, "never got {what}");
            let line = self.line();
            if pred(&line) {
                return line;
            }
        }
    }

    /// Sends `request` and expects `answer` as the next line.
    #[track_caller]
    fn ask(&mut self, request: &str, answer: &str) {
        self.send(request);
        assert_eq!(self.line(), answer, "answer to {request:?}");
    }

    /// Reads everything up to EOF (which must come within the deadline).
    #[track_caller]
    fn rest(&mut self) -> String {
        let until = Instant::now() + DEADLINE;
        while self.fill(until) > 0 {}
        String::from_utf8_lossy(&std::mem::take(&mut self.buf)).into_owned()
    }
}

/// A log line starts with an RFC 3339 time stamp: `2024-05-01T12:00:00...`.
fn timestamped(line: &str) -> bool {
    let b = line.as_bytes();
    b.len() > 20
        && b[..4].iter().all(u8::is_ascii_digit)
        && b[4] == b'-'
        && b[7] == b'-'
        && b[10] == b'T'
        && b[13] == b':'
        && b[16] == b':'
}

/// A `-d` run: the parent's exit status and what it printed. The parent
/// also gets a descriptor that is not a standard stream (fd 100, a socket
/// whose other end is returned), as launchers often leak one.
fn daemon_start(site: &Site) -> (ExitStatus, String, String, UnixStream) {
    use std::os::fd::AsRawFd;
    use std::os::unix::process::CommandExt;
    let out = site.dir.path().join("parent.out");
    let err = site.dir.path().join("parent.err");
    let (ours, leaked) = UnixStream::pair().unwrap();
    let leaked_fd = leaked.as_raw_fd();
    let mut command = site.command(&["-d"]);
    command
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap());
    // SAFETY: only dup2 (async-signal-safe) between fork and exec; dup2
    // clears close-on-exec on the copy.
    unsafe {
        command.pre_exec(move || {
            if libc::dup2(leaked_fd, 100) < 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut parent = Proc::spawn(&mut command);
    drop(leaked);
    let status = parent.exit();
    (status, read(&out), read(&err), ours)
}

/// True when every holder of the other end of `stream` has closed it.
fn peer_closed(mut stream: UnixStream) -> bool {
    stream
        .set_read_timeout(Some(Duration::from_secs(2)))
        .unwrap();
    matches!(stream.read(&mut [0u8; 16]), Ok(0))
}

// ------------------------------------------------------------------ tests --

/// `-d` in `dir` with `site`'s configuration: the parent's exit status and
/// what it printed on stderr.
fn daemon_start_in(site: &Site, dir: &Path) -> (ExitStatus, String) {
    let err = site.dir.path().join("parent.err");
    let mut command = site.command(&["-d"]);
    command
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&err).unwrap());
    let status = Proc::spawn(&mut command).exit();
    (status, read(&err))
}

#[test]
fn the_daemon_holds_its_pid_file_and_one_left_by_a_crash_does_not_block() {
    become_subreaper();
    let first = Site::new();
    first.simulated();
    let second = Site::new();
    second.simulated();
    // Both started in the first site's folder: the same default pid file.
    let dir = first.dir.path();
    let pid_file = dir.join("PLCComS.pid");
    let (status, err) = daemon_start_in(&first, dir);
    assert!(status.success(), "{err}");
    let daemon = Daemon::find(&first.ini()).expect("the first daemon");
    assert_eq!(read(&pid_file).trim(), daemon.pid.to_string());
    first.wait_log(&format!("pid {}", daemon.pid));

    let (status, err) = daemon_start_in(&second, dir);
    assert!(
        !status.success(),
        "a second server with the same pid file starts"
    );
    assert!(
        err.contains(&format!(
            "another plccoms (pid {}) is running with it",
            daemon.pid
        )),
        "{err}"
    );
    assert!(Daemon::find(&second.ini()).is_none());

    // A crash leaves the file behind; the next start takes it over.
    drop(daemon);
    assert!(pid_file.exists(), "SIGKILL leaves the file");
    let (status, err) = daemon_start_in(&second, dir);
    assert!(status.success(), "a stale pid file blocks the start: {err}");
    let daemon = Daemon::find(&second.ini()).expect("the second daemon");
    assert_eq!(read(&pid_file).trim(), daemon.pid.to_string());
    assert_eq!(daemon.terminate(), 0);
    assert!(!pid_file.exists(), "removed at a clean stop");
}

/// `-vv`: the server's own trace, without the I/O loop's (`mio::poll`) or
/// other libraries' below info.
#[test]
fn verbose_traces_the_server_and_not_its_libraries() {
    let site = Site::new();
    site.simulated();
    let server = site.run(&["-vv"]);
    let mut c = site.client();
    c.ask("GET:__PLC_RUN\n", "GET:__PLC_RUN,1");
    drop(c);
    drop(server);
    let log = site.log_text();
    let debug_or_trace: Vec<&str> = log
        .lines()
        .filter(|l| l.contains(" TRACE ") || l.contains(" DEBUG "))
        .collect();
    assert!(
        debug_or_trace.iter().any(|l| l.contains(" plccoms")),
        "no trace of the server's own:\n{log}"
    );
    let foreign: Vec<&&str> = debug_or_trace
        .iter()
        .filter(|l| !(l.contains(" plccoms") || l.contains(" plcsim")))
        .collect();
    assert!(
        foreign.is_empty(),
        "libraries' debug or trace lines: {foreign:#?}"
    );
}

/// Under systemd the configuration's folder is read-only (`/etc/plccoms`,
/// `ProtectSystem=strict`): what the server writes, the history and the
/// MQTT queues, goes to `$STATE_DIRECTORY`; run by hand, beside the
/// configuration, as before.
#[test]
fn written_state_goes_to_the_state_directory_under_systemd() {
    let broker = common::mqtt::Broker::anonymous();
    for systemd in [true, false] {
        let site = Site::new();
        let state = tempfile::tempdir().unwrap();
        site.write_ini(&format!(
            "[*]\nCOMM_LOOP_DELAY = 20\nMQTT_URL = {}\n[Demo]\nSIMULATOR = Yes\n\
             SIMULATOR_PROGRAM = demo\nIPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {}\n\
             PUBFILE = //demo.pub\nHISTORY = COUNTER\n",
            broker.url(),
            site.port
        ));
        let mut command = site.command(&[]);
        if systemd {
            command.env("STATE_DIRECTORY", state.path());
        } else {
            command.env_remove("STATE_DIRECTORY");
        }
        let server = Proc::spawn(command.stdout(Stdio::null()).stderr(Stdio::null()));
        site.wait_log("running");
        let (written, clean) = if systemd {
            (state.path(), site.dir.path())
        } else {
            (site.dir.path(), state.path())
        };
        wait_for("the history and the MQTT queue folders", || {
            written.join("history").is_dir() && written.join("mqtt-spool").is_dir()
        });
        for folder in ["history", "mqtt-spool"] {
            assert!(
                !clean.join(folder).exists(),
                "systemd {systemd}: {folder} in {}",
                clean.display()
            );
        }
        drop(server);
    }
}

/// A configured consumer that cannot write its folder stops the start with
/// one line naming the key, the path and the fix (tests run as root, so
/// the folder is a file: a permission would not stop root). With -d the
/// parent prints it and exits 1.
#[test]
fn a_consumer_that_cannot_write_its_folder_stops_the_start() {
    become_subreaper();
    let broker = common::mqtt::Broker::anonymous();
    for (key, extra) in [
        ("HISTORY_DIR", String::new()),
        ("MQTT_SPOOL", format!("MQTT_URL = {}\n", broker.url())),
    ] {
        let site = Site::new();
        std::fs::write(site.dir.path().join("blocked"), "a file, not a folder").unwrap();
        site.write_ini(&format!(
            "[*]\nCOMM_LOOP_DELAY = 20\n{key} = blocked/inner\n{extra}[Demo]\n\
             SIMULATOR = Yes\nSIMULATOR_PROGRAM = demo\nIPADDR_LOCAL = 127.0.0.1\n\
             SERVER_PORT = {}\nPUBFILE = //demo.pub\nHISTORY = COUNTER\n",
            site.port
        ));
        let (status, err) = daemon_start_in(&site, site.dir.path());
        assert_eq!(status.code(), Some(1), "{key}: {err}");
        let blocked = site.dir.path().join("blocked/inner");
        assert!(
            err.contains(&format!("{key} {}", blocked.display()))
                && err.contains(&format!(
                    "make the folder writable by the server's user, or set {key}"
                )),
            "{key}: {err}"
        );
        assert!(
            !site.log_text().contains("section(s)"),
            "said running:\n{}",
            site.log_text()
        );
        // The child reports the failure to the parent before it exits: it
        // is gone once it has (a busy machine may take a moment).
        wait_for(&format!("{key}: the server to exit"), || {
            Daemon::find(&site.ini()).is_none()
        });
    }
}

#[test]
fn daemon_starts_listening_and_appends_to_its_log() {
    become_subreaper();
    let site = Site::new();
    site.simulated();
    let mut runs = Vec::new();
    for run in 0..2 {
        let (status, out, err, leaked) = daemon_start(&site);
        let daemon = Daemon::find(&site.ini());
        assert!(status.success(), "run {run}: {status}; {err}");
        assert!(
            peer_closed(leaked),
            "the daemon keeps a descriptor it inherited"
        );
        // The parent returned only once the child listens.
        TcpStream::connect(("127.0.0.1", site.port)).expect("listening when the parent exits");
        assert_eq!(
            (out.as_str(), err.as_str()),
            ("", ""),
            "nothing on the terminal"
        );
        let daemon = daemon.expect("the daemon process");
        let mut c = site.client();
        c.ask("GETINFO:ipaddr\n", "GETINFO:IPADDR,127.0.0.1");
        drop(c);
        assert_eq!(daemon.terminate(), 0);
        runs.push(site.log_text());
    }
    let (first, second) = (&runs[0], &runs[1]);
    assert!(
        second.starts_with(first.as_str()),
        "the log was not appended"
    );
    for line in second.lines() {
        assert!(timestamped(line), "no time stamp: {line:?}");
    }
    for log in [first, &second[first.len()..]] {
        assert_eq!(count(log, "listening"), 1, "{log}");
        assert!(
            log.lines()
                .any(|l| l.contains("listening") && l.contains("section=Demo")),
            "section not named: {log}"
        );
        assert!(log.contains("SIGTERM"), "{log}");
        assert!(log.trim_end().ends_with("stopped"), "{log}");
    }
}

#[test]
fn daemon_start_up_errors_are_printed_by_the_parent() {
    become_subreaper();
    // A bad [*] value: file, line, key, value and range.
    let site = Site::new();
    site.write_ini(&format!(
        "[*]\nCOMM_LOOP_DELAY = 5000\n[Demo]\nSIMULATOR = Yes\nSERVER_PORT = {}\n",
        site.port
    ));
    let (status, out, err, _) = daemon_start(&site);
    assert_eq!(status.code(), Some(1), "{err}");
    assert_eq!(out, "");
    let ini = site.ini().display().to_string();
    assert!(
        err.contains(&format!("{ini}:2:"))
            && err.contains("COMM_LOOP_DELAY = 5000")
            && err.contains("1-1000"),
        "{err}"
    );
    wait_for("no daemon left", || Daemon::find(&site.ini()).is_none());

    // The only section cannot listen: its port is taken.
    let site = Site::new();
    let taken = TcpListener::bind(("127.0.0.1", site.port)).unwrap();
    site.simulated();
    let (status, out, err, _) = daemon_start(&site);
    assert_eq!(status.code(), Some(1), "{err}");
    assert_eq!(out, "");
    assert!(
        err.contains("Demo") && err.contains(&site.port.to_string()) && err.contains("in use"),
        "the reason is missing: {err}"
    );
    assert!(site.log_text().contains("in use"), "{}", site.log_text());
    wait_for("no daemon left", || Daemon::find(&site.ini()).is_none());
    drop(taken);
}

#[test]
fn dash_t_exits_when_the_configuration_changes() {
    // An appended comment.
    let site = Site::new();
    site.simulated();
    let mut server = site.run(&["-t"]);
    let mut file = std::fs::OpenOptions::new()
        .append(true)
        .open(site.ini())
        .unwrap();
    file.write_all(b"# edited\n").unwrap();
    drop(file);
    assert_eq!(server.exit().code(), Some(0));
    let log = site.log_text();
    assert!(log.contains("changed: exiting (-t)"), "{log}");
    assert!(log.trim_end().ends_with("stopped"), "{log}");

    // Replaced by rename, as editors do.
    let site = Site::new();
    site.simulated();
    let mut server = site.run(&["-t"]);
    let new = site.dir.path().join("PLCComS.ini.new");
    std::fs::write(&new, read(&site.ini()) + "# edited\n").unwrap();
    std::fs::rename(&new, site.ini()).unwrap();
    assert_eq!(server.exit().code(), Some(0));
    let log = site.log_text();
    assert!(log.contains("changed: exiting (-t)"), "{log}");
    assert!(log.trim_end().ends_with("stopped"), "{log}");
}

/// SIGTERM or SIGINT with two clients: one with requests in flight, one only
/// receiving DIFFs. (No WRITEFILE part: file transfers are not on main yet.)
fn graceful_stop(sig: libc::c_int, name: &str) {
    let site = Site::new();
    site.simulated();
    let mut server = site.run(&[]);
    let mut watcher = site.client();
    watcher.ask(
        "EN:sinus\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'",
    );
    watcher.until_match("a DIFF", |l| l.starts_with("DIFF:SINUS,"));
    let mut busy = site.client();
    busy.ask("GET:counter\n", "GET:COUNTER,0");
    busy.send(&"LIST:\nGETINFO:\nGET:counter\n".repeat(20));
    // The server is answering: stop it now.
    assert!(busy.line().starts_with("LIST:"));
    signal(server.pid(), sig);
    let rest = busy.rest();
    // Every request got its whole answer, then the connection closed.
    assert_eq!(count(&rest, "GET:COUNTER,0"), 20, "{rest}");
    assert_eq!(rest.matches("\r\nLIST:\r\n").count(), 20, "{rest}");
    assert_eq!(rest.matches("\r\nGETINFO:\r\n").count(), 20, "{rest}");
    assert!(rest.ends_with("GET:COUNTER,0\r\n"), "{rest:?}");
    let tail = watcher.rest();
    assert!(tail.lines().all(|l| l.starts_with("DIFF:SINUS,")), "{tail}");
    assert_eq!(server.exit().code(), Some(0));
    let log = site.log_text();
    let last: Vec<&str> = log.lines().rev().take(2).collect();
    assert!(
        last[0].ends_with("stopped") && last[1].contains(&format!("{name}: shutting down")),
        "{log}"
    );
}

#[test]
fn sigterm_answers_clients_then_exits_0() {
    graceful_stop(libc::SIGTERM, "SIGTERM");
}

#[test]
fn sigint_answers_clients_then_exits_0() {
    graceful_stop(libc::SIGINT, "SIGINT");
}

/// A SIGTERM while the sections start (the first one's port accepts, the
/// others are still starting) stops the server as it would later. The
/// handler used to be installed once every section had started: until
/// then the signal's default action killed the server (10 of 10 tries
/// with 200 sections), its history and MQTT unclosed.
#[test]
fn sigterm_during_start_up_stops_gracefully() {
    const SECTIONS: u16 = 200;
    let site = Site::new();
    let first = free_ports(SECTIONS);
    let mut ini = String::from("[*]\nCOMM_LOOP_DELAY = 1000\n");
    for i in 0..SECTIONS {
        ini += &format!(
            "[S{i}]\nSIMULATOR = Yes\nIPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {}\n",
            first + i
        );
    }
    site.write_ini(&ini);
    let mut server = Proc::spawn(
        site.command(&[])
            .stdout(Stdio::null())
            .stderr(Stdio::null()),
    );
    wait_for("the first section to listen", || {
        assert!(server.running(), "server exited:\n{}", site.log_text());
        TcpStream::connect(("127.0.0.1", first)).is_ok()
    });
    signal(server.pid(), libc::SIGTERM);
    let status = server.exit();
    let log = site.log_text();
    assert_eq!(status.code(), Some(0), "{status:?}\n{log}");
    assert!(log.contains("SIGTERM: shutting down"), "{log}");
}

/// demo.pub without `v_byte`, with a new `extra`, and a fresh CRC trailer.
fn changed_demo_pub() -> Vec<u8> {
    let mut text: Vec<u8> = DEMO_PUB
        .split_inclusive(|&b| b == b'\n')
        .filter(|line| !line.starts_with(b" v_byte ") && !line.starts_with(b";*"))
        .flatten()
        .copied()
        .collect();
    text.extend_from_slice(b" extra R B 300 INT PUB_INOUT\r\n");
    let crc = plccoms_plc::pubfile::crc_of(&text);
    text.extend_from_slice(format!(";* Crc=\"{crc:08X}\"\r\n").as_bytes());
    text
}

#[test]
fn a_program_change_in_the_plc_reloads_the_public_file() {
    let plc = Plcsim::start("idle");
    let site = Site::new();
    site.external(plc.udp);
    let _server = site.run(&[]);
    // The public file comes from the PLC at its first connection.
    site.wait_log("PLC connected");
    let mut c = site.client();
    c.ask(
        "EN:counter\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'",
    );
    assert_eq!(c.line(), "DIFF:COUNTER,0");
    c.ask(
        "EN:setpoint\n",
        "WARNING:252 Changed active variables in public file: '[4/29]'",
    );
    assert_eq!(c.line(), "DIFF:SETPOINT,0.000000");
    c.ask(
        "HIDE:note\n",
        "WARNING:253 Changed hidden variables in public file: '[1]'",
    );
    let mut other = site.client();
    other.ask("GET:v_byte\n", "GET:V_BYTE,0");

    // The PLC gets a new program.
    let new_pub = changed_demo_pub();
    let path = plc.files.path().join("demo.pub");
    std::fs::write(&path, &new_pub).unwrap();
    plc.control(&format!("pub {}", path.display()));
    let warning = "WARNING:250 Changed public file: 'demo.pub'";
    let before = c.until(warning);
    assert!(before.iter().all(|l| l.starts_with("DIFF:")), "{before:?}");
    other.until(warning);

    c.send("LIST:\n");
    let list = c.until("LIST:");
    assert_eq!(list.len(), 29, "{list:?}");
    for want in [
        "LIST:__PLC_RUN,BOOL",
        "LIST:__PF_CRC,DWORD",
        "LIST:COUNTER,INT",
        "LIST:SETPOINT,REAL",
        "LIST:NOTE,STRING[40]*~",
        "LIST:EXTRA,INT*",
        "LIST:V_WORD,WORD*",
    ] {
        assert!(list.iter().any(|l| l == want), "{want} missing: {list:?}");
    }
    assert!(
        !list.iter().any(|l| l.starts_with("LIST:V_BYTE")),
        "{list:?}"
    );
    other.ask(
        "GET:v_byte\n",
        "ERROR:33 Unknown variable name in request: 'GET:v_byte'",
    );
    other.ask("GET:extra\n", "GET:EXTRA,0");

    // Polling goes on through the new table for the still-enabled variables.
    plc.control("animate counter extra");
    let mut seen = std::collections::BTreeSet::new();
    while seen.len() < 3 {
        let line = c.line();
        assert!(
            line.starts_with("DIFF:COUNTER,") || line.starts_with("DIFF:SETPOINT,"),
            "{line}"
        );
        seen.insert(line);
    }
    let log = site.log_text();
    assert!(log.contains("__PF_CRC changed"), "{log}");
}

#[test]
fn setconf_every_key() {
    let plc = Plcsim::start("idle");
    let other_pub = changed_demo_pub();
    std::fs::write(plc.files.path().join("other.pub"), &other_pub).unwrap();
    let site = Site::new();
    site.external(plc.udp);
    // other.pub describes another program than the PLC runs: only without
    // the CRC check may a client load it.
    let ini = std::fs::read_to_string(site.ini()).unwrap();
    site.write_ini(&ini.replace("PUBFILE_CRC = Yes", "PUBFILE_CRC = No"));
    let _server = site.run(&[]);
    // The public file comes from the PLC at its first connection.
    site.wait_log("PLC connected");
    let mut c = site.client();
    let mut other = site.client();
    c.ask("GET:counter\n", "GET:COUNTER,0");
    let same = "WARNING:251 Public file not changed: 'demo.pub'";
    let mut notices = Vec::new();

    // ipaddr: a loopback address where nothing answers is refused and
    // changes nothing; the same address again reloads.
    c.ask(
        "SETCONF:ipaddr,127.0.0.2\n",
        "ERROR:10 Unable to connect to PLC.",
    );
    c.ask("GETINFO:ipaddr\n", "GETINFO:IPADDR,127.0.0.1");
    c.ask("GET:counter\n", "GET:COUNTER,0");
    c.ask("SETCONF:ipaddr,127.0.0.1\n", same);
    notices.push(same);
    c.ask("GET:counter\n", "GET:COUNTER,0");
    c.ask(
        "SETCONF:ipaddr,127.0.0.256\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:ipaddr,127.0.0.256'",
    );

    // epsaddr: 1-126.
    for bad in ["0", "127", "x"] {
        c.ask(
            &format!("SETCONF:epsaddr,{bad}\n"),
            &format!("ERROR:35 Wrong parameter value in request: 'SETCONF:epsaddr,{bad}'"),
        );
    }
    for good in ["1", "126"] {
        c.ask(&format!("SETCONF:epsaddr,{good}\n"), same);
        notices.push(same);
        c.ask("GETINFO:epsaddr\n", &format!("GETINFO:EPSADDR,{good}"));
    }

    // epsport: a port where nothing answers is refused and changes nothing;
    // the PLC's own port again reloads.
    let dead = free_udp_port();
    c.ask(
        &format!("SETCONF:epsport,{dead}\n"),
        "ERROR:10 Unable to connect to PLC.",
    );
    c.ask("GETINFO:epsport\n", &format!("GETINFO:EPSPORT,{}", plc.udp));
    c.ask(&format!("SETCONF:epsport,{}\n", plc.udp), same);
    notices.push(same);
    c.ask("GETINFO:epsport\n", &format!("GETINFO:EPSPORT,{}", plc.udp));
    c.ask(
        "SETCONF:epsport,0\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:epsport,0'",
    );

    // serial_device / serial_speed: no PLC answers on /dev/ttyS0 here (or
    // there is no such device): ERROR:10, and the section stays on its link.
    c.ask(
        "SETCONF:serial_device,/dev/ttyS0\n",
        "ERROR:10 Unable to connect to PLC.",
    );
    c.ask("GETINFO:serial_device\n", "GETINFO:SERIAL_DEVICE,");
    // A speed alone changes nothing on an Ethernet link: 251.
    c.ask("SETCONF:serial_speed,115200\n", same);
    notices.push(same);
    c.ask(
        "SETCONF:serial_speed,fast\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:serial_speed,fast'",
    );
    c.ask("GET:counter\n", "GET:COUNTER,0");
    c.ask("SETCONF:ipaddr,127.0.0.1\n", same);
    notices.push(same);

    // pubfile: the same file, another one, and back.
    c.ask("SETCONF:pubfile,//demo.pub\n", same);
    notices.push(same);
    let other_changed = "WARNING:250 Changed public file: 'other.pub'";
    c.ask("SETCONF:pubfile,//other.pub\n", other_changed);
    notices.push(other_changed);
    c.ask("GET:extra\n", "GET:EXTRA,0");
    c.ask(
        "GETINFO:pubfile\n",
        "GETINFO:PUBFILE,2/29 [FIXED.pub,other.pub]",
    );
    let demo_changed = "WARNING:250 Changed public file: 'demo.pub'";
    c.ask("SETCONF:pubfile,//demo.pub\n", demo_changed);
    notices.push(demo_changed);
    c.ask(
        "SETCONF:pubfile,//missing.pub\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,//missing.pub'",
    );

    // crlf and diff: this client only, echoed.
    c.send("SETCONF:crlf,no\n");
    assert_eq!(c.raw_line(), b"SETCONF:CRLF,NO\n");
    c.send("GET:counter\n");
    assert_eq!(c.raw_line(), b"GET:COUNTER,0\n");
    c.ask("SETCONF:crlf,yes\n", "SETCONF:CRLF,YES");
    c.ask(
        "SETCONF:crlf,maybe\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:crlf,maybe'",
    );
    c.ask("SETCONF:diff,no\n", "SETCONF:DIFF,NO");
    c.ask("SETCONF:diff,yes\n", "SETCONF:DIFF,YES");

    c.ask(
        "SETCONF:nothing,1\n",
        "ERROR:50 Unknown name in request: 'SETCONF:nothing,1'",
    );

    // The other client heard of every reload, in order, and its line end
    // did not change.
    for notice in notices {
        assert_eq!(other.line(), notice);
    }
    other.ask("GET:counter\n", "GET:COUNTER,0");
}

#[test]
fn getinfo_with_several_clients() {
    let plc = Plcsim::start("idle");
    let site = Site::new();
    site.external(plc.udp);
    let _server = site.run(&[]);
    // The public file comes from the PLC at its first connection.
    site.wait_log("PLC connected");
    let mut clients: Vec<Client> = (0..3).map(|_| site.client()).collect();
    let c = &mut clients[0];
    // The PLC's identification once the link is up.
    let mut version_plc = String::new();
    wait_for("VERSION_PLC", || {
        c.send("GETINFO:version_plc\n");
        version_plc = c.line();
        version_plc != "GETINFO:VERSION_PLC,"
    });
    // The server's start-up probe connection may still be leaving.
    wait_for("three clients listed", || {
        c.send("GETINFO:network\n");
        c.until("GETINFO:").len() == 3
    });
    c.send("GETINFO:\n");
    let lines = c.until("GETINFO:");
    // The vendor's shape: `Ver 5.5 Sep  9 2020 16:10:19`.
    let version = |line: &str, key: &str, number: &str| {
        let date = line
            .strip_prefix(&format!("GETINFO:{key},Ver {number} "))
            .unwrap_or_else(|| panic!("{line:?}"));
        let b = date.as_bytes();
        assert!(
            b.len() == 20 && b[3] == b' ' && b[6] == b' ' && b[11] == b' ' && b[14] == b':',
            "{line:?}"
        );
    };
    let number = concat!(
        env!("CARGO_PKG_VERSION_MAJOR"),
        ".",
        env!("CARGO_PKG_VERSION_MINOR")
    );
    version(&lines[0], "VERSION", number);
    version(&lines[1], "VERSION_EPSNET", number);
    version(&lines[2], "VERSION_INI", "0.21");
    let head = [version_plc.clone(), "GETINFO:IPADDR,127.0.0.1".to_string()];
    assert_eq!(lines[3..5], head, "{lines:#?}");
    assert!(lines[5].starts_with("GETINFO:EPSADDR,"), "{lines:#?}");
    assert_eq!(lines[6], format!("GETINFO:EPSPORT,{}", plc.udp));
    assert_eq!(lines[7], "GETINFO:PUBFILE,2/29 [FIXED.pub,demo.pub]");
    let network = &lines[8..];
    assert_eq!(network.len(), 3, "{lines:#?}");
    let today = chrono::Local::now().format("%Y-%m-%d").to_string();
    for (i, line) in network.iter().enumerate() {
        let prefix = format!("GETINFO:NETWORK,{}/128 [127.0.0.1       ", i + 1);
        let rest = line
            .strip_prefix(&prefix)
            .unwrap_or_else(|| panic!("{line:?}"));
        // yyyy-mm-dd hh:mm:ss]
        let b = rest.as_bytes();
        assert_eq!(b.len(), 20, "{line:?}");
        assert!(
            b[10] == b' ' && b[13] == b':' && b[16] == b':' && b[19] == b']',
            "{line:?}"
        );
        assert!(
            rest[..10] <= *today.as_str() && rest[..4] >= *"2024",
            "{line:?}"
        );
    }

    c.send("GETINFO:network\n");
    assert_eq!(c.until("GETINFO:"), network);
    c.ask("GETINFO:version_plc\n", &version_plc);
    c.ask("GETINFO:VERSION_plc\n", &version_plc);
    c.ask(
        "GETINFO:pubfile\n",
        "GETINFO:PUBFILE,2/29 [FIXED.pub,demo.pub]",
    );
    c.ask(
        "GETINFO:nothing\n",
        "ERROR:60 Unknown name in request: 'GETINFO:nothing'",
    );
    // One client leaves: the list follows.
    drop(clients.pop());
    let c = &mut clients[0];
    wait_for("two clients listed", || {
        c.send("GETINFO:network\n");
        c.until("GETINFO:").len() == 2
    });
}

#[test]
fn a_lost_plc_is_logged_once_and_comes_back() {
    let mut plc = Plcsim::start("demo");
    let site = Site::new();
    site.external(plc.udp);
    let mut server = site.run(&[]);
    site.wait_log("PLC connected");
    let mut c = site.client();
    c.ask(
        "EN:sinus\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'",
    );
    c.until_match("a DIFF", |l| l.starts_with("DIFF:SINUS,"));
    site.wait_log("PLC connected");

    plc.kill();
    wait_for("PLC lost", || {
        match server.child.try_wait() {
            Ok(None) => {}
            other => panic!("server ended: {other:?}\n{}", site.log_text()),
        }
        site.log_text().contains("PLC lost")
    });
    // Many poll cycles and reconnect attempts later, still one line.
    let lost_at = Instant::now();
    c.ask("GET:sinus\n", "ERROR:10 Unable to connect to PLC.");
    std::thread::sleep(Duration::from_secs(2).saturating_sub(lost_at.elapsed()));
    let log = site.log_text();
    assert_eq!(count(&log, "PLC lost"), 1, "{log}");
    assert_eq!(count(&log, "cannot reach PLC"), 0, "{log}");
    assert_eq!(count(&log, "PLC connected"), 1, "{log}");

    plc.restart();
    wait_for("PLC connected again", || {
        count(&site.log_text(), "PLC connected") == 2
    });
    // DIFFs resume.
    c.buf.clear();
    let mut values = std::collections::BTreeSet::new();
    while values.len() < 3 {
        let line = c.until_match("a DIFF", |l| l.starts_with("DIFF:SINUS,"));
        values.insert(line);
    }
    let log = site.log_text();
    assert_eq!(count(&log, "PLC lost"), 1, "{log}");
    assert_eq!(count(&log, "PLC connected"), 2, "{log}");
}

#[test]
fn halt_then_run_reinitialises_the_link() {
    let plc = Plcsim::start("demo");
    let site = Site::new();
    site.external(plc.udp);
    let _server = site.run(&[]);
    // The public file comes from the PLC at its first connection.
    site.wait_log("PLC connected");
    let mut c = site.client();
    c.ask(
        "EN:__PLC_RUN\n",
        "WARNING:252 Changed active variables in public file: '[2/29]'",
    );
    assert_eq!(c.line(), "DIFF:__PLC_RUN,1");
    plc.control("halt");
    assert_eq!(c.line(), "DIFF:__PLC_RUN,0");
    plc.control("run");
    assert_eq!(c.line(), "DIFF:__PLC_RUN,1");
    site.wait_log("HALT -> RUN: PLC link re-initialised");
    let log = site.log_text();
    assert_eq!(count(&log, "PLC is in HALT"), 1, "{log}");
    assert_eq!(count(&log, "PLC is in RUN"), 1, "{log}");
}

// ------------------------------------------ a year unattended (issue 17) --

/// The vendor's shipped PLCComS.ini with only its PLC's address and ports
/// changed, against `plcsim --files DIR --pub VARLIST.PUB` (the pairing the
/// README gives): the public file is fetched from the simulated PLC's file
/// system, where plcsim serves it under its own name, and its CRC checked.
#[test]
fn the_vendors_ini_runs_against_plcsim_serving_its_public_file() {
    let vendor = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/vendor");
    let site = Site::new();
    let plc_files = tempfile::tempdir().unwrap();
    let program = tempfile::tempdir().unwrap();
    let pubfile = program.path().join("VARLIST.PUB");
    std::fs::write(&pubfile, DEMO_PUB).unwrap();
    let udp = free_udp_port();
    let log = std::fs::File::create(program.path().join("plcsim.log")).unwrap();
    let _plc = Proc::spawn(
        Command::new(common::process::plcsim_bin())
            .arg("--bind")
            .arg(format!("127.0.0.1:{udp}"))
            .arg("--files")
            .arg(plc_files.path())
            .arg("--pub")
            .arg(&pubfile)
            .stdout(Stdio::null())
            .stderr(log),
    );
    std::fs::copy(
        vendor.join("FIXED_Foxtrot.pub"),
        site.dir.path().join("FIXED_Foxtrot.pub"),
    )
    .unwrap();
    let ini = read(&vendor.join("PLCComS.ini"))
        .replace(
            "IPADDR        = 192.168.89.1",
            &format!("IPADDR        = 127.0.0.1\nEPSPORT       = {udp}"),
        )
        .replace(
            "SERVER_PORT   = 5011",
            &format!("SERVER_PORT   = {}", site.port),
        );
    assert!(ini.contains("PUBFILE       = //VARLIST.PUB"), "{ini}");
    site.write_ini(&ini);
    let _server = site.run(&[]);
    let mut c = site.client();
    wait_for("the public file from the PLC", || {
        c.send("GETINFO:pubfile\n");
        // Its arrival is announced (WARNING:25x) between answers.
        let mut line = c.line();
        while line.starts_with("WARNING:") {
            line = c.line();
        }
        line != "GETINFO:PUBFILE,2/2 [FIXED_Foxtrot.pub]"
    });
    c.ask(
        "GETINFO:pubfile\n",
        "GETINFO:PUBFILE,2/29 [FIXED_Foxtrot.pub,VARLIST.PUB]",
    );
    c.ask("GET:text\n", "GET:TEXT,\"Have a nice day\"");
    let log = site.log_text();
    assert!(log.contains("//VARLIST.PUB fetched from the PLC"), "{log}");
    // Nothing was written into the PLC's folder to make it so.
    assert_eq!(std::fs::read_dir(plc_files.path()).unwrap().count(), 0);
}

/// A public file that is neither on this machine nor on the PLC: the log
/// says "file not found on the PLC" and names the local path it tried.
#[test]
fn a_public_file_missing_on_the_plc_is_reported_with_where_it_was_looked_for() {
    let plc = Plcsim::start("demo");
    let site = Site::new();
    site.external(plc.udp);
    site.write_ini(&read(&site.ini()).replace("//demo.pub", "//MISSING.PUB"));
    let _server = site.run(&[]);
    site.wait_log("file not found on the PLC");
    let log = site.log_text();
    let line = log
        .lines()
        .find(|l| l.contains("file not found on the PLC"))
        .unwrap();
    let local = site.dir.path().join("MISSING.PUB");
    assert!(
        line.contains("//MISSING.PUB") && line.contains(&format!("not at {}", local.display())),
        "{line}"
    );
    assert!(
        !line.contains("wrong service parameters (0x0C)\""),
        "{line}"
    );
}

/// logrotate's way: move the log away, then SIGHUP. The server logs that
/// it reopened, writes on in a new file at the old path, and keeps serving.
#[test]
fn sighup_reopens_the_log_file() {
    let site = Site::new();
    site.simulated();
    let mut server = site.run(&[]);
    let mut c = site.client();
    c.ask("GET:counter\n", "GET:COUNTER,0");
    let rotated = site.dir.path().join("plccoms.log.1");
    std::fs::rename(site.log(), &rotated).unwrap();
    signal(server.pid(), libc::SIGHUP);
    site.wait_log("reopened");
    assert!(server.running());
    let old = read(&rotated);
    assert!(old.contains("SIGHUP: reopening the log file"), "{old}");
    assert!(!old.contains("reopened"), "{old}");
    // The same clients and new ones are served; the new log gets the rest.
    c.ask("GET:counter\n", "GET:COUNTER,0");
    site.client().ask("GET:counter\n", "GET:COUNTER,0");
    signal(server.pid(), libc::SIGTERM);
    assert_eq!(server.exit().code(), Some(0));
    let new = site.log_text();
    assert!(new.lines().all(timestamped), "{new}");
    assert!(new.trim_end().ends_with("stopped"), "{new}");
}

/// Reports on a pipe (journald, docker, redirection) carry no colour
/// escapes; SIGHUP without a log file is logged and changes nothing.
#[test]
fn stderr_on_a_pipe_is_plain_text_and_sighup_reloads_harmlessly() {
    let site = Site::new();
    site.simulated();
    let mut server = Proc::spawn(
        Command::new(PLCCOMS)
            .arg("-c")
            .arg(site.ini())
            .current_dir(site.dir.path())
            .stdout(Stdio::null())
            .stderr(Stdio::piped()),
    );
    let stderr = common::process::Capture::start(server.child.stderr.take().unwrap());
    wait_for("the server to listen", || {
        assert!(server.running(), "exited: {}", stderr.text());
        TcpStream::connect(("127.0.0.1", site.port)).is_ok()
    });
    signal(server.pid(), libc::SIGHUP);
    wait_for("SIGHUP logged", || stderr.text().contains("SIGHUP"));
    site.client().ask("GET:counter\n", "GET:COUNTER,0");
    signal(server.pid(), libc::SIGTERM);
    assert_eq!(server.exit().code(), Some(0));
    let text = stderr.finish();
    assert!(!text.contains(&0x1b), "{}", String::from_utf8_lossy(&text));
    let text = String::from_utf8_lossy(&text);
    assert!(text.contains(" INFO "), "{text}");
    // No log file to reopen: SIGHUP re-reads the unchanged configuration.
    assert!(
        text.contains("SIGHUP: configuration reloaded: 1 unchanged"),
        "{text}"
    );
}

/// SIGTERM with three busy sections: on each, a client that pipelines
/// requests and never reads its answers (its session cannot finish) and
/// one taking every DIFF. All sections stop together, within 5 s.
#[test]
fn sigterm_under_load_stops_every_section_within_5_s() {
    let site = Site::new();
    let ports = [site.port, free_port(), free_port()];
    let mut ini = String::from("[*]\nCOMM_LOOP_DELAY = 10\n");
    for (i, port) in ports.iter().enumerate() {
        ini.push_str(&format!(
            "[S{i}]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = demo\nIPADDR_LOCAL = 127.0.0.1\n\
             SERVER_PORT = {port}\nPUBFILE = //demo.pub\n"
        ));
    }
    site.write_ini(&ini);
    let mut server = site.run(&[]);
    let mut clients = Vec::new();
    for port in ports {
        let mut watcher = Client::connect(port);
        watcher.ask(
            "EN:*\n",
            "WARNING:252 Changed active variables in public file: '[29/29]'",
        );
        watcher.until_match("a DIFF", |l| l.starts_with("DIFF:"));
        let mut stuck = Client::connect(port);
        let burst = "LIST:\nGETINFO:\nGET:*\n".repeat(200);
        stuck.stream.set_nonblocking(true).unwrap();
        // Until the server stops taking requests for a whole second: its
        // answers fill every buffer between it and this client.
        let mut blocked_since = None;
        wait_for("the server to stop reading", || {
            loop {
                match stuck.stream.write(burst.as_bytes()) {
                    Ok(_) => blocked_since = None,
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                    Err(e) => panic!("write: {e}"),
                }
            }
            blocked_since.get_or_insert_with(Instant::now).elapsed() > Duration::from_secs(1)
        });
        clients.push((watcher, stuck));
    }
    let start = Instant::now();
    signal(server.pid(), libc::SIGTERM);
    let status = server.exit();
    let took = start.elapsed();
    assert_eq!(status.code(), Some(0), "{}", site.log_text());
    assert!(
        took < Duration::from_secs(5),
        "took {took:?}:\n{}",
        site.log_text()
    );
    let log = site.log_text();
    assert!(log.trim_end().ends_with("stopped"), "{log}");
    assert!(log.contains("session(s) still busy at shutdown"), "{log}");
    eprintln!("SIGTERM under load, 3 sections: exited in {took:?}");
}

/// The built-in demo (no -c, no PLCComS.ini) says loudly that its PLC is
/// simulated and listens on loopback only.
#[test]
fn the_built_in_demo_says_so_and_listens_on_loopback_only() {
    let deadline = Instant::now() + DEADLINE;
    while !common::process::port_is_free(5010) {
        assert!(
            Instant::now() < deadline,
            "port 5010 is in use by another program; the demo listens there"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let server = common::process::ServerProcess::built_in(5010);
    let log = server.log();
    assert!(log.contains("WARN DEMO:"), "{log}");
    assert!(log.contains("SIMULATED demo PLC"), "{log}");
    assert!(log.contains("clients on 127.0.0.1:5010 only"), "{log}");
    assert!(log.contains("plccoms -c /path/to/PLCComS.ini"), "{log}");
    assert!(!log.contains('\x1b'), "{log}");
    // The kernel's listening sockets on port 5010 (0x1392): loopback only.
    let listening: Vec<String> = ["/proc/net/tcp", "/proc/net/tcp6"]
        .iter()
        .flat_map(|table| {
            read(Path::new(table))
                .lines()
                .skip(1)
                .map(str::to_string)
                .collect::<Vec<_>>()
        })
        .filter_map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let listen = fields.get(3) == Some(&"0A");
            (listen && fields[1].ends_with(":1392")).then(|| fields[1].to_string())
        })
        .collect();
    assert_eq!(listening, ["0100007F:1392"]);
}

/// The real logrotate with the shipped snippet (`conf/plccoms.logrotate`,
/// its path, user and signal command pointed at this test's server): the
/// old lines end up in `.1`, the new ones in a new log.
#[test]
fn logrotate_with_the_shipped_snippet_rotates_a_running_servers_log() {
    let logrotate = ["/usr/sbin/logrotate", "/sbin/logrotate"]
        .into_iter()
        .find(|p| Path::new(p).exists())
        .expect("logrotate is not installed (Debian: apt-get install logrotate; .ci/run does)");
    let site = Site::new();
    site.simulated();
    let mut server = site.run(&[]);
    site.client().ask("GET:counter\n", "GET:COUNTER,0");
    let snippet = read(&Path::new(env!("CARGO_MANIFEST_DIR")).join("conf/plccoms.logrotate"));
    let signal_line = snippet
        .lines()
        .find(|l| l.contains("systemctl kill --signal=HUP"))
        .expect("the snippet signals the service");
    let config = snippet
        .replace(
            "/var/log/plccoms/*.log",
            &format!("{}/*.log", site.dir.path().display()),
        )
        .replace("    su plccoms plccoms\n", "")
        .replace(signal_line, &format!("        kill -HUP {}", server.pid()));
    let conf = site.dir.path().join("logrotate.conf");
    std::fs::write(&conf, config).unwrap();
    let status = Command::new(logrotate)
        .arg("--force")
        .arg("--state")
        .arg(site.dir.path().join("logrotate.state"))
        .arg(&conf)
        .status()
        .unwrap();
    assert!(status.success(), "logrotate: {status}");
    site.wait_log("reopened");
    let old = read(&site.dir.path().join("plccoms.log.1"));
    assert!(old.contains("running, 1 section(s)"), "{old}");
    site.client().ask("GET:counter\n", "GET:COUNTER,0");
    signal(server.pid(), libc::SIGTERM);
    assert_eq!(server.exit().code(), Some(0));
    let new = site.log_text();
    assert!(!new.contains("running, 1 section(s)"), "{new}");
    assert!(new.trim_end().ends_with("stopped"), "{new}");
}
