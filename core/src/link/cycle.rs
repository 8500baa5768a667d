//! One poll cycle: the plan (what to read: every variable some client or
//! subscriber enabled, plus the fixed ones, in as few block reads as
//! possible), the read, the publish with the poll's time, and what the
//! system variables say (`__PLC_RUN` HALT -> RUN, `__PF_CRC` changed). A
//! block the PLC refuses is split until only the variables at fault are
//! left out ([`super::refusals`]).

use std::time::Duration;

use plccoms_protocol::value::Value;
use tokio::time::Instant;
use tracing::{debug, info};

use super::plan::{Limits, Range, ReadPlan};
use super::refusals::Refusals;
use crate::changes::{PollStamp, Publisher};
use crate::driver::{PlcBackend, PlcError};
use crate::vars::VarId;

/// A poll is read in slices; SETs that came in meanwhile go before the next
/// slice, so a write waits for one slice, not a whole poll. A slice is as
/// many blocks as the last ones show fit in this time, at least
/// [`SLICE_MIN`] (so pipelined transactions keep flowing): on a fast link the
/// rest of a poll after its first slice is one read.
pub const SLICE_TIME: Duration = Duration::from_millis(2);
/// Fewest blocks a slice reads.
pub const SLICE_MIN: usize = 8;

/// A poll under way: what is read so far.
pub struct Round {
    limits: Limits,
    answers: Vec<crate::driver::Answer<Vec<u8>>>,
    /// Publisher sequence when it began: a value read after that (a SET's
    /// read-back) is newer than the poll's.
    first_seq: u64,
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
        self.finish(backend, publisher, round).await
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

    /// Publishes what the poll read, stamped with the time the answers were
    /// complete (a variable a SET read back meanwhile keeps that value);
    /// splits refused blocks; system-variable events wait in
    /// [`Cycle::take_events`].
    pub async fn finish(
        &mut self,
        backend: &mut dyn PlcBackend,
        publisher: &mut Publisher,
        round: Round,
    ) -> Result<(), PlcError> {
        let stamp = PollStamp::now();
        let (data, refused) = self.plan.assemble_answers(round.answers);
        let table = publisher.table().clone();
        let newer = |publisher: &Publisher, id: VarId| publisher.read_seq(id) >= round.first_seq;
        // Read back since the poll began (a SET between its slices): kept,
        // and read by this poll as much as what it read itself.
        let mut kept = Vec::new();
        let mut suspects = Vec::new();
        for (index, &id) in self.poll_vars.iter().enumerate() {
            let alone = self.refusals.alone.contains(&id);
            match self.plan.range_answer(&data, index) {
                Ok(bytes) => {
                    if newer(publisher, id) {
                        kept.push(id);
                    } else {
                        publisher.update(id, bytes, stamp.unix_ms);
                    }
                    if alone {
                        let range = self.ranges(&table)[index];
                        self.refusals
                            .readable_again(&self.section, &table, id, range);
                        self.replan = true;
                    }
                }
                Err(_) if alone => {}
                Err(_) => suspects.push(id),
            }
        }
        if !refused.is_empty() && !suspects.is_empty() {
            let ranges = self.ranges(&table);
            let mut group: Vec<_> = self
                .poll_vars
                .iter()
                .zip(ranges)
                .filter(|(id, _)| suspects.contains(id))
                .map(|(&id, range)| (id, range))
                .collect();
            group.sort_unstable_by_key(|(_, r)| (r.area, r.offset));
            let mut found = Vec::new();
            self.refusals
                .split(
                    &self.section,
                    &table,
                    backend,
                    &round.limits,
                    group,
                    &mut found,
                )
                .await?;
            for (id, bytes) in found {
                if newer(publisher, id) {
                    kept.push(id);
                } else {
                    publisher.update(id, &bytes, stamp.unix_ms);
                }
            }
            self.replan = true;
        }
        if let Some(names) = backend.take_uncertain() {
            let uncertain: std::collections::HashSet<VarId> =
                names.iter().filter_map(|name| table.lookup(name)).collect();
            // What this poll read carries the publish's sequence (a SET's
            // read-back meanwhile was published already).
            let seq = publisher.next_seq();
            for &id in &self.poll_vars {
                if publisher.read_seq(id) == seq {
                    publisher.set_uncertain(id, uncertain.contains(&id), stamp.unix_ms);
                }
            }
        }
        // Not current after this publish unless counted as read by it;
        // after the uncertain marks, which are of what the poll read.
        for id in kept {
            publisher.mark_read(id);
        }
        publisher.publish_poll(stamp);
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
