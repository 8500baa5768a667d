//! Counters, gauges and histograms the server keeps as it works, rendered in
//! the Prometheus text format (`/metrics`). Plain atomics: recording costs
//! an uncontended atomic add, so the hot paths (the poll cycle, DIFF
//! fan-out) can afford it; reading happens only when someone scrapes.
//!
//! Names follow Prometheus conventions: `plccoms_` prefix, base units
//! (seconds, bytes), `_total` for counters, one `section` label.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

/// A monotonically increasing count.
#[derive(Debug, Default)]
pub struct Counter(AtomicU64);

impl Counter {
    pub fn inc(&self) {
        self.add(1);
    }

    pub fn add(&self, n: u64) {
        self.0.fetch_add(n, Ordering::Relaxed);
    }

    pub fn get(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
    }
}

/// A value that goes up and down.
#[derive(Debug, Default)]
pub struct Gauge(AtomicU64);

impl Gauge {
    pub fn set(&self, value: u64) {
        self.0.store(value, Ordering::Relaxed);
    }

    pub fn add(&self, n: u64) {
        self.0.fetch_add(n, Ordering::Relaxed);
    }

    pub fn sub(&self, n: u64) {
        self.0.fetch_sub(n, Ordering::Relaxed);
    }

    /// Raises the gauge to `value` if that is higher (a high-water mark).
    pub fn raise(&self, value: u64) {
        self.0.fetch_max(value, Ordering::Relaxed);
    }

    pub fn get(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
    }
}

/// Upper bounds (seconds) of the duration buckets: from half a millisecond
/// (a poll on loopback) to ten seconds (a link timing out).
pub const DURATION_BUCKETS: [f64; 14] = [
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// Upper bounds (seconds) of the lateness buckets: from 0.1 ms (a timer's
/// jitter) to a second (a section starved of its thread).
pub const LATENESS_BUCKETS: [f64; 13] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
];

/// Durations in fixed buckets ([`DURATION_BUCKETS`] unless made with
/// [`Histogram::with_buckets`]).
#[derive(Debug)]
pub struct Histogram {
    bounds: &'static [f64],
    /// Per bucket of `bounds` plus one for +Inf (not cumulative).
    buckets: Box<[AtomicU64]>,
    sum_ns: AtomicU64,
    count: AtomicU64,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram::with_buckets(&DURATION_BUCKETS)
    }
}

impl Histogram {
    /// A histogram of these upper bounds (seconds, ascending).
    pub fn with_buckets(bounds: &'static [f64]) -> Self {
        Histogram {
            bounds,
            buckets: (0..=bounds.len()).map(|_| AtomicU64::new(0)).collect(),
            sum_ns: AtomicU64::new(0),
            count: AtomicU64::new(0),
        }
    }

    pub fn observe(&self, duration: Duration) {
        let seconds = duration.as_secs_f64();
        let index = self
            .bounds
            .iter()
            .position(|&bound| seconds <= bound)
            .unwrap_or(self.bounds.len());
        self.buckets[index].fetch_add(1, Ordering::Relaxed);
        let ns = u64::try_from(duration.as_nanos()).unwrap_or(u64::MAX);
        self.sum_ns.fetch_add(ns, Ordering::Relaxed);
        self.count.fetch_add(1, Ordering::Relaxed);
    }

    pub fn count(&self) -> u64 {
        self.count.load(Ordering::Relaxed)
    }

    /// The total of what was observed.
    pub fn sum(&self) -> Duration {
        Duration::from_nanos(self.sum_ns.load(Ordering::Relaxed))
    }

    /// The mean of what was observed, if anything was.
    pub fn mean(&self) -> Option<Duration> {
        let count = self.count();
        (count > 0).then(|| Duration::from_nanos(self.sum_ns.load(Ordering::Relaxed) / count))
    }

