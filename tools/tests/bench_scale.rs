//! bench-scale end to end at a small size: the real plcsim, plccoms and
//! Mosquitto processes it starts, every section online, one dead device
//! declared lost while the others stay online, and every change plcsim made
//! delivered (telnet DIFF lines; MQTT messages and history rows). The
//! figures (jitter, CPU) are the bench's business, not asserted here.

use std::net::{Ipv4Addr, TcpListener};
use std::path::Path;
use std::process::Command;

/// The plccoms and plcsim binaries beside bench-scale, up to date.
fn build_servers() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let bin = Path::new(env!("CARGO_BIN_EXE_bench-scale"));
    let mut command = Command::new(cargo);
    command.args([
        "build", "--quiet", "-p", "plccoms", "--bin", "plccoms", "-p", "plcsim", "--bin", "plcsim",
    ]);
    if bin.parent().is_some_and(|d| d.ends_with("release")) {
        command.arg("--release");
    }
    let status = command
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .status()
        .expect("cargo build");
    assert!(status.success(), "cargo build of plccoms and plcsim failed");
}

/// `n` consecutive free TCP ports in 23000..32000 (below the ephemeral
/// range, as the root tests pick theirs).
fn free_block(n: u16) -> u16 {
    let seed = std::process::id() as u64
        ^ std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
    for attempt in 0..5000u64 {
        let base =
            23_000 + ((seed.wrapping_mul(6364136223846793005) + attempt * 7919) % 8_800) as u16;
        if (base..base + n).all(|p| TcpListener::bind((Ipv4Addr::LOCALHOST, p)).is_ok()) {
            return base;
        }
    }
    panic!("no block of {n} free ports");
}

fn bench(args: &[&str]) -> String {
    let devices: u16 = args
        .iter()
        .position(|a| *a == "--devices")
        .and_then(|i| args.get(i + 1)?.parse().ok())
        .expect("--devices");
    let port = free_block(2 * devices + 3).to_string();
    let output = Command::new(env!("CARGO_BIN_EXE_bench-scale"))
        .args(args)
        .args(["--port", &port, "--seconds", "2", "--warmup", "1"])
        .output()
        .expect("run bench-scale");
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "bench-scale {args:?}: {stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

#[test]
fn modbus_and_epsnet_sections_lose_nothing_and_survive_a_dead_device() {
    build_servers();
    let line = bench(&[
        "--protocol",
        "modbus",
        "--devices",
        "6",
        "--tags",
        "50",
        "--period",
        "200",
    ]);
    assert!(
        line.contains("6 sections x 50 tags = 300 at 200 ms"),
        "{line}"
    );
    assert!(line.contains("lost 0 (goal 0)"), "{line}");
    assert!(line.contains("one dead device: lost after"), "{line}");
    assert!(line.contains("others 5/5 online"), "{line}");
    let line = bench(&[
        "--protocol",
        "epsnet",
        "--devices",
        "3",
        "--tags",
        "40",
        "--period",
        "100",
    ]);
    assert!(line.contains("lost 0 (goal 0)"), "{line}");
    assert!(line.contains("others 2/2 online"), "{line}");
}

#[test]
fn mqtt_and_the_historian_lose_nothing() {
    build_servers();
    let line = bench(&[
        "--devices",
        "4",
        "--tags",
        "50",
        "--period",
        "200",
        "--change-rate",
        "0.5",
        "--mqtt",
        "--history",
        "--no-dead",
    ]);
    let changes: u64 = line
        .split("changes made ")
        .nth(1)
        .and_then(|rest| rest.split(',').next()?.parse().ok())
        .unwrap_or_else(|| panic!("changes made in {line}"));
    assert!(changes > 0, "{line}");
    assert!(
        line.contains(&format!("MQTT messages {changes}, lost 0")),
        "{line}"
    );
    assert!(
        line.contains(&format!("history rows {changes}, lost 0")),
        "{line}"
    );
}
