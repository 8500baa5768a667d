//! A SET served between the slices of a poll leaves a value newer than what
//! the poll read of that variable before it: the poll keeps it, and it
//! counts as read by that poll. It was not counted so: until the next poll
//! the variable was not current, and a session that took the poll's
//! snapshot without the SET's before it (a busy one, or one that enabled
//! everything) never sent its DIFF: measured against node-opcua, 1-4 of
//! 1,000 SETs' values never reached an `EN:*` client.
//!
//! A SET that comes in while the link applies a poll's values is served
//! between the pieces of that finish, not after the whole.

mod common;

use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use async_trait::async_trait;
use tokio::sync::Notify;

use common::memory::{Hooked, Hooks};
use plccoms_core::driver::ReadRequest;
use plccoms_protocol::Area;

/// Reads in blocks of two bytes, each taking a millisecond, so that a poll
/// is many slices; once armed, the next read of `TEST_1` (R0, 2 bytes)
/// waits for the test.
struct Sliced {
    armed: Arc<AtomicBool>,
    /// Rung when the armed read began; it goes on at `go`.
    reading: Arc<Notify>,
    go: Arc<Notify>,
    /// The `R` ranges (offset, length) the held read covered.
    held: Arc<Mutex<Vec<(u32, u32)>>>,
}

fn reads_test_1(requests: &[ReadRequest]) -> bool {
    requests.iter().any(|r| r.area == Area::R && r.offset == 0)
}

#[async_trait]
impl Hooks for Sliced {
    fn describe(&self) -> String {
        "in-process memory, read in small slices".into()
    }

    fn max_read_block(&self) -> u32 {
        2
    }

    async fn before_read(&mut self, requests: &[ReadRequest]) {
        if reads_test_1(requests) && self.armed.swap(false, Ordering::SeqCst) {
            *self.held.lock().unwrap() = requests
                .iter()
                .filter(|r| r.area == Area::R)
                .map(|r| (r.offset, r.len))
                .collect();
            self.reading.notify_one();
            self.go.notified().await;
        }
        tokio::time::sleep(Duration::from_millis(requests.len() as u64)).await;
    }
}

#[tokio::test]
async fn a_value_set_between_a_polls_slices_is_current_after_that_poll() {
    let backend = Hooked::new(Sliced {
        armed: Arc::default(),
        reading: Arc::default(),
        go: Arc::default(),
        held: Arc::default(),
    });
    let (armed, reading, go, held) = (
        backend.hooks.armed.clone(),
        backend.hooks.reading.clone(),
        backend.hooks.go.clone(),
        backend.hooks.held.clone(),
    );
    let server = common::start_on("", &common::user_pub(), Some(Box::new(backend))).await;
    let section = &server.section.section;
    let id = section.latest().table.lookup(b"TEST_1").expect("TEST_1");
    let mut watcher = server.client().await;
    watcher.send(b"EN:*\r\n").await;
    watcher
        .wait_for_line(b"DIFF:TEST_1,0\r\n", Duration::from_secs(10))
        .await;
    let mut polls = section.subscribe(&["TEST_1"]).every_poll().every_change();

    // A poll holds in the slice that reads TEST_1, one of many.
    armed.store(true, Ordering::SeqCst);
    tokio::time::timeout(Duration::from_secs(10), reading.notified())
        .await
        .expect("a poll's read");
    let slice = held.lock().unwrap().clone();
    assert!(
        slice.contains(&(0, 2)) && slice.len() < 20,
        "the held slice read TEST_1 and not the whole poll: {slice:?}"
    );
    let mut writer = server.client().await;
    writer.send(b"SET:TEST_1,5\r\n").await;
    // The SET reaches the link's queue meanwhile (a session's hop).
    tokio::time::sleep(Duration::from_millis(500)).await;
    go.notify_one();
    writer.expect(b"DIFF:TEST_1,5\r\n").await;
    watcher
        .wait_for_line(b"DIFF:TEST_1,5\r\n", Duration::from_secs(10))
        .await;

    // The SET's publish, then that poll's: the value is the SET's, and
    // current (live, and owed to every client as news).
    let set_seq = section.latest().slot(id).changed_seq;
    let polled = loop {
        let batch = tokio::time::timeout(Duration::from_secs(10), polls.next())
            .await
            .expect("the poll's publish")
            .expect("the section runs");
        let snapshot = batch.snapshot;
        if snapshot.poll_seq > set_seq && snapshot.seq == snapshot.poll_seq {
            break snapshot;
        }
    };
    assert_eq!(polled.slot(id).text(), Some(&b"5"[..]));
    assert!(
        polled.current(id).is_some(),
        "TEST_1 (read back at {set_seq}) is not current after the poll published at {}",
        polled.poll_seq
    );
    watcher.ask("GET:TEST_1\r\n", "GET:TEST_1,5\r\n").await;
}