    fn render(&self, out: &mut String, name: &str, labels: &str) {
        let mut cumulative = 0;
        for (i, bound) in self.bounds.iter().enumerate() {
            cumulative += self.buckets[i].load(Ordering::Relaxed);
            let _ = writeln!(out, "{name}_bucket{{{labels},le=\"{bound}\"}} {cumulative}");
        }
        cumulative += self.buckets[self.bounds.len()].load(Ordering::Relaxed);
        let _ = writeln!(out, "{name}_bucket{{{labels},le=\"+Inf\"}} {cumulative}");
        let sum = self.sum_ns.load(Ordering::Relaxed) as f64 / 1e9;
        let _ = writeln!(out, "{name}_sum{{{labels}}} {sum}");
        let _ = writeln!(out, "{name}_count{{{labels}}} {cumulative}");
    }
}

/// What a backend counts: one set per section, kept across new links
/// (SETCONF), handed to each backend the section opens.
#[derive(Debug, Default)]
pub struct BackendCounters {
    /// Request datagrams or transactions sent, retries included.
    pub requests: Counter,
    /// Of those, retransmissions.
    pub retries: Counter,
    /// Exchanges that got no answer in time after their retries.
    pub timeouts: Counter,
    /// Answers that were malformed, foreign or refused as a whole.
    pub errors: Counter,
    /// From sending a request to its answer.
    pub round_trip: Histogram,
}

/// One section's metrics.
#[derive(Debug)]
pub struct SectionMetrics {
    /// Wall time of each poll cycle (its reads).
    pub poll_cycle: Histogram,
    /// Poll deadlines missed because a cycle (or other work) ran too long.
    pub overruns: Counter,
    /// How late each poll cycle starts against its deadline (jitter).
    pub poll_start_late: Histogram,
    pub backend: Arc<BackendCounters>,
    /// 1 while the link is up.
    pub link_up: Gauge,
    pub clients: Gauge,
    pub diff_lines: Counter,
    pub diff_bytes: Counter,
    pub pubfile_reloads: Counter,
}

impl Default for SectionMetrics {
    fn default() -> Self {
        SectionMetrics {
            poll_cycle: Histogram::default(),
            overruns: Counter::default(),
            poll_start_late: Histogram::with_buckets(&LATENESS_BUCKETS),
            backend: Arc::default(),
            link_up: Gauge::default(),
            clients: Gauge::default(),
            diff_lines: Counter::default(),
            diff_bytes: Counter::default(),
            pubfile_reloads: Counter::default(),
        }
    }
}

/// One metric family: name, help and type, for its header lines.
struct Family {
    name: &'static str,
    help: &'static str,
    kind: &'static str,
}

const fn family(name: &'static str, kind: &'static str, help: &'static str) -> Family {
    Family { name, help, kind }
}

const SECTION_FAMILIES: [Family; 14] = [
    family(
        "plccoms_poll_cycle_seconds",
        "histogram",
        "Duration of each poll cycle's reads.",
    ),
    family(
        "plccoms_poll_overruns_total",
        "counter",
        "Poll deadlines missed because a cycle ran too long.",
    ),
    family(
        "plccoms_poll_start_late_seconds",
        "histogram",
        "How late each poll cycle started against its deadline.",
    ),
    family(
        "plccoms_backend_requests_total",
        "counter",
        "Requests sent to the PLC, retries included.",
    ),
    family(
        "plccoms_backend_retries_total",
        "counter",
        "Requests sent again for want of an answer.",
    ),
    family(
        "plccoms_backend_timeouts_total",
        "counter",
        "Exchanges the PLC did not answer in time after the retries.",
    ),
    family(
        "plccoms_backend_errors_total",
        "counter",
        "Malformed, foreign or refused answers from the PLC.",
    ),
    family(
        "plccoms_backend_round_trip_seconds",
        "histogram",
        "From sending a request to the PLC to its answer.",
    ),
    family(
        "plccoms_link_up",
        "gauge",
        "1 while the link to the PLC is up.",
    ),
    family(
        "plccoms_clients_connected",
        "gauge",
        "Clients connected to the section's port.",
    ),
    family(
        "plccoms_diff_lines_total",
        "counter",
        "DIFF lines sent to clients.",
    ),
    family(
        "plccoms_diff_bytes_total",
        "counter",
        "Bytes of DIFF lines sent to clients.",
    ),
    family(
        "plccoms_client_output_queue_max_bytes",
        "gauge",
        "Largest output queued for one connected client now.",
    ),
    family(
        "plccoms_pubfile_reloads_total",
        "counter",
        "Public files loaded after start-up (program change, SETCONF).",
    ),
];

