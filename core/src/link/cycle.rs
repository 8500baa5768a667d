//! One poll cycle: the plan (what to read: every variable some client or
//! subscriber enabled, plus the fixed ones, in as few block reads as
//! possible), the read, the publish with the poll's time, and what the
//! system variables say (`__PLC_RUN` HALT -> RUN, `__PF_CRC` changed). A
//! block the PLC refuses is split until only the variables at fault are
//! left out ([`super::refusals`]).

use std::collections::HashSet;
use std::time::Duration;

use plccoms_protocol::value::Value;
use tokio::time::Instant;
use tracing::{debug, info};

use super::plan::{Limits, Range, ReadPlan};
use super::refusals::Refusals;
use crate::changes::{PollStamp, Publisher};
use crate::driver::{PlcBackend, PlcError};
use crate::vars::{VarId, VarTable};

/// A poll is read in slices; SETs that came in meanwhile go before the next
/// slice, so a write waits for one slice, not a whole poll. A slice is as
/// many blocks as the last ones show fit in this time, at least
/// [`SLICE_MIN`] (so pipelined transactions keep flowing): on a fast link the
/// rest of a poll after its first slice is one read.
pub const SLICE_TIME: Duration = Duration::from_millis(2);
/// Fewest blocks a slice reads.
pub const SLICE_MIN: usize = 8;
/// Fewest values a piece of a poll's finish applies ([`Cycle::finish_piece`]);
/// the clock is read once a piece of this many.
pub const FINISH_PIECE_MIN: usize = 256;

/// A poll under way: what is read so far.
pub struct Round {
    limits: Limits,
    answers: Vec<crate::driver::Answer<Vec<u8>>>,
    /// Publisher sequence when it began: a value read after that (a SET's
    /// read-back) is newer than the poll's.
    first_seq: u64,
}

/// A poll being published: its answers, and how far they are applied.
pub struct Finishing {
    limits: Limits,
    first_seq: u64,
    stamp: PollStamp,
    data: super::plan::PlanData,
    refused: Vec<usize>,
    /// Index in the poll's variables of the next value to apply.
    next: usize,
    /// The values before this index were applied and published since,
    /// by a publish outside the poll.
    published_through: usize,
    /// The publisher's next sequence when the last piece ended.
    seq: u64,
    /// Read back since the poll began: kept, and counted as read by it.
    kept: Vec<VarId>,
    /// In a refused block: split to find which refuse.
    suspects: Vec<VarId>,
    /// What the backend said was uncertain of the poll's reads (`None`: a
    /// device without a per-value quality).
    uncertain: Option<HashSet<VarId>>,
}

/// What the system variables of a completed poll say.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SystemEvents {
    /// `__PLC_RUN` went from HALT to RUN: the link is re-initialised.
    pub halt_to_run: bool,
    /// `__PF_CRC` changed (from, to): the PLC runs another program, or a
    /// Modbus section's tag file was edited. The link logs it in its
    /// backend's terms.
    pub crc_changed: Option<(u64, u64)>,
    /// `__PF_CRC` as read, once known.
    pub pf_crc: Option<u64>,
}

#[derive(Default)]
pub struct Cycle {
    section: String,
    poll_vars: Vec<VarId>,
    plan: ReadPlan,
    last_run: Option<bool>,
    last_crc: Option<u64>,
    /// What the PLC refuses to read.
    refusals: Refusals,
    /// How long one block took in the last slice read.
    per_block: Option<Duration>,
    /// The plan must be made anew (refusals learned).
    replan: bool,
    /// What polls found that the link has not handled yet.
    events: SystemEvents,
}

impl Cycle {
    pub fn new(section: String) -> Cycle {
        Cycle {
            section,
            ..Cycle::default()
        }
    }

    /// A new table or a new link: plan anew, forget what was seen.
    pub fn reset(&mut self) {
        self.poll_vars.clear();
        self.plan = ReadPlan::default();
        self.last_run = None;
        self.last_crc = None;
        self.refusals.clear();
        self.per_block = None;
        self.events = SystemEvents::default();
    }

