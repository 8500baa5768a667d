//! What the serial-line benchmarks share: a socat pty pair, and a client
//! that enables every variable of a section and drains its DIFFs.

use std::path::{Path, PathBuf};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// A socat pty pair in `dir`: `plc` for the simulator, `server` for the
/// section's SERIAL_DEVICE. Stopped when dropped.
pub struct PtyPair {
    pub plc: PathBuf,
    pub server: PathBuf,
    socat: std::process::Child,
}

impl PtyPair {
    pub async fn new(dir: &Path) -> PtyPair {
        let (plc, server) = (dir.join("plc"), dir.join("server"));
        let end = |p: &Path| format!("pty,raw,echo=0,link={}", p.display());
        let socat = std::process::Command::new("socat")
            .args([end(&plc), end(&server)])
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("socat (apt-get install socat)");
        while !(plc.exists() && server.exists()) {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        PtyPair { plc, server, socat }
    }
}

impl Drop for PtyPair {
    fn drop(&mut self) {
        let _ = self.socat.kill();
        let _ = self.socat.wait();
    }
}

/// `EN:*` on the section at `port`, its DIFFs drained in the background.
pub async fn enable_all(port: u16) {
    let mut client = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
    client.write_all(b"EN:*\n").await.unwrap();
    tokio::spawn(async move {
        let mut buf = vec![0u8; 1 << 16];
        while matches!(client.read(&mut buf).await, Ok(n) if n > 0) {}
    });
}
