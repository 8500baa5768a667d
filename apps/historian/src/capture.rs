//! Event capture (`HISTORY_TRIGGER`, `HISTORY_PRE`, `HISTORY_POST`): on a
//! rising edge of a BOOL variable, every recorded variable is recorded at
//! each cycle from PRE cycles before the edge to POST cycles after, changed
//! or not.
//!
//! The cycles before are the last PRE poll snapshots, kept in a ring. A
//! snapshot shares every value that did not change with the next one
//! (copy-on-write chunks), so the ring costs little more than the changes
//! of PRE cycles. An edge seen while a capture runs extends it; a cycle is
//! never handed out twice.

use std::collections::VecDeque;
use std::sync::Arc;

use plccoms_protocol::value::Value;

use plccoms_core::changes::Snapshot;
use plccoms_core::vars::VarId;

pub struct Capture {
    trigger: VarId,
    pre: usize,
    post: u32,
    ring: VecDeque<Arc<Snapshot>>,
    last: Option<bool>,
    /// Cycles still to record after the last edge.
    remaining: u32,
    /// Poll sequence of the last cycle handed out.
    captured_to: u64,
}

/// What a cycle brings.
#[derive(Default)]
pub struct Captured {
    /// The trigger rose at this cycle.
    pub edge: bool,
    /// Cycles to record in full, oldest first.
    pub cycles: Vec<Arc<Snapshot>>,
}

impl Capture {
    pub fn new(trigger: VarId, pre: u32, post: u32) -> Capture {
        Capture {
            trigger,
            pre: pre as usize,
            post,
            ring: VecDeque::with_capacity(pre as usize),
            last: None,
            remaining: 0,
            captured_to: 0,
        }
    }

    /// One poll cycle's snapshot, in order.
    pub fn on_poll(&mut self, snapshot: &Arc<Snapshot>) -> Captured {
        let mut captured = Captured::default();
        let now = match snapshot.current(self.trigger).map(|slot| {
            slot.value(snapshot.table.var(self.trigger))
                .is_some_and(|v| matches!(v, Value::Bool(true)))
        }) {
            Some(on) => Some(on),
            // Not read this cycle (link lost, read refused): no edge either way.
            None => self.last,
        };
        let rose = self.last == Some(false) && now == Some(true);
        self.last = now;
        if rose {
            captured.edge = true;
            captured.cycles.extend(
                self.ring
                    .iter()
                    .filter(|s| s.poll_seq > self.captured_to)
                    .cloned(),
            );
            self.remaining = self.post + 1;
        }
        if self.remaining > 0 {
            self.remaining -= 1;
            captured.cycles.push(snapshot.clone());
            self.captured_to = snapshot.poll_seq;
        }
        if self.pre > 0 {
            if self.ring.len() == self.pre {
                self.ring.pop_front();
            }
            self.ring.push_back(snapshot.clone());
        }
        captured
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use plccoms_protocol::value::FormatOptions;

    use super::*;
    use plccoms_core::changes::{PollStamp, Publisher};
    use plccoms_core::vars::table_of;

    fn cycle(publisher: &mut Publisher, trigger: VarId, on: bool) -> Arc<Snapshot> {
        let stream = publisher.stream();
        publisher.update(trigger, &[u8::from(on)], 0);
        publisher.publish_poll(PollStamp::now());
        stream.latest()
    }

    #[test]
    fn pre_and_post_cycles_around_rising_edges() {
        let table = Arc::new(table_of(&[("T", "BOOL")]));
        let t = table.lookup(b"T").unwrap();
        let (mut publisher, _stream) =
            Publisher::new(table, FormatOptions::default(), Duration::from_secs(1));
        let mut capture = Capture::new(t, 2, 3);
        let mut seen = Vec::new();
        let mut edges = Vec::new();
        let levels = [0, 0, 0, 1, 1, 0, 0, 0, 0, 0, 1, 0, 1, 0, 0, 0, 0, 0];
        for (i, &on) in levels.iter().enumerate() {
            let snapshot = cycle(&mut publisher, t, on == 1);
            let captured = capture.on_poll(&snapshot);
            if captured.edge {
                edges.push(i);
            }
            seen.extend(captured.cycles.iter().map(|s| s.poll_seq));
        }
        assert_eq!(edges, [3, 10, 12]);
        // Polls are numbered from 1: cycle i is poll i + 1. Edge at 3: 2
        // before, it, 3 after; edge at 10: 8, 9, 10..13, extended by the edge
        // at 12 to 15, with no cycle twice.
        let expected: Vec<u64> = [1, 2, 3, 4, 5, 6, 8, 9, 10, 11, 12, 13, 14, 15]
            .iter()
            .map(|i| i + 1)
            .collect();
        assert_eq!(seen, expected);
    }
}