    /// The link was lost: a PLC that comes back is a new start for HALT/RUN.
    pub fn link_lost(&mut self) {
        self.last_run = None;
    }

    /// `__PF_CRC` as last read.
    pub fn pf_crc(&self) -> Option<u64> {
        self.last_crc
    }

    /// Block reads of the current plan.
    pub fn requests(&self) -> usize {
        self.plan.blocks().len()
    }

    fn ranges(&self, table: &crate::vars::VarTable) -> Vec<Range> {
        self.poll_vars
            .iter()
            .map(|&id| {
                let var = table.var(id);
                Range {
                    area: var.area,
                    offset: var.offset,
                    len: var.byte_len(),
                }
            })
            .collect()
    }

    fn rebuild_plan(&mut self, publisher: &Publisher, limits: &Limits) {
        let table = publisher.table().clone();
        let interest = publisher.interest().clone();
        self.poll_vars = (0..table.len() as VarId)
            .filter(|&id| table.is_fixed(id) || interest.is_wanted(id))
            .collect();
        let ranges = self.ranges(&table);
        let alone: Vec<bool> = self
            .poll_vars
            .iter()
            .map(|id| self.refusals.alone.contains(id))
            .collect();
        self.plan = ReadPlan::with_holes(&ranges, &alone, limits, &self.refusals.holes);
        self.replan = false;
        debug!(
            section = %self.section,
            variables = self.poll_vars.len(),
            requests = self.plan.blocks().len(),
            bytes = self.plan.bytes(),
            alone = self.refusals.alone.len(),
            "poll plan rebuilt"
        );
    }

    /// What the polls since the last call found in the system variables.
    pub fn take_events(&mut self) -> SystemEvents {
        std::mem::take(&mut self.events)
    }

    /// Starts a poll: plans anew when something changed. The blocks are
    /// then read a slice at a time ([`Cycle::read_slice`]), so SETs can go
    /// between slices, and [`Cycle::finish`] publishes.
    pub fn begin(&mut self, backend: &mut dyn PlcBackend, publisher: &Publisher) -> Round {
        // Marks of reads outside the poll (GETs, SET read-backs) are not its.
        backend.take_uncertain();
        let limits = Limits::of(backend);
        if publisher.interest().take_dirty() || self.poll_vars.is_empty() || self.replan {
            self.rebuild_plan(publisher, &limits);
        }
        Round {
            limits,
            answers: Vec::with_capacity(self.plan.blocks().len()),
            first_seq: publisher.next_seq(),
        }
    }

    /// A whole poll at once (between the blocks of a file transfer).
    pub async fn poll(
        &mut self,
        backend: &mut dyn PlcBackend,
        publisher: &mut Publisher,
    ) -> Result<(), PlcError> {
        let mut round = self.begin(backend, publisher);
        while self.read_slice(backend, &mut round).await? {}
        let finishing = self.finish_begin(backend, publisher, round);
        self.finish_end(backend, publisher, finishing).await
    }

    /// Reads the next slice of the plan; `false` once every block is read.
    /// A failed read is the link's to judge: nothing is published.
    pub async fn read_slice(
        &mut self,
        backend: &mut dyn PlcBackend,
        round: &mut Round,
    ) -> Result<bool, PlcError> {
        let blocks = self.plan.blocks();
        let from = round.answers.len();
        let fit = match self.per_block {
            Some(each) if !each.is_zero() => (SLICE_TIME.as_nanos() / each.as_nanos()) as usize,
            Some(_) => usize::MAX,
            None => SLICE_MIN,
        };
        let to = from.saturating_add(fit.max(SLICE_MIN)).min(blocks.len());
        if from < to {
            let started = Instant::now();
            let answers = backend.read(&blocks[from..to]).await?;
            round.answers.extend(answers);
            self.per_block = Some(started.elapsed() / (to - from) as u32);
        }
        Ok(to < blocks.len())
    }

