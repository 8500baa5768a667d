//! One client's view of the variable table: what it enabled and hid, its
//! deltas, and what it has been sent. Picks the DIFF lines it is owed from
//! each snapshot.
//!
//! Per-variable arrays are allocated on first use, so an idle client costs a
//! few hundred bytes whatever the size of the project.

use std::collections::HashMap;
use std::sync::Arc;

use plccoms_protocol::value::{Delta, FormatOptions, Value};

use plccoms_core::changes::Interest;
use plccoms_core::changes::Snapshot;
use plccoms_core::vars::{VarId, VarTable};

/// `sent` marker: take the next value seen as known without sending it.
const BASELINE: u64 = u64::MAX;

#[derive(Debug, Default, Clone)]
struct Bits(Vec<u64>);

impl Bits {
    fn get(&self, id: VarId) -> bool {
        self.0
            .get(id as usize / 64)
            .is_some_and(|w| w & (1 << (id % 64)) != 0)
    }

    /// Sets the bit; returns whether it changed.
    fn set(&mut self, id: VarId, on: bool, len: usize) -> bool {
        if self.0.is_empty() {
            if !on {
                return false;
            }
            self.0 = vec![0; len.div_ceil(64)];
        }
        let word = &mut self.0[id as usize / 64];
        let mask = 1u64 << (id % 64);
        let was = *word & mask != 0;
        if on {
            *word |= mask;
        } else {
            *word &= !mask;
        }
        was != on
    }
}

struct DeltaState {
    delta: Delta,
    last_sent: Option<Value>,
}

pub struct ClientTable {
    table: Arc<VarTable>,
    interest: Arc<Interest>,
    enabled: Bits,
    hidden: Bits,
    /// User variables this client enabled (fixed ones are always enabled).
    enabled_count: usize,
    hidden_count: usize,
    /// Per variable: change sequence of the value last sent (0 = none).
    sent: Vec<u64>,
    deltas: HashMap<VarId, DeltaState>,
    /// Enabled variables still owed their first value.
    pending: Vec<VarId>,
    seen_seq: u64,
    /// Every change up to this snapshot sequence was sent (through the
    /// shared DIFF block), whatever `sent` says.
    floor: u64,
    /// Highest sequence a SET's answer marked as sent.
    last_mark: u64,
}

impl ClientTable {
    /// A new client's table. With `all_enabled` (PF_VAR_DISABLED = No) every
    /// variable starts enabled. Fixed variables count as already sent as of
    /// `snapshot`, so a client hears of them when they change, not on connect.
    pub fn new(snapshot: &Snapshot, all_enabled: bool) -> ClientTable {
        let table = snapshot.table.clone();
        let mut client = ClientTable {
            interest: snapshot.interest.clone(),
            enabled: Bits::default(),
            hidden: Bits::default(),
            enabled_count: 0,
            hidden_count: 0,
            sent: Vec::new(),
            deltas: HashMap::new(),
            pending: Vec::new(),
            seen_seq: snapshot.seq,
            floor: 0,
            last_mark: 0,
            table,
        };
        client.ensure_sent();
        for id in 0..client.table.fixed_count() as VarId {
            let seen = snapshot.slot(id).changed_seq;
            client.sent[id as usize] = if seen == 0 { BASELINE } else { seen };
        }
        if all_enabled {
            let ids: Vec<VarId> = (0..client.table.len() as VarId).collect();
            for id in ids {
                client.enable(id);
            }
        }
        client
    }

    fn ensure_sent(&mut self) {
        if self.sent.is_empty() {
            // Only the fixed variables until something is enabled.
            self.sent = vec![0; self.table.fixed_count()];
        }
    }

    fn grow_sent(&mut self) {
        if self.sent.len() < self.table.len() {
            self.sent.resize(self.table.len(), 0);
        }
    }

    pub fn table(&self) -> &Arc<VarTable> {
        &self.table
    }

    pub fn is_enabled(&self, id: VarId) -> bool {
        self.table.is_fixed(id) || self.enabled.get(id)
    }

    pub fn is_hidden(&self, id: VarId) -> bool {
        self.hidden.get(id)
    }

    /// Enabled variables including the fixed ones, for WARNING:252.
    pub fn enabled_total(&self) -> usize {
        self.enabled_count + self.table.fixed_count()
    }

    pub fn hidden_count(&self) -> usize {
        self.hidden_count
    }

    /// Enables `id`; the next current value goes out as a DIFF.
    pub fn enable(&mut self, id: VarId) {
        if self.table.is_fixed(id) {
            self.sent[id as usize] = 0;
            self.pending.push(id);
            return;
        }
        if self.enabled.set(id, true, self.table.len()) {
            self.enabled_count += 1;
            self.interest.add(id);
            self.grow_sent();
            self.sent[id as usize] = 0;
            self.pending.push(id);
            if let Some(state) = self.deltas.get_mut(&id) {
                state.last_sent = None;
            }
        }
    }