/// What a section knows only at the scrape: read from its clients, so a
/// scrape changes nothing (any number of scrapers see the same).
pub trait SectionProbe: Send + Sync {
    /// The most output queued for one connected client, in bytes.
    fn max_output_queue(&self) -> u64;
}

impl SectionMetrics {
    /// Appends this section's samples of family `index` of
    /// [`SECTION_FAMILIES`].
    fn render_family(
        &self,
        index: usize,
        labels: &str,
        probe: &Weak<dyn SectionProbe>,
        out: &mut String,
    ) {
        let name = SECTION_FAMILIES[index].name;
        let backend = &self.backend;
        let value = match index {
            0 => return self.poll_cycle.render(out, name, labels),
            1 => self.overruns.get(),
            2 => return self.poll_start_late.render(out, name, labels),
            3 => backend.requests.get(),
            4 => backend.retries.get(),
            5 => backend.timeouts.get(),
            6 => backend.errors.get(),
            7 => return backend.round_trip.render(out, name, labels),
            8 => self.link_up.get(),
            9 => self.clients.get(),
            10 => self.diff_lines.get(),
            11 => self.diff_bytes.get(),
            12 => probe.upgrade().map_or(0, |p| p.max_output_queue()),
            _ => self.pubfile_reloads.get(),
        };
        let _ = writeln!(out, "{name}{{{labels}}} {value}");
    }
}

/// Something outside the sections that reports metrics (the historian, the
/// MQTT client): appends whole families, headers included.
pub trait Source: Send + Sync {
    fn render(&self, out: &mut String);
}

/// Every section's metrics and the other sources, rendered together.
#[derive(Default)]
pub struct Registry {
    sections: Mutex<Vec<Arc<RegisteredSection>>>,
    sources: Mutex<Vec<Arc<dyn Source>>>,
    /// The length of the last whole rendering: the next starts with that
    /// much room (1,000 sections render about 3 MB).
    last_len: AtomicUsize,
}

struct RegisteredSection {
    name: String,
    /// `section="..."`, escaped once here rather than per line per scrape.
    labels: String,
    metrics: Arc<SectionMetrics>,
    probe: Weak<dyn SectionProbe>,
}

impl Registry {
    pub fn add_section(
        &self,
        name: &str,
        metrics: Arc<SectionMetrics>,
        probe: Weak<dyn SectionProbe>,
    ) {
        lock(&self.sections).push(Arc::new(RegisteredSection {
            name: name.to_string(),
            labels: format!("section=\"{}\"", escape_label(name)),
            metrics,
            probe,
        }));
    }

    /// Forgets a section that stopped (removed or restarted by a reload).
    pub fn remove_section(&self, name: &str) {
        lock(&self.sections).retain(|s| s.name != name);
    }

    /// Whether a section of this name reports.
    pub fn has_section(&self, name: &str) -> bool {
        lock(&self.sections).iter().any(|s| s.name == name)
    }

    pub fn add_source(&self, source: Arc<dyn Source>) {
        lock(&self.sources).push(source);
    }

    /// The Prometheus text exposition of everything.
    pub fn render(&self) -> String {
        let mut out = self.render_into(String::with_capacity(self.last_len()), &|_| true);
        for source in lock(&self.sources).iter() {
            source.render(&mut out);
        }
        self.last_len.store(out.len(), Ordering::Relaxed);
        out
    }

