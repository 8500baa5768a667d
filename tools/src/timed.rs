//! The benchmarks' backend decorator (bench-modbus, bench-s7): each `read`
//! of the link timed and its requests counted, and the poll cycles found in
//! them.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use plccoms_core::driver::{Answer, PlcBackend, PlcError, PlcStatus, ReadRequest, WriteRequest};
use plccoms_core::metrics::BackendCounters;
use plccoms_protocol::Area;

/// One `read` call of the link.
#[derive(Clone, Copy)]
pub struct Read {
    start: Instant,
    end: Instant,
    /// Its first block.
    first: ReadRequest,
    transactions: u64,
    /// A SET's read-back (the read right after a write), not a poll slice.
    readback: bool,
}

/// A backend, each `read` timed and its requests counted.
pub struct Timed {
    inner: Box<dyn PlcBackend>,
    counters: Arc<BackendCounters>,
    reads: Arc<Mutex<Vec<Read>>>,
    after_write: bool,
}

impl Timed {
    pub fn new(inner: Box<dyn PlcBackend>, reads: Arc<Mutex<Vec<Read>>>) -> Timed {
        Timed {
            inner,
            counters: Arc::default(),
            reads,
            after_write: false,
        }
    }
}

/// Poll cycles in `reads` (the link reads a poll in slices, SETs between
/// them): each begins with the plan's first block. The partial cycles at
/// either end are left out. Per cycle: duration and transactions.
pub fn cycles(reads: &[Read]) -> Vec<(Duration, u64)> {
    let polls: Vec<&Read> = reads.iter().filter(|r| !r.readback).collect();
    let Some(first) = polls
        .iter()
        .map(|r| r.first)
        .min_by_key(|r| (r.area, r.offset))
    else {
        return Vec::new();
    };
    let starts: Vec<usize> = (0..polls.len())
        .filter(|&i| polls[i].first == first)
        .collect();
    starts
        .windows(2)
        .map(|w| {
            let slices = &polls[w[0]..w[1]];
            let end = slices.last().map_or(slices[0].end, |r| r.end);
            (
                end - slices[0].start,
                slices.iter().map(|r| r.transactions).sum(),
            )
        })
        .collect()
}

#[async_trait]
impl PlcBackend for Timed {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn max_read_block(&self, area: Area) -> u32 {
        self.inner.max_read_block(area)
    }
    fn read_gap(&self, area: Area) -> Option<u32> {
        self.inner.read_gap(area)
    }
    fn read_align(&self, area: Area) -> u32 {
        self.inner.read_align(area)
    }
    fn probe_backoff(&self) -> (Duration, Duration) {
        self.inner.probe_backoff()
    }
    fn max_file_block(&self) -> u32 {
        self.inner.max_file_block()
    }
    fn answer_timeout(&self) -> Duration {
        self.inner.answer_timeout()
    }
    fn set_counters(&mut self, counters: Arc<BackendCounters>) {
        self.counters = counters.clone();
        self.inner.set_counters(counters);
    }
    async fn connect(&mut self) -> Result<String, PlcError> {
        self.inner.connect().await
    }
    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let before = self.counters.requests.get();
        let start = Instant::now();
        let answers = self.inner.read(requests).await;
        if let Some(&first) = requests.first() {
            self.reads.lock().unwrap().push(Read {
                start,
                end: Instant::now(),
                first,
                transactions: self.counters.requests.get() - before,
                readback: std::mem::take(&mut self.after_write),
            });
        }
        answers
    }
    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        self.after_write = true;
        self.inner.write(requests).await
    }
    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        self.inner.status().await
    }
}
