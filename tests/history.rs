//! The historian end to end, with the built `plccoms` and `plcsim`
//! binaries as processes: values written through SET recorded with their
//! poll's time and quality, exported by `plccoms history` and read back by
//! pandas (CSV, JSON, Parquet) with exact values; PLC-stamped samples and
//! event capture; an outage visible as one; kill -9 under heavy writing and
//! a restart (files pass `PRAGMA integrity_check`, at most the sync interval
//! lost); a full disk (a small tmpfs when the test may mount one, else the
//! size limit) without a crash, and recording resuming when space returns.
//!
//! pandas and pyarrow must be installed (`.ci/run` installs them).

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use common::process::{free_port, free_udp_port, plcsim_bin, ChildGuard, PLCCOMS};

/// Longest wait for anything: the machine is shared and may be slow.
const DEADLINE: Duration = Duration::from_secs(30);

fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_millis() as i64
}

#[track_caller]
fn wait_for(what: &str, mut ready: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ready() {
        assert!(start.elapsed() < DEADLINE, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A simulated PLC process running `pub_text`.
struct Plc {
    _child: ChildGuard,
    udp: u16,
    control: u16,
}

impl Plc {
    fn start(dir: &Path, pub_text: &[u8], args: &[&str]) -> Plc {
        std::fs::write(dir.join("plc.pub"), pub_text).unwrap();
        let udp = free_udp_port();
        let control = free_port();
        let child = ChildGuard::spawn(
            "plcsim",
            Command::new(plcsim_bin())
                .arg("--bind")
                .arg(format!("127.0.0.1:{udp}"))
                .arg("--pub")
                .arg(dir.join("plc.pub"))
                .arg("--control")
                .arg(format!("127.0.0.1:{control}"))
                .args(["--cycle", "100"])
                .args(args)
                .stdout(Stdio::null())
                .stderr(Stdio::null()),
        );
        wait_for("plcsim's control port", || {
            TcpStream::connect(("127.0.0.1", control)).is_ok()
        });
        Plc {
            _child: child,
            udp,
            control,
        }
    }

    fn control(&self, command: &str) {
        let stream = TcpStream::connect(("127.0.0.1", self.control)).unwrap();
        writeln!(&stream, "{command}").unwrap();
        let mut answer = String::new();
        BufReader::new(&stream).read_line(&mut answer).unwrap();
        assert!(answer.starts_with("OK"), "{command}: {answer}");
    }
}

/// `plccoms -c plccoms.ini` in `dir`, its log in `plccoms.log` (appended).
struct Server {
    child: ChildGuard,
    dir: PathBuf,
    port: u16,
}

impl Server {
    fn start(dir: &Path, plc: &Plc, section: &str, global: &str) -> Server {
        let port = free_port();
        let ini = format!(
            "[*]\nCOMM_LOOP_DELAY = 100\n{global}\n\n[Hist]\nIPADDR = 127.0.0.1\nIPADDR_LOCAL = 127.0.0.1\n\
             EPSPORT = {}\nSERVER_PORT = {port}\nPUBFILE = //plc.pub\nPUBFILE_CRC = No\nPUBFILE_WRITE = No\n{section}\n",
            plc.udp
        );
        std::fs::write(dir.join("plccoms.ini"), ini).unwrap();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(dir.join("plccoms.log"))
            .unwrap();
        let child = ChildGuard::spawn(
            "plccoms",
            Command::new(PLCCOMS)
                .args(["-c", "plccoms.ini"])
                .current_dir(dir)
                .env_remove("RUST_LOG")
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(log),
        );
        let server = Server {
            child,
            dir: dir.to_path_buf(),
            port,
        };
        wait_for("plccoms to accept", || {
            TcpStream::connect(("127.0.0.1", port)).is_ok()
        });
        server
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.join("plccoms.log")).unwrap_or_default()
    }

    /// Sends a request, returns the first answer line.
    fn ask(&self, request: &[u8]) -> String {
        let stream = TcpStream::connect(("127.0.0.1", self.port)).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        (&stream).write_all(request).unwrap();
        (&stream).write_all(b"\r\n").unwrap();
        let mut line = Vec::new();
        if let Err(e) = BufReader::new(&stream).read_until(b'\n', &mut line) {
            panic!("reading the answer: {e}; the server's log:\n{}", self.log());
        }
        String::from_utf8_lossy(&line).trim_end().to_string()
    }

    fn getinfo(&self, key: &str) -> String {
        self.ask(format!("GETINFO:{key}").as_bytes())
    }

    /// SIGTERM and wait: the historian commits and closes its files.
    fn stop(mut self) {
        let pid = self.child.child().id();
        // SAFETY: a plain syscall on our own child.
        unsafe { libc::kill(pid as libc::pid_t, libc::SIGTERM) };
        assert!(
            self.child.wait_timeout(DEADLINE).is_some(),
            "plccoms did not stop"
        );
    }

    fn kill9(mut self) {
        let pid = self.child.child().id();
        // SAFETY: a plain syscall on our own child.
        unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
        self.child.wait_timeout(DEADLINE);
    }
}

/// `plccoms history -c plccoms.ini --section Hist ...` in `dir`.
fn history(dir: &Path, args: &[&str]) -> String {
    let out = Command::new(PLCCOMS)
        .args(["history", "-c", "plccoms.ini", "--section", "Hist"])
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "plccoms history {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn day_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir.join("history/Hist"))
        .map(|d| {
            d.filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|e| e == "sqlite"))
                .collect()
        })
        .unwrap_or_default();
    files.sort();
    files
}

