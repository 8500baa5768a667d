//! From a section's change stream to samples: which variables are recorded,
//! the deadband, heartbeats, link loss and return, PLC time stamps and event
//! capture. [`Recorder`] is plain logic over [`ChangeBatch`]es, so every rule
//! is tested without a PLC; the section's task (`mod.rs`) feeds it.

use std::collections::HashMap;
use std::sync::Arc;

use plccoms_protocol::mask::Mask;
use plccoms_protocol::value::{FormatOptions, Value};
use plccoms_protocol::IecType;
use tracing::warn;

use super::capture::Capture;
use super::sample::{is_stamp_type, Event, EventKind, Sample, Stored};
use plccoms_core::changes::{ChangeBatch, LinkEvent, Quality, Snapshot};
use plccoms_core::config::History;
use plccoms_core::vars::{VarId, VarTable};

/// What one batch gave.
#[derive(Debug, Default)]
pub struct Output {
    pub samples: Vec<Sample>,
    pub events: Vec<Event>,
}

impl Output {
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty() && self.events.is_empty()
    }
}

pub struct Recorder {
    section: String,
    settings: History,
    format: FormatOptions,
    table: Option<Arc<VarTable>>,
    /// Recorded variables of `table`, ascending.
    recorded: Vec<VarId>,
    is_recorded: Vec<bool>,
    /// Value variable -> its stamp variable.
    stamp_of: HashMap<VarId, VarId>,
    /// Stamp variable -> the value variables it stamps.
    stamps: HashMap<VarId, Vec<VarId>>,
    /// Per variable: the value last recorded (the deadband's reference).
    last_value: Vec<Option<Value>>,
    /// Per variable: UTC ms of the sample last recorded (heartbeats).
    last_t: Vec<i64>,
    capture: Option<Capture>,
    seen_poll: u64,
    /// Per variable: emitted in the batch at hand (of its latest snapshot).
    emitted: Vec<bool>,
    emitted_list: Vec<(VarId, i64)>,
}

impl Recorder {
    pub fn new(section: &str, settings: History, format: FormatOptions) -> Recorder {
        Recorder {
            section: section.to_string(),
            settings,
            format,
            table: None,
            recorded: Vec::new(),
            is_recorded: Vec::new(),
            stamp_of: HashMap::new(),
            stamps: HashMap::new(),
            last_value: Vec::new(),
            last_t: Vec::new(),
            capture: None,
            seen_poll: 0,
            emitted: Vec::new(),
            emitted_list: Vec::new(),
        }
    }

    /// What to subscribe to: the recorded variables, the trigger and the
    /// stamps.
    pub fn masks(settings: &History) -> Vec<String> {
        let mut masks = settings.masks.clone();
        masks.extend(settings.trigger.iter().cloned());
        for pair in &settings.stamps {
            masks.push(pair.value.clone());
            masks.push(pair.stamp.clone());
        }
        masks
    }

    /// Resolves names against a new table.
    fn resolve(&mut self, table: &Arc<VarTable>) {
        let masks: Vec<Mask> = self
            .settings
            .masks
            .iter()
            .map(|m| Mask::new(m.as_bytes()))
            .collect();
        let len = table.len();
        self.is_recorded = table
            .vars()
            .iter()
            .map(|var| masks.iter().any(|m| m.matches(&var.name)))
            .collect();
        self.stamp_of.clear();
        self.stamps.clear();
        for pair in &self.settings.stamps {
            let (Some(value), Some(stamp)) = (
                table.lookup(pair.value.as_bytes()),
                table.lookup(pair.stamp.as_bytes()),
            ) else {
                warn!(section = %self.section, "HISTORY_STAMP {}:{}: no such variable in the public file; not paired", pair.value, pair.stamp);
                continue;
            };
            let ty = table.var(stamp).ty;
            if !is_stamp_type(ty) {
                warn!(section = %self.section, "HISTORY_STAMP {}:{}: {} is {ty}, not DT, DATE, LINT, ULINT or LWORD; not paired", pair.value, pair.stamp, pair.stamp);
                continue;
            }
            self.is_recorded[value as usize] = true;
            self.stamp_of.insert(value, stamp);
            self.stamps.entry(stamp).or_default().push(value);
        }
        self.recorded = (0..len as VarId)
            .filter(|&id| self.is_recorded[id as usize])
            .collect();
        self.last_value = vec![None; len];
        self.last_t = vec![i64::MIN; len];
        self.emitted = vec![false; len];
        self.capture = None;
        if let Some(name) = &self.settings.trigger {
            match table.lookup(name.as_bytes()) {
                Some(id) if table.var(id).ty == IecType::Bool => {
                    self.capture = Some(Capture::new(id, self.settings.pre, self.settings.post));
                }
                Some(id) => {
                    warn!(section = %self.section, "HISTORY_TRIGGER {name} is {}, not BOOL: no event capture", table.var(id).ty)
                }
                None => {
                    warn!(section = %self.section, "HISTORY_TRIGGER {name}: no such variable in the public file: no event capture")
                }
            }
        }
        self.table = Some(table.clone());
    }