    /// Starts publishing what the poll read, stamped with the time the
    /// answers were complete: [`Cycle::finish_piece`] applies the values a
    /// piece at a time, so SETs can go between pieces as between slices,
    /// and [`Cycle::finish_end`] publishes the poll.
    pub fn finish_begin(
        &mut self,
        backend: &mut dyn PlcBackend,
        publisher: &Publisher,
        round: Round,
    ) -> Finishing {
        let stamp = PollStamp::now();
        let (data, refused) = self.plan.assemble_answers(round.answers);
        // Marks of the poll's reads (those before it were taken at its
        // start); applied with each value, so a SET between pieces cannot
        // take a mark of the poll's read.
        let uncertain = uncertain_of(backend, publisher.table());
        Finishing {
            limits: round.limits,
            first_seq: round.first_seq,
            stamp,
            data,
            refused,
            next: 0,
            published_through: 0,
            seq: publisher.next_seq(),
            kept: Vec::new(),
            suspects: Vec::new(),
            uncertain,
        }
    }

    /// Applies the next piece of the poll's values: as many as fit in
    /// `budget`, at least [`FINISH_PIECE_MIN`]. `false` once every value is
    /// applied. A variable read back since the poll began (a SET between
    /// its slices or pieces) keeps that newer value.
    pub fn finish_piece(
        &mut self,
        publisher: &mut Publisher,
        finishing: &mut Finishing,
        budget: Duration,
    ) -> bool {
        let f = finishing;
        if publisher.next_seq() != f.seq {
            // Published since the last piece (a SET's read-back): what the
            // poll applied so far carries an earlier sequence than its own.
            f.published_through = f.next;
        }
        let table = publisher.table().clone();
        let started = Instant::now();
        let mut index = f.next;
        while index < self.poll_vars.len() {
            if (index - f.next).is_multiple_of(FINISH_PIECE_MIN)
                && index > f.next
                && started.elapsed() >= budget
            {
                break;
            }
            let id = self.poll_vars[index];
            let alone = self.refusals.alone.contains(&id);
            match self.plan.range_answer(&f.data, index) {
                Ok(bytes) => {
                    if !apply(publisher, f, id, bytes, f.uncertain.as_ref()) {
                        f.kept.push(id);
                    }
                    if alone {
                        let range = self.ranges(&table)[index];
                        self.refusals
                            .readable_again(&self.section, &table, id, range);
                        self.replan = true;
                    }
                }
                Err(_) if alone => {}
                Err(_) => f.suspects.push(id),
            }
            index += 1;
        }
        f.next = index;
        f.seq = publisher.next_seq();
        index < self.poll_vars.len()
    }

    /// Publishes the poll once [`Cycle::finish_piece`] applied every value:
    /// splits refused blocks; system-variable events wait in
    /// [`Cycle::take_events`].
    pub async fn finish_end(
        &mut self,
        backend: &mut dyn PlcBackend,
        publisher: &mut Publisher,
        mut finishing: Finishing,
    ) -> Result<(), PlcError> {
        while self.finish_piece(publisher, &mut finishing, Duration::MAX) {}
        let mut f = finishing;
        let mut kept = std::mem::take(&mut f.kept);
        let table = publisher.table().clone();
        if !f.refused.is_empty() && !f.suspects.is_empty() {
            let ranges = self.ranges(&table);
            let mut group: Vec<_> = self
                .poll_vars
                .iter()
                .zip(ranges)
                .filter(|(id, _)| f.suspects.contains(id))
                .map(|(&id, range)| (id, range))
                .collect();
            group.sort_unstable_by_key(|(_, r)| (r.area, r.offset));
            let mut found = Vec::new();
            self.refusals
                .split(&self.section, &table, backend, &f.limits, group, &mut found)
                .await?;
            let uncertain = uncertain_of(backend, &table);
            for (id, bytes) in found {
                if !apply(publisher, &f, id, &bytes, uncertain.as_ref()) {
                    kept.push(id);
                }
            }
            self.replan = true;
        }
        // Not current after this publish unless counted as read by it: what
        // a publish between pieces carried, and what was read back newer.
        for index in 0..f.published_through {
            if self.plan.range_answer(&f.data, index).is_ok() {
                publisher.mark_read(self.poll_vars[index]);
            }
        }
        for id in kept {
            publisher.mark_read(id);
        }
        publisher.publish_poll(f.stamp);
        self.system_events(publisher);
        Ok(())
    }

