//! Packing a cycle's blocks into as few S7 jobs as the negotiated PDU and
//! the server's item limit allow.
//!
//! A read job of `n` items costs `10 + 2 + 12 n` bytes; its answer
//! `12 + 2 + sum(4 + len + pad)`, where an odd item is padded to even. Both
//! must fit the PDU, and `n` must not pass the item limit. Jobs are filled
//! in address order: each takes blocks until its answer is full or it has
//! its items, and a block that does not fit the room left is cut there
//! (an even cut) and goes on in the next job; a block larger than one
//! answer is cut the same way. No job but the last is left with room for
//! another item, so the count is the least the limits allow.
//!
//! The merge rule the poll planner applies before this ([`gap`]): two
//! wanted ranges of one area are read as one block when the bytes between
//! them are fewer than an item slot is worth, the answer's room divided by
//! the item limit: 11 bytes at PDU 240, 23 at 480, 47 at 960 (20 items).

use super::frame::{Item, ACK_HEADER, ANSWER_ITEM_HEAD, JOB_HEADER, PARAM_HEAD};
use super::Region;

/// The most items a job may carry: Snap7's server and S7-300/400 CPUs take
/// at most 20.
pub const MAX_ITEMS: usize = 20;

/// What a job may hold: the negotiated PDU and the item limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Budget {
    pub pdu: u16,
    pub max_items: usize,
}

impl Budget {
    pub fn new(pdu: u16) -> Budget {
        Budget {
            pdu,
            max_items: MAX_ITEMS,
        }
    }

    /// Items one read job may carry (its request must fit the PDU too).
    pub fn read_items(&self) -> usize {
        let by_request =
            usize::from(self.pdu).saturating_sub(JOB_HEADER + PARAM_HEAD) / Item::SPEC_LEN;
        by_request.min(self.max_items).max(1)
    }

    /// Answer bytes a read job's items may use (headers and data).
    fn read_room(&self) -> usize {
        usize::from(self.pdu).saturating_sub(ACK_HEADER + PARAM_HEAD)
    }

    /// Most data one read item may carry (even).
    pub fn max_read_item(&self) -> u32 {
        (self.read_room().saturating_sub(ANSWER_ITEM_HEAD) as u32 & !1).max(2)
    }

    /// Room a write job's items may use (spec, data head, data).
    fn write_room(&self) -> usize {
        usize::from(self.pdu).saturating_sub(JOB_HEADER + PARAM_HEAD)
    }

    /// Most data one write item may carry (even).
    pub fn max_write_item(&self) -> u32 {
        (self.write_room().saturating_sub(Item::SPEC_LEN + 4) as u32 & !1).max(2)
    }

    /// The merge rule's gap: the answer bytes an item slot is worth.
    pub fn gap(&self) -> u32 {
        (self.read_room() / self.read_items()) as u32
    }
}

/// A block to read: `len` bytes from `start` of `region`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Block {
    pub region: Region,
    pub start: u32,
    pub len: u32,
}

/// A piece of a job: which block, from where in it, and the item.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Piece {
    pub block: usize,
    /// Offset of the item's first byte in the block.
    pub at: u32,
    pub item: Item,
}

/// The read jobs for `blocks`, each a list of pieces.
pub fn reads(blocks: &[Block], budget: Budget) -> Vec<Vec<Piece>> {
    let room = budget.read_room();
    let items = budget.read_items();
    let mut jobs: Vec<Vec<Piece>> = Vec::new();
    let mut job: Vec<Piece> = Vec::new();
    let mut used = 0usize;
    for (b, block) in blocks.iter().enumerate() {
        let mut at = 0u32;
        while at < block.len {
            let rest = block.len - at;
            let left = room.saturating_sub(used + ANSWER_ITEM_HEAD);
            let whole = (rest + rest % 2) as usize <= left;
            if job.len() == items || (!whole && left < 2) {
                jobs.push(std::mem::take(&mut job));
                used = 0;
                continue;
            }
            let len = if whole { rest } else { left as u32 & !1 };
            job.push(Piece {
                block: b,
                at,
                item: Item::bytes(block.region, block.start + at, len as u16),
            });
            used += ANSWER_ITEM_HEAD + (len + len % 2) as usize;
            at += len;
        }
    }
    if !job.is_empty() {
        jobs.push(job);
    }
    jobs
}