    /// Disables `id`; fixed variables stay enabled.
    pub fn disable(&mut self, id: VarId) {
        if self.table.is_fixed(id) {
            return;
        }
        if self.enabled.set(id, false, self.table.len()) {
            self.enabled_count -= 1;
            self.interest.remove(id);
        }
    }

    pub fn set_delta(&mut self, id: VarId, delta: Delta) {
        if delta.is_zero() {
            self.deltas.remove(&id);
        } else {
            self.deltas
                .entry(id)
                .or_insert(DeltaState {
                    delta,
                    last_sent: None,
                })
                .delta = delta;
        }
    }

    pub fn set_hidden(&mut self, id: VarId, hidden: bool) {
        if self.hidden.set(id, hidden, self.table.len()) {
            if hidden {
                self.hidden_count += 1;
            } else {
                self.hidden_count -= 1;
            }
        }
    }

    /// The client was just sent `id`'s value as of `seq` (a SET's answer).
    pub fn mark_sent(&mut self, id: VarId, seq: u64, value: Option<Value>) {
        if !self.is_enabled(id) {
            return;
        }
        self.grow_sent();
        self.sent[id as usize] = seq;
        self.last_mark = self.last_mark.max(seq);
        if let Some(state) = self.deltas.get_mut(&id) {
            state.last_sent = value;
        }
        self.pending.retain(|&p| p != id);
    }

    /// Appends the DIFF lines owed from `snapshot` to `out`; returns how
    /// many.
    pub fn collect_diffs(
        &mut self,
        snapshot: &Snapshot,
        format: &FormatOptions,
        eol: &[u8],
        out: &mut Vec<u8>,
    ) -> usize {
        if !Arc::ptr_eq(&snapshot.table, &self.table) {
            // A new public file; the session rebuilds the table first.
            return 0;
        }
        let consecutive = snapshot.seq == self.seen_seq + 1;
        self.seen_seq = snapshot.seq;
        if !snapshot.online {
            return 0;
        }
        let mut lines = 0;
        // Values owed to variables just enabled go first, in the order they
        // were enabled (EN:*: the table's), then this snapshot's changes:
        // the first DIFFs after EN:* come in table order whether the first
        // snapshot the session sees holds the new variables' first poll
        // or not. The shared block would send some of them again.
        let owed = !self.pending.is_empty();
        if owed {
            let pending = std::mem::take(&mut self.pending);
            let mut waiting = Vec::new();
            for id in pending {
                if !self.is_enabled(id) {
                    continue;
                }
                if snapshot.current(id).is_some() {
                    // Owed its value now, whatever went out before.
                    lines += usize::from(self.offer(snapshot, id, format, eol, out, false));
                } else {
                    waiting.push(id);
                }
            }
            self.pending.extend(waiting);
        }
        if consecutive && !owed && self.takes_block(snapshot, eol) {
            if let Some(block) = snapshot.diff_block() {
                out.extend_from_slice(&block.bytes);
                lines += block.lines;
            }
            self.floor = snapshot.seq;
        } else if consecutive {
            for &id in &snapshot.changed {
                lines += usize::from(self.offer(snapshot, id, format, eol, out, true));
            }
        } else {
            // Missed snapshots: compare everything enabled.
            for id in 0..self.table.len() as VarId {
                if self.is_enabled(id) {
                    lines += usize::from(self.offer(snapshot, id, format, eol, out, true));
                }
            }
        }
        lines
    }

    /// Whether this client is owed exactly the snapshot's shared DIFF block:
    /// it enabled everything, has no deltas, owes no first values, answered
    /// no SET with this change, and uses the block's line end.
    fn takes_block(&self, snapshot: &Snapshot, eol: &[u8]) -> bool {
        let fixed = self.table.fixed_count();
        self.pending.is_empty()
            && self.deltas.is_empty()
            && self.enabled_count == self.table.len() - fixed
            && self.last_mark < snapshot.seq
            && self.sent[..fixed].iter().all(|&s| s != BASELINE)
            && snapshot.diff_block_eol().is_none_or(|b| b == eol)
    }

    fn offer(
        &mut self,
        snapshot: &Snapshot,
        id: VarId,
        format: &FormatOptions,
        eol: &[u8],
        out: &mut Vec<u8>,
        use_floor: bool,
    ) -> bool {
        if !self.is_enabled(id) {
            return false;
        }
        let Some(slot) = snapshot.current(id) else {
            return false;
        };
        let mut sent = self.sent.get(id as usize).copied().unwrap_or(0);
        if sent == BASELINE {
            // A fixed variable's first value is not news to this client.
            self.sent[id as usize] = slot.changed_seq;
            return false;
        }
        if use_floor {
            sent = sent.max(self.floor);
        }
        if slot.changed_seq <= sent {
            return false;
        }
        let var = self.table.var(id);
        // Most clients set no delta: skip the map lookup on the hot path.
        let state = if self.deltas.is_empty() {
            None
        } else {
            self.deltas.get_mut(&id)
        };
        if let Some(state) = state {
            let value = slot.value(var);
            if let (Some(now), Some(last)) = (&value, &state.last_sent) {
                if !now.exceeds(last, &state.delta, var.ty, format) {
                    return false;
                }
            }
            state.last_sent = value;
        }
        if self.sent.len() < self.table.len() {
            self.sent.resize(self.table.len(), 0);
        }
        self.sent[id as usize] = slot.changed_seq;
        let text = slot.text().expect("current slots have a value");
        out.extend_from_slice(b"DIFF:");
        out.extend_from_slice(&var.name);
        out.push(b',');
        out.extend_from_slice(text);
        out.extend_from_slice(eol);
        true
    }

