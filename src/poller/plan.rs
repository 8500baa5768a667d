//! Read planning: turn a set of memory ranges into as few block reads as the
//! backend's block size allows.
//!
//! Ranges are merged into contiguous spans (also across gaps no larger than a
//! request costs on the wire), and each span is cut into blocks of at most
//! `max_block` bytes at byte granularity, so a dense region of N bytes costs
//! exactly ceil(N / max_block) requests. A range that straddles two blocks is
//! reassembled from both.

use plccoms_protocol::Area;

use crate::backend::{Answer, Exception, ReadRequest};

/// Largest gap (bytes) merged into a span: reading it costs less than the
/// header and parameters of one more request.
pub const MERGE_GAP: u32 = 16;

/// One wanted range, tagged with the caller's key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Range {
    pub area: Area,
    pub offset: u32,
    pub len: u32,
}

#[derive(Debug, Clone)]
struct Span {
    area: Area,
    offset: u32,
    len: u32,
    /// Index of the span's first byte in the concatenated block data.
    data_start: usize,
}

/// Where each requested range lands in the block data.
#[derive(Debug, Clone, Default)]
pub struct ReadPlan {
    blocks: Vec<ReadRequest>,
    spans: Vec<Span>,
    /// Per input range: start in the concatenated data.
    locations: Vec<usize>,
    lens: Vec<u32>,
}

impl ReadPlan {
    /// Plans reads for `ranges` (any order, overlaps allowed).
    pub fn new(ranges: &[Range], max_block: u32) -> ReadPlan {
        let max_block = max_block.max(1);
        let mut order: Vec<u32> = (0..ranges.len() as u32).collect();
        order.sort_unstable_by_key(|&i| {
            let r = &ranges[i as usize];
            (r.area, r.offset)
        });

        let mut plan = ReadPlan {
            locations: vec![0; ranges.len()],
            lens: ranges.iter().map(|r| r.len).collect(),
            ..ReadPlan::default()
        };
        let mut data_len = 0usize;
        for &i in &order {
            let r = ranges[i as usize];
            let end = u64::from(r.offset) + u64::from(r.len);
            let extend = plan.spans.last().is_some_and(|s: &Span| {
                s.area == r.area
                    && u64::from(r.offset)
                        <= u64::from(s.offset) + u64::from(s.len) + u64::from(MERGE_GAP)
            });
            if extend {
                let span = plan.spans.last_mut().expect("checked above");
                let span_end = u64::from(span.offset) + u64::from(span.len);
                if end > span_end {
                    let grow = (end - span_end) as u32;
                    span.len += grow;
                    data_len += grow as usize;
                }
                plan.locations[i as usize] = span.data_start + (r.offset - span.offset) as usize;
            } else {
                plan.spans.push(Span {
                    area: r.area,
                    offset: r.offset,
                    len: r.len,
                    data_start: data_len,
                });
                plan.locations[i as usize] = data_len;
                data_len += r.len as usize;
            }
        }
        for span in &plan.spans {
            let mut offset = span.offset;
            let end = span.offset + span.len;
            while offset < end {
                let len = (end - offset).min(max_block);
                plan.blocks.push(ReadRequest {
                    area: span.area,
                    offset,
                    len,
                });
                offset += len;
            }
        }
        plan
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
                        _ => Exception::BadParameters,
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
    failed: Vec<(std::ops::Range<usize>, Exception)>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn r(area: Area, offset: u32, len: u32) -> Range {
        Range { area, offset, len }
    }

    #[test]
    fn dense_region_costs_the_minimum() {
        let ranges: Vec<Range> = (0..10_000).map(|i| r(Area::R, i * 4, 4)).collect();
        let plan = ReadPlan::new(&ranges, 1230);
        assert_eq!(plan.blocks().len(), 40_000usize.div_ceil(1230));
        assert_eq!(plan.bytes(), 40_000);
    }

    #[test]
    fn small_gaps_merge_large_gaps_split_areas_never_merge() {
        let ranges = [
            r(Area::R, 100, 4),
            r(Area::R, 110, 2), // gap 6: merged
            r(Area::R, 500, 1), // gap > MERGE_GAP: new span
            r(Area::S, 501, 1), // other area
        ];
        let plan = ReadPlan::new(&ranges, 1230);
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
                    len: 12
                },
                ReadRequest {
                    area: Area::R,
                    offset: 500,
                    len: 1
                },
            ]
        );
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
        ];
        let plan = ReadPlan::new(&ranges, 7);
        let answers = plan
            .blocks()
            .iter()
            .map(|b| Ok(memory[b.offset as usize..(b.offset + b.len) as usize].to_vec()))
            .collect();
        let (data, refused) = plan.assemble_answers(answers);
        assert!(refused.is_empty());
        for (i, range) in ranges.iter().enumerate() {
            let want = &memory[range.offset as usize..(range.offset + range.len) as usize];
            assert_eq!(plan.range_answer(&data, i).unwrap(), want, "range {i}");
        }
        assert!(plan.blocks().iter().all(|b| b.len <= 7));
    }

    #[test]
    fn refused_and_short_blocks_fail_only_their_ranges() {
        let ranges = [r(Area::R, 0, 4), r(Area::R, 100, 4), r(Area::R, 200, 4)];
        let plan = ReadPlan::new(&ranges, 1230);
        let answers = vec![
            Ok(vec![1; 4]),
            Err(Exception::BadParameters),
            Ok(vec![3; 3]),
        ];
        let (data, refused) = plan.assemble_answers(answers);
        assert_eq!(refused, vec![1, 2]);
        assert_eq!(plan.range_answer(&data, 0), Ok(&[1u8; 4][..]));
        assert_eq!(plan.range_answer(&data, 1), Err(Exception::BadParameters));
        assert_eq!(plan.range_answer(&data, 2), Err(Exception::BadParameters));
    }
}
