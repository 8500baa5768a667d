//! Packing (HISTORY_COMPACT) through the store itself: a day file read back
//! before and after its samples are packed into blocks gives the same
//! samples, value for value, in the same order; late samples into a packed
//! range are still found, deduplicated and shifted; the freed pages go back.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use plccoms_core::changes::Quality;
use plccoms_core::vars::VarTable;
use plccoms_historian::query::{self, Query, Row};
use plccoms_historian::sample::{Sample, Stored};
use plccoms_historian::store::{day_path, DayFile, DAY_MS, MIN_BLOCK};

/// A day long past: nothing else writes to it.
const DAY: i64 = 19_000;

fn table() -> Arc<VarTable> {
    let text = b" B R B 0 .0 BOOL PUB_INOUT\r\n I R B 2 INT PUB_INOUT\r\n \
        U R B 4 ULINT PUB_INOUT\r\n F R F 12 REAL PUB_INOUT\r\n \
        D R F 16 LREAL PUB_INOUT\r\n S R B 24 STRING[16] PUB_INOUT\r\n \
        T R B 44 DT PUB_INOUT\r\n EV R B 48 INT PUB_INOUT\r\n";
    Arc::new(VarTable::from_public_text("p.pub", text).expect("table"))
}

fn id(table: &VarTable, name: &str) -> u32 {
    table.lookup(name.as_bytes()).expect(name)
}

/// `cycles` polls of every variable, 100 ms apart, with outages, NaN,
/// extreme integers, texts and PLC stamps.
fn samples(table: &VarTable, cycles: i64) -> Vec<Sample> {
    let start = DAY * DAY_MS + 3_600_000;
    let mut out = Vec::new();
    for c in 0..cycles {
        let t = start + c * 100 + (c % 3);
        let quality = match c % 500 {
            200..=210 => Quality::LinkLost,
            211 => Quality::Stale,
            _ => Quality::Good,
        };
        let mut push = |name: &str, value: Stored, plc_time: Option<i64>| {
            out.push(Sample {
                t,
                var: id(table, name),
                value,
                quality,
                plc_time,
            })
        };
        push("B", Stored::Int(c % 2), None);
        push("I", Stored::Int((c * 37) % 65_536 - 32_768), None);
        push(
            "U",
            Stored::Int(if c % 2 == 0 { -1 } else { i64::MAX - c }),
            None,
        );
        push(
            "F",
            Stored::Real(f64::from(((c as f64) * 0.01).sin() as f32)),
            None,
        );
        let d = match c % 97 {
            0 => Stored::Null,
            1 => Stored::Real(f64::INFINITY),
            _ => Stored::Real((c as f64 * 0.001).cos() * 1e6),
        };
        push("D", d, None);
        if c % 10 == 0 {
            push("S", Stored::Text(format!("count {c} ěščř")), None);
        }
        push("T", Stored::Int(1_700_000_000_000 + c * 1000), None);
        push("EV", Stored::Int(c), Some(t - 250));
    }
    out
}

fn query(dir: &Path, from_ms: i64, to_ms: i64, masks: &[&str]) -> Query {
    Query {
        dir: dir.to_path_buf(),
        section: "Pack".into(),
        masks: masks.iter().map(|m| m.to_string()).collect(),
        from_ms,
        to_ms,
    }
}

fn read(dir: &Path, from_ms: i64, to_ms: i64, masks: &[&str]) -> Vec<Row> {
    query::rows(&query(dir, from_ms, to_ms, masks))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap()
}

/// Day `DAY` of section "Pack" in `dir`, `samples` written to it.
fn day_with(dir: &Path, table: &Arc<VarTable>, samples: &[Sample]) -> DayFile {
    let mut file = DayFile::open(dir, "Pack", DAY).unwrap();
    file.write(&[(table, samples)], &[]).unwrap();
    file
}

