//! A real Mosquitto broker on a loopback port, started by the test, and its
//! command-line clients (`mosquitto_sub`, `mosquitto_pub`) as subscriber and
//! publisher. Every process is killed when its guard drops.

use std::net::{Ipv4Addr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use super::process::{free_port, plcsim_bin, which, Capture, ChildGuard};

/// Longest wait for anything in these tests.
pub const DEADLINE: Duration = Duration::from_secs(30);

/// The broker binary: Debian puts it in /usr/sbin, which is not always on
/// PATH.
pub fn mosquitto_bin() -> PathBuf {
    which("mosquitto")
        .or_else(|| {
            let sbin = PathBuf::from("/usr/sbin/mosquitto");
            sbin.exists().then_some(sbin)
        })
        .expect("mosquitto is not installed (apt-get install mosquitto mosquitto-clients)")
}

/// A Mosquitto broker with its configuration and persistence in a
/// temporary folder.
pub struct Broker {
    pub port: u16,
    pub dir: tempfile::TempDir,
    /// Extra configuration lines (listeners, passwords, TLS).
    extra: String,
    child: Option<ChildGuard>,
}

impl Broker {
    /// Anonymous access on a free port; `extra` is appended to the
    /// configuration (`{dir}` stands for the broker's folder).
    pub fn start(extra: &str) -> Broker {
        let dir = tempfile::tempdir().expect("tempdir");
        let extra = extra.replace("{dir}", &dir.path().display().to_string());
        let mut broker = Broker {
            port: 0,
            dir,
            extra,
            child: None,
        };
        for _ in 0..20 {
            broker.port = free_port();
            if broker.run() {
                return broker;
            }
        }
        panic!("mosquitto did not start; its log:\n{}", broker.log());
    }

    pub fn anonymous() -> Broker {
        Broker::start("allow_anonymous true\n")
    }

    fn run(&mut self) -> bool {
        let conf = self.dir.path().join("mosquitto.conf");
        // As root, mosquitto drops to its own user, which cannot write the
        // test's folder (its log, its persistence file): it stays root.
        // SAFETY: plain syscall without arguments.
        let user = if unsafe { libc::geteuid() } == 0 {
            "user root\n"
        } else {
            ""
        };
        let text = format!(
            "{user}listener {port} 127.0.0.1\n{extra}\npersistence true\npersistence_location {dir}/\nlog_dest file {dir}/mosquitto.log\nlog_type all\n",
            port = self.port,
            extra = self.extra,
            dir = self.dir.path().display()
        );
        std::fs::write(&conf, text).expect("write mosquitto.conf");
        let mut child = ChildGuard::spawn(
            "mosquitto",
            Command::new(mosquitto_bin())
                .arg("-c")
                .arg(&conf)
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::null()),
        );
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(10) {
            if child.exited().is_some() {
                return false;
            }
            if TcpStream::connect((Ipv4Addr::LOCALHOST, self.port)).is_ok() {
                self.child = Some(child);
                return true;
            }
            thread::sleep(Duration::from_millis(20));
        }
        false
    }

    /// Stops the broker as a service manager would (SIGTERM: it saves its
    /// persistence file) and waits for it. The signal is sent again each
    /// half second: mosquitto accepts connections before its main loop
    /// starts, and a SIGTERM its handler takes in that gap is undone by the
    /// loop's start (`run = 1`), so the first may be lost (under load: a
    /// broker stopped just after it started ran on for the whole deadline).
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let start = Instant::now();
            loop {
                signal(child.child().id(), libc::SIGTERM);
                if child.wait_timeout(Duration::from_millis(500)).is_some() {
                    break;
                }
                assert!(start.elapsed() < DEADLINE, "mosquitto did not stop");
            }
        }
    }

    /// Starts the broker again, same port and configuration.
    pub fn restart(&mut self) {
        let start = Instant::now();
        while !self.run() {
            assert!(start.elapsed() < DEADLINE, "mosquitto did not restart");
            thread::sleep(Duration::from_millis(200));
        }
    }

    pub fn url(&self) -> String {
        format!("mqtt://127.0.0.1:{}", self.port)
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("mosquitto.log")).unwrap_or_default()
    }

    /// Subscribes to `filters` (QoS 1, clean session).
    pub fn subscribe(&self, filters: &[&str]) -> Sub {
        Sub::start(self.port, filters, None)
    }

    /// `mosquitto_pub` of one message, QoS 1.
    pub fn publish(&self, topic: &str, payload: &str, retain: bool) {
        let mut command = Command::new("mosquitto_pub");
        command
            .args(["-h", "127.0.0.1", "-p", &self.port.to_string()])
            .args(["-q", "1", "-t", topic, "-m", payload]);
        if retain {
            command.arg("-r");
        }
        let status = command.status().expect("run mosquitto_pub");
        assert!(status.success(), "mosquitto_pub -t {topic} -m {payload}");
    }
}

