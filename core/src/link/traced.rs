//! The frame trace of a PLC link (see [`crate::trace`]): a backend wrapped
//! so that every request the link makes and every answer is written, when
//! the section's trace is on, whatever the backend. Reads and writes show
//! area, offset and length and the data in hex; refusals and link errors as
//! they are reported.

use std::fmt::Write as _;
use std::time::Instant;

use async_trait::async_trait;
use plccoms_protocol::Area;

use crate::driver::{
    Answer, DirEntry, FileInfo, PlcBackend, PlcError, PlcStatus, Pushed, PushedVar, ReadRequest,
    WriteData, WriteRequest,
};
use crate::trace::{hex, FrameTrace};

/// A backend whose requests and answers go to the section's trace.
pub struct Traced {
    inner: Box<dyn PlcBackend>,
    trace: FrameTrace,
}

impl Traced {
    /// `backend`, traced; a backend already traced is returned as it is.
    pub fn wrap(backend: Box<dyn PlcBackend>, trace: FrameTrace) -> Box<dyn PlcBackend> {
        if backend.is_traced() {
            return backend;
        }
        Box::new(Traced {
            inner: backend,
            trace,
        })
    }

    /// A request to the PLC; `what` is only made while the trace is on.
    fn request(&self, what: impl FnOnce() -> String) {
        if self.trace.on() {
            self.trace.plc("->", format_args!("{}", what()));
        }
    }

    /// The answer to a request whose trace started at `started` (`None`:
    /// the trace was off, nothing to write).
    fn answer<T>(
        &self,
        started: Option<Instant>,
        result: &Result<T, PlcError>,
        show: impl FnOnce(&T) -> String,
    ) {
        let Some(started) = started else { return };
        let ms = started.elapsed().as_secs_f64() * 1000.0;
        match result {
            Ok(value) => self
                .trace
                .plc("<-", format_args!("{} ({ms:.1} ms)", show(value))),
            Err(e) => self.trace.plc("<-", format_args!("{e} ({ms:.1} ms)")),
        }
    }
}

fn area(area: Area) -> String {
    format!("{area:?}")
}

fn answers<T>(list: &[Answer<T>], show: impl Fn(&T) -> String) -> String {
    let mut out = String::new();
    for (i, answer) in list.iter().enumerate() {
        if i > 0 {
            out.push_str(" | ");
        }
        match answer {
            Ok(value) => out.push_str(&show(value)),
            Err(refusal) => {
                let _ = write!(out, "refused: {refusal}");
            }
        }
    }
    out
}

#[async_trait]
impl PlcBackend for Traced {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn source_address(&self) -> Option<u8> {
        self.inner.source_address()
    }
    fn max_read_block(&self, area: Area) -> u32 {
        self.inner.max_read_block(area)
    }
    fn read_gap(&self, area: Area) -> Option<u32> {
        self.inner.read_gap(area)
    }
    fn read_align(&self, area: Area) -> u32 {
        self.inner.read_align(area)
    }
    fn refusal_hint(
        &self,
        area: Area,
        offset: u32,
        refusal: &plccoms_plc::Refusal,
    ) -> Option<String> {
        self.inner.refusal_hint(area, offset, refusal)
    }
    fn probe_backoff(&self) -> (std::time::Duration, std::time::Duration) {
        self.inner.probe_backoff()
    }
    fn max_file_block(&self) -> u32 {
        self.inner.max_file_block()
    }
    fn answer_timeout(&self) -> std::time::Duration {
        self.inner.answer_timeout()
    }
    fn set_counters(&mut self, counters: std::sync::Arc<crate::metrics::BackendCounters>) {
        self.inner.set_counters(counters)
    }
    fn is_traced(&self) -> bool {
        true
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        self.request(|| format!("connect {}", self.inner.describe()));
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.connect().await;
        self.answer(started, &result, |ident| format!("identified: {ident}"));
        result
    }