    /// The recorded variables of the current table.
    pub fn recorded(&self) -> &[VarId] {
        &self.recorded
    }

    /// Turns a batch into samples and events; `now_ms` is the time it
    /// arrived (link loss has no poll time).
    pub fn on_batch(&mut self, batch: &ChangeBatch, now_ms: i64, out: &mut Output) {
        let snapshot = &batch.snapshot;
        let new_table = !self
            .table
            .as_ref()
            .is_some_and(|t| Arc::ptr_eq(t, &snapshot.table));
        if new_table {
            if self.table.is_some() {
                out.events.push(Event {
                    t: now_ms,
                    kind: EventKind::Table,
                    detail: snapshot
                        .table
                        .user_file
                        .clone()
                        .unwrap_or_else(|| snapshot.table.fixed_file.clone()),
                });
            }
            self.resolve(&snapshot.table);
        }
        if batch.missed > 0 {
            out.events.push(Event {
                t: now_ms,
                kind: EventKind::Missed,
                detail: format!("{} publishes not seen", batch.missed),
            });
        }
        let polled_ms = snapshot.polled.map(|p| p.unix_ms);
        let mut whole_cycle_done = false;
        match batch.link {
            Some(LinkEvent::Lost) => {
                out.events.push(Event {
                    t: now_ms,
                    kind: EventKind::LinkLost,
                    detail: String::new(),
                });
                self.record_all(snapshot, now_ms, Some(Quality::LinkLost), out);
            }
            Some(LinkEvent::Restored) => {
                let t = polled_ms.unwrap_or(now_ms);
                out.events.push(Event {
                    t,
                    kind: EventKind::LinkRestored,
                    detail: String::new(),
                });
                self.record_all(snapshot, t, None, out);
                whole_cycle_done = true;
            }
            None => {}
        }
        let new_poll = snapshot.poll_seq > self.seen_poll;
        self.seen_poll = snapshot.poll_seq;
        if new_poll {
            if let Some(capture) = &mut self.capture {
                let captured = capture.on_poll(snapshot);
                if captured.edge {
                    out.events.push(Event {
                        t: polled_ms.unwrap_or(now_ms),
                        kind: EventKind::Capture,
                        detail: format!(
                            "{} cycles before, {} after",
                            captured.cycles.len().saturating_sub(1),
                            self.settings.post
                        ),
                    });
                }
                for cycle in &captured.cycles {
                    let Some(t) = cycle.polled.map(|p| p.unix_ms) else {
                        continue;
                    };
                    if Arc::ptr_eq(cycle, snapshot) {
                        if !whole_cycle_done {
                            self.record_all(snapshot, t, None, out);
                            whole_cycle_done = true;
                        }
                    } else {
                        // Past cycles: values as they were then. A sample
                        // already recorded then is the same one again; the
                        // store keeps one.
                        for &id in &self.recorded {
                            if let Some(sample) = sample_of(cycle, id, t, None, &self.stamp_of) {
                                out.samples.push(sample);
                            }
                        }
                    }
                }
            }
        }
        if !whole_cycle_done {
            self.record_changes(batch, out);
            if new_poll && snapshot.online && !self.settings.heartbeat.is_zero() {
                if let Some(t) = polled_ms {
                    self.record_heartbeats(snapshot, t, out);
                }
            }
        }
        for (id, t) in self.emitted_list.drain(..) {
            self.emitted[id as usize] = false;
            self.last_t[id as usize] = self.last_t[id as usize].max(t);
        }
    }

    /// Every recorded variable with a value, at `t`.
    fn record_all(
        &mut self,
        snapshot: &Snapshot,
        t: i64,
        quality: Option<Quality>,
        out: &mut Output,
    ) {
        for index in 0..self.recorded.len() {
            let id = self.recorded[index];
            self.emit(snapshot, id, t, quality, out);
        }
    }

    fn emit(
        &mut self,
        snapshot: &Snapshot,
        id: VarId,
        t: i64,
        quality: Option<Quality>,
        out: &mut Output,
    ) {
        if self.emitted[id as usize] {
            return;
        }
        if let Some(sample) = sample_of(snapshot, id, t, quality, &self.stamp_of) {
            if !self.settings.delta.0.is_zero() {
                self.last_value[id as usize] = snapshot.slot(id).value(snapshot.table.var(id));
            }
            self.emitted[id as usize] = true;
            self.emitted_list.push((id, t));
            out.samples.push(sample);
        }
    }

