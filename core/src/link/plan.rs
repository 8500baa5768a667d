//! Read planning: turn a set of memory ranges into as few block reads as the
//! backend's [`Limits`] allow.
//!
//! Greedy covering with fixed windows, which is optimal for the number of
//! requests: a block starts at the first byte still needed and covers every
//! wanted byte within `max_block` bytes of it (reading through the gaps in
//! between, which costs bytes but no request), then ends at the last wanted
//! byte inside that window. A dense region of N bytes costs ceil(N /
//! max_block) requests. A range that straddles two blocks lies in adjacent
//! blocks and is reassembled from both.
//!
//! A backend may narrow this per area: a widest gap to read through (a
//! Modbus device may have holes in its register map), an alignment (whole
//! registers), and the planner never reads through a known hole: a span the
//! PLC refused (see `cycle`). Ranges marked alone get blocks of their own.

use plccoms_protocol::Area;

use crate::driver::{Answer, PlcBackend, ReadRequest, Refusal};

/// One wanted range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Range {
    pub area: Area,
    pub offset: u32,
    pub len: u32,
}

impl Range {
    fn end(&self) -> u64 {
        u64::from(self.offset) + u64::from(self.len)
    }

    /// Whether this hole forbids a block of `area` ending at `from` to grow
    /// to `to`: it lies in between (a hole of length 0 is a cut at its
    /// offset).
    fn blocks(&self, area: Area, from: u64, to: u64) -> bool {
        let offset = u64::from(self.offset);
        self.area == area
            && if self.len == 0 {
                from <= offset && offset <= to
            } else {
                offset < to && self.end() > from
            }
    }
}

/// How a backend wants reads cut, per area (indexed by [`Area::index`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest block, in bytes.
    pub max_block: [u32; 4],
    /// Widest run of unwanted bytes a block reads through to join two
    /// ranges (`u32::MAX`: any within the window).
    pub gap: [u32; 4],
    /// Blocks start and end on multiples of this.
    pub align: [u32; 4],
}

impl Limits {
    /// The same block limit everywhere, any gap, byte alignment.
    pub fn uniform(max_block: u32) -> Limits {
        Limits {
            max_block: [max_block; 4],
            gap: [u32::MAX; 4],
            align: [1; 4],
        }
    }

    /// What `backend` asks for.
    pub fn of(backend: &dyn PlcBackend) -> Limits {
        let mut limits = Limits::uniform(1);
        for area in Area::ALL {
            let i = area.index();
            limits.align[i] = backend.read_align(area).max(1);
            // A window is whole aligned units.
            let max = backend.max_read_block(area).max(1);
            limits.max_block[i] = (max - max % limits.align[i]).max(limits.align[i]);
            limits.gap[i] = backend.read_gap(area).unwrap_or(u32::MAX);
        }
        limits
    }

    /// `range` widened to whole aligned units: (start, end).
    fn aligned(&self, range: &Range) -> (u64, u64) {
        let align = u64::from(self.align[range.area.index()]);
        let start = u64::from(range.offset) / align * align;
        (start, range.end().div_ceil(align) * align)
    }
}

/// Where each requested range lands in the block data.
#[derive(Debug, Clone, Default)]
pub struct ReadPlan {
    blocks: Vec<ReadRequest>,
    /// Per input range: start in the concatenated block data.
    locations: Vec<usize>,
    lens: Vec<u32>,
}

impl ReadPlan {
    /// Plans reads for `ranges` (any order, overlaps allowed).
    pub fn new(ranges: &[Range], limits: &Limits) -> ReadPlan {
        ReadPlan::with_holes(ranges, &[], limits, &[])
    }