    async fn probe(&mut self) -> Result<String, PlcError> {
        self.request(|| format!("probe {}", self.inner.describe()));
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.probe().await;
        self.answer(started, &result, |ident| format!("identified: {ident}"));
        result
    }

    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        if self.trace.on() {
            let list: Vec<String> = requests
                .iter()
                .map(|r| format!("{} {}+{}", area(r.area), r.offset, r.len))
                .collect();
            self.trace
                .plc("->", format_args!("read {}", list.join(", ")));
        }
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.read(requests).await;
        self.answer(started, &result, |list| answers(list, |data| hex(data)));
        result
    }

    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        if self.trace.on() {
            let list: Vec<String> = requests
                .iter()
                .map(|w| match &w.data {
                    WriteData::Bytes(bytes) => {
                        format!("{} {}: {}", area(w.area), w.offset, hex(bytes))
                    }
                    WriteData::Bit { bit, value } => {
                        format!("{} {}.{bit} = {}", area(w.area), w.offset, u8::from(*value))
                    }
                })
                .collect();
            self.trace
                .plc("->", format_args!("write {}", list.join(", ")));
        }
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.write(requests).await;
        self.answer(started, &result, |list| {
            answers(list, |()| "ok".to_string())
        });
        result
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        self.request(|| "status".to_string());
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.status().await;
        self.answer(started, &result, |s| {
            if s.run { "RUN" } else { "STOP" }.to_string()
        });
        result
    }

    fn take_pushed(&mut self) -> Vec<Pushed> {
        let pushed = self.inner.take_pushed();
        if self.trace.on() {
            for value in &pushed {
                let name = match &value.var {
                    PushedVar::Named(name) => Some(name.clone()),
                    &PushedVar::Listed { list, index } => self.inner.pushed_name(list, index),
                };
                self.trace.plc(
                    "<-",
                    format_args!(
                        "pushed {} at {} ms: {}{}",
                        String::from_utf8_lossy(name.as_deref().unwrap_or(b"?")),
                        value.unix_ms,
                        hex(&value.bytes),
                        if value.uncertain { " (uncertain)" } else { "" }
                    ),
                );
            }
        }
        pushed
    }

    fn pushed_name(&self, list: u32, index: u32) -> Option<std::sync::Arc<[u8]>> {
        self.inner.pushed_name(list, index)
    }

    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        self.inner.wait_pushed().await
    }

    fn take_uncertain(&mut self) -> Option<Vec<Box<[u8]>>> {
        let uncertain = self.inner.take_uncertain();
        if let (true, Some(names)) = (self.trace.on(), &uncertain) {
            for name in names {
                self.trace.plc(
                    "<-",
                    format_args!("uncertain {}", String::from_utf8_lossy(name)),
                );
            }
        }
        uncertain
    }

    async fn file_info(&mut self, path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        self.request(|| format!("file info {}", String::from_utf8_lossy(path)));
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.file_info(path).await;
        self.answer(started, &result, |a| match a {
            Ok(info) => format!("{} bytes", info.size),
            Err(refusal) => format!("refused: {refusal}"),
        });
        result
    }

    async fn read_file(
        &mut self,
        path: &[u8],
        offset: u64,
        len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        self.request(|| {
            let name = String::from_utf8_lossy(path);
            format!("read file {name} {offset}+{len}")
        });
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.read_file(path, offset, len).await;
        self.answer(started, &result, |a| match a {
            Ok(data) => format!("{} bytes: {}", data.len(), hex(data)),
            Err(refusal) => format!("refused: {refusal}"),
        });
        result
    }

    async fn write_file(
        &mut self,
        path: &[u8],
        offset: u64,
        data: &[u8],
        last: bool,
    ) -> Result<Answer<()>, PlcError> {
        self.request(|| {
            let name = String::from_utf8_lossy(path);
            let last = if last { " (last)" } else { "" };
            format!("write file {name} {offset}+{}{last}", data.len())
        });
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.write_file(path, offset, data, last).await;
        self.answer(started, &result, |a| match a {
            Ok(()) => "ok".to_string(),
            Err(refusal) => format!("refused: {refusal}"),
        });
        result
    }

    async fn write_file_info(
        &mut self,
        path: &[u8],
        info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        self.request(|| format!("write file info {}", String::from_utf8_lossy(path)));
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.write_file_info(path, info).await;
        self.answer(started, &result, |a| match a {
            Ok(()) => "ok".to_string(),
            Err(refusal) => format!("refused: {refusal}"),
        });
        result
    }

    async fn list_dir(&mut self, path: &[u8]) -> Result<Answer<Vec<DirEntry>>, PlcError> {
        self.request(|| format!("list {}", String::from_utf8_lossy(path)));
        let started = self.trace.on().then(Instant::now);
        let result = self.inner.list_dir(path).await;
        self.answer(started, &result, |a| match a {
            Ok(entries) => format!("{} entries", entries.len()),
            Err(refusal) => format!("refused: {refusal}"),
        });
        result
    }
}
