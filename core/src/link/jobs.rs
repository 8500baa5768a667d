//! Client work the link serves between polls: direct reads (GET of what is
//! not polled, GETMEM) and SETs, batched so that a burst shares PLC round
//! trips.
//!
//! Reads of a batch go through one shared plan; a block the PLC refuses is
//! retried range by range, so one bad address does not fail its neighbours.
//! SETs go in rounds: consecutive SETs whose writes touch different memory
//! share one write request and one read-back; a SET touching what an earlier
//! one of the batch wrote starts a new round, so each SET is answered with
//! the value after it (`SET:c,1` `SET:c,2` `SET:c,3` read back 1, 2, 3).

use std::ops::Range as Span;
use std::sync::Arc;

use tokio::sync::oneshot;
use tokio::time::Instant;
use tracing::debug;

use super::plan::{Limits, Range, ReadPlan};
use super::{LinkError, ReadReply, SetOutcome, SetReply};
use crate::changes::{unix_ms, Publisher};
use crate::driver::{Answer, PlcBackend, PlcError, ReadRequest, Refusal, WriteData, WriteRequest};
use crate::vars::{VarId, VarTable};

/// A SET: write, then read the variable back.
#[derive(Debug, Clone)]
pub struct SetItem {
    pub write: WriteRequest,
    pub readback: ReadRequest,
    /// The table variable, so other clients get the DIFF too; ignored when
    /// the table changed meanwhile.
    pub var: Option<(Arc<VarTable>, VarId)>,
}

/// Reads arbitrary ranges through one shared plan.
pub async fn read_ranges(
    backend: &mut dyn PlcBackend,
    requests: &[ReadRequest],
) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
    let limits = Limits::of(backend);
    let max = |area: plccoms_protocol::Area| limits.max_block[area.index()];
    let ranges: Vec<Range> = requests
        .iter()
        .map(|r| Range {
            area: r.area,
            offset: r.offset,
            len: r.len,
        })
        .collect();
    let plan = ReadPlan::new(&ranges, &limits);
    let (data, refused) = plan.assemble_answers(backend.read(plan.blocks()).await?);
    let mut answers: Vec<Answer<Vec<u8>>> = (0..requests.len())
        .map(|i| plan.range_answer(&data, i).map(<[u8]>::to_vec))
        .collect();
    if refused.is_empty() {
        return Ok(answers);
    }
    let retry: Vec<usize> = (0..requests.len())
        .filter(|&i| answers[i].is_err())
        .collect();
    let single: Vec<ReadRequest> = retry
        .iter()
        .flat_map(|&i| split(requests[i], max(requests[i].area)))
        .collect();
    let mut results = backend.read(&single).await?.into_iter();
    for &i in &retry {
        let parts = split(requests[i], max(requests[i].area)).count();
        let mut bytes = Vec::with_capacity(requests[i].len as usize);
        let mut failure: Option<Refusal> = None;
        for answer in results.by_ref().take(parts) {
            match answer {
                Ok(b) => bytes.extend_from_slice(&b),
                Err(e) => failure = failure.or(Some(e)),
            }
        }
        answers[i] = match failure {
            Some(e) => Err(e),
            None if bytes.len() == requests[i].len as usize => Ok(bytes),
            None => Err(Refusal::BAD_PARAMETERS),
        };
    }
    Ok(answers)
}

/// Serves a group of direct reads in one shared plan; answers in order.
pub async fn serve_reads(
    backend: &mut dyn PlcBackend,
    group: Vec<(Vec<ReadRequest>, oneshot::Sender<ReadReply>)>,
) -> Result<(), PlcError> {
    let requests: Vec<ReadRequest> = group.iter().flat_map(|(r, _)| r.iter().copied()).collect();
    match read_ranges(backend, &requests).await {
        Ok(mut answers) => {
            for (requests, reply) in group.into_iter().rev() {
                let mine = answers.split_off(answers.len() - requests.len());
                let _ = reply.send(Ok(mine));
            }
            Ok(())
        }
        Err(err) => {
            fail_all(group.into_iter().map(|(_, reply)| reply), &err);
            Err(err)
        }
    }
}