    /// Plans reads for `ranges`, never reading through `holes`; the ranges
    /// whose `alone` flag is set get blocks of their own (`alone` may be
    /// shorter than `ranges`: the rest are not alone).
    pub fn with_holes(
        ranges: &[Range],
        alone: &[bool],
        limits: &Limits,
        holes: &[Range],
    ) -> ReadPlan {
        let is_alone = |i: usize| alone.get(i).copied().unwrap_or(false);
        let mut order: Vec<u32> = (0..ranges.len() as u32)
            .filter(|&i| !is_alone(i as usize))
            .collect();
        order.sort_unstable_by_key(|&i| {
            let r = &ranges[i as usize];
            (r.area, r.offset)
        });
        let mut plan = ReadPlan {
            locations: vec![0; ranges.len()],
            lens: ranges.iter().map(|r| r.len).collect(),
            blocks: Vec::new(),
        };
        // The block being filled: index, and where its data starts.
        let mut open: Option<(usize, usize)> = None;
        let mut data_len = 0usize;
        for &i in &order {
            let r = ranges[i as usize];
            let a = r.area.index();
            let max = u64::from(limits.max_block[a].max(1));
            let (start, end) = limits.aligned(&r);
            let window = open.filter(|&(b, _)| {
                let block = &plan.blocks[b];
                let block_end = u64::from(block.offset) + u64::from(block.len);
                block.area == r.area
                    && start < u64::from(block.offset) + max
                    && (start < block_end
                        || (start - block_end <= u64::from(limits.gap[a])
                            && !holes.iter().any(|h| h.blocks(r.area, block_end, start))))
            });
            let offset = u64::from(r.offset);
            match window {
                Some((b, data_start)) => {
                    let block_start = u64::from(plan.blocks[b].offset);
                    // A range may start before the open block when it lies in
                    // the run of adjacent blocks an earlier range opened; their
                    // data is contiguous.
                    plan.locations[i as usize] = if offset >= block_start {
                        data_start + (offset - block_start) as usize
                    } else {
                        data_start - (block_start - offset) as usize
                    };
                    let block_end = block_start + u64::from(plan.blocks[b].len);
                    if end > block_end {
                        let grow_to = end.min(block_start + max);
                        plan.blocks[b].len = (grow_to - block_start) as u32;
                        data_len += (grow_to - block_end) as usize;
                        if end > grow_to {
                            // Straddles the window: continue in adjacent blocks.
                            open = Some(plan.push_blocks(r.area, grow_to, end, max, &mut data_len));
                        }
                    }
                }
                None => {
                    plan.locations[i as usize] = data_len + (offset - start) as usize;
                    open = Some(plan.push_blocks(r.area, start, end, max, &mut data_len));
                }
            }
        }
        for i in (0..ranges.len()).filter(|&i| is_alone(i)) {
            let r = ranges[i];
            let max = u64::from(limits.max_block[r.area.index()].max(1));
            let (start, end) = limits.aligned(&r);
            plan.locations[i] = data_len + (u64::from(r.offset) - start) as usize;
            plan.push_blocks(r.area, start, end, max, &mut data_len);
        }
        plan
    }

    /// Adds adjacent blocks covering `start..end`; returns the last one (the
    /// open window) and where its data starts.
    fn push_blocks(
        &mut self,
        area: Area,
        start: u64,
        end: u64,
        max: u64,
        data_len: &mut usize,
    ) -> (usize, usize) {
        let mut offset = start;
        loop {
            let len = (end - offset).min(max);
            let data_start = *data_len;
            self.blocks.push(ReadRequest {
                area,
                offset: offset as u32,
                len: len as u32,
            });
            *data_len += len as usize;
            offset += len;
            if offset >= end {
                return (self.blocks.len() - 1, data_start);
            }
        }
    }

    /// The block reads to issue, in order.
    pub fn blocks(&self) -> &[ReadRequest] {
        &self.blocks
    }

    /// Total bytes the blocks read.
    pub fn bytes(&self) -> usize {
        self.blocks.iter().map(|b| b.len as usize).sum()
    }

    /// Concatenates block answers (in `blocks()` order) into the data that
    /// `range_answer` indexes. Refused or short blocks are remembered, and
    /// returned by index, so that only the ranges they hold fail.
    pub fn assemble_answers(&self, answers: Vec<Answer<Vec<u8>>>) -> (PlanData, Vec<usize>) {
        let mut data = PlanData {
            data: Vec::with_capacity(self.bytes()),
            failed: Vec::new(),
        };
        let mut refused = Vec::new();
        let mut answers = answers.into_iter();
        for (i, block) in self.blocks.iter().enumerate() {
            let start = data.data.len();
            let len = block.len as usize;
            match answers.next() {
                Some(Ok(bytes)) if bytes.len() == len => data.data.extend_from_slice(&bytes),
                other => {
                    let exception = match other {
                        Some(Err(e)) => e,
                        _ => Refusal::BAD_PARAMETERS,
                    };
                    data.data.resize(start + len, 0);
                    data.failed.push((start..start + len, exception));
                    refused.push(i);
                }
            }
        }
        (data, refused)
    }