    fn system_events(&mut self, publisher: &Publisher) {
        let table = publisher.table();
        let events = &mut self.events;
        let run = publisher
            .slot(table.plc_run())
            .value(table.var(table.plc_run()))
            .map(|v| matches!(v, Value::Bool(true)));
        if let Some(run) = run {
            if self.last_run != Some(run) {
                if self.last_run.is_some() {
                    info!(section = %self.section, "PLC is in {}", if run { "RUN" } else { "HALT" });
                }
                events.halt_to_run |= self.last_run == Some(false) && run;
                self.last_run = Some(run);
            }
        }
        let crc = match publisher
            .slot(table.pf_crc())
            .value(table.var(table.pf_crc()))
        {
            Some(Value::Unsigned(crc)) => Some(crc),
            _ => None,
        };
        if let (Some(last), Some(now)) = (self.last_crc, crc) {
            if last != now {
                events.crc_changed = Some((last, now));
            }
        }
        self.last_crc = crc;
        events.pf_crc = crc;
    }
}

/// The variables `backend` named uncertain since the last take, as ids of
/// `table`; `None` for a device without a per-value quality.
fn uncertain_of(backend: &mut dyn PlcBackend, table: &VarTable) -> Option<HashSet<VarId>> {
    let names = backend.take_uncertain()?;
    Some(names.iter().filter_map(|name| table.lookup(name)).collect())
}

