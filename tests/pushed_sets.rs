//! A SET that comes in while the link applies a take of pushed values (an
//! OPC UA publish of 10,000 notifications, ADS notifications) is served
//! within the take, not after all of it; and the take's values of the
//! variable it set, sampled before the Write, do not undo it.

mod common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use async_trait::async_trait;

use common::memory::{Hooked, Hooks, MemoryBackend};
use plccoms_core::driver::{PlcError, Pushed, PushedVar, ReadRequest, WriteData, WriteRequest};
use plccoms_protocol::Area;

/// Pushed values in a take, and where in it the SET's variable comes.
const TAKE: usize = 3000;
const STALE_AT: usize = 2500;
/// Where the user public file has them.
const V_DINT_AT: u32 = 60;
const V_UINT_AT: u32 = 74;

/// One take of pushed values, handed out once the test has sent its SET.
struct Pushing {
    take: Arc<Mutex<Option<Vec<Pushed>>>>,
    wake: Arc<tokio::sync::Notify>,
    /// Rung when the link takes the values; it gets them once `go`.
    taking: Arc<tokio::sync::Notify>,
    go: Arc<(Mutex<bool>, std::sync::Condvar)>,
    /// From the take's return to the link's next wait or read.
    applying: Arc<AtomicBool>,
    /// Whether each write came while a take was being applied.
    writes: Arc<Mutex<Vec<bool>>>,
}

#[async_trait]
impl Hooks for Pushing {
    fn describe(&self) -> String {
        "in-process memory, pushing".into()
    }

    async fn before_read(&mut self, _requests: &[ReadRequest]) {
        self.applying.store(false, Ordering::SeqCst);
    }

    fn before_write(&mut self, _requests: &[WriteRequest]) {
        let applying = self.applying.load(Ordering::SeqCst);
        self.writes.lock().unwrap().push(applying);
    }

    fn take_pushed(&mut self, memory: &MemoryBackend) -> Vec<Pushed> {
        let Some(take) = self.take.lock().unwrap().take() else {
            return Vec::new();
        };
        self.taking.notify_one();
        // The link blocks here until the SET is on its way: it is queued
        // while this take is applied.
        let (go, turn) = &*self.go;
        let go = go.lock().unwrap();
        drop(turn.wait_timeout_while(go, Duration::from_secs(10), |go| !*go));
        self.applying.store(true, Ordering::SeqCst);
        // Reads answer what was pushed last, as a pushing device's do.
        let mut device = memory.device().lock().unwrap();
        for (offset, value) in [(V_UINT_AT, &take[TAKE - 1]), (V_DINT_AT, &take[STALE_AT])] {
            let data = WriteData::Bytes(value.bytes.to_vec());
            device.write(Area::R, offset, &data).unwrap();
        }
        drop(device);
        take
    }

    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        self.applying.store(false, Ordering::SeqCst);
        self.wake.notified().await;
        Ok(())
    }
}

fn pushed(name: &str, bytes: Vec<u8>) -> Pushed {
    Pushed {
        var: PushedVar::Named(name.as_bytes().into()),
        bytes: bytes.into(),
        unix_ms: 1_700_000_000_000,
        uncertain: false,
    }
}