    /// The bytes of input range `index`, or the PLC's refusal of a block
    /// that holds part of it.
    pub fn range_answer<'a>(&self, data: &'a PlanData, index: usize) -> Answer<&'a [u8]> {
        let start = self.locations[index];
        let end = start + self.lens[index] as usize;
        if let Some((_, e)) = data
            .failed
            .iter()
            .find(|(r, _)| r.start < end && start < r.end)
        {
            return Err(*e);
        }
        Ok(&data.data[start..end])
    }

    pub fn len(&self) -> usize {
        self.locations.len()
    }

    pub fn is_empty(&self) -> bool {
        self.locations.is_empty()
    }
}

/// The data of all blocks of a plan, concatenated.
#[derive(Debug, Default)]
pub struct PlanData {
    data: Vec<u8>,
    failed: Vec<(std::ops::Range<usize>, Refusal)>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn r(area: Area, offset: u32, len: u32) -> Range {
        Range { area, offset, len }
    }

    /// The bytes of `memory` a range or block covers (areas share one memory).
    fn slice<'a>(memory: &'a [u8], range: &Range) -> &'a [u8] {
        &memory[range.offset as usize..(range.offset + range.len) as usize]
    }

    /// What a PLC holding `memory` answers to every block of `plan`.
    fn answers_from(memory: &[u8], plan: &ReadPlan) -> Vec<Answer<Vec<u8>>> {
        plan.blocks()
            .iter()
            .map(|b| Ok(slice(memory, &r(b.area, b.offset, b.len)).to_vec()))
            .collect()
    }

    #[test]
    fn dense_region_costs_the_minimum() {
        let ranges: Vec<Range> = (0..10_000).map(|i| r(Area::R, i * 4, 4)).collect();
        let plan = ReadPlan::new(&ranges, &Limits::uniform(1230));
        assert_eq!(plan.blocks().len(), 40_000usize.div_ceil(1230));
        assert_eq!(plan.bytes(), 40_000);
    }

    #[test]
    fn gaps_inside_a_window_cost_no_request_areas_never_merge() {
        let ranges = [
            r(Area::R, 100, 4),
            r(Area::R, 110, 2),
            r(Area::R, 1300, 1), // within 1230 of 100: same block
            r(Area::R, 1400, 8), // past the window: next block
            r(Area::S, 501, 1),  // other area
        ];
        let plan = ReadPlan::new(&ranges, &Limits::uniform(1230));
        assert_eq!(
            plan.blocks(),
            &[
                ReadRequest {
                    area: Area::S,
                    offset: 501,
                    len: 1
                },
                ReadRequest {
                    area: Area::R,
                    offset: 100,
                    len: 1201
                },
                ReadRequest {
                    area: Area::R,
                    offset: 1400,
                    len: 8
                },
            ]
        );
    }

    #[test]
    fn scattered_ranges_need_the_fewest_windows() {
        // 300 four-byte variables 40 bytes apart: 12,000 bytes of address
        // space, so ceil(11,964 / 1230) = 10 windows.
        let ranges: Vec<Range> = (0..300).map(|i| r(Area::R, i * 40, 4)).collect();
        let plan = ReadPlan::new(&ranges, &Limits::uniform(1230));
        assert_eq!(plan.blocks().len(), 10);
        assert!(plan.blocks().iter().all(|b| b.len <= 1230));
    }

    #[test]
    fn straddling_ranges_and_overlaps_reassemble() {
        // Memory where byte i holds i mod 251.
        let memory: Vec<u8> = (0..5000u32).map(|i| (i % 251) as u8).collect();
        let ranges = [
            r(Area::R, 8, 8),
            r(Area::R, 1, 10),
            r(Area::R, 10, 3),
            r(Area::R, 2000, 81),
            r(Area::R, 2005, 2),
            r(Area::R, 4000, 3),
            r(Area::R, 4005, 3),
        ];
        let plan = ReadPlan::new(&ranges, &Limits::uniform(7));
        let (data, refused) = plan.assemble_answers(answers_from(&memory, &plan));
        assert!(refused.is_empty());
        for (i, range) in ranges.iter().enumerate() {
            assert_eq!(
                plan.range_answer(&data, i).unwrap(),
                slice(&memory, range),
                "range {i}"
            );
        }
        assert!(plan.blocks().iter().all(|b| b.len <= 7));
    }

    #[test]
    fn refused_and_short_blocks_fail_only_their_ranges() {
        let ranges = [r(Area::R, 0, 4), r(Area::R, 2000, 4), r(Area::R, 4000, 4)];
        let plan = ReadPlan::new(&ranges, &Limits::uniform(1230));
        let answers = vec![Ok(vec![1; 4]), Err(Refusal::BAD_PARAMETERS), Ok(vec![3; 3])];
        let (data, refused) = plan.assemble_answers(answers);
        assert_eq!(refused, vec![1, 2]);
        assert_eq!(plan.range_answer(&data, 0), Ok(&[1u8; 4][..]));
        assert_eq!(plan.range_answer(&data, 1), Err(Refusal::BAD_PARAMETERS));
        assert_eq!(plan.range_answer(&data, 2), Err(Refusal::BAD_PARAMETERS));
    }

    #[test]
    fn gaps_alignment_holes_and_ranges_alone() {
        // Registers: two-byte alignment, a gap of at most 4 bytes.
        let limits = Limits {
            max_block: [250; 4],
            gap: [4; 4],
            align: [2; 4],
        };
        let block = |offset, len| ReadRequest {
            area: Area::R,
            offset,
            len,
        };
        let ranges = [
            r(Area::R, 0, 2),
            r(Area::R, 7, 1), // the low byte of register 3: read whole
            r(Area::R, 20, 4),
            r(Area::R, 26, 2),
            r(Area::R, 40, 2),
        ];
        let plan = ReadPlan::new(&ranges, &limits);
        assert_eq!(plan.blocks(), &[block(0, 8), block(20, 8), block(40, 2)]);
        let memory: Vec<u8> = (0..100).collect();
        let (data, _) = plan.assemble_answers(answers_from(&memory, &plan));
        assert_eq!(plan.range_answer(&data, 1).unwrap(), &[7]);
        // A hole between 24 and 26, a cut at 2, and the range at 40 alone.
        let holes = [r(Area::R, 24, 2), r(Area::R, 2, 0)];
        let plan = ReadPlan::with_holes(
            &ranges,
            &[false, false, false, false, true],
            &limits,
            &holes,
        );
        assert_eq!(
            plan.blocks(),
            &[
                block(0, 2),
                block(6, 2),
                block(20, 4),
                block(26, 2),
                block(40, 2)
            ]
        );
        let (data, _) = plan.assemble_answers(answers_from(&memory, &plan));
        for (i, range) in ranges.iter().enumerate() {
            assert_eq!(plan.range_answer(&data, i).unwrap(), slice(&memory, range));
        }
    }

    proptest::proptest! {
        /// Any ranges: every range reassembles exactly, no block exceeds the
        /// limit, and no more blocks are used than one per range.
        #[test]
        fn any_ranges_reassemble(
            raw in proptest::collection::vec((0u8..2, 0u32..6000, 1u32..300), 1..60),
            max in 1u32..1500,
        ) {
            let memory: Vec<u8> = (0..7000u32).map(|i| (i % 253) as u8).collect();
            let ranges: Vec<Range> = raw
                .iter()
                .map(|&(a, offset, len)| r(if a == 0 { Area::R } else { Area::S }, offset, len))
                .collect();
            let plan = ReadPlan::new(&ranges, &Limits::uniform(max));
            let (data, refused) = plan.assemble_answers(answers_from(&memory, &plan));
            proptest::prop_assert!(refused.is_empty());
            for (i, range) in ranges.iter().enumerate() {
                proptest::prop_assert_eq!(plan.range_answer(&data, i).unwrap(), slice(&memory, range));
            }
            proptest::prop_assert!(plan.blocks().iter().all(|b| b.len <= max && b.len > 0));
            let naive: u32 = ranges.iter().map(|r| r.len.div_ceil(max)).sum();
            proptest::prop_assert!(plan.blocks().len() as u32 <= naive);
        }
    }
}
