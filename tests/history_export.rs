//! `plccoms history` on day files written here through the store (no
//! server, no PLC): what an export does with damaged files and hostile
//! content, and with the file it writes to.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::process::PLCCOMS;
use plccoms_core::changes::Quality;
use plccoms_core::vars::VarTable;
use plccoms_historian::sample::{Sample, Stored};
use plccoms_historian::store::{day_path, DayFile, DAY_MS};

/// A day long past: 2022-01-08.
const DAY: i64 = 19_000;
const DATE: &str = "2022-01-08";
const NEXT_DATE: &str = "2022-01-09";

/// `dir/plccoms.ini` with section [Hist]; its history in `dir/history`.
fn ini(dir: &Path) {
    std::fs::write(
        dir.join("plccoms.ini"),
        "[*]\nCOMM_LOOP_DELAY = 100\n\n[Hist]\nIPADDR = 127.0.0.1\nIPADDR_LOCAL = 127.0.0.1\n\
         EPSPORT = 61682\nSERVER_PORT = 5010\nPUBFILE = //plc.pub\nPUBFILE_CRC = No\n\
         PUBFILE_WRITE = No\nHISTORY = *\n",
    )
    .unwrap();
}

fn table(public_text: &str) -> Arc<VarTable> {
    Arc::new(VarTable::from_public_text("p.pub", public_text.as_bytes()).expect("table"))
}

/// Day `DAY` of section Hist in `dir/history`, `samples` written to it.
fn day_with(dir: &Path, table: &Arc<VarTable>, samples: &[Sample]) -> DayFile {
    let mut file = DayFile::open(&dir.join("history"), "Hist", DAY).unwrap();
    file.write(&[(table, samples)], &[]).unwrap();
    file
}

fn sample(table: &VarTable, name: &str, t: i64, value: Stored) -> Sample {
    Sample {
        t,
        var: table.lookup(name.as_bytes()).expect(name),
        value,
        quality: Quality::Good,
        plc_time: None,
    }
}

/// `plccoms history -c plccoms.ini --section Hist --from DATE --to
/// NEXT_DATE <args>` in `dir`.
fn history(dir: &Path, args: &[&str]) -> Output {
    Command::new(PLCCOMS)
        .args(["history", "-c", "plccoms.ini", "--section", "Hist"])
        .args(["--from", DATE, "--to", NEXT_DATE])
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap()
}