/// The write jobs for `items` (with their data lengths, in order): indexes
/// into `items`, each job within the PDU and the item limit. An item larger
/// than [`Budget::max_write_item`] must be cut by the caller first.
pub fn writes(lens: &[usize], budget: Budget) -> Vec<Vec<usize>> {
    let room = budget.write_room();
    let mut jobs: Vec<Vec<usize>> = Vec::new();
    let mut job = Vec::new();
    let mut used = 0usize;
    for (i, &len) in lens.iter().enumerate() {
        let cost = Item::SPEC_LEN + 4 + len + len % 2;
        if !job.is_empty() && (job.len() == budget.max_items || used + cost > room) {
            jobs.push(std::mem::take(&mut job));
            used = 0;
        }
        job.push(i);
        used += cost;
    }
    if !job.is_empty() {
        jobs.push(job);
    }
    jobs
}

#[cfg(test)]
mod tests {
    use super::*;

    fn answer_len(job: &[Piece]) -> usize {
        ACK_HEADER
            + PARAM_HEAD
            + job
                .iter()
                .map(|p| 4 + usize::from(p.item.len) + usize::from(p.item.len) % 2)
                .sum::<usize>()
    }

    #[test]
    fn limits_of_the_usual_pdus() {
        let b = Budget::new(240);
        assert_eq!((b.read_items(), b.max_read_item(), b.gap()), (19, 222, 11));
        let b = Budget::new(480);
        assert_eq!((b.read_items(), b.max_read_item(), b.gap()), (20, 462, 23));
        let b = Budget::new(960);
        assert_eq!((b.read_items(), b.max_read_item(), b.gap()), (20, 942, 47));
    }

    #[test]
    fn big_blocks_fill_whole_answers() {
        let budget = Budget::new(240);
        let blocks = [Block {
            region: Region::Db(1),
            start: 0,
            len: 1000,
        }];
        let jobs = reads(&blocks, budget);
        // 226 bytes of room: 222 of data a job.
        assert_eq!(jobs.len(), 1000usize.div_ceil(222));
        let mut next = 0;
        for job in &jobs {
            assert!(answer_len(job) <= 240);
            for p in job {
                assert_eq!(p.at, next);
                assert_eq!(p.item.start, p.at);
                next += u32::from(p.item.len);
            }
        }
        assert_eq!(next, 1000);
    }

    #[test]
    fn small_blocks_fill_the_item_limit() {
        let blocks: Vec<Block> = (0..100)
            .map(|i| Block {
                region: Region::Db(2),
                start: i * 100,
                len: 2,
            })
            .collect();
        let jobs = reads(&blocks, Budget::new(480));
        assert_eq!(jobs.len(), 5);
        assert!(jobs.iter().all(|j| j.len() == 20));
        let jobs = reads(&blocks, Budget::new(240));
        assert_eq!(jobs.len(), 100usize.div_ceil(19));
    }

    #[test]
    fn writes_fit_the_request() {
        let budget = Budget::new(240);
        let lens = vec![100, 100, 100, 1, 1];
        let jobs = writes(&lens, budget);
        for job in &jobs {
            let size = JOB_HEADER
                + PARAM_HEAD
                + job
                    .iter()
                    .map(|&i| 16 + lens[i] + lens[i] % 2)
                    .sum::<usize>();
            assert!(size <= 240, "{size}");
        }
        assert_eq!(jobs.concat(), vec![0, 1, 2, 3, 4]);
        assert_eq!(budget.max_write_item(), 212);
    }
}
