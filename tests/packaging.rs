//! What the packaging ships, checked with the real tools: the systemd
//! unit's hardening as `systemd-analyze security` rates it. (The logrotate
//! snippet runs in `tests/process.rs`; the .deb is built, installed and
//! started by `packaging/deb-smoke`, from `.ci/run`.)

use std::path::Path;
use std::process::Command;

const UNIT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/conf/plccoms.service");

/// `systemd-analyze security --offline=true` on the shipped unit: under 3
/// ("OK"), while what the server needs stays allowed.
#[test]
fn the_unit_is_hardened_under_3_and_keeps_what_the_server_needs() {
    let out = Command::new("systemd-analyze")
        .args(["security", "--offline=true", "--no-pager", UNIT])
        .output()
        .expect("systemd-analyze is not installed (Debian: apt-get install systemd; .ci/run does)");
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    let level: f64 = text
        .lines()
        .find_map(|l| {
            l.split("Overall exposure level for plccoms.service:")
                .nth(1)
        })
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no exposure level in:\n{text}"));
    assert!(level < 3.0, "exposure {level}:\n{text}");
    eprintln!("systemd-analyze security: {level}");

    let unit = std::fs::read_to_string(UNIT).unwrap();
    let settings: Vec<&str> = unit
        .lines()
        .filter(|l| !l.starts_with('#') && l.contains('='))
        .collect();
    let has = |line: &str| settings.contains(&line);
    // COMM_SCHED_PRI: real-time priority for the poll threads.
    assert!(has("AmbientCapabilities=CAP_SYS_NICE"), "{unit}");
    assert!(has("CapabilityBoundingSet=CAP_SYS_NICE"), "{unit}");
    assert!(!settings.iter().any(|l| l.starts_with("RestrictRealtime=")));
    // PLCs and clients anywhere; the SIMULATOR's UDP on loopback.
    for open in ["PrivateNetwork=", "IPAddressDeny=", "PrivateUsers="] {
        assert!(!settings.iter().any(|l| l.starts_with(open)), "{open}");
    }
    assert!(
        has("RestrictAddressFamilies=AF_INET AF_INET6 AF_UNIX"),
        "{unit}"
    );
    // A writable working folder and log folder; the rest read-only.
    assert!(has("ProtectSystem=strict") && has("StateDirectory=plccoms"));
    assert!(has("WorkingDirectory=/var/lib/plccoms") && has("LogsDirectory=plccoms"));
    assert!(Path::new(UNIT).with_file_name("plccoms.logrotate").exists());
}

/// The Dockerfile turns the example's loopback-only demo into one that
/// listens on the container's interfaces by rewriting one line: that line
/// must stay as the Dockerfile expects it (the image is not built in CI).
#[test]
fn the_dockerfile_finds_the_line_it_rewrites() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let example = std::fs::read_to_string(root.join("PLCComS.ini.example")).unwrap();
    let dockerfile = std::fs::read_to_string(root.join("Dockerfile")).unwrap();
    assert!(dockerfile.contains(r"s/^IPADDR_LOCAL  = 127\.0\.0\.1 .*/"));
    assert_eq!(
        example
            .lines()
            .filter(|l| l.starts_with("IPADDR_LOCAL  = 127.0.0.1 "))
            .count(),
        1,
        "{example}"
    );
    assert!(dockerfile.contains("USER nonroot"));
}