/// tools/history_read.py's `samples` of `file` as `s`, then `check`; a
/// damaged block must raise its "damaged" error.
fn python_reader(file: &Path, check: &str) {
    let script = format!(
        "import sys\nsys.path.insert(0, sys.argv[1])\nfrom history_read import samples\n\
         try:\n    s = samples(sys.argv[2])\nexcept ValueError as e:\n    \
         assert 'damaged' in str(e), e\n    raise SystemExit(0)\n{check}\n"
    );
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(format!("{}/tools", env!("CARGO_MANIFEST_DIR")))
        .arg(file)
        .output()
        .expect("python3");
    assert!(out.status.success(), "python: {}", stderr(&out));
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The value of variable `var` (0..4) at cycle `c`: scattered, so blocks
/// do not compress to nothing.
fn value_at(c: i64, var: i64) -> f64 {
    let mut x = (c as u64) << 2 | var as u64;
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    (x ^ (x >> 31)) as f64 / 7.0
}

/// 4 LREALs, 50,000 cycles 100 ms apart: 200,000 samples, packed into
/// blocks of 65,536.
fn packed_day(dir: &Path) -> PathBuf {
    let table = table(
        " V0 R F 0 LREAL PUB_INOUT\r\n V1 R F 8 LREAL PUB_INOUT\r\n \
         V2 R F 16 LREAL PUB_INOUT\r\n V3 R F 24 LREAL PUB_INOUT\r\n",
    );
    let samples: Vec<Sample> = (0..50_000i64)
        .flat_map(|c| {
            let table = &table;
            (0..4).map(move |v| {
                sample(
                    table,
                    &format!("V{v}"),
                    DAY * DAY_MS + c * 100,
                    Stored::Real(value_at(c, v)),
                )
            })
        })
        .collect();
    let mut file = day_with(dir, &table, &samples);
    file.pack(i64::MAX, Instant::now() + Duration::from_secs(3600))
        .unwrap();
    file.close();
    day_path(&dir.join("history"), "Hist", DAY)
}

/// A bit of 256 bytes in the middle of a packed block flipped (a bad sector, a bad
/// copy): SQLite's own check sees nothing wrong. The export leaves that
/// block's samples out, writes every other sample exactly, names the file
/// and the block's time range, and exits with 2.
#[test]
fn a_damaged_block_is_named_and_the_rest_exported() {
    let dir = tempfile::tempdir().unwrap();
    ini(dir.path());
    let path = packed_day(dir.path());
    python_reader(&path, "assert len(s) == 200000, len(s)");
    let conn = rusqlite::Connection::open(&path).unwrap();
    let blocks: Vec<(i64, i64, i64)> = conn
        .prepare("SELECT first_key, last_key, samples FROM blocks ORDER BY first_key")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert!(blocks.len() >= 3, "{blocks:?}");
    let (first, last, damaged) = blocks[1];
    let mut data: Vec<u8> = conn
        .query_row(
            "SELECT data FROM blocks WHERE first_key = ?1",
            [first],
            |r| r.get(0),
        )
        .unwrap();
    let middle = data.len() / 2;
    for b in &mut data[middle..middle + 256] {
        *b ^= 0x01;
    }
    conn.execute(
        "UPDATE blocks SET data = ?1 WHERE first_key = ?2",
        rusqlite::params![data, first],
    )
    .unwrap();
    let check: String = conn
        .query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .unwrap();
    assert_eq!(check, "ok");
    drop(conn);

    // The documented format's own Python reader checks the seal too.
    python_reader(&path, "raise SystemExit('read a damaged block')");

    let out = history(dir.path(), &["--out", "out.csv"]);
    let message = stderr(&out);
    assert_eq!(out.status.code(), Some(2), "{message}");
    let iso = |key: i64| {
        let mut text = Vec::new();
        plccoms_historian::time::iso(DAY * DAY_MS + (key >> 15), &mut text);
        String::from_utf8(text).unwrap()
    };
    assert!(
        message.contains("history/Hist/Hist-2022-01-08.sqlite")
            && message.contains(&iso(first))
            && message.contains(&iso(last))
            && message.contains("damaged"),
        "{message}"
    );
    let csv = std::fs::read_to_string(dir.path().join("out.csv")).unwrap();
    let day_start = DAY * DAY_MS;
    let mut count = 0i64;
    // The range left out is marked in the export itself, as a gap.
    let marked: Vec<&str> = csv.lines().filter(|l| l.contains(",__DAMAGED,")).collect();
    assert_eq!(
        marked,
        [
            format!("{},__DAMAGED,,damaged_from,damaged", iso(first)),
            format!("{},__DAMAGED,,damaged_to,damaged", iso(last)),
        ]
    );
    for line in csv.lines().skip(1).filter(|l| !l.contains(",__")) {
        let fields: Vec<&str> = line.split(',').collect();
        let t = chrono::DateTime::parse_from_rfc3339(fields[0])
            .unwrap()
            .timestamp_millis();
        let var: i64 = fields[1][1..].parse().unwrap();
        let key = ((t - day_start) << 15) | var;
        assert!(
            !(first..=last).contains(&key),
            "a sample of the damaged block: {line}"
        );
        let c = (t - day_start) / 100;
        let value: f64 = fields[2].parse().unwrap();
        assert_eq!(value.to_bits(), value_at(c, var).to_bits(), "{line}");
        count += 1;
    }
    assert_eq!(count, 200_000 - damaged);
}

/// The files of `dir` other than `keep`.
fn others(dir: &Path, keep: &[&str]) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| !keep.contains(&n.as_str()))
        .collect();
    names.sort();
    names
}