/// Equal row lists; a difference is shown as the first row that differs.
#[track_caller]
fn assert_same(got: &[Row], want: &[Row]) {
    if let Some(i) = (0..got.len().min(want.len())).find(|&i| got[i] != want[i]) {
        panic!("row {i} differs:\n got  {:?}\n want {:?}", got[i], want[i]);
    }
    assert_eq!(got.len(), want.len(), "row count");
}

fn count(path: &Path, sql: &str) -> i64 {
    rusqlite::Connection::open(path)
        .unwrap()
        .query_row(sql, [], |r| r.get(0))
        .unwrap()
}

fn far() -> Instant {
    Instant::now() + Duration::from_secs(3600)
}

#[test]
fn packed_samples_read_back_exactly_and_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let table = table();
    let written = samples(&table, 30_000);
    let mut file = DayFile::open(dir.path(), "Pack", DAY).unwrap();
    for chunk in written.chunks(10_000) {
        file.write(&[(&table, chunk)], &[]).unwrap();
    }
    let all = (DAY * DAY_MS, (DAY + 1) * DAY_MS);
    let before = read(dir.path(), all.0, all.1, &["*"]);
    assert_eq!(before.len(), written.len());
    let window = (
        DAY * DAY_MS + 3_600_000 + 777_777,
        DAY * DAY_MS + 3_600_000 + 2_222_222,
    );
    let window_before = read(dir.path(), window.0, window.1, &["D", "s*"]);
    let path = day_path(dir.path(), "Pack", DAY);
    let rows_bytes = std::fs::metadata(&path).unwrap().len();

    // The first half (by time) into blocks: rows and blocks are merged.
    let half = written[written.len() / 2].t;
    let packing = file.pack(half, far()).unwrap();
    assert!(packing.blocks >= 1 && !packing.more, "{packing:?}");
    assert_eq!(
        count(&path, "SELECT count(*) FROM samples") as u64 + packing.samples,
        written.len() as u64
    );
    assert_same(&read(dir.path(), all.0, all.1, &["*"]), &before);
    assert_same(
        &read(dir.path(), window.0, window.1, &["D", "s*"]),
        &window_before,
    );

    // Then all of it; a file opened again knows its blocks.
    drop(file);
    let mut file = DayFile::open(dir.path(), "Pack", DAY).unwrap();
    let rest = file.pack(i64::MAX, far()).unwrap();
    assert!(!rest.more);
    assert_eq!(count(&path, "SELECT count(*) FROM samples"), 0);
    assert_eq!(count(&path, "SELECT count(*) FROM qualities"), 0);
    assert_eq!(count(&path, "SELECT count(*) FROM stamps"), 0);
    assert_eq!(
        count(&path, "SELECT sum(samples) FROM blocks"),
        written.len() as i64
    );
    assert_same(&read(dir.path(), all.0, all.1, &["*"]), &before);
    assert_same(
        &read(dir.path(), window.0, window.1, &["D", "s*"]),
        &window_before,
    );
    // Outages and stamps came through.
    assert!(before.iter().any(|r| r.quality == Quality::LinkLost));
    assert!(before.iter().any(|r| r.quality == Quality::Stale));
    assert!(before.iter().any(|r| r.plc_time.is_some()));

    // Late samples into the packed range: the same one again is a
    // duplicate, another value at a packed millisecond moves one later.
    let ev = id(&table, "EV");
    let packed_sample = written.iter().find(|s| s.var == ev).unwrap().clone();
    let counts = file
        .write(&[(&table, std::slice::from_ref(&packed_sample))], &[])
        .unwrap();
    assert_eq!((counts.written, counts.duplicates), (0, 1));
    let mut other = packed_sample.clone();
    other.value = Stored::Int(-12345);
    other.plc_time = None;
    let counts = file.write(&[(&table, &[other.clone()])], &[]).unwrap();
    assert_eq!((counts.written, counts.shifted), (1, 1));
    let after = read(dir.path(), all.0, all.1, &["EV"]);
    let late = after
        .iter()
        .position(|r| r.value == Stored::Int(-12345))
        .expect("the late sample");
    assert_eq!(after[late].t, other.t + 1);
    assert!(after.windows(2).all(|w| w[0].t <= w[1].t), "time order");
    assert_eq!(
        after.len(),
        before.iter().filter(|r| r.var.name == "EV").count() + 1
    );

    // The rows' pages go back; the file passes SQLite's own check.
    while !file.shrink(1024).unwrap() {}
    file.close();
    let packed_bytes = std::fs::metadata(&path).unwrap().len();
    eprintln!(
        "{} samples: {rows_bytes} bytes as rows, {packed_bytes} packed ({:.1} and {:.1} bytes a sample)",
        written.len(),
        rows_bytes as f64 / written.len() as f64,
        packed_bytes as f64 / written.len() as f64
    );
    assert!(
        packed_bytes * 3 < rows_bytes,
        "{packed_bytes} of {rows_bytes}"
    );
    let check: String = rusqlite::Connection::open(&path)
        .unwrap()
        .query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .unwrap();
    assert_eq!(check, "ok");
}