    fn record_changes(&mut self, batch: &ChangeBatch, out: &mut Output) {
        let snapshot = &batch.snapshot;
        let deadband = self.settings.delta.0;
        for &id in &batch.changes {
            let slot = snapshot.slot(id);
            if self.is_recorded[id as usize] && !self.emitted[id as usize] {
                let pass = deadband.is_zero() || self.stamp_of.contains_key(&id) || {
                    let var = snapshot.table.var(id);
                    match (slot.value(var), &self.last_value[id as usize]) {
                        (Some(new), Some(last)) => {
                            new.exceeds(last, &deadband, var.ty, &self.format)
                        }
                        _ => true,
                    }
                };
                if pass {
                    self.emit(snapshot, id, slot.changed_ms, None, out);
                }
            }
            // A new stamp is a new event of the variables it stamps, even
            // with the same value.
            if let Some(values) = self.stamps.get(&id).cloned() {
                for value in values {
                    self.emit(snapshot, value, slot.changed_ms, None, out);
                }
            }
        }
    }

    fn record_heartbeats(&mut self, snapshot: &Snapshot, t: i64, out: &mut Output) {
        let every = i64::try_from(self.settings.heartbeat.as_millis()).unwrap_or(i64::MAX);
        for index in 0..self.recorded.len() {
            let id = self.recorded[index];
            if t.saturating_sub(self.last_t[id as usize]) >= every {
                self.emit(snapshot, id, t, None, out);
            }
        }
    }
}

