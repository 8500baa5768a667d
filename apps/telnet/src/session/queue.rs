//! A session's ordered answers, and what waits behind what.
//!
//! Requests are answered in the order they came. An answer that needs the
//! link waits in this queue while later requests are already taken and sent
//! on, so a burst shares PLC round trips; answers that are complete behind
//! it wait as bytes. The rules the session applies through it:
//! - DIFF lines wait while a SET of this client is unanswered
//!   ([`AnswerQueue::set_outstanding`]): the SET's answer carries the change;
//! - requests and public-file notices wait while a SETCONF is unanswered
//!   ([`AnswerQueue::conf_outstanding`]): later requests may name variables
//!   of the file it loads;
//! - DIFF lines wait while a GETFILE answer streams at the head
//!   ([`AnswerQueue::streaming`]), so none lands inside its blocks.

use std::collections::VecDeque;

use crate::cmd::getfile::Stream;
use crate::cmd::{Completion, WaitKind, Waiting};
use plccoms_core::link::files::FileReply;
use plccoms_core::link::LinkError;

pub enum Entry {
    Ready(Vec<u8>),
    Wait(Waiting),
    Stream(Box<Stream>),
}

/// What the head of the queue was waiting for.
pub enum HeadDone {
    Wait(Completion),
    Stream(FileReply),
}

#[derive(Default)]
pub struct AnswerQueue {
    entries: VecDeque<Entry>,
    /// Bytes of the complete answers waiting behind the head.
    ready_bytes: usize,
    /// Unanswered SETs in the queue.
    sets: usize,
    /// What the waiting answers are expected to take, in bytes.
    estimated: usize,
    /// Entries that are not complete answers.
    incomplete: usize,
}

impl AnswerQueue {
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn ready_bytes(&self) -> usize {
        self.ready_bytes
    }

    /// Output this queue holds or will produce: complete answers and the
    /// estimates of those still waiting.
    pub fn ahead(&self) -> usize {
        self.ready_bytes + self.estimated
    }

    pub fn push_ready(&mut self, bytes: Vec<u8>) {
        if !bytes.is_empty() {
            self.ready_bytes += bytes.len();
            self.entries.push_back(Entry::Ready(bytes));
        }
    }

    pub fn push_wait(&mut self, waiting: Waiting) {
        if waiting.kind() == WaitKind::Set {
            self.sets += 1;
        }
        self.estimated += waiting.estimate();
        self.incomplete += 1;
        self.entries.push_back(Entry::Wait(waiting));
    }

    pub fn push_stream(&mut self, stream: Box<Stream>) {
        self.incomplete += 1;
        self.entries.push_back(Entry::Stream(stream));
    }

    /// Some answer is not complete yet (it waits for the link, or streams).
    pub fn waiting(&self) -> bool {
        self.incomplete > 0
    }

    /// A SET of this client is unanswered.
    pub fn set_outstanding(&self) -> bool {
        self.sets > 0
    }

    /// A SETCONF is unanswered. Nothing is queued behind one, so it can only
    /// be the last entry: checked in O(1) for every request parsed.
    pub fn conf_outstanding(&self) -> bool {
        matches!(self.entries.back(), Some(Entry::Wait(w)) if w.kind() == WaitKind::Conf)
    }

    /// A GETFILE answer is being sent.
    pub fn streaming(&self) -> bool {
        matches!(self.entries.front(), Some(Entry::Stream(_)))
    }

    /// The head waits for the link.
    pub fn head_waiting(&mut self) -> bool {
        match self.entries.front_mut() {
            Some(Entry::Wait(_)) => true,
            Some(Entry::Stream(stream)) => stream.waiting().is_some(),
            _ => false,
        }
    }

    /// Resolves when the head's answer (or its stream's block) arrives.
    pub async fn head_done(&mut self) -> HeadDone {
        match self.entries.front_mut() {
            Some(Entry::Wait(waiting)) => HeadDone::Wait(waiting.ready().await),
            Some(Entry::Stream(stream)) => match stream.waiting() {
                Some(rx) => HeadDone::Stream(rx.await.unwrap_or(Err(LinkError::Offline))),
                None => std::future::pending().await,
            },
            _ => std::future::pending().await,
        }
    }

    /// Takes the head, which must not be a finished answer.
    pub fn pop_head(&mut self) -> Option<Entry> {
        let head = self.entries.pop_front()?;
        match &head {
            Entry::Ready(bytes) => self.ready_bytes -= bytes.len(),
            Entry::Wait(w) => {
                self.incomplete -= 1;
                self.estimated -= w.estimate();
                if w.kind() == WaitKind::Set {
                    self.sets -= 1;
                }
            }
            Entry::Stream(_) => self.incomplete -= 1,
        }
        Some(head)
    }

    /// Puts a stream that is not done back at the head.
    pub fn push_front_stream(&mut self, stream: Box<Stream>) {
        self.incomplete += 1;
        self.entries.push_front(Entry::Stream(stream));
    }

    /// The head if it is a stream.
    pub fn head_stream(&mut self) -> Option<&mut Stream> {
        match self.entries.front_mut() {
            Some(Entry::Stream(stream)) => Some(stream),
            _ => None,
        }
    }

    /// The complete answers at the head, in order.
    pub fn pop_ready(&mut self) -> Option<Vec<u8>> {
        match self.entries.front() {
            Some(Entry::Ready(_)) => match self.pop_head() {
                Some(Entry::Ready(bytes)) => Some(bytes),
                _ => None,
            },
            _ => None,
        }
    }
}