    /// This client's settings carried over to the table of `snapshot` (a new
    /// public file), by name: enabled, hidden and deltas; names that
    /// vanished are dropped. Every enabled variable is owed its value again.
    pub fn remap(&self, snapshot: &Snapshot, all_enabled: bool) -> ClientTable {
        let mut next = ClientTable::new(snapshot, all_enabled);
        let new_table = next.table.clone();
        for (id, var) in self.table.vars().iter().enumerate() {
            let id = id as VarId;
            let Some(new_id) = new_table.lookup(&var.name) else {
                continue;
            };
            if !self.table.is_fixed(id) && self.enabled.get(id) {
                next.enable(new_id);
            } else if all_enabled && !new_table.is_fixed(new_id) && !self.enabled.get(id) {
                next.disable(new_id);
            }
            if self.hidden.get(id) {
                next.set_hidden(new_id, true);
            }
            if let Some(state) = self.deltas.get(&id) {
                next.set_delta(new_id, state.delta);
            }
        }
        next
    }

    /// The client leaves: its interest goes with it.
    pub fn release(&mut self) {
        for id in 0..self.table.len() as VarId {
            if !self.table.is_fixed(id) && self.enabled.get(id) {
                self.interest.remove(id);
            }
        }
        self.enabled = Bits::default();
        self.enabled_count = 0;
    }
}

impl Drop for ClientTable {
    fn drop(&mut self) {
        self.release();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::changes::{PollStamp, Publisher};
    use std::time::Duration;

    /// The names of the DIFF lines `client` is owed from `snapshot`.
    fn diff_names(client: &mut ClientTable, snapshot: &Snapshot) -> Vec<String> {
        let mut out = Vec::new();
        client.collect_diffs(snapshot, &FormatOptions::default(), b"\n", &mut out);
        String::from_utf8(out)
            .expect("text")
            .lines()
            .map(|l| l.split(',').next().unwrap_or_default().to_string())
            .collect()
    }

    /// A session slow to look (a loaded machine) first sees EN:*'s
    /// variables in the snapshot of their first poll: their values are
    /// that snapshot's changes, and the fixed ones', polled before, are
    /// owed. Both go out in table order, as when it looks in time.
    #[test]
    fn en_all_owes_every_first_value_in_table_order_when_the_first_poll_is_in() {
        let table = Arc::new(
            VarTable::from_public_text(
                "t.pub",
                b" A R B 0 INT PUB_INOUT\r\n B R B 2 INT PUB_INOUT\r\n",
            )
            .expect("table"),
        );
        assert_eq!(table.fixed_count(), 2);
        let (publisher, stream) = Publisher::new(
            table.clone(),
            FormatOptions::default(),
            Duration::from_secs(60),
        );
        let mut publisher = publisher;
        let poll = |publisher: &mut Publisher, ids: &[(VarId, &[u8])]| {
            let stamp = PollStamp::now();
            for (id, bytes) in ids {
                publisher.update(*id, bytes, stamp.unix_ms);
            }
            publisher.publish_poll(stamp);
        };
        // Connected: the fixed variables are polled before any EN.
        let fixed: [(VarId, &[u8]); 2] = [(0, &[0x04]), (1, &[0x80, 0xDA, 0x54, 0x15])];
        poll(&mut publisher, &fixed);
        let mut client = ClientTable::new(&stream.latest(), false);
        for id in 0..table.len() as VarId {
            client.enable(id);
        }
        // The first poll with A and B: the fixed ones again, unchanged.
        poll(
            &mut publisher,
            &[fixed[0], fixed[1], (2, &[5, 0]), (3, &[6, 0])],
        );
        assert_eq!(
            diff_names(&mut client, &stream.latest()),
            ["DIFF:__PLC_RUN", "DIFF:__PF_CRC", "DIFF:A", "DIFF:B"]
        );
        // Owed once: the next poll, nothing changed, sends nothing.
        poll(
            &mut publisher,
            &[fixed[0], fixed[1], (2, &[5, 0]), (3, &[6, 0])],
        );
        assert!(diff_names(&mut client, &stream.latest()).is_empty());
    }
}