#[tokio::test]
async fn a_set_is_served_within_a_take_of_pushed_values_and_not_undone_by_it() {
    // V_DINT once, to a value sampled before the SET; V_UINT last; the
    // others of a variable the table has not (skipped, as after a change
    // of the server's variables).
    let take: Vec<Pushed> = (0..TAKE)
        .map(|n| match n {
            STALE_AT => pushed("V_DINT", 7i32.to_le_bytes().to_vec()),
            _ if n == TAKE - 1 => pushed("V_UINT", (n as u16).to_le_bytes().to_vec()),
            _ => pushed("GONE", vec![0; 2]),
        })
        .collect();
    let backend = Hooked::new(Pushing {
        take: Arc::default(),
        wake: Arc::default(),
        taking: Arc::default(),
        go: Arc::default(),
        applying: Arc::default(),
        writes: Arc::default(),
    });
    let (pending, wake, taking, go, writes) = (
        backend.hooks.take.clone(),
        backend.hooks.wake.clone(),
        backend.hooks.taking.clone(),
        backend.hooks.go.clone(),
        backend.hooks.writes.clone(),
    );
    let server = common::start_on("", &common::user_pub(), Some(Box::new(backend))).await;
    let mut watcher = server.client().await;
    watcher.send(b"EN:V_DINT\r\nEN:V_UINT\r\n").await;
    // Each EN answered.
    for _ in 0..2 {
        assert!(watcher.line().await.starts_with(b"WARNING:252"));
    }
    let mut writer = server.client().await;
    let mut every = server.section.section.subscribe(&["V_DINT"]).every_change();
    // Its first batch: the value as it is (the first poll's).
    let first = every.next().await.expect("a first batch");
    assert_eq!(first.changes.len(), 1);

    *pending.lock().unwrap() = Some(take);
    wake.notify_one();
    taking.notified().await;
    writer.send(b"SET:V_DINT,5\r\n").await;
    // The SET reaches the link's queue meanwhile (a session's hop).
    tokio::time::sleep(Duration::from_millis(1000)).await;
    {
        let (flag, turn) = &*go;
        *flag.lock().unwrap() = true;
        turn.notify_all();
    }
    writer.expect(b"DIFF:V_DINT,5\r\n").await;
    let last = format!("DIFF:V_UINT,{}\r\n", TAKE - 1);
    let seen = watcher
        .wait_for_line(last.as_bytes(), Duration::from_secs(10))
        .await;
    assert_eq!(
        *writes.lock().unwrap(),
        [true],
        "the SET was written while the take was applied"
    );
    // Every value V_DINT was published with (a session shows the latest
    // only, and the poll after the take puts 5 back at once).
    let mut values = Vec::new();
    while let Ok(Some(batch)) = tokio::time::timeout(Duration::from_millis(500), every.next()).await
    {
        for &id in &batch.changes {
            let text = batch.snapshot.slot(id).text().unwrap_or_default();
            values.push(String::from_utf8_lossy(text).into_owned());
        }
    }
    assert_eq!(values, ["5"], "the take's older V_DINT undid the SET");
    assert!(seen.iter().all(|line| line != b"DIFF:V_DINT,7\r\n"));
    writer.ask("GET:V_DINT\r\n", "GET:V_DINT,5\r\n").await;
}

/// A device that pushes without a pause, from when `on` until `until`.
struct Flooding {
    flood: Arc<Flood>,
}

#[derive(Default)]
struct Flood {
    on: AtomicBool,
    until: Mutex<Option<std::time::Instant>>,
    wake: tokio::sync::Notify,
    /// Per write: whether the device was still flooding.
    writes: Mutex<Vec<bool>>,
    taken: std::sync::atomic::AtomicU16,
}

impl Flood {
    fn flooding(&self) -> bool {
        self.on.load(Ordering::SeqCst)
            && self
                .until
                .lock()
                .unwrap()
                .is_some_and(|until| std::time::Instant::now() < until)
    }
}

#[async_trait]
impl Hooks for Flooding {
    fn describe(&self) -> String {
        "in-process memory, flooding".into()
    }

    /// Longer than the flood: a SET it held up is served late, not refused.
    fn answer_timeout(&self) -> Duration {
        Duration::from_secs(20)
    }

    fn before_write(&mut self, _requests: &[WriteRequest]) {
        let flooding = self.flood.flooding();
        self.flood.writes.lock().unwrap().push(flooding);
        self.flood.on.store(false, Ordering::SeqCst);
    }

    fn take_pushed(&mut self, _memory: &MemoryBackend) -> Vec<Pushed> {
        if !self.flood.flooding() {
            return Vec::new();
        }
        let n = self.flood.taken.fetch_add(1, Ordering::SeqCst);
        vec![pushed("V_UINT", n.to_le_bytes().to_vec())]
    }

    /// Ready at once, without ever pending, while it floods.
    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        loop {
            if self.flood.flooding() {
                return Ok(());
            }
            self.flood.wake.notified().await;
        }
    }
}

/// A device whose pushed values never pause (a wait for them is ready at
/// once, every time) does not keep a SET waiting for the flood's end or
/// the next poll: it is served between two takes.
#[tokio::test]
async fn a_device_that_pushes_without_a_pause_does_not_hold_up_a_set() {
    let flood = Arc::new(Flood::default());
    let backend = Hooked::new(Flooding {
        flood: flood.clone(),
    });
    let server = common::start_on(
        "COMM_LOOP_DELAY = 1000\n",
        &common::user_pub(),
        Some(Box::new(backend)),
    )
    .await;
    let mut writer = server.client().await;
    writer.ask("GET:V_DINT\r\n", "GET:V_DINT,0\r\n").await;
    *flood.until.lock().unwrap() = Some(std::time::Instant::now() + Duration::from_secs(5));
    flood.on.store(true, Ordering::SeqCst);
    flood.wake.notify_one();
    // Flooding: some takes applied before the SET is sent.
    while flood.taken.load(Ordering::SeqCst) < 100 {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    writer.send(b"SET:V_DINT,5\r\n").await;
    writer
        .wait_for_line(b"DIFF:V_DINT,5\r\n", Duration::from_secs(15))
        .await;
    assert_eq!(
        *flood.writes.lock().unwrap(),
        [true],
        "the SET was written while the device still flooded"
    );
}