fn integrity(path: &Path) -> String {
    let conn = rusqlite::Connection::open(path).unwrap();
    conn.query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .unwrap()
}

/// Runs a Python script with arguments; panics with its output if it
/// fails.
fn python(script: &str, args: &[&str]) {
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "python failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

const TYPED_PUB: &str = "\
 V_BOOL R B 0 .0 BOOL PUB_INOUT
 TRIG R B 1 .0 BOOL PUB_INOUT
 V_INT R B 2 INT PUB_INOUT
 V_DINT R B 4 DINT PUB_INOUT
 V_UDINT R B 8 UDINT PUB_INOUT
 V_ULINT R B 16 ULINT PUB_INOUT
 V_REAL R F 24 REAL PUB_INOUT
 V_LREAL R F 28 LREAL PUB_INOUT
 V_WORD R B 36 WORD PUB_INOUT
 V_STR R B 40 STRING[16] PUB_INOUT
 V_DT R B 60 DT PUB_INOUT
 STAMP R B 72 LINT PUB_INOUT
 EV R B 80 INT PUB_INOUT
";

/// Per variable: its kind for the comparison in Python, and the values SET
/// in three rounds (as SET takes them, and as expected back).
fn typed_values() -> Vec<(&'static str, &'static str, [String; 3], [String; 3])> {
    let same = |a: &str, b: &str, c: &str| [a.to_string(), b.to_string(), c.to_string()];
    let dt = |s: f64| s.to_bits().to_string();
    vec![
        ("V_BOOL", "int", same("1", "0", "1"), same("1", "0", "1")),
        (
            "V_INT",
            "int",
            same("-32768", "5", "32767"),
            same("-32768", "5", "32767"),
        ),
        (
            "V_DINT",
            "int",
            same("-2147483648", "123456", "2147483647"),
            same("-2147483648", "123456", "2147483647"),
        ),
        (
            "V_UDINT",
            "int",
            same("4294967295", "0", "7"),
            same("4294967295", "0", "7"),
        ),
        (
            "V_ULINT",
            "int",
            same("18446744073709551615", "9007199254740993", "3"),
            same("18446744073709551615", "9007199254740993", "3"),
        ),
        (
            "V_REAL",
            "f32",
            same("0.1", "-3.4028235e38", "1.17549435e-38"),
            same("0.1", "-3.4028235e38", "1.17549435e-38"),
        ),
        (
            "V_LREAL",
            "f64",
            same("0.1", "1e-300", "-2.5"),
            same("0.1", "1e-300", "-2.5"),
        ),
        (
            "V_WORD",
            "int",
            same("65535", "1", "2"),
            same("65535", "1", "2"),
        ),
        (
            "V_STR",
            "str",
            same("\"a,\"b\"\"", "\"\"", "\"\u{9E}lu\u{9D}ou\u{E8}k\u{FD}\""),
            same("a,\"b\"", "", "žluťoučký"),
        ),
        (
            "V_DT",
            "str",
            [
                dt(1_700_000_000.0),
                dt(1_700_000_001.0),
                dt(1_800_000_000.0),
            ],
            same(
                "2023-11-14T22:13:20.000Z",
                "2023-11-14T22:13:21.000Z",
                "2027-01-15T08:00:00.000Z",
            ),
        ),
    ]
}

/// SET with the value's characters as cp1250 bytes (the test writes them
/// as the chars of those code points).
fn set(server: &Server, name: &str, value: &str) {
    let mut request = format!("SET:{name},").into_bytes();
    request.extend(value.chars().map(|c| c as u32 as u8));
    let answer = server.ask(&request);
    assert!(
        answer.starts_with("DIFF:"),
        "SET:{name},{value} -> {answer}"
    );
}

const CHECK_EXPORTS: &str = r#"
import json, sys, math
import numpy as np, pandas as pd, pyarrow.parquet as pq
expected = json.loads(open(sys.argv[1]).read())
d = sys.argv[2]

def same(kind, got, want):
    if kind == "int":
        return int(got) == int(want)
    if kind == "f32":
        return np.float32(float(got)) == np.float32(float(want))
    if kind == "f64":
        return float(got) == float(want)
    return str(got) == str(want)

def collapse(values):
    out = []
    for v in values:
        if not out or out[-1] != v:
            out.append(v)
    return out

def check(label, series_by_name, kind_override=None):
    for name, spec in expected.items():
        kind = spec["kind"]
        got = collapse([v for v in series_by_name(name)])
        want = spec["values"]
        # The first sample is the PLC's memory before the SETs (zero).
        assert len(got) == len(want) + 1, (label, name, got, want)
        for g, w in zip(got[1:], want):
            assert same(kind, g, w), (label, name, g, w)

def column(n):
    """Numbers are in `value`, strings and times in `text`."""
    return "text" if expected[n]["kind"] == "str" else "value"

# As text, for exact integers beyond 2^53; then as pandas types it.
long = pd.read_csv(d + "/long.csv", dtype={"value": str, "text": str}, keep_default_na=False)
assert list(long.columns) == ["time", "name", "value", "text", "quality"]
samples = long[~long["name"].str.startswith("__")]
assert set(samples["quality"]) == {"good"}, set(samples["quality"])
server = long[long["name"] == "__SERVER"]
assert list(server["text"]) == ["start", "stop"] and set(server["quality"]) == {"stopped"}, server
pd.to_datetime(long["time"], format="ISO8601", utc=True)
check("csv", lambda n: list(long[long["name"] == n][column(n)]))
typed = pd.read_csv(d + "/long.csv", parse_dates=["time"])
assert str(typed["value"].dtype) == "float64", typed.dtypes
assert str(typed["time"].dtype).startswith("datetime64"), typed.dtypes

wide = pd.read_csv(d + "/wide.csv", dtype=str, keep_default_na=False)
assert list(wide.columns[:2]) == ["time", "quality"], list(wide.columns)
assert set(wide["quality"]) == {"good", "stopped"}, set(wide["quality"])
# An empty string and no value read alike in pandas: V_STR is checked in
# the other forms.
saved = expected
expected = {k: v for k, v in saved.items() if k != "V_STR"}
check("wide csv", lambda n: [v for v in wide[n] if v != ""])
expected = saved
typed = pd.read_csv(d + "/wide.csv")
for n, spec in expected.items():
    if n == "V_ULINT":
        continue  # above 2^63 with gaps: pandas needs its dtype named
    numeric = pd.api.types.is_numeric_dtype(typed[n])
    assert numeric == (spec["kind"] != "str"), (n, typed[n].dtype)
typed = pd.read_csv(d + "/wide.csv", dtype={"V_ULINT": "UInt64"})
assert 18446744073709551615 in list(typed["V_ULINT"].dropna()), typed["V_ULINT"]

js = json.load(open(d + "/long.json"))
assert all(list(r) == ["time", "name", "value", "text", "quality"] for r in js), js[0]
check("json", lambda n: [r[column(n)] for r in js if r["name"] == n])
assert all(isinstance(r["value"], (int, float)) for r in js if r["name"] == "V_LREAL")

lp = pq.read_table(d + "/long.parquet").to_pandas()
assert str(lp["time"].dtype).startswith("datetime64"), lp["time"].dtype
def long_parquet(n):
    rows = lp[lp["name"] == n]
    if expected[n]["kind"] == "str":
        return list(rows["text"].fillna(""))
    return list(rows["value"])
expected_long = {k: v for k, v in expected.items() if k != "V_ULINT"}  # beyond 2^53 in a double
saved = expected
expected = expected_long
check("long parquet", long_parquet)
expected = saved

wp = pq.read_table(d + "/wide.parquet")
types = {f.name: str(f.type) for f in wp.schema}
assert types["quality"] == "string", types
assert types["V_REAL"] == "float", types
assert types["V_ULINT"] == "uint64", types
assert types["V_BOOL"] == "bool", types
assert types["V_DT"].startswith("timestamp[ms"), types
def wide_parquet(n):
    col = [v for v in wp.column(n).to_pylist() if v is not None]
    if n == "V_DT":
        return [t.strftime("%Y-%m-%dT%H:%M:%S.000Z") for t in col]
    if n == "V_BOOL":
        return [int(v) for v in col]
    if n == "V_REAL":
        return [str(np.float32(v)) for v in col]
    return list(col)
check("wide parquet", wide_parquet)

# The PLC-stamped variable carries the PLC's time.
ev = long[long["name"] == "EV"]
assert "2023-11-14T22:13:20.123Z" in list(ev["time"]), list(ev["time"])
print("ok")
"#;

#[test]
fn values_recorded_with_poll_time_and_read_back_exactly_by_pandas() {
    let dir = tempfile::tempdir().unwrap();
    let plc = Plc::start(dir.path(), TYPED_PUB.as_bytes(), &["--program", "idle"]);
    let section = "HISTORY = V_*\nHISTORY_STAMP = EV:STAMP\nHISTORY_TRIGGER = TRIG\nHISTORY_PRE = 2\nHISTORY_POST = 2";
    let server = Server::start(dir.path(), &plc, section, "");
    let values = typed_values();
    // Let the first poll record the initial values.
    wait_for("the first commit", || {
        server
            .getinfo("HISTORY_SAMPLES")
            .contains(&format!("{} written", values.len() + 1))
            || !day_files(dir.path()).is_empty()
    });
    std::thread::sleep(Duration::from_millis(300));
    for round in 0..3 {
        for (name, _, set_values, _) in &values {
            set(&server, name, &set_values[round]);
        }
        std::thread::sleep(Duration::from_millis(250));
    }
    set(&server, "STAMP", "1700000000123");
    set(&server, "EV", "5");
    assert_eq!(server.getinfo("HISTORY"), "GETINFO:HISTORY,recording");
    let info = server.ask(b"GETINFO:");
    assert!(info.starts_with("GETINFO:VERSION,"), "{info}");
    // Event capture: V_WORD does not change, yet is recorded at every
    // cycle from 2 before the edge to 2 after.
    let before = now_ms();
    set(&server, "TRIG", "1");
    std::thread::sleep(Duration::from_millis(1000));
    server.stop();

    let files = day_files(dir.path());
    assert!(!files.is_empty());
    let conn = rusqlite::Connection::open(files.last().unwrap()).unwrap();
    // Poll times: samples of one poll share its time, polls ~100 ms apart
    // (commits are a second apart).
    let word_times: Vec<i64> = conn
        .prepare(
            "SELECT time_ms FROM history WHERE name = 'V_WORD' AND time_ms >= ?1 ORDER BY time_ms",
        )
        .unwrap()
        .query_map([before - 300], |r| r.get(0))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert!(word_times.len() >= 5, "capture: {word_times:?}");
    for pair in word_times.windows(2) {
        let gap = pair[1] - pair[0];
        assert!((30..=400).contains(&gap), "capture cycles: {word_times:?}");
    }
    let captures: i64 = conn
        .query_row(
            "SELECT count(*) FROM events WHERE kind = 'capture'",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(captures, 1);
    let bool_and_word_at_capture: i64 = conn
        .query_row(
            "SELECT count(*) FROM history a JOIN history b ON a.time_ms = b.time_ms \
             WHERE a.name = 'V_BOOL' AND b.name = 'V_WORD' AND a.time_ms >= ?1",
            [before - 300],
            |r| r.get(0),
        )
        .unwrap();
    assert!(bool_and_word_at_capture >= 5, "one time per poll for all");
    assert_eq!(integrity(files.last().unwrap()), "ok");
    drop(conn);

    // Exports, read back by pandas.
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let o = |name: &str| out.join(name).to_string_lossy().into_owned();
    for (format, wide, file) in [
        ("csv", false, "long.csv"),
        ("csv", true, "wide.csv"),
        ("json", false, "long.json"),
        ("parquet", false, "long.parquet"),
        ("parquet", true, "wide.parquet"),
    ] {
        let mut args = vec!["--from", "-1h", "--format", format, "--out"];
        let path = o(file);
        args.push(&path);
        if wide {
            args.push("--wide");
        }
        history(dir.path(), &args);
    }
    // Standard output works too, and the masks select.
    let csv = history(dir.path(), &["--vars", "v_int", "--from", "-1h"]);
    assert!(csv.starts_with("time,name,value,text,quality\n"));
    assert!(
        csv.lines()
            .skip(1)
            .all(|l| l.contains(",V_INT,") || l.contains(",__SERVER,")),
        "{csv}"
    );
    let expected: serde_json::Map<String, serde_json::Value> = values
        .iter()
        .map(|(name, kind, _, want)| {
            (
                name.to_string(),
                serde_json::json!({"kind": kind, "values": want}),
            )
        })
        .collect();
    let expected_path = out.join("expected.json");
    std::fs::write(&expected_path, serde_json::to_string(&expected).unwrap()).unwrap();
    python(
        CHECK_EXPORTS,
        &[&expected_path.to_string_lossy(), &out.to_string_lossy()],
    );
}

/// A public file of `n` UDINTs `ANIM_nnnnn` for `plcsim --animate`.
fn animated_pub(n: usize) -> Vec<u8> {
    plcsim::genpub::generate(&plcsim::genpub::Layout {
        vars: n,
        animated: n,
        setvars: 0,
    })
}

#[test]
fn kill_9_under_heavy_writing_loses_at_most_the_sync_interval() {
    let dir = tempfile::tempdir().unwrap();
    let plc = Plc::start(
        dir.path(),
        &animated_pub(2000),
        &["--program", "idle", "--animate", "ANIM_*"],
    );
    let server = Server::start(dir.path(), &plc, "HISTORY = ANIM_*", "HISTORY_SYNC = 1");
    wait_for("samples written", || {
        server
            .getinfo("HISTORY_SAMPLES")
            .split(' ')
            .next()
            .and_then(|s| s.rsplit(',').next())
            .and_then(|n| n.parse::<u64>().ok())
            .is_some_and(|n| n > 50_000)
    });
    let killed = now_ms();
    server.kill9();
    let file = day_files(dir.path()).pop().unwrap();
    assert_eq!(integrity(&file), "ok");
    let last: i64 = rusqlite::Connection::open(&file)
        .unwrap()
        .query_row("SELECT max(time_ms) FROM history", [], |r| r.get(0))
        .unwrap();
    let lost = killed - last;
    eprintln!("kill -9: the last sample on disk is {lost} ms before the kill (HISTORY_SYNC = 1 s)");
    // One sync interval, the poll and the commit itself, with room for a
    // loaded machine.
    assert!(lost <= 4_000, "lost {lost} ms");

    // A restart goes on in the same file.
    let server = Server::start(dir.path(), &plc, "HISTORY = ANIM_*", "HISTORY_SYNC = 1");
    let restarted = now_ms();
    wait_for("new samples after the restart", || {
        let conn = rusqlite::Connection::open(&file).unwrap();
        conn.query_row("SELECT max(time_ms) FROM history", [], |r| {
            r.get::<_, i64>(0)
        })
        .unwrap()
            > restarted
    });
    server.stop();
    assert_eq!(integrity(&file), "ok");
    let starts: i64 = rusqlite::Connection::open(&file)
        .unwrap()
        .query_row(
            "SELECT count(*) FROM events WHERE kind = 'start'",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(starts, 2);
}

/// The first number of a GETINFO answer (`HISTORY_SAMPLES,12 written, ...`).
fn first_number(answer: &str) -> u64 {
    answer
        .split(' ')
        .next()
        .and_then(|s| s.rsplit(',').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or(0)
}

/// Samples in a day file: rows and packed.
fn stored_samples(file: &Path) -> i64 {
    rusqlite::Connection::open(file)
        .unwrap()
        .query_row(
            "SELECT (SELECT count(*) FROM samples) + (SELECT coalesce(sum(samples), 0) FROM blocks)",
            [],
            |r| r.get(0),
        )
        .unwrap()
}

#[test]
fn packing_under_heavy_writing_survives_kill_9_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let plc = Plc::start(
        dir.path(),
        &animated_pub(2000),
        &["--program", "idle", "--animate", "ANIM_*"],
    );
    let global = "HISTORY_SYNC = 1\nHISTORY_COMPACT = 1";
    let server = Server::start(dir.path(), &plc, "HISTORY = ANIM_*", global);
    wait_for("samples packed", || {
        first_number(&server.getinfo("HISTORY_PACKED")) > 60_000
    });
    let written = first_number(&server.getinfo("HISTORY_SAMPLES"));
    server.kill9();
    let file = day_files(dir.path()).pop().unwrap();
    assert_eq!(integrity(&file), "ok");
    // What was reported written is on disk, rows and blocks together.
    let stored = stored_samples(&file);
    assert!(
        stored as u64 >= written,
        "{stored} stored of {written} written"
    );

    // A restart goes on packing the same file, where it was.
    let server = Server::start(dir.path(), &plc, "HISTORY = ANIM_*", global);
    wait_for("packing after the restart", || {
        first_number(&server.getinfo("HISTORY_PACKED")) > 10_000
    });
    server.stop();
    assert_eq!(integrity(&file), "ok");
    let (blocks, rows): (i64, i64) = rusqlite::Connection::open(&file)
        .unwrap()
        .query_row(
            "SELECT (SELECT count(*) FROM blocks), (SELECT count(*) FROM samples)",
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    assert!(blocks > 1, "{blocks} blocks");

    // Read back through rows and blocks: every sample once, each
    // variable's in time order, the count the file holds.
    let csv = history(dir.path(), &["--vars", "*", "--from", "-1d", "--to", "now"]);
    let mut last: std::collections::HashMap<&str, &str> = Default::default();
    let (mut n, mut sum) = (0i64, 0u128);
    // (The gap rows, `__SERVER` and the like, are no samples.)
    for line in csv.lines().skip(1).filter(|l| !l.contains(",__")) {
        let mut fields = line.split(',');
        let (time, name) = (fields.next().unwrap(), fields.next().unwrap());
        sum += fields.next().unwrap().parse::<u128>().unwrap();
        if let Some(previous) = last.insert(name, time) {
            assert!(previous < time, "{name}: {previous} then {time}");
        }
        n += 1;
    }
    assert_eq!(n, stored_samples(&file), "{blocks} blocks and {rows} rows");
    // The file alone, read by the documented format's Python reader, holds
    // the same samples.
    python(
        r#"
import sys
sys.path.insert(0, sys.argv[1])
from history_read import samples
s = samples(sys.argv[2])
assert len(s) == int(sys.argv[3]), (len(s), sys.argv[3])
assert sum(v for _, _, v, _, _ in s) == int(sys.argv[4])
assert all(a[0] <= b[0] for a, b in zip(s, s[1:]))
"#,
        &[
            &format!("{}/tools", env!("CARGO_MANIFEST_DIR")),
            file.to_str().unwrap(),
            &n.to_string(),
            &sum.to_string(),
        ],
    );
    eprintln!(
        "packed: {blocks} blocks, {rows} rows left, {} bytes for {n} samples",
        std::fs::metadata(&file).unwrap().len()
    );
}

/// The ISO 8601 form of UTC ms, as `--from`/`--to` take it.
fn iso(ms: i64) -> String {
    chrono::DateTime::from_timestamp_millis(ms)
        .unwrap()
        .format("%Y-%m-%dT%H:%M:%S%.3fZ")
        .to_string()
}

/// The README's recipe (History, "Gaps"), run on the exports of a
/// recording with a link outage and a server stop and start: pandas reads
/// the values as numbers, the outage rows are there, and a forward fill
/// that keeps to good stretches leaves NaN across every gap (a plain one
/// would not). duckdb and polars, where installed, type `value` as numbers
/// too.
const CHECK_GAPS: &str = r#"
import sys
import pandas as pd
d = sys.argv[1]

# Long CSV: typed as read; the gaps as rows.
long = pd.read_csv(d + "/long.csv", parse_dates=["time"])
assert str(long["value"].dtype) in ("int64", "float64"), long.dtypes
assert str(long["time"].dtype).startswith("datetime64"), long.dtypes
link = long[long["name"] == "__LINK"]
assert list(link["text"]) == ["link_lost", "link_restored"], link
assert set(link["quality"]) == {"link_lost"} and link["value"].isna().all(), link
server = long[long["name"] == "__SERVER"]
assert list(server["text"]) == ["start", "stop", "start", "stop"], server
assert set(server["quality"]) == {"stopped"} and server["value"].isna().all(), server
lost = long[(long["name"] == "ANIM_00003") & (long["quality"] == "link_lost")]
assert len(lost) == 1, lost

def recipe(wide):
    """The README's recipe: gaps NaN by quality, forward fill within good
    stretches only."""
    values = wide.columns.drop(["time", "quality"])
    gap = wide["quality"] != "good"
    wide.loc[gap, values] = float("nan")
    return wide[values].groupby(gap.cumsum()).ffill(), values

def check_wide(wide, label):
    filled, values = recipe(wide.copy())
    for c in values:
        assert pd.api.types.is_numeric_dtype(wide[c]), (label, c, wide[c].dtype)
    gaps = wide.index[wide["quality"] != "good"]
    assert list(wide.loc[gaps, "quality"]) == \
        ["stopped", "link_lost", "link_lost", "stopped", "stopped", "stopped"], (label, wide.loc[gaps])
    # From each gap's start to its end, the fill leaves NaN (a plain fill
    # carries the last value across).
    for start, end in [(gaps[1], gaps[2]), (gaps[3], gaps[4])]:
        inside = filled.loc[start:end]
        assert inside.isna().all().all(), (label, inside)
        assert not wide[values].ffill().loc[start:end].isna().all().all(), label
    # After each gap the next good row has every value again.
    for g in gaps[[0, 2, 4]]:
        after = filled.loc[g + 1]
        assert wide.loc[g + 1, "quality"] == "good" and after.notna().all(), (label, wide.loc[g:g + 2])

check_wide(pd.read_csv(d + "/wide.csv", parse_dates=["time"]), "wide csv")

# Parquet: the same rows, typed.
lp = pd.read_parquet(d + "/long.parquet")
assert str(lp["value"].dtype) == "float64", lp.dtypes
assert list(lp[lp["name"] == "__SERVER"]["text"]) == ["start", "stop", "start", "stop"]
assert list(lp[lp["name"] == "__LINK"]["quality"]) == ["link_lost", "link_lost"]
assert len(lp) == len(long)
check_wide(pd.read_parquet(d + "/wide.parquet"), "wide parquet")

try:
    import duckdb
except ImportError:
    print("duckdb is not installed: its check is skipped")
else:
    # fetchall: duckdb 2 dropped fetchone from relations.
    [(kind, top)] = duckdb.sql(
        f"SELECT typeof(max(value)), max(value) FROM read_csv_auto('{d}/long.csv')").fetchall()
    assert kind in ("BIGINT", "DOUBLE"), kind
    assert top == long["value"].max(), (top, long["value"].max())
try:
    import polars as pl
except ImportError:
    print("polars is not installed: its check is skipped")
else:
    p = pl.read_csv(d + "/long.csv", try_parse_dates=True)
    assert p["value"].dtype.is_numeric() and p["text"].dtype == pl.Utf8, p.schema
print("ok")
"#;

/// A link outage and a server stop and start are gaps in every export, as
/// rows a forward fill cannot mistake for a flat line; `/api/history` gives
/// the rows of `plccoms history` byte for byte.
#[test]
fn outages_and_server_downtime_are_gaps_in_every_export() {
    let dir = tempfile::tempdir().unwrap();
    let began = now_ms();
    let plc = Plc::start(
        dir.path(),
        &animated_pub(10),
        &["--program", "idle", "--animate", "ANIM_*"],
    );
    let section = "HISTORY = ANIM_*\nEPSTOUT = 200\nEPSTOUT_STEP = 0";
    let server = Server::start(dir.path(), &plc, section, "");
    std::thread::sleep(Duration::from_millis(500));
    plc.control("loss 1");
    wait_for("the link to be declared lost", || {
        server.log().contains("PLC lost")
    });
    std::thread::sleep(Duration::from_millis(500));
    plc.control("loss 0");
    wait_for("the link to return", || {
        server.log().contains("connected again")
    });
    std::thread::sleep(Duration::from_millis(500));
    server.stop();
    let stopped = now_ms();
    std::thread::sleep(Duration::from_millis(300));
    let http = free_port();
    let server = Server::start(dir.path(), &plc, section, &format!("HTTP_PORT = {http}"));
    std::thread::sleep(Duration::from_millis(500));
    // The first run, written and closed: the web's rows are the export's.
    let web = common::http::get_body(
        http,
        &format!("/api/history?section=Hist&from={began}&to={stopped}&format=csv"),
    );
    let from = iso(began);
    let to = iso(stopped + 1); // --to excludes its end; the web's to does not.
    let cli = history(dir.path(), &["--from", &from, "--to", &to]);
    assert_eq!(web, cli);
    assert!(cli.contains(",__LINK,,link_lost,link_lost\n"), "{cli}");
    let web_json = common::http::get_body(
        http,
        &format!("/api/history?section=Hist&from={began}&to={stopped}"),
    );
    let cli_json = history(
        dir.path(),
        &["--from", &from, "--to", &to, "--format", "json"],
    );
    assert_eq!(web_json, cli_json);
    server.stop();

    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    for (format, wide, file) in [
        ("csv", false, "long.csv"),
        ("csv", true, "wide.csv"),
        ("parquet", false, "long.parquet"),
        ("parquet", true, "wide.parquet"),
    ] {
        let path = out.join(file).to_string_lossy().into_owned();
        let mut args = vec!["--from", &from, "--format", format, "--out", &path];
        if wide {
            args.push("--wide");
        }
        history(dir.path(), &args);
    }
    let file = day_files(dir.path()).pop().unwrap();
    let events: Vec<String> = rusqlite::Connection::open(&file)
        .unwrap()
        .prepare("SELECT kind FROM events ORDER BY id")
        .unwrap()
        .query_map([], |r| r.get(0))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(
        events,
        [
            "start",
            "link_lost",
            "link_restored",
            "stop",
            "start",
            "stop"
        ]
    );
    python(CHECK_GAPS, &[&out.to_string_lossy()]);
}

/// A tmpfs of `kib` KiB at a new folder, unmounted on drop; `None` when
/// this process may not mount.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(at: &Path, kib: u64) -> Option<Tmpfs> {
        std::fs::create_dir_all(at).ok()?;
        let ok = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={kib}k"), "tmpfs"])
            .arg(at)
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        ok.then(|| Tmpfs(at.to_path_buf()))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

#[test]
fn a_full_disk_stops_recording_and_it_resumes_when_space_returns() {
    full_disk("", 1300);
}

/// The same while samples are being packed: packing fails with the disk
/// (quietly: recording's line says why), and both resume.
#[test]
fn a_full_disk_while_packing_stops_and_resumes_both() {
    full_disk("HISTORY_COMPACT = 1", 1700);
}

/// Records 500 variables changing every 100 ms into a 2 MiB tmpfs of which
/// `filler_kib` are taken, until recording stops; then frees the filler.
fn full_disk(global: &str, filler_kib: usize) {
    let dir = tempfile::tempdir().unwrap();
    let plc = Plc::start(
        dir.path(),
        &animated_pub(500),
        &["--program", "idle", "--animate", "ANIM_*"],
    );
    let mount = dir.path().join("small");
    let Some(tmpfs) = Tmpfs::mount(&mount, 2048) else {
        eprintln!("cannot mount a tmpfs here (not root): the size limit stands in for a full disk, without the resume");
        let server = Server::start(
            dir.path(),
            &plc,
            "HISTORY = ANIM_*",
            "HISTORY_RETENTION = 200KB",
        );
        wait_for("recording to stop at the size limit", || {
            server.getinfo("HISTORY").contains("stopped")
        });
        assert!(server.ask(b"GET:ANIM_00001").starts_with("GET:ANIM_00001,"));
        server.stop();
        return;
    };
    let filler = mount.join("filler");
    std::fs::write(&filler, vec![0u8; filler_kib * 1024]).unwrap();
    let server = Server::start(
        dir.path(),
        &plc,
        "HISTORY = ANIM_*",
        &format!("HISTORY_DIR = {}\n{global}", mount.display()),
    );
    wait_for("recording to stop on the full disk", || {
        server.getinfo("HISTORY").contains("stopped")
    });
    // Polling and the clients go on.
    for _ in 0..3 {
        assert!(server.ask(b"GET:ANIM_00001").starts_with("GET:ANIM_00001,"));
        std::thread::sleep(Duration::from_millis(300));
    }
    assert_eq!(
        server.log().matches("recording stopped").count(),
        1,
        "{}",
        server.log()
    );
    std::fs::remove_file(&filler).unwrap();
    wait_for("recording to resume", || {
        server.getinfo("HISTORY") == "GETINFO:HISTORY,recording"
    });
    assert!(server.log().contains("recording resumed"));
    if !global.is_empty() {
        wait_for("samples packed after the resume", || {
            first_number(&server.getinfo("HISTORY_PACKED")) > 0
        });
        assert!(
            !server.log().contains("packing samples failed"),
            "{}",
            server.log()
        );
    }
    server.stop();
    let files: Vec<PathBuf> = std::fs::read_dir(mount.join("Hist"))
        .unwrap()
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "sqlite"))
        .collect();
    assert_eq!(files.len(), 1);
    assert_eq!(integrity(&files[0]), "ok");
    drop(tmpfs);
}

/// Today's day file of section Hist, written before the server starts:
/// `vars` variables `OLD_nnn` (UDINT), `per_var` samples each, spread over
/// the part of today that is over, so a query of today has plenty to read.
fn prefill_today(dir: &Path, vars: usize, per_var: i64) -> PathBuf {
    use plccoms_historian::sample::{Sample, Stored};
    use plccoms_historian::store::{day_of, DayFile, DAY_MS};
    // Room for distinct times before now (the first minute of a day waits).
    while now_ms() % DAY_MS < 120_000 {
        std::thread::sleep(Duration::from_secs(1));
    }
    let day = day_of(now_ms());
    let text: String = (0..vars)
        .map(|i| format!(" OLD_{i:03} R B {} UDINT PUB_INOUT\r\n", i * 4))
        .collect();
    let table = std::sync::Arc::new(
        plccoms_core::vars::VarTable::from_public_text("old.pub", text.as_bytes()).unwrap(),
    );
    let start = day * DAY_MS;
    let step = (now_ms() - 60_000 - start) / per_var;
    let samples: Vec<Sample> = (0..per_var)
        .flat_map(|c| {
            let table = &table;
            (0..vars).map(move |i| Sample {
                t: start + c * step,
                var: table.lookup(format!("OLD_{i:03}").as_bytes()).unwrap(),
                value: Stored::Int(c * 7 + i as i64),
                quality: plccoms_core::changes::Quality::Good,
                plc_time: None,
            })
        })
        .collect();
    let mut file = DayFile::open(&dir.join("history"), "Hist", day).unwrap();
    file.write(&[(&table, &samples)], &[]).unwrap();
    let path = file.path.clone();
    file.close();
    path
}

/// A PASSIVE checkpoint of `file`'s WAL from here: whether it took every
/// committed frame (no reader holds an older snapshot) and there were some.
fn checkpoint_complete(file: &Path) -> bool {
    let conn = rusqlite::Connection::open(file).unwrap();
    conn.busy_timeout(Duration::from_secs(1)).unwrap();
    let (busy, log, done): (i64, i64, i64) = conn
        .query_row("PRAGMA wal_checkpoint(PASSIVE)", [], |r| {
            Ok((r.get(0)?, r.get(1)?, r.get(2)?))
        })
        .unwrap();
    busy == 0 && log > 0 && log == done
}

/// A client of `/api/history` that reads the head of the answer and then
/// stops reading (a small receive buffer, nothing read): the server reads
/// no further than it can send, holds no read transaction of today's file
/// meanwhile (the recorder's checkpoints go through, the WAL does not grow
/// with every commit), and ends the answer at HISTORY_QUERY_TIMEOUT with an
/// error line the client sees once it reads again.
#[test]
fn a_stalled_history_reader_holds_no_snapshot_and_is_cut_off() {
    use std::io::Read;
    let dir = tempfile::tempdir().unwrap();
    let file = prefill_today(dir.path(), 50, 8000);
    let plc = Plc::start(
        dir.path(),
        &animated_pub(300),
        &["--program", "idle", "--animate", "ANIM_*"],
    );
    let http = free_port();
    let limit_s = 15;
    let server = Server::start(
        dir.path(),
        &plc,
        "HISTORY = ANIM_*",
        &format!("HTTP_PORT = {http}\nHISTORY_SYNC = 1\nHISTORY_QUERY_TIMEOUT = {limit_s}"),
    );
    wait_for("the recorder writing today's file", || {
        first_number(&server.getinfo("HISTORY_SAMPLES")) > 1000
    });
    let socket = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    socket
        .connect(&std::net::SocketAddr::from(([127, 0, 0, 1], http)).into())
        .unwrap();
    let mut client: TcpStream = socket.into();
    client
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let day_start = now_ms() - now_ms() % 86_400_000;
    let asked = Instant::now();
    write!(
        client,
        "GET /api/history?section=Hist&vars=*&format=csv&from={day_start} HTTP/1.1\r\n\
         Host: 127.0.0.1:{http}\r\n\r\n"
    )
    .unwrap();
    let mut head = vec![0u8; 64 * 1024];
    client.read_exact(&mut head).unwrap();
    assert!(
        head.starts_with(b"HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&head[..200])
    );
    // The client stops reading; the recorder goes on committing.
    std::thread::sleep(Duration::from_secs(2));
    let start = Instant::now();
    while !checkpoint_complete(&file) {
        assert!(
            start.elapsed() < Duration::from_secs(15),
            "a checkpoint never took the whole WAL: a reader holds a snapshot \
             (WAL {} bytes)",
            store_wal_bytes(&file)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    assert!(
        asked.elapsed() < Duration::from_secs(limit_s),
        "the checkpoint went through only after the time limit cut the reader"
    );
    // Read on once the limit is past: the answer ends with the time
    // limit's error, not as if complete.
    std::thread::sleep(
        (asked + Duration::from_secs(limit_s + 1)).saturating_duration_since(Instant::now()),
    );
    let mut rest = Vec::new();
    let end = Instant::now() + Duration::from_secs(limit_s) + DEADLINE;
    let mut buf = vec![0u8; 256 * 1024];
    while !rest.ends_with(b"\r\n0\r\n\r\n") {
        assert!(Instant::now() < end, "the answer did not end");
        match client.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => rest.extend_from_slice(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => panic!("reading the answer: {e}"),
        }
    }
    let tail = String::from_utf8_lossy(&rest[rest.len().saturating_sub(400)..]).into_owned();
    assert!(
        tail.contains(",__ERROR,,") && tail.contains("HISTORY_QUERY_TIMEOUT"),
        "{tail}"
    );
    server.stop();
    assert_eq!(integrity(&file), "ok");
}

fn store_wal_bytes(file: &Path) -> u64 {
    std::fs::metadata(format!("{}-wal", file.display())).map_or(0, |m| m.len())
}

/// Today's day file damaged while the server was down (its header
/// overwritten): the server keeps it as `<name>.damaged-<time>`, says so,
/// and records into a new file of today at once, instead of stopping until
/// the next day.
#[test]
fn a_damaged_file_of_today_is_set_aside_and_recording_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let plc = Plc::start(
        dir.path(),
        &animated_pub(10),
        &["--program", "idle", "--animate", "ANIM_*"],
    );
    let server = Server::start(dir.path(), &plc, "HISTORY = ANIM_*", "");
    wait_for("samples written", || {
        first_number(&server.getinfo("HISTORY_SAMPLES")) > 0
    });
    server.stop();
    let file = day_files(dir.path()).pop().unwrap();
    let mut damaged = std::fs::read(&file).unwrap();
    damaged[..64].copy_from_slice(&[b'X'; 64]);
    std::fs::write(&file, &damaged).unwrap();

    let server = Server::start(dir.path(), &plc, "HISTORY = ANIM_*", "");
    wait_for("samples written after the restart", || {
        first_number(&server.getinfo("HISTORY_SAMPLES")) > 0
    });
    assert_eq!(server.getinfo("HISTORY"), "GETINFO:HISTORY,recording");
    server.stop();
    let name = file.file_name().unwrap().to_string_lossy().into_owned();
    let aside: Vec<PathBuf> = std::fs::read_dir(file.parent().unwrap())
        .unwrap()
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with(&format!("{name}.damaged-"))
        })
        .collect();
    assert_eq!(aside.len(), 1, "{aside:?}");
    assert_eq!(std::fs::read(&aside[0]).unwrap(), damaged);
    let log = server_log(dir.path());
    let aside_name = aside[0].file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        log.contains(&aside_name) && log.contains("damaged"),
        "{log}"
    );
    assert_eq!(integrity(&file), "ok");
    assert!(stored_samples(&file) > 0);
}

fn server_log(dir: &Path) -> String {
    std::fs::read_to_string(dir.join("plccoms.log")).unwrap_or_default()
}