/// Consecutive spans of `writes` whose members touch different memory: each
/// span can share one write request and one read-back.
pub fn set_rounds(writes: &[&WriteRequest]) -> Vec<Span<usize>> {
    let mut rounds = Vec::new();
    let mut start = 0;
    for i in 0..writes.len() {
        if writes[start..i].iter().any(|w| overlaps(w, writes[i])) {
            rounds.push(start..i);
            start = i;
        }
    }
    if start < writes.len() {
        rounds.push(start..writes.len());
    }
    rounds
}

/// Whether two writes touch the same memory (two bits of one byte do not).
fn overlaps(a: &WriteRequest, b: &WriteRequest) -> bool {
    if a.area != b.area {
        return false;
    }
    match (&a.data, &b.data) {
        (WriteData::Bit { bit: x, .. }, WriteData::Bit { bit: y, .. }) => {
            a.offset == b.offset && x == y
        }
        _ => {
            let end = |w: &WriteRequest| w.offset as u64 + write_len(w);
            (a.offset as u64) < end(b) && (b.offset as u64) < end(a)
        }
    }
}

fn write_len(write: &WriteRequest) -> u64 {
    match &write.data {
        WriteData::Bytes(bytes) => bytes.len() as u64,
        WriteData::Bit { .. } => 1,
    }
}

/// Serves a group of SETs in rounds. Each value read back is published
/// before the SET is answered, so a client that asks again at once finds it.
/// Returns the first link error (the remaining SETs are answered with it and
/// never sent).
///
/// `arrived` is when the oldest SET of the group arrived: the time it
/// waited is logged with the round's parts at debug level, target
/// [`SET_TIMING`].
pub async fn serve_sets(
    backend: &mut dyn PlcBackend,
    publisher: &mut Publisher,
    group: Vec<(SetItem, oneshot::Sender<SetReply>)>,
    arrived: Instant,
) -> Result<(), PlcError> {
    let writes: Vec<&WriteRequest> = group.iter().map(|(item, _)| &item.write).collect();
    let rounds = set_rounds(&writes);
    let mut group = group.into_iter();
    for round in rounds {
        let members: Vec<_> = group.by_ref().take(round.len()).collect();
        if let Err(err) = set_round(backend, publisher, members, arrived).await {
            // What was not sent never will be.
            fail_all(group.map(|(_, reply)| reply), &err);
            return Err(err);
        }
    }
    Ok(())
}

async fn set_round(
    backend: &mut dyn PlcBackend,
    publisher: &mut Publisher,
    round: Vec<(SetItem, oneshot::Sender<SetReply>)>,
    arrived: Instant,
) -> Result<(), PlcError> {
    let writes: Vec<WriteRequest> = round.iter().map(|(item, _)| item.write.clone()).collect();
    let sent = Instant::now();
    let written = match backend.write(&writes).await {
        Ok(written) if written.len() == writes.len() => Ok(written),
        Ok(_) => Err(PlcError::Protocol("write answer count mismatch".into())),
        Err(err) => Err(err),
    };
    let written = match written {
        Ok(written) => written,
        Err(err) => {
            fail_all(round.into_iter().map(|(_, reply)| reply), &err);
            return Err(err);
        }
    };
    let readbacks: Vec<ReadRequest> = round.iter().map(|(item, _)| item.readback).collect();
    let confirming = Instant::now();
    let read = match read_ranges(backend, &readbacks).await {
        Ok(read) => read,
        Err(err) => {
            fail_all(round.into_iter().map(|(_, reply)| reply), &err);
            return Err(err);
        }
    };
    let publishing = Instant::now();
    let seq = publisher.next_seq();
    let now = unix_ms(std::time::SystemTime::now());
    let mut outcomes = Vec::with_capacity(round.len());
    for (((item, reply), write), read) in round.into_iter().zip(written).zip(read) {
        let answer = write.and(read);
        let var = item
            .var
            .filter(|(table, _)| Arc::ptr_eq(table, publisher.table()))
            .map(|(_, id)| id);
        if let (Some(var), Ok(bytes)) = (var, &answer) {
            publisher.update(var, bytes, now);
        }
        outcomes.push((reply, SetOutcome { answer, seq }));
    }
    // Published before answering: a client that reads its answer and asks
    // again at once must find the new value. The writer holds back DIFF
    // lines while its SET is unanswered, so it does not get it twice.
    publisher.publish();
    for (reply, outcome) in outcomes {
        let _ = reply.send(Ok(outcome));
    }
    let done = Instant::now();
    debug!(
        target: SET_TIMING,
        sets = writes.len(),
        queued_us = micros(sent - arrived),
        write_us = micros(confirming - sent),
        confirm_us = micros(publishing - confirming),
        publish_us = micros(done - publishing),
        "set round"
    );
    Ok(())
}

