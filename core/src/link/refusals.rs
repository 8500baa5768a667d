//! What the PLC refuses to read, learned while polling, so that one bad
//! variable does not take its neighbours down with it.
//!
//! A poll block the PLC refuses (a Modbus device answers "illegal data
//! address" for a register it lacks, or for a gap the block reads through)
//! is split in halves, each read on its own, down to the variable at fault.
//! What is found is remembered: a variable whose own read is refused is
//! polled alone (its value stays stale, the others go on), and the planner
//! never reads through its range again; a failed read whose halves both
//! succeed marks the span between them as a hole not to read through. A
//! variable polled alone that reads again joins the others. Everything is
//! forgotten with a new table or a new link.

use std::collections::HashSet;

use futures::future::BoxFuture;
use tracing::{info, warn};

use super::plan::{Limits, Range, ReadPlan};
use crate::driver::{PlcBackend, PlcError, Refusal};
use crate::vars::{VarId, VarTable};

#[derive(Debug, Default)]
pub struct Refusals {
    /// Spans not to read through: refused variables' ranges, and the cuts
    /// between ranges that read alone but not together (length 0 when they
    /// are adjacent).
    pub holes: Vec<Range>,
    /// Variables whose own read is refused: polled alone.
    pub alone: HashSet<VarId>,
}

/// A poll variable and its range.
pub type Wanted = (VarId, Range);

impl Refusals {
    pub fn clear(&mut self) {
        self.holes.clear();
        self.alone.clear();
    }

    /// A variable polled alone read again: it joins the others.
    pub fn readable_again(&mut self, section: &str, table: &VarTable, id: VarId, range: Range) {
        if self.alone.remove(&id) {
            self.holes.retain(|h| *h != range);
            info!(section = %section, "{}: read again; polled with the others", name(table, id));
        }
    }

    /// Splits the refused `group` (sorted by area and offset) until the
    /// variables at fault are found; the values of the others, as read on
    /// the way, go to `found`.
    pub async fn split(
        &mut self,
        section: &str,
        table: &VarTable,
        backend: &mut dyn PlcBackend,
        limits: &Limits,
        group: Vec<Wanted>,
        found: &mut Vec<(VarId, Vec<u8>)>,
    ) -> Result<(), PlcError> {
        let mut split = Split {
            section,
            table,
            backend,
            limits,
            refusals: self,
            found,
        };
        split.read(group).await.map(|_| ())
    }
}

fn name(table: &VarTable, id: VarId) -> String {
    plccoms_protocol::cp1250::decode(&table.var(id).name).into_owned()
}

struct Split<'a> {
    section: &'a str,
    table: &'a VarTable,
    backend: &'a mut dyn PlcBackend,
    limits: &'a Limits,
    refusals: &'a mut Refusals,
    found: &'a mut Vec<(VarId, Vec<u8>)>,
}

impl Split<'_> {
    /// Reads `group` as one plan; splits what is refused. Returns whether
    /// all of it read.
    fn read(&mut self, group: Vec<Wanted>) -> BoxFuture<'_, Result<bool, PlcError>> {
        Box::pin(async move {
            let ranges: Vec<Range> = group.iter().map(|(_, r)| *r).collect();
            let plan = ReadPlan::with_holes(&ranges, &[], self.limits, &self.refusals.holes);
            let (data, _) = plan.assemble_answers(self.backend.read(plan.blocks()).await?);
            let mut refused: Vec<(Wanted, Refusal)> = Vec::new();
            for (i, wanted) in group.iter().enumerate() {
                match plan.range_answer(&data, i) {
                    Ok(bytes) => self.found.push((wanted.0, bytes.to_vec())),
                    Err(e) => refused.push((*wanted, e)),
                }
            }
            match refused.len() {
                0 => Ok(true),
                1 => {
                    let ((id, range), exception) = refused[0];
                    if group.len() == 1 {
                        self.refuse(id, range, exception);
                    } else {
                        // Refused together with others, but maybe not alone.
                        self.read(vec![(id, range)]).await?;
                    }
                    Ok(false)
                }
                n => {
                    let mut refused: Vec<Wanted> = refused.into_iter().map(|(w, _)| w).collect();
                    let second = refused.split_off(n / 2);
                    let (first_last, second_first) = (refused[n / 2 - 1].1, second[0].1);
                    let first_ok = self.read(refused).await?;
                    let second_ok = self.read(second).await?;
                    if first_ok && second_ok {
                        self.cut(first_last, second_first);
                    }
                    Ok(false)
                }
            }
        })
    }

    fn refuse(&mut self, id: VarId, range: Range, exception: Refusal) {
        if self.refusals.alone.insert(id) {
            self.refusals.holes.push(range);
            let var = self.table.var(id);
            let hint = self
                .backend
                .refusal_hint(var.area, var.offset, &exception)
                .map(|hint| format!("; {hint}"))
                .unwrap_or_default();
            warn!(
                section = %self.section,
                "{}: the PLC refuses to read it ({exception}); polled alone, the others go on{hint}",
                name(self.table, id)
            );
        }
    }

    /// Two ranges read alone but not in one block: never join them again.
    fn cut(&mut self, before: Range, after: Range) {
        if before.area != after.area {
            return;
        }
        let from = before.offset + before.len;
        let hole = Range {
            area: before.area,
            offset: from.min(after.offset),
            len: after.offset.saturating_sub(from),
        };
        warn!(
            section = %self.section,
            "the PLC refuses reads spanning {}{}..{} whose parts it answers: not reading through there again{}",
            hole.area,
            before.offset,
            after.offset + after.len,
            if hole.len == 0 {
                " (adjacent: a smaller block limit may be needed)"
            } else {
                ""
            }
        );
        self.refusals.holes.push(hole);
    }
}