pub fn signal(pid: u32, sig: libc::c_int) {
    // SAFETY: plain syscall; the pid is a process this test started.
    unsafe {
        libc::kill(pid as libc::pid_t, sig);
    }
}

/// A message as `mosquitto_sub -F %j` printed it.
#[derive(Debug, Clone, PartialEq)]
pub struct Received {
    pub topic: String,
    pub payload: String,
    pub retain: bool,
}

impl Received {
    /// The payload as JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.payload)
            .unwrap_or_else(|e| panic!("{}: not JSON ({e}): {}", self.topic, self.payload))
    }
}

/// A `mosquitto_sub` process and what it printed.
pub struct Sub {
    _child: ChildGuard,
    out: Capture,
}

impl Sub {
    /// `mosquitto_sub` on `filters`, QoS 1; with `session`, a persistent
    /// session of that client id (it reconnects by itself and the broker
    /// keeps its messages while it is away).
    pub fn start(port: u16, filters: &[&str], session: Option<&str>) -> Sub {
        let mut command = Command::new("mosquitto_sub");
        command
            .args(["-h", "127.0.0.1", "-p", &port.to_string()])
            .args(["-q", "1", "-F", "%j"]);
        if let Some(id) = session {
            command.args(["-c", "-i", id]);
        }
        for filter in filters {
            command.args(["-t", filter]);
        }
        let mut child = ChildGuard::spawn(
            "mosquitto_sub",
            command
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::null()),
        );
        let out = Capture::start(child.child().stdout.take().expect("stdout"));
        // Subscribed once the broker shows it; a short settle is enough on
        // loopback, and every wait below has its own deadline anyway.
        thread::sleep(Duration::from_millis(300));
        Sub { _child: child, out }
    }

    /// Every message so far.
    pub fn messages(&self) -> Vec<Received> {
        self.out
            .text()
            .lines()
            .filter_map(|line| {
                let v: serde_json::Value = serde_json::from_str(line).ok()?;
                Some(Received {
                    topic: v["topic"].as_str()?.to_string(),
                    payload: v["payload"].as_str().unwrap_or_default().to_string(),
                    retain: v["retain"].as_u64() == Some(1) || v["retain"] == true,
                })
            })
            .collect()
    }

    /// Messages on `topic` so far.
    pub fn on(&self, topic: &str) -> Vec<Received> {
        self.messages()
            .into_iter()
            .filter(|m| m.topic == topic)
            .collect()
    }

    /// Waits for a message on `topic` that `accept` takes; returns it.
    #[track_caller]
    pub fn wait(&self, topic: &str, accept: impl Fn(&Received) -> bool) -> Received {
        self.wait_for(&format!("a message on {topic}"), || {
            self.on(topic).into_iter().find(|m| accept(m))
        })
    }

    /// Waits for the payload `payload` on `topic`.
    #[track_caller]
    pub fn wait_payload(&self, topic: &str, payload: &str) -> Received {
        self.wait_for(&format!("'{payload}' on {topic}"), || {
            self.on(topic).into_iter().find(|m| m.payload == payload)
        })
    }

    #[track_caller]
    pub fn wait_for<T>(&self, what: &str, mut found: impl FnMut() -> Option<T>) -> T {
        let start = Instant::now();
        loop {
            if let Some(value) = found() {
                return value;
            }
            if start.elapsed() > DEADLINE {
                let seen: Vec<String> = self
                    .messages()
                    .iter()
                    .rev()
                    .take(30)
                    .map(|m| format!("{} {}", m.topic, m.payload))
                    .collect();
                panic!("timed out waiting for {what}; last messages (newest first):\n{seen:#?}");
            }
            thread::sleep(Duration::from_millis(20));
        }
    }
}

/// Writes `text` to `path` (a test's file).
pub fn write(path: &Path, text: &str) {
    std::fs::write(path, text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

/// The simulated PLC as a process of its own (it outlives a server), with
/// the demo project in its file system.
pub fn plcsim(files: &Path, udp: u16) -> ChildGuard {
    std::fs::write(
        files.join("demo.pub"),
        include_bytes!("../../conf/demo.pub"),
    )
    .unwrap();
    ChildGuard::spawn(
        "plcsim",
        Command::new(plcsim_bin())
            .args(["--bind", &format!("127.0.0.1:{udp}"), "--program", "idle"])
            .arg("--files")
            .arg(files)
            .arg("--pub")
            .arg(files.join("demo.pub"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null()),
    )
}