#[test]
fn a_few_samples_wait_for_a_block_worth_unless_the_day_is_over() {
    let dir = tempfile::tempdir().unwrap();
    let table = table();
    let written = samples(&table, (MIN_BLOCK / 10) as i64);
    assert!(written.len() < MIN_BLOCK);
    let mut file = day_with(dir.path(), &table, &written);
    let waiting = file.pack(written.last().unwrap().t + 1, far()).unwrap();
    assert_eq!(waiting.blocks, 0);
    // A deadline already past packs nothing and says there is more.
    let more = file.pack(i64::MAX, Instant::now()).unwrap();
    assert!(more.more && more.blocks == 0);
    let finished = file.pack(i64::MAX, far()).unwrap();
    assert_eq!(
        (finished.blocks, finished.samples),
        (1, written.len() as u64)
    );
    // Nothing left: no more, even past the deadline.
    assert!(!file.pack(i64::MAX, Instant::now()).unwrap().more);
}

#[test]
fn a_damaged_block_is_an_error_that_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let table = table();
    let mut file = day_with(dir.path(), &table, &samples(&table, 1000));
    file.pack(i64::MAX, far()).unwrap();
    file.close();
    let path = day_path(dir.path(), "Pack", DAY);
    rusqlite::Connection::open(&path)
        .unwrap()
        .execute("UPDATE blocks SET data = substr(data, 1, 40)", [])
        .unwrap();
    let all = query(dir.path(), DAY * DAY_MS, (DAY + 1) * DAY_MS, &["*"]);
    let err = query::rows(&all)
        .unwrap()
        .find_map(Result::err)
        .expect("an error");
    let text = err.to_string();
    assert!(text.contains("Pack-") && text.contains("damaged"), "{text}");
    assert!(matches!(err, query::QueryError::Damaged { .. }), "{err:?}");
    // Data of another type than a blob is damage of the block too.
    rusqlite::Connection::open(&path)
        .unwrap()
        .execute("UPDATE blocks SET data = 'text'", [])
        .unwrap();
    let err = query::rows(&all)
        .unwrap()
        .find_map(Result::err)
        .expect("an error");
    assert!(err.to_string().contains("not a blob"), "{err}");
}