/// The sample of `id` in `snapshot` at `t`, if it has a value; quality as
/// the snapshot says unless given.
fn sample_of(
    snapshot: &Snapshot,
    id: VarId,
    t: i64,
    quality: Option<Quality>,
    stamp_of: &HashMap<VarId, VarId>,
) -> Option<Sample> {
    let value = snapshot.slot(id).value(snapshot.table.var(id))?;
    let plc_time = stamp_of.get(&id).and_then(|&stamp| {
        let value = snapshot.slot(stamp).value(snapshot.table.var(stamp))?;
        Stored::from_value(&value).as_ms()
    });
    Some(Sample {
        t,
        var: id,
        value: Stored::from_value(&value),
        quality: quality.unwrap_or_else(|| snapshot.quality(id)),
        plc_time,
    })
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use plccoms_core::changes::{ChangeStream, PollStamp, Publisher, Subscription};
    use plccoms_core::config::history::{parse_deadband, parse_stamps};
    use plccoms_core::vars::table_of;

    struct Rig {
        publisher: Publisher,
        sub: Subscription,
        recorder: Recorder,
        table: Arc<VarTable>,
        _stream: ChangeStream,
        t: i64,
    }

    impl Rig {
        fn new(settings: History) -> Rig {
            let table = Arc::new(table_of(&[
                ("A", "INT"),
                ("B", "REAL"),
                ("S", "STRING"),
                ("TRIG", "BOOL"),
                ("STAMP", "DT"),
                ("OTHER", "INT"),
            ]));
            let (publisher, stream) = Publisher::new(
                table.clone(),
                FormatOptions::default(),
                Duration::from_secs(1),
            );
            let sub = stream.subscribe(&Recorder::masks(&settings)).every_poll();
            Rig {
                publisher,
                sub,
                recorder: Recorder::new("Test", settings, FormatOptions::default()),
                table,
                _stream: stream,
                t: 1_700_000_000_000,
            }
        }

        fn id(&self, name: &str) -> VarId {
            self.table.lookup(name.as_bytes()).unwrap()
        }

        /// One poll 100 ms after the previous, writing `values` (raw
        /// bytes), and what the recorder makes of it.
        async fn poll(&mut self, values: &[(&str, Vec<u8>)]) -> Output {
            self.t += 100;
            for (name, bytes) in values {
                let id = self.id(name);
                self.publisher.update(id, bytes, self.t);
            }
            let stamp = PollStamp {
                at: tokio::time::Instant::now(),
                unix_ms: self.t,
            };
            self.publisher.publish_poll(stamp);
            self.next().await
        }

        async fn next(&mut self) -> Output {
            let batch = self.sub.next().await.unwrap();
            let mut out = Output::default();
            self.recorder.on_batch(&batch, self.t + 50, &mut out);
            out
        }

        fn names(&self, out: &Output) -> Vec<(String, i64, Stored, Quality)> {
            out.samples
                .iter()
                .map(|s| {
                    let name = String::from_utf8_lossy(&self.table.var(s.var).name).into_owned();
                    (name, s.t - 1_700_000_000_000, s.value.clone(), s.quality)
                })
                .collect()
        }
    }

    fn int(v: i16) -> Vec<u8> {
        v.to_le_bytes().to_vec()
    }

    fn history(masks: &[&str]) -> History {
        History {
            masks: masks.iter().map(|m| m.to_string()).collect(),
            pre: 2,
            post: 1,
            ..History::default()
        }
    }

    use Quality::*;
    use Stored::*;

    #[tokio::test]
    async fn changes_with_poll_time_and_quality_and_an_outage() {
        let mut rig = Rig::new(history(&["A", "b"]));
        let out = rig
            .poll(&[("A", int(1)), ("B", 1.5f32.to_le_bytes().to_vec())])
            .await;
        assert_eq!(
            rig.names(&out),
            [
                ("A".into(), 100, Int(1), Good),
                ("B".into(), 100, Real(1.5), Good)
            ]
        );
        // Unchanged: nothing; OTHER is not recorded.
        let out = rig.poll(&[("A", int(1)), ("OTHER", int(3))]).await;
        assert!(rig.names(&out).is_empty());
        let out = rig.poll(&[("A", int(2))]).await;
        assert_eq!(rig.names(&out), [("A".into(), 300, Int(2), Good)]);
        // Loss: every recorded variable, last value, link_lost, at the
        // time it is noticed.
        rig.publisher.publish_offline();
        let out = rig.next().await;
        assert_eq!(
            rig.names(&out),
            [
                ("A".into(), 350, Int(2), LinkLost),
                ("B".into(), 350, Real(1.5), LinkLost)
            ]
        );
        assert_eq!(out.events[0].kind, EventKind::LinkLost);
        // Return: every recorded variable again at the poll's time.
        let out = rig
            .poll(&[("A", int(2)), ("B", 1.5f32.to_le_bytes().to_vec())])
            .await;
        assert_eq!(
            rig.names(&out),
            [
                ("A".into(), 400, Int(2), Good),
                ("B".into(), 400, Real(1.5), Good)
            ]
        );
        assert_eq!(out.events[0].kind, EventKind::LinkRestored);
    }

    #[tokio::test]
    async fn deadband() {
        let mut rig = Rig::new(History {
            delta: parse_deadband("2").unwrap(),
            ..history(&["A"])
        });
        let mut recorded = Vec::new();
        for v in [10, 11, 12, 13, 9, 8, 6] {
            let out = rig.poll(&[("A", int(v))]).await;
            recorded.extend(rig.names(&out).into_iter().map(|s| s.2));
        }
        // |v - last recorded| > 2: 10, 13 (from 10), 9 (from 13), 6 (from 9).
        assert_eq!(recorded, [Int(10), Int(13), Int(9), Int(6)]);
    }

    #[tokio::test]
    async fn heartbeat() {
        let mut rig = Rig::new(History {
            heartbeat: Duration::from_millis(300),
            ..history(&["A"])
        });
        let mut times = Vec::new();
        for v in [1, 1, 1, 1, 2, 2, 2, 2, 2] {
            let out = rig.poll(&[("A", int(v))]).await;
            times.extend(rig.names(&out).into_iter().map(|s| s.1));
        }
        // Recorded at 100 (first), 400 (heartbeat), 500 (change), 800
        // (heartbeat).
        assert_eq!(times, [100, 400, 500, 800]);
    }

    #[tokio::test]
    async fn stamps_and_capture() {
        let mut rig = Rig::new(History {
            stamps: parse_stamps("A:STAMP").unwrap(),
            trigger: Some("trig".into()),
            ..history(&["S"])
        });
        let dt = |s: f64| s.to_le_bytes().to_vec();
        let out = rig
            .poll(&[("A", int(5)), ("STAMP", dt(1000.0)), ("TRIG", vec![0])])
            .await;
        let a = out.samples.iter().find(|s| s.var == rig.id("A")).unwrap();
        assert_eq!((a.value.clone(), a.plc_time), (Int(5), Some(1_000_000)));
        // Same value, new stamp: a new event.
        let out = rig.poll(&[("STAMP", dt(1001.0))]).await;
        assert_eq!(out.samples.len(), 1);
        assert_eq!(out.samples[0].plc_time, Some(1_001_000));
        // Capture: S and A are recorded at the 2 cycles before, the edge
        // and 1 after, changed or not.
        rig.poll(&[("S", b"x\0".to_vec())]).await;
        let out = rig.poll(&[("TRIG", vec![1])]).await;
        assert_eq!(out.events[0].kind, EventKind::Capture);
        let times: Vec<i64> = rig.names(&out).iter().map(|s| s.1).collect();
        // A at 200 and 300, S at 300 (no value before), both at 400.
        assert_eq!(times, [200, 300, 300, 400, 400]);
        let out = rig.poll(&[]).await;
        assert_eq!(out.samples.len(), 2);
        let out = rig.poll(&[]).await;
        assert!(out.samples.is_empty());
    }
}