const IDLE: u8 = 0;
const ARMED: u8 = 1;
/// Armed, and a read came: the next take of marks starts a finish.
const READ_SINCE: u8 = 2;

/// Once armed, the link's first take of uncertain marks after a read (the
/// start of a poll's finish, after its last read slice) holds until the
/// test says go.
struct HeldFinish {
    /// [`IDLE`], [`ARMED`] or [`READ_SINCE`].
    state: Arc<AtomicU8>,
    holding: Arc<Notify>,
    go: std::sync::mpsc::Receiver<()>,
}

#[async_trait]
impl Hooks for HeldFinish {
    fn describe(&self) -> String {
        "in-process memory, its finish held".into()
    }

    async fn before_read(&mut self, _requests: &[ReadRequest]) {
        let _ = self
            .state
            .compare_exchange(ARMED, READ_SINCE, Ordering::SeqCst, Ordering::SeqCst);
    }

    fn take_uncertain(&mut self) -> Option<Vec<Box<[u8]>>> {
        if self
            .state
            .compare_exchange(READ_SINCE, IDLE, Ordering::SeqCst, Ordering::SeqCst)
            .is_ok()
        {
            self.holding.notify_one();
            // A blocking wait, as a finish is synchronous: the link's
            // thread is held, the clients' runtime goes on.
            let _ = self.go.recv_timeout(Duration::from_secs(10));
        }
        None
    }
}

/// A SET that comes in while the link applies a poll's values is served
/// between the pieces of that finish, before the poll is published: the
/// link no longer holds it for all of them (a poll of 90,000 variables
/// takes tens of milliseconds to apply in a debug build: many pieces of
/// 2 ms).
#[tokio::test]
async fn a_set_during_a_polls_finish_is_served_before_the_poll_is_published() {
    const VARS: usize = 90_000;
    let mut user = b"; many small variables\r\n".to_vec();
    for i in 0..VARS {
        user.extend_from_slice(format!(" V{i} R B {i} USINT PUB_INOUT\r\n").as_bytes());
    }
    let (go, go_rx) = std::sync::mpsc::channel();
    let backend = Hooked::new(HeldFinish {
        state: Arc::default(),
        holding: Arc::default(),
        go: go_rx,
    });
    let (state, holding) = (backend.hooks.state.clone(), backend.hooks.holding.clone());
    let server = common::start_on("", &user, Some(Box::new(backend))).await;
    let section = &server.section.section;
    let last = format!("V{}", VARS - 1);
    let id = section
        .latest()
        .table
        .lookup(last.as_bytes())
        .expect("the last variable");
    // Every variable wanted, so that every poll reads and applies them all.
    let mut polls = section.subscribe(&["V*"]).every_poll().every_change();
    let polled = tokio::time::timeout(Duration::from_secs(30), async {
        loop {
            let batch = polls.next().await.expect("the section runs");
            if batch.snapshot.slot(id).text() == Some(&b"0"[..]) {
                break;
            }
        }
    })
    .await;
    polled.expect("a poll of every variable");

    state.store(ARMED, Ordering::SeqCst);
    tokio::time::timeout(Duration::from_secs(10), holding.notified())
        .await
        .expect("a poll's finish");
    // The last poll published before the held one.
    let before = section.latest().poll_seq;
    // Through the apps' write path: queued for the link when it returns.
    let table = section.latest().table.clone();
    let pending = section
        .start_write(&table, last.as_bytes(), b"5")
        .expect("a valid SET");
    go.send(()).expect("the held finish waits");
    let reply = tokio::time::timeout(Duration::from_secs(10), pending.reply)
        .await
        .expect("the SET's answer")
        .expect("the link answers");
    let written = pending.target.confirm(reply).expect("the SET confirmed");
    assert_eq!(written.text, b"5");

    // The first publish that holds the SET's value came before the held
    // poll's own publish.
    let set_in = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            let batch = polls.next().await.expect("the section runs");
            if batch.snapshot.slot(id).text() == Some(&b"5"[..]) {
                break batch.snapshot;
            }
        }
    })
    .await
    .expect("the SET's publish");
    assert_eq!(
        set_in.poll_seq, before,
        "the SET was published after the poll whose finish it came in during"
    );
    // And that poll, published next, keeps it.
    let after = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            let batch = polls.next().await.expect("the section runs");
            if batch.snapshot.poll_seq > before {
                break batch.snapshot;
            }
        }
    })
    .await
    .expect("the held poll's publish");
    assert_eq!(after.slot(id).text(), Some(&b"5"[..]));
    assert!(
        after.current(id).is_some(),
        "{last} is current after the poll"
    );
}