/// `--out` names an existing file: an export that fails (a typo in the
/// masks) leaves it as it was; one that succeeds replaces it whole, with no
/// file of its own left beside it.
#[test]
fn a_failed_export_leaves_the_out_file_as_it_was() {
    let dir = tempfile::tempdir().unwrap();
    ini(dir.path());
    packed_day(dir.path());
    let out_dir = dir.path().join("exports");
    std::fs::create_dir(&out_dir).unwrap();
    let target = out_dir.join("report.csv");
    std::fs::write(&target, "precious work\n").unwrap();
    let out = history(
        dir.path(),
        &["--vars", "V9*", "--out", "exports/report.csv"],
    );
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(stderr(&out).contains("matches V9*"), "{}", stderr(&out));
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious work\n");
    assert_eq!(others(&out_dir, &["report.csv"]), Vec::<String>::new());

    let out = history(dir.path(), &["--vars", "V1", "--out", "exports/report.csv"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let csv = std::fs::read_to_string(&target).unwrap();
    assert_eq!(csv.lines().count(), 50_001);
    assert_eq!(others(&out_dir, &["report.csv"]), Vec::<String>::new());
}

/// `--out` naming a symbolic link is refused: the export never writes
/// through it to the file it points at (another user's link in a shared
/// folder), and the link stays.
#[test]
fn an_export_does_not_write_through_a_symbolic_link() {
    let dir = tempfile::tempdir().unwrap();
    ini(dir.path());
    packed_day(dir.path());
    let victim = dir.path().join("victim.txt");
    std::fs::write(&victim, "not yours\n").unwrap();
    std::os::unix::fs::symlink(&victim, dir.path().join("out.csv")).unwrap();
    let out = history(dir.path(), &["--vars", "V1", "--out", "out.csv"]);
    let message = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{message}");
    assert!(
        message.contains("out.csv") && message.contains("symbolic link"),
        "{message}"
    );
    assert_eq!(std::fs::read_to_string(&victim).unwrap(), "not yours\n");
    assert!(std::fs::symlink_metadata(dir.path().join("out.csv"))
        .unwrap()
        .file_type()
        .is_symlink());
}

/// An export killed halfway leaves no file at `--out` that looks complete:
/// it writes beside it and renames only at the end.
#[test]
fn a_killed_export_leaves_no_file_at_out() {
    let dir = tempfile::tempdir().unwrap();
    ini(dir.path());
    packed_day(dir.path());
    let mut child = Command::new(PLCCOMS)
        .args(["history", "-c", "plccoms.ini", "--section", "Hist"])
        .args([
            "--from", DATE, "--to", NEXT_DATE, "--wide", "--format", "json",
        ])
        .args(["--out", "out.json"])
        .current_dir(dir.path())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    // Killed once its output is under way.
    loop {
        if child.try_wait().unwrap().is_some() {
            eprintln!("the export finished before it could be killed: nothing to check");
            return;
        }
        let partial = others(dir.path(), &["plccoms.ini", "history"]);
        if !partial.is_empty() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no output under way: {partial:?}"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(!dir.path().join("out.json").exists());
}

/// Text a spreadsheet would run as a formula (OWASP "CSV injection": a
/// cell beginning with = + - @ TAB or CR) is written with a `'` before it,
/// in names and text values, long and wide; numbers, negative ones
/// included, and text that reads as a number stay as they are. pandas
/// reads the cells back.
#[test]
fn csv_cells_a_spreadsheet_would_run_are_escaped() {
    let dir = tempfile::tempdir().unwrap();
    ini(dir.path());
    let table = table(
        " S R B 0 STRING[16] PUB_INOUT\r\n I R B 20 INT PUB_INOUT\r\n F R F 24 LREAL PUB_INOUT\r\n",
    );
    let texts = [
        "=1+2", "+CMD", "-5", "-1+2", "@SUM(A1)", "\tx", "\rx", "plain", "'quoted",
    ];
    let t0 = DAY * DAY_MS + 1000;
    let mut samples = Vec::new();
    for (i, text) in texts.iter().enumerate() {
        let t = t0 + i as i64 * 100;
        samples.push(sample(&table, "S", t, Stored::Text(text.to_string())));
        samples.push(sample(&table, "I", t, Stored::Int(-32768 + i as i64)));
        samples.push(sample(&table, "F", t, Stored::Real(-1.5 - i as f64)));
    }
    day_with(dir.path(), &table, &samples).close();
    // Names as a PLC's public file may have them.
    let path = day_path(&dir.path().join("history"), "Hist", DAY);
    let conn = rusqlite::Connection::open(&path).unwrap();
    conn.execute("UPDATE vars SET name = '+CMD' WHERE name = 'I'", [])
        .unwrap();
    conn.execute("UPDATE vars SET name = '@F' WHERE name = 'F'", [])
        .unwrap();
    drop(conn);
    for (wide, file) in [(false, "long.csv"), (true, "wide.csv")] {
        let mut args = vec!["--out", file];
        if wide {
            args.push("--wide");
        }
        let out = history(dir.path(), &args);
        assert!(out.status.success(), "{}", stderr(&out));
    }
    let script = r#"
import sys
import pandas as pd
d = sys.argv[1]
texts = ["'=1+2", "'+CMD", "-5", "'-1+2", "'@SUM(A1)", "'\tx", "'\rx", "plain", "'quoted"]
long = pd.read_csv(d + "/long.csv", dtype=str, keep_default_na=False)
assert sorted(set(long["name"])) == ["'+CMD", "'@F", "S"], set(long["name"])
assert list(long[long["name"] == "S"]["text"]) == texts, list(long[long["name"] == "S"]["text"])
assert list(long[long["name"] == "'+CMD"]["value"]) == [str(-32768 + i) for i in range(9)]
assert list(long[long["name"] == "'@F"]["value"]) == [str(-1.5 - i) for i in range(9)]
wide = pd.read_csv(d + "/wide.csv", keep_default_na=False)
assert list(wide.columns) == ["time", "quality", "S", "'+CMD", "'@F"], list(wide.columns)
assert list(wide["S"]) == texts, list(wide["S"])
assert str(wide["'+CMD"].dtype) == "int64" and wide["'+CMD"].iloc[0] == -32768
assert str(wide["'@F"].dtype) == "float64" and wide["'@F"].iloc[0] == -1.5
print("ok")
"#;
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(dir.path())
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "python: {}\n{}",
        stderr(&out),
        std::fs::read_to_string(dir.path().join("long.csv")).unwrap()
    );
}
