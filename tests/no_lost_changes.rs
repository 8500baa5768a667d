//! The historian and MQTT (QoS 1) see every change, in order, while they
//! lag by less than `FOLLOW_BOUND` publishes: with both cores kept busy by
//! the test, every value a client writes in quick succession is recorded
//! and published, none skipped, none out of order.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::mqtt::{Broker, DEADLINE};
use common::process::{free_port, ServerProcess, PLCCOMS};

/// Values written one after another, each confirmed before the next: each
/// is one publish of the change stream, beside the polls.
const WRITES: i32 = 400;

/// Busy loops on every core until dropped: the consumers compete for CPU
/// with them and with the link.
struct Stress {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Stress {
    fn start() -> Stress {
        let stop = Arc::new(AtomicBool::new(false));
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        let threads = (0..cores)
            .map(|_| {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    let mut x = 0u64;
                    while !stop.load(Ordering::Relaxed) {
                        x = std::hint::black_box(
                            x.wrapping_mul(6364136223846793005).wrapping_add(1),
                        );
                    }
                })
            })
            .collect();
        Stress { stop, threads }
    }
}

impl Drop for Stress {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for thread in self.threads.drain(..) {
            let _ = thread.join();
        }
    }
}

/// The values of `values` from the first `1` on: what the writes made.
fn from_first_write(values: &[i64]) -> Vec<i64> {
    match values.iter().position(|&v| v == 1) {
        Some(start) => values[start..].to_vec(),
        None => Vec::new(),
    }
}

#[test]
fn under_cpu_stress_every_written_value_is_recorded_and_published_in_order() {
    let broker = Broker::anonymous();
    let sub = broker.subscribe(&["plccoms/S/COUNTER"]);
    let port = free_port();
    let ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 20\nHISTORY_SYNC = 1\nMQTT_URL = {}\n\n\
         [S]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = idle\nIPADDR_LOCAL = 127.0.0.1\n\
         SERVER_PORT = {port}\nPUBFILE = //demo.pub\nHISTORY = COUNTER\nMQTT_PUBLISH = COUNTER\n",
        broker.url()
    );
    let server = ServerProcess::with_config(&ini, port);
    let stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
    stream.set_read_timeout(Some(DEADLINE)).unwrap();
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    let mut writer = stream;
    // The first value reaches both consumers before the stress begins.
    sub.wait_for("MQTT's first COUNTER", || {
        (!sub.on("plccoms/S/COUNTER").is_empty()).then_some(())
    });

    let stress = Stress::start();
    let started = Instant::now();
    for value in 1..=WRITES {
        writer
            .write_all(format!("SET:counter,{value}\r\n").as_bytes())
            .unwrap();
        let mut line = String::new();
        reader.read_line(&mut line).unwrap();
        assert_eq!(line.trim_end(), format!("DIFF:COUNTER,{value}"));
    }
    let writing = started.elapsed();
    drop(stress);
    eprintln!("{WRITES} writes under stress in {writing:?}");

    // MQTT: every value, in order.
    let published = sub.wait_for("MQTT's last COUNTER", || {
        let values: Vec<i64> = sub
            .on("plccoms/S/COUNTER")
            .iter()
            .filter_map(|m| m.payload.trim().parse().ok())
            .collect();
        (values.last() == Some(&i64::from(WRITES))).then_some(values)
    });
    let expected: Vec<i64> = (1..=i64::from(WRITES)).collect();
    assert_eq!(
        from_first_write(&published),
        expected,
        "MQTT skipped or reordered"
    );

    // The historian: every value, in order, and no gap of its own.
    let deadline = Instant::now() + Duration::from_secs(30);
    let recorded = loop {
        let out = Command::new(PLCCOMS)
            .args(["history", "-c", "plccoms.ini", "--section", "S"])
            .args(["--vars", "COUNTER", "--from", "-1h", "--format", "csv"])
            .current_dir(server.dir.path())
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            !text.contains("__RECORDER"),
            "the recorder missed changes:\n{text}"
        );
        // time,name,value,text,quality
        let values: Vec<i64> = text
            .lines()
            .skip(1)
            .filter_map(|line| {
                let fields: Vec<&str> = line.split(',').collect();
                (fields.get(1) == Some(&"COUNTER")).then(|| fields[2].parse().ok())?
            })
            .collect();
        if values.last() == Some(&i64::from(WRITES)) {
            break values;
        }
        assert!(
            Instant::now() < deadline,
            "the history never reached {WRITES}: {:?}\n{}",
            values.last(),
            String::from_utf8_lossy(&out.stderr)
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    assert_eq!(
        from_first_write(&recorded),
        expected,
        "the historian skipped or reordered"
    );
}