/// The tracing target of the SET's parts and of what a SET may wait
/// behind (`RUST_LOG=info,plccoms::set_timing=debug`; bench-opcua
/// `--split`): a disabled debug event costs one load and a branch.
pub const SET_TIMING: &str = "plccoms::set_timing";

/// A [`SET_TIMING`] event's field: whole µs, saturating.
pub fn micros(d: std::time::Duration) -> u64 {
    u64::try_from(d.as_micros()).unwrap_or(u64::MAX)
}

/// Answers every reply with the link error `err`.
pub fn fail_all<T>(
    replies: impl IntoIterator<Item = oneshot::Sender<Result<T, LinkError>>>,
    err: &PlcError,
) {
    for reply in replies {
        let _ = reply.send(Err(LinkError::from_failure(err)));
    }
}

/// `request` cut into blocks of at most `max` bytes.
fn split(request: ReadRequest, max: u32) -> impl Iterator<Item = ReadRequest> {
    let max = max.max(1);
    let end = request.offset + request.len;
    (request.offset..end)
        .step_by(max as usize)
        .map(move |offset| ReadRequest {
            area: request.area,
            offset,
            len: (end - offset).min(max),
        })
}

#[cfg(test)]
mod tests {
    use plccoms_protocol::Area;

    use super::*;

    fn bytes(offset: u32, len: usize) -> WriteRequest {
        WriteRequest {
            area: Area::R,
            offset,
            data: WriteData::Bytes(vec![0; len]),
        }
    }

    fn bit(offset: u32, bit: u8) -> WriteRequest {
        WriteRequest {
            area: Area::R,
            offset,
            data: WriteData::Bit { bit, value: true },
        }
    }

    #[test]
    fn sets_of_one_variable_go_in_rounds_of_their_own() {
        let same = [bytes(0, 2), bytes(0, 2), bytes(0, 2)];
        let refs: Vec<&WriteRequest> = same.iter().collect();
        assert_eq!(set_rounds(&refs), [0..1, 1..2, 2..3]);
        // Different variables share a round until one repeats.
        let mixed = [
            bytes(0, 2),
            bytes(2, 4),
            bit(8, 0),
            bit(8, 1),
            bytes(1, 2),
            bit(8, 0),
        ];
        let refs: Vec<&WriteRequest> = mixed.iter().collect();
        assert_eq!(set_rounds(&refs), [0..4, 4..6]);
        // A bit and the whole byte overlap; other areas never do.
        let other = WriteRequest {
            area: Area::S,
            ..bytes(8, 1)
        };
        let refs = [&mixed[2], &other, &bytes(8, 1)];
        assert_eq!(set_rounds(&refs), [0..2, 2..3]);
        assert!(set_rounds(&[]).is_empty());
    }
}