/// Records what the poll read of `id`, with its quality; `false` (nothing
/// recorded) for a value read back since the poll began, which is newer.
fn apply(
    publisher: &mut Publisher,
    finishing: &Finishing,
    id: VarId,
    bytes: &[u8],
    uncertain: Option<&HashSet<VarId>>,
) -> bool {
    if publisher.read_seq(id) >= finishing.first_seq {
        return false;
    }
    let unix_ms = finishing.stamp.unix_ms;
    publisher.update(id, bytes, unix_ms);
    if let Some(uncertain) = uncertain {
        publisher.set_uncertain(id, uncertain.contains(&id), unix_ms);
    }
    true
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use async_trait::async_trait;
    use plccoms_protocol::value::FormatOptions;
    use plccoms_protocol::Area;

    use super::*;
    use crate::changes::Quality;
    use crate::driver::{Answer, PlcStatus, ReadRequest, WriteRequest};
    use crate::vars::table_of;

    /// R memory of INTs 16 bytes apart (as [`table_of`] lays them out);
    /// every read of it names `marked` uncertain.
    struct Memory {
        r: Vec<u8>,
        marked: Box<[u8]>,
        uncertain: Vec<Box<[u8]>>,
    }

    impl Memory {
        fn set_all(&mut self, value: impl Fn(usize) -> i16) {
            for i in 0..self.r.len() / 16 {
                self.r[i * 16..i * 16 + 2].copy_from_slice(&value(i).to_le_bytes());
            }
        }
    }

    #[async_trait]
    impl PlcBackend for Memory {
        fn describe(&self) -> String {
            "memory".into()
        }
        fn max_read_block(&self, _area: Area) -> u32 {
            1024
        }
        fn max_file_block(&self) -> u32 {
            1024
        }
        async fn connect(&mut self) -> Result<String, PlcError> {
            Ok("memory".into())
        }
        async fn read(
            &mut self,
            requests: &[ReadRequest],
        ) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
            Ok(requests
                .iter()
                .map(|r| {
                    let (from, to) = (r.offset as usize, (r.offset + r.len) as usize);
                    if r.area == Area::R {
                        self.uncertain.push(self.marked.clone());
                        Ok(self.r[from..to].to_vec())
                    } else {
                        Ok(vec![0; r.len as usize])
                    }
                })
                .collect())
        }
        async fn write(&mut self, _requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
            Err(PlcError::Unsupported("write"))
        }
        async fn status(&mut self) -> Result<PlcStatus, PlcError> {
            Ok(PlcStatus { run: true })
        }
        fn take_uncertain(&mut self) -> Option<Vec<Box<[u8]>>> {
            Some(std::mem::take(&mut self.uncertain))
        }
    }

    /// A SET served between two pieces of a poll's finish (its read-back
    /// published) leaves: the poll's values applied before it published
    /// with it, its own value kept over the poll's, and after the poll's
    /// publish every value current, each with the poll's quality.
    #[tokio::test]
    async fn a_set_between_pieces_of_a_finish_keeps_its_value_and_every_value_is_current() {
        const N: usize = 2000;
        let names: Vec<String> = (0..N).map(|i| format!("V{i}")).collect();
        let vars: Vec<(&str, &str)> = names.iter().map(|n| (n.as_str(), "INT")).collect();
        let table = Arc::new(table_of(&vars));
        let (mut publisher, stream) = Publisher::new(
            table.clone(),
            FormatOptions::default(),
            Duration::from_secs(60),
        );
        let id = |i: usize| table.lookup(names[i].as_bytes()).expect("a variable");
        for i in 0..N {
            publisher.interest().add(id(i));
        }
        let mut memory = Memory {
            r: vec![0; N * 16],
            marked: b"V5"[..].into(),
            uncertain: Vec::new(),
        };
        memory.set_all(|i| i as i16);
        let mut cycle = Cycle::new("test".into());
        cycle
            .poll(&mut memory, &mut publisher)
            .await
            .expect("a poll");
        let first = stream.latest();
        assert_eq!(first.slot(id(7)).text(), Some(&b"7"[..]));
        assert_eq!(first.quality(id(5)), Quality::Stale, "V5 read uncertain");
        assert_eq!(first.quality(id(6)), Quality::Good);

        memory.set_all(|i| i as i16 + 10_000);
        let mut round = cycle.begin(&mut memory, &publisher);
        while cycle
            .read_slice(&mut memory, &mut round)
            .await
            .expect("read")
        {}
        let mut finishing = cycle.finish_begin(&mut memory, &publisher, round);
        assert!(cycle.finish_piece(&mut publisher, &mut finishing, Duration::ZERO));
        // The fixed variables come first in the poll; the piece ends at
        // its minimum with no time to spare.
        let applied = FINISH_PIECE_MIN - table.fixed_count();
        let text =
            |publisher: &Publisher, i: usize| publisher.slot(id(i)).text().map(<[u8]>::to_vec);
        let last = applied - 1;
        assert_eq!(
            text(&publisher, last),
            Some(format!("{}", last + 10_000).into_bytes())
        );
        assert_eq!(
            text(&publisher, applied),
            Some(format!("{applied}").into_bytes())
        );

        // A SET of one variable the poll applied and of one it has not yet.
        let now = PollStamp::now().unix_ms;
        publisher.update(id(10), &7i16.to_le_bytes(), now);
        publisher.update(id(1000), &8i16.to_le_bytes(), now);
        publisher.publish();
        let between = stream.latest();
        assert!(between.changed.contains(&id(0)) && between.changed.contains(&id(1000)));
        assert!(!between.changed.contains(&id(applied)));
        assert!((0..N).all(|i| between.current(id(i)).is_some()));

        while cycle.finish_piece(&mut publisher, &mut finishing, Duration::ZERO) {}
        cycle
            .finish_end(&mut memory, &mut publisher, finishing)
            .await
            .expect("the poll's end");
        let polled = stream.latest();
        assert_eq!(polled.poll_seq, polled.seq);
        let text = |i: usize| polled.slot(id(i)).text().map(|t| t.to_vec());
        assert_eq!(text(10), Some(b"7".to_vec()), "the SET's value, applied");
        assert_eq!(
            text(1000),
            Some(b"8".to_vec()),
            "the SET's value, not applied yet"
        );
        assert_eq!(text(0), Some(b"10000".to_vec()));
        assert_eq!(
            text(N - 1),
            Some(format!("{}", N - 1 + 10_000).into_bytes())
        );
        for i in 0..N {
            assert!(
                polled.current(id(i)).is_some(),
                "V{i} not current after the poll"
            );
        }
        assert_eq!(polled.quality(id(5)), Quality::Stale, "V5 read uncertain");
        assert_eq!(polled.quality(id(4)), Quality::Good);
        assert_eq!(polled.quality(id(1500)), Quality::Good);
    }
}
