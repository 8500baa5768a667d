//! A section's frame trace: its PLC link's requests and answers and its
//! clients' lines, in the log at trace level under the target
//! [`TARGET`], as a protocol analyser would show them. Off unless the
//! section's `TRACE = Yes`, `SETCONF:trace,Yes` switched it on at run time,
//! or the server runs with `-vv` ([`trace_all`]). The check is one atomic
//! load, so a section that is not traced pays nothing for it.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// The log target of every frame line (the log filter lets it through at
/// trace level; whether a line is written is decided here, per section).
pub const TARGET: &str = "plccoms_frames";

/// Bytes of a frame shown in hex before the rest is summed up.
pub const SHOWN_BYTES: usize = 64;

static ALL: AtomicBool = AtomicBool::new(false);

/// Every section traced (`-vv`).
pub fn trace_all(on: bool) {
    ALL.store(on, Ordering::Relaxed);
}

/// One section's switch, shared by its link and its sessions.
#[derive(Clone, Debug)]
pub struct FrameTrace {
    inner: Arc<Inner>,
}

#[derive(Debug)]
struct Inner {
    section: String,
    on: AtomicBool,
}

impl FrameTrace {
    pub fn new(section: &str, on: bool) -> Self {
        FrameTrace {
            inner: Arc::new(Inner {
                section: section.to_string(),
                on: AtomicBool::new(on),
            }),
        }
    }

    /// Switches this section's trace (SETCONF:trace).
    pub fn set(&self, on: bool) {
        self.inner.on.store(on, Ordering::Relaxed);
    }

    /// Whether this section's own switch is on (`-vv` aside).
    pub fn switched_on(&self) -> bool {
        self.inner.on.load(Ordering::Relaxed)
    }

    /// Whether frame lines are written for this section now.
    pub fn on(&self) -> bool {
        self.switched_on() || ALL.load(Ordering::Relaxed)
    }

    /// A line of the PLC link: `dir` is `->` (to the PLC) or `<-`.
    pub fn plc(&self, dir: &str, what: std::fmt::Arguments<'_>) {
        if self.on() {
            tracing::trace!(target: TARGET, section = %self.inner.section, "PLC {dir} {what}");
        }
    }

    /// A client's line: `dir` is `->` (from the client) or `<-`.
    pub fn client(&self, peer: &std::net::SocketAddr, dir: &str, line: &[u8]) {
        if self.on() {
            tracing::trace!(
                target: TARGET,
                section = %self.inner.section,
                "client {peer} {dir} {}",
                printable(line)
            );
        }
    }
}

/// `bytes` as hex pairs, at most [`SHOWN_BYTES`] of them, then how many
/// more there were.
pub fn hex(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len().min(SHOWN_BYTES) * 3 + 16);
    for (i, b) in bytes.iter().take(SHOWN_BYTES).enumerate() {
        if i > 0 {
            out.push(' ');
        }
        out.push_str(&format!("{b:02x}"));
    }
    if bytes.len() > SHOWN_BYTES {
        out.push_str(&format!(" ... (+{} bytes)", bytes.len() - SHOWN_BYTES));
    }
    out
}

/// A line as text: printable ASCII as it is, line ends dropped, anything
/// else as `\xNN`, long lines cut (a client's line can be 100 KB).
pub fn printable(line: &[u8]) -> String {
    const SHOWN: usize = 200;
    let line = line
        .strip_suffix(b"\n")
        .map(|l| l.strip_suffix(b"\r").unwrap_or(l))
        .unwrap_or(line);
    let mut out = String::with_capacity(line.len().min(SHOWN) + 16);
    for &b in line.iter().take(SHOWN) {
        if (0x20..0x7f).contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("\\x{b:02x}"));
        }
    }
    if line.len() > SHOWN {
        out.push_str(&format!(" ... (+{} bytes)", line.len() - SHOWN));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_is_cut_after_the_shown_bytes() {
        assert_eq!(hex(&[0x01, 0xab]), "01 ab");
        let long = hex(&[0u8; 70]);
        assert!(long.ends_with("00 ... (+6 bytes)"), "{long}");
    }

    #[test]
    fn lines_are_shown_printable() {
        assert_eq!(printable(b"GET:tim\r\n"), "GET:tim");
        assert_eq!(printable(b"a\x01\xec"), "a\\x01\\xec");
    }

    #[test]
    fn the_switch_is_per_section() {
        let a = FrameTrace::new("A", false);
        let b = FrameTrace::new("B", true);
        assert!(!a.switched_on() && b.switched_on());
        a.clone().set(true);
        assert!(a.switched_on());
    }
}