    /// The section families of the sections `wanted` picks by name, and
    /// nothing else (`/metrics?section=`: a scrape per group of devices).
    pub fn render_sections(&self, wanted: &dyn Fn(&str) -> bool) -> String {
        self.render_into(String::new(), wanted)
    }

    fn last_len(&self) -> usize {
        // A little over, so a scrape that grew by a line does not copy.
        let last = self.last_len.load(Ordering::Relaxed);
        last + last / 16
    }

    fn render_into(&self, mut out: String, wanted: &dyn Fn(&str) -> bool) -> String {
        let sections: Vec<Arc<RegisteredSection>> = lock(&self.sections)
            .iter()
            .filter(|s| wanted(&s.name))
            .cloned()
            .collect();
        for (index, family) in SECTION_FAMILIES.iter().enumerate() {
            header(&mut out, family.name, family.kind, family.help);
            for s in &sections {
                s.metrics
                    .render_family(index, &s.labels, &s.probe, &mut out);
            }
        }
        out
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|p| p.into_inner())
}

/// `# HELP` and `# TYPE` lines of a family.
pub fn header(out: &mut String, name: &str, kind: &str, help: &str) {
    let _ = writeln!(out, "# HELP {name} {help}");
    let _ = writeln!(out, "# TYPE {name} {kind}");
}

