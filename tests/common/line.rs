//! A serial line for tests: a pty pair made by socat (Debian's `socat`,
//! installed by `.ci/run`), each end a real tty device under a fixed path,
//! as a USB adapter would be.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use super::process::{which, ChildGuard};

pub struct PtyLine {
    /// The simulated PLC's end.
    pub plc: PathBuf,
    /// The server's end (SERIAL_DEVICE).
    pub server: PathBuf,
    dir: tempfile::TempDir,
    socat: Option<ChildGuard>,
}

impl PtyLine {
    pub fn new() -> PtyLine {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut line = PtyLine {
            plc: dir.path().join("plc"),
            server: dir.path().join("server"),
            dir,
            socat: None,
        };
        line.plug();
        line
    }

    /// Starts socat: both ends appear (again) under their paths.
    pub fn plug(&mut self) {
        let socat = which("socat").expect("socat is not installed (apt-get install socat)");
        let end = |path: &PathBuf| format!("pty,raw,echo=0,link={}", path.display());
        let child = ChildGuard::spawn(
            "socat",
            Command::new(socat)
                .arg(end(&self.plc))
                .arg(end(&self.server))
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::null()),
        );
        self.socat = Some(child);
        let start = Instant::now();
        while !(self.plc.exists() && self.server.exists()) {
            assert!(
                start.elapsed() < Duration::from_secs(10),
                "socat made no pty pair in {}",
                self.dir.path().display()
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Both devices disappear, as an unplugged USB adapter's: its links
    /// go first, then socat (killed, it could not remove them; a link
    /// left dangling could meanwhile name another test's new pty, which
    /// the server would open instead).
    pub fn unplug(&mut self) {
        let _ = std::fs::remove_file(&self.plc);
        let _ = std::fs::remove_file(&self.server);
        self.socat = None;
        assert!(!self.plc.exists() && !self.server.exists());
    }

    pub fn server_device(&self) -> String {
        self.server.display().to_string()
    }

    pub fn plc_device(&self) -> String {
        self.plc.display().to_string()
    }
}