/// A day file of schema version 1 (no blocks, no incremental vacuum), as
/// an earlier release left it: opened for writing it gains the tables, is
/// packed, rebuilt without its freed pages, and reads back the same.
#[test]
fn a_version_1_file_is_upgraded_packed_and_read_back_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let table = table();
    let written = samples(&table, 2000);
    day_with(dir.path(), &table, &written).close();
    let path = day_path(dir.path(), "Pack", DAY);
    rusqlite::Connection::open(&path)
        .unwrap()
        .execute_batch(
            "DROP TABLE blocks; DROP TABLE packed_stamps; \
             UPDATE meta SET value = 1 WHERE key = 'version'; \
             PRAGMA auto_vacuum = NONE; VACUUM;",
        )
        .unwrap();
    assert_eq!(count(&path, "PRAGMA auto_vacuum"), 0);
    let all = (DAY * DAY_MS, (DAY + 1) * DAY_MS);
    let before = read(dir.path(), all.0, all.1, &["*"]);
    assert_eq!(before.len(), written.len());

    let mut file = DayFile::open(dir.path(), "Pack", DAY).unwrap();
    assert_eq!(
        count(&path, "SELECT value FROM meta WHERE key = 'version'"),
        plccoms_historian::store::VERSION
    );
    let packed = file.pack(i64::MAX, far()).unwrap();
    assert_eq!(packed.samples, written.len() as u64);
    assert!(file.shrink(1024).unwrap());
    file.close();
    assert_eq!(count(&path, "PRAGMA freelist_count"), 0);
    assert_same(&read(dir.path(), all.0, all.1, &["*"]), &before);
}

/// A day file of version 2, whose blocks are the bare zstd frame without a
/// checksum: read as it is, and written to, it becomes version 3 with its
/// old blocks still read and its new ones sealed.
#[test]
fn a_version_2_file_with_unsealed_blocks_is_still_read() {
    let dir = tempfile::tempdir().unwrap();
    let table = table();
    let written = samples(&table, 4000);
    let (old, new) = written.split_at(written.len() / 2);
    let mut file = day_with(dir.path(), &table, old);
    file.pack(i64::MAX, far()).unwrap();
    file.close();
    let path = day_path(dir.path(), "Pack", DAY);
    let all = (DAY * DAY_MS, (DAY + 1) * DAY_MS);
    let before = read(dir.path(), all.0, all.1, &["*"]);
    assert_eq!(before.len(), old.len());
    let conn = rusqlite::Connection::open(&path).unwrap();
    // Version 2 stored the zstd frame alone: the sealed form less its
    // 5-byte header.
    let unsealed = conn
        .execute("UPDATE blocks SET data = substr(data, 6)", [])
        .unwrap();
    assert!(unsealed > 0);
    conn.execute("UPDATE meta SET value = 2 WHERE key = 'version'", [])
        .unwrap();
    drop(conn);
    assert_same(&read(dir.path(), all.0, all.1, &["*"]), &before);

    let mut file = DayFile::open(dir.path(), "Pack", DAY).unwrap();
    file.write(&[(&table, new)], &[]).unwrap();
    file.pack(i64::MAX, far()).unwrap();
    file.close();
    assert_eq!(
        count(&path, "SELECT value FROM meta WHERE key = 'version'"),
        3
    );
    assert_eq!(
        count(
            &path,
            "SELECT count(*) FROM blocks WHERE substr(data, 1, 1) = x'02'"
        ),
        1
    );
    let after = read(dir.path(), all.0, all.1, &["*"]);
    assert_eq!(after.len(), written.len());
    // The new samples are later than the old ones.
    assert_same(&after[..before.len()], &before);
}

/// A query holds no snapshot between its chunks (a stalled reader must
/// not pin the WAL): samples packed into blocks while it is half way are
/// read once each, in order, none lost.
#[test]
fn samples_packed_while_a_query_is_half_way_are_read_once() {
    let dir = tempfile::tempdir().unwrap();
    let table = table();
    let written = samples(&table, 30_000);
    let mut file = day_with(dir.path(), &table, &written);
    let all = (DAY * DAY_MS, (DAY + 1) * DAY_MS);
    let want = read(dir.path(), all.0, all.1, &["*"]);
    assert_eq!(want.len(), written.len());
    let mut rows = query::rows(&query(dir.path(), all.0, all.1, &["*"])).unwrap();
    let mut got: Vec<Row> = rows
        .by_ref()
        .take(query::CHUNK + 100)
        .map(Result::unwrap)
        .collect();
    let packing = file.pack(i64::MAX, far()).unwrap();
    assert_eq!(packing.samples, written.len() as u64);
    got.extend(rows.map(Result::unwrap));
    assert_same(&got, &want);
}