/// A label value with `\`, `"` and newlines escaped.
pub fn escape_label(value: &str) -> String {
    value
        .replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prometheus_text_of_a_section() {
        struct Queues(u64);
        impl SectionProbe for Queues {
            fn max_output_queue(&self) -> u64 {
                self.0
            }
        }
        let registry = Registry::default();
        let metrics = Arc::new(SectionMetrics::default());
        let queues: Arc<dyn SectionProbe> = Arc::new(Queues(10));
        registry.add_section("Demo \"1\"", metrics.clone(), Arc::downgrade(&queues));
        metrics.poll_cycle.observe(Duration::from_micros(700));
        metrics.poll_cycle.observe(Duration::from_secs(20));
        metrics.diff_lines.add(3);
        let text = registry.render();
        assert!(text.contains("# TYPE plccoms_poll_cycle_seconds histogram\n"));
        assert!(text.contains(
            "plccoms_poll_cycle_seconds_bucket{section=\"Demo \\\"1\\\"\",le=\"0.0005\"} 0\n"
        ));
        assert!(text.contains(
            "plccoms_poll_cycle_seconds_bucket{section=\"Demo \\\"1\\\"\",le=\"0.001\"} 1\n"
        ));
        assert!(text.contains(
            "plccoms_poll_cycle_seconds_bucket{section=\"Demo \\\"1\\\"\",le=\"+Inf\"} 2\n"
        ));
        assert!(text.contains("plccoms_poll_cycle_seconds_count{section=\"Demo \\\"1\\\"\"} 2\n"));
        assert!(text.contains("plccoms_diff_lines_total{section=\"Demo \\\"1\\\"\"} 3\n"));
        assert!(
            text.contains("plccoms_client_output_queue_max_bytes{section=\"Demo \\\"1\\\"\"} 10\n")
        );
        // A scrape changes nothing; a section gone reports no queue.
        assert_eq!(registry.render(), text);
        drop(queues);
        assert!(registry
            .render()
            .contains("plccoms_client_output_queue_max_bytes{section=\"Demo \\\"1\\\"\"} 0\n"));
    }

    /// 1,000 sections: the size of a scrape and its rendering time,
    /// measured (printed, not asserted: a figure for the notes), and the
    /// shape asserted: a fixed number of lines per section, no
    /// per-variable series.
    #[test]
    fn a_thousand_sections_render_a_bounded_text_and_one_section_alone() {
        let registry = Registry::default();
        let probe: Arc<dyn SectionProbe> = Arc::new(NoQueue);
        let mut all = Vec::new();
        for i in 0..1000 {
            let metrics = Arc::new(SectionMetrics::default());
            metrics.poll_cycle.observe(Duration::from_millis(3));
            metrics
                .backend
                .round_trip
                .observe(Duration::from_micros(900));
            metrics.diff_lines.add(i);
            registry.add_section(
                &format!("device{i:04}"),
                metrics.clone(),
                Arc::downgrade(&probe),
            );
            all.push(metrics);
        }
        let text = registry.render();
        // The fastest of ten: the machine's other work only slows one.
        let fastest = (0..10)
            .map(|_| {
                let started = std::time::Instant::now();
                let text = registry.render();
                (started.elapsed(), text)
            })
            .min_by_key(|(took, _)| *took);
        let (took, again) = fastest.unwrap();
        eprintln!(
            "/metrics of 1,000 sections: {} bytes, {} lines; rendered in {took:?} (fastest of 10)",
            text.len(),
            text.lines().count()
        );
        // 3 histograms (their buckets, +Inf, sum, count) and 11 single
        // samples per section, and a HELP and TYPE per family.
        let per_section = 2 * (DURATION_BUCKETS.len() + 3) + LATENESS_BUCKETS.len() + 3 + 11;
        assert_eq!(
            text.lines().filter(|l| !l.starts_with('#')).count(),
            1000 * per_section
        );
        assert_eq!(
            text.lines().filter(|l| l.starts_with('#')).count(),
            2 * SECTION_FAMILIES.len()
        );
        assert_eq!(again.len(), text.len());
        assert!(again.capacity() >= again.len());
        assert!(text.contains("plccoms_diff_lines_total{section=\"device0999\"} 999\n"));
        let one = registry.render_sections(&|name| name == "device0007");
        assert_eq!(
            one.lines().filter(|l| !l.starts_with('#')).count(),
            per_section
        );
        assert!(one.contains("plccoms_diff_lines_total{section=\"device0007\"} 7\n"));
        assert!(!one.contains("device0008"));
        assert!(registry.has_section("device0999") && !registry.has_section("device1000"));
    }

    struct NoQueue;
    impl SectionProbe for NoQueue {
        fn max_output_queue(&self) -> u64 {
            0
        }
    }

    #[test]
    fn poll_start_lateness_in_its_own_buckets() {
        let registry = Registry::default();
        let metrics = Arc::new(SectionMetrics::default());
        let none: Weak<dyn SectionProbe> = Weak::<Never>::new();
        registry.add_section("a", metrics.clone(), none);
        metrics.poll_start_late.observe(Duration::from_micros(50));
        metrics.poll_start_late.observe(Duration::from_micros(3000));
        metrics.poll_start_late.observe(Duration::from_secs(2));
        let text = registry.render();
        assert!(text.contains("# TYPE plccoms_poll_start_late_seconds histogram\n"));
        for (le, count) in [
            ("0.0001", 1),
            ("0.0025", 1),
            ("0.005", 2),
            ("1", 2),
            ("+Inf", 3),
        ] {
            let line = format!(
                "plccoms_poll_start_late_seconds_bucket{{section=\"a\",le=\"{le}\"}} {count}\n"
            );
            assert!(text.contains(&line), "{line} in {text}");
        }
        assert!(text.contains("plccoms_poll_start_late_seconds_count{section=\"a\"} 3\n"));
        // Next to the missed cycles, each family once.
        let late = text.find("# TYPE plccoms_poll_start_late_seconds").unwrap();
        assert!(text.find("# TYPE plccoms_poll_overruns_total").unwrap() < late);
        assert_eq!(
            text.matches("# TYPE plccoms_poll_start_late_seconds")
                .count(),
            1
        );
    }

    struct Never;
    impl SectionProbe for Never {
        fn max_output_queue(&self) -> u64 {
            0
        }
    }
}
