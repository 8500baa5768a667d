//! Fan-out latency as the server itself sees it (build with `--features
//! fanout-trace`; never in default builds): for every poll cycle, the time
//! from the poll's completion to the moment the last client's socket took
//! the DIFF lines of it, and the same per client write. A load generator on
//! the same cores cannot tell this apart from its own delay in reading;
//! this can. The summary is logged when the server stops.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Duration;

use tokio::time::Instant;

#[derive(Default)]
struct Trace {
    /// Per snapshot sequence: the latest client write that completed it.
    last_write: HashMap<u64, Duration>,
    /// Every client write of DIFF lines, from the poll's completion.
    writes: Vec<Duration>,
    /// Only polls completed in this window count (SIGUSR1 opens it,
    /// SIGUSR2 closes it; without them, every poll): a load generator
    /// marks its measurement window, leaving out its clients' initial
    /// full snapshots and the end, when it stops reading.
    window: (Option<Instant>, Option<Instant>),
}

static TRACE: Mutex<Option<Trace>> = Mutex::new(None);

fn with_trace<T>(f: impl FnOnce(&mut Trace) -> T) -> T {
    let mut trace = TRACE.lock().unwrap_or_else(|p| p.into_inner());
    f(trace.get_or_insert_with(Trace::default))
}

/// Opens the window on SIGUSR1 (forgetting what was recorded before) and
/// closes it on SIGUSR2.
pub fn listen() {
    use tokio::signal::unix::{signal, SignalKind};
    let (Ok(mut open), Ok(mut close)) = (
        signal(SignalKind::user_defined1()),
        signal(SignalKind::user_defined2()),
    ) else {
        tracing::warn!("fan-out trace: no signal handlers; every poll counts");
        return;
    };
    tokio::spawn(async move {
        loop {
            tokio::select! {
                _ = open.recv() => with_trace(|t| {
                    *t = Trace::default();
                    t.window.0 = Some(Instant::now());
                }),
                _ = close.recv() => with_trace(|t| t.window.1 = Some(Instant::now())),
            }
        }
    });
}

/// A client's socket took every DIFF line of the snapshots in `blocks`
/// (sequence, poll completion).
pub fn written(blocks: &mut Vec<(u64, Instant)>) {
    let now = Instant::now();
    let mut trace = TRACE.lock().unwrap_or_else(|p| p.into_inner());
    let trace = trace.get_or_insert_with(Trace::default);
    let (from, to) = trace.window;
    for (seq, polled) in blocks.drain(..) {
        if from.is_some_and(|from| polled < from) || to.is_some_and(|to| polled > to) {
            continue;
        }
        let took = now.saturating_duration_since(polled);
        trace.writes.push(took);
        let last = trace.last_write.entry(seq).or_default();
        *last = (*last).max(took);
    }
}

/// The summary of what was traced, if anything.
pub fn summary() -> Option<String> {
    let trace = TRACE.lock().unwrap_or_else(|p| p.into_inner());
    let trace = trace.as_ref()?;
    let mut cycles: Vec<Duration> = trace.last_write.values().copied().collect();
    let mut writes = trace.writes.clone();
    // Per poll cycle: from its completion to the last client's write.
    Some(format!(
        "fan-out trace: cycles={} {} writes={} {}",
        cycles.len(),
        percentiles("cycle", &mut cycles),
        writes.len(),
        percentiles("write", &mut writes)
    ))
}

/// `<what>_p50_ms=.. <what>_p99_ms=.. <what>_max_ms=..`
fn percentiles(what: &str, values: &mut [Duration]) -> String {
    if values.is_empty() {
        return String::new();
    }
    values.sort_unstable();
    let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize].as_secs_f64() * 1e3;
    format!(
        "{what}_p50_ms={:.3} {what}_p99_ms={:.3} {what}_max_ms={:.3}",
        at(0.5),
        at(0.99),
        at(1.0)
    )
}
