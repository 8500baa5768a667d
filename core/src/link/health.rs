//! Link health: whether the PLC answers, when to probe it again while it does
//! not, and what to log. Pure: the link tells it what happened and when.
//!
//! Rules (the link applies them):
//! - the PLC is lost when an exchange fails after its one retry, that is
//!   within EPSTOUT + (EPSTOUT + EPSTOUT_STEP) of going silent (2.5 s at the
//!   vendor's defaults); the loss is logged once;
//! - while it is lost, requests are answered with the link error at once
//!   (the handle refuses them without queueing) and one probe at a time
//!   looks for its return, [`PROBE_MIN`] doubling to [`PROBE_MAX`] apart,
//!   measured from the start of one probe to the start of the next (a probe
//!   that takes longer, such as one the PLC leaves unanswered until its
//!   EPSTOUT, is followed by the next one at once). A probe is one request
//!   without retry ([`crate::driver::PlcBackend::probe`]), so a PLC that
//!   returns is found within [`PROBE_MAX`] (or the probe's own timeout, if
//!   longer) plus the jitter, and polled at once: values again within 2 s of
//!   its return at the defaults, however long it was away. Each pause is
//!   shortened by a random [`JITTER`] of it, and a probe that overran its
//!   pause is followed after a random half of that, so that many sections
//!   that lost their PLCs together do not probe in step;
//! - a failed first connection is logged once too, then retried the same
//!   way; the return is logged with the outage's length;
//! - a link lost before [`STEADY_POLLS`] good polls since it connected,
//!   twice in a row, is unsteady (a device that connects but fails its
//!   reads, or a lossy line): the second loss is logged, later losses and
//!   reconnections stay quiet and a count of them is logged at most every
//!   [`FLAP_REPORT`], until a run of [`STEADY_POLLS`] good polls. A loss
//!   with no good poll at all since connecting is a flap: the reconnection
//!   waits a pause that doubles from the backend's first one to
//!   [`FLAP_MAX`], reset by a good poll (a lossy line that polls between its
//!   losses is not slowed down). A PLC that is really away meanwhile (its
//!   probes fail) is probed as in any outage, so it is polled again within
//!   [`PROBE_MAX`] of its return.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::time::Instant;

use crate::driver::{PROBE_MAX, PROBE_MIN};

/// Good polls in a row after a connection before the link counts as steady
/// again (at COMM_LOOP_DELAY 100 ms, one second).
pub const STEADY_POLLS: u32 = 10;
/// Longest pause before reconnecting a link that keeps failing right after
/// it connects.
pub const FLAP_MAX: Duration = Duration::from_secs(30);
/// Flaps are logged as a count at most this often.
pub const FLAP_REPORT: Duration = Duration::from_secs(60);
/// The largest part of a probe pause taken off it at random (one fifth).
pub const JITTER: u32 = 5;

/// The state of a section's link to its PLC.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum LinkState {
    /// No PLC configured (`IPADDR = 0.0.0.0`): waiting for SETCONF.
    NoPlc = 0,
    /// Not connected yet since start-up or a new address.
    Connecting = 1,
    Online = 2,
    /// The PLC stopped answering; probing for its return.
    Lost = 3,
}

impl LinkState {
    fn from_u8(value: u8) -> LinkState {
        match value {
            0 => LinkState::NoPlc,
            1 => LinkState::Connecting,
            2 => LinkState::Online,
            _ => LinkState::Lost,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            LinkState::NoPlc => "no_plc",
            LinkState::Connecting => "connecting",
            LinkState::Online => "online",
            LinkState::Lost => "lost",
        }
    }

    /// Whether requests go to the link (else they get the link error at once).
    pub fn accepts_requests(self) -> bool {
        matches!(self, LinkState::Online | LinkState::Connecting)
    }
}

/// The state, readable from any thread without a lock (every request checks
/// it).
#[derive(Debug, Clone)]
pub struct SharedState(Arc<AtomicU8>);

impl SharedState {
    pub fn new(state: LinkState) -> SharedState {
        SharedState(Arc::new(AtomicU8::new(state as u8)))
    }

    pub fn get(&self) -> LinkState {
        LinkState::from_u8(self.0.load(Ordering::Acquire))
    }

    fn set(&self, state: LinkState) {
        self.0.store(state as u8, Ordering::Release);
    }
}

/// What a failure means.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// The link was up: it is lost now (log it).
    Lost,
    /// The first attempt to reach the PLC failed (log it).
    Unreachable,
    /// One more failed probe of a known outage (stay quiet).
    StillDown,
    /// The link failed before a run of good polls since it connected: it
    /// flaps from now on (log it).
    Unsteady,
    /// One more failure of a flapping link (stay quiet; counted).
    Flapped,
}

/// What a successful connection means.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Connected {
    /// The first connection (log it).
    First,
    /// Back after an outage of this length (log it).
    Again(Duration),
    /// A flapping link connected once more (stay quiet).
    Retrial,
}

/// A link that keeps failing soon after it connects.
#[derive(Debug, Clone, Copy)]
struct Flapping {
    /// Flaps since the link was last steady.
    count: u32,
    /// Flaps not logged yet, and when the count was last logged.
    unreported: u32,
    reported: Instant,
    /// The pause before the next reconnection after a flap.
    pause: Duration,
}

/// A flapping link held [`STEADY_POLLS`] good polls.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Steady {
    pub flaps: u32,
    /// Since the first failure of the flapping.
    pub unsteady_for: Duration,
}

#[derive(Debug)]
pub struct Health {
    state: LinkState,
    shared: SharedState,
    pause: Duration,
    /// The first pause of an outage and the longest it doubles to.
    backoff: (Duration, Duration),
    next_probe: Instant,
    /// When the probe under way started (pauses are measured from it).
    probe_started: Option<Instant>,
    /// State of the jitter's generator (xorshift), seeded per link.
    rng: u64,
    /// Since when the PLC has not answered.
    down_since: Option<Instant>,
    /// Good polls since the link last connected.
    good_polls: u32,
    /// The last loss came before a run of good polls: another one like it
    /// is a flap.
    lost_unsteady: bool,
    flapping: Option<Flapping>,
}

impl Health {
    pub fn new(has_plc: bool, now: Instant) -> Health {
        let state = if has_plc {
            LinkState::Connecting
        } else {
            LinkState::NoPlc
        };
        Health {
            state,
            shared: SharedState::new(state),
            pause: PROBE_MIN,
            backoff: (PROBE_MIN, PROBE_MAX),
            next_probe: now,
            probe_started: None,
            rng: seed(),
            down_since: None,
            good_polls: 0,
            lost_unsteady: false,
            flapping: None,
        }
    }

    /// A random part of `pause`, up to 1/[`JITTER`] of it.
    fn jitter(&mut self, pause: Duration) -> Duration {
        // xorshift64: plenty for spreading probes.
        let mut x = self.rng;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.rng = x;
        let fraction = (x >> 11) as f64 / (1u64 << 53) as f64;
        pause.mul_f64(fraction) / JITTER
    }

    /// A connection attempt starts at `now`: the pause before the next one
    /// is measured from here.
    pub fn probing(&mut self, now: Instant) {
        self.probe_started = Some(now);
    }

    /// Probes of an outage pause `min` doubling to `max` (the backend's
    /// choice).
    pub fn set_backoff(&mut self, (min, max): (Duration, Duration)) {
        self.backoff = (min, max.max(min));
        self.pause = min;
    }

    pub fn state(&self) -> LinkState {
        self.state
    }

    pub fn shared(&self) -> SharedState {
        self.shared.clone()
    }

    fn set(&mut self, state: LinkState) {
        self.state = state;
        self.shared.set(state);
    }

    /// Whether a connection attempt is due at `now`.
    pub fn probe_due(&self, now: Instant) -> bool {
        matches!(self.state, LinkState::Connecting | LinkState::Lost) && now >= self.next_probe
    }

    /// The PLC answered a connection attempt.
    pub fn connected(&mut self, now: Instant) -> Connected {
        self.probe_started = None;
        self.set(LinkState::Online);
        self.pause = self.backoff.0;
        self.good_polls = 0;
        if self.flapping.is_some() {
            return Connected::Retrial;
        }
        match self.down_since.take() {
            Some(since) => Connected::Again(now - since),
            None => Connected::First,
        }
    }

    /// A poll succeeded. Returns the end of a flapping, once.
    pub fn polled(&mut self, now: Instant) -> Option<Steady> {
        self.good_polls = self.good_polls.saturating_add(1);
        if self.good_polls != STEADY_POLLS {
            return None;
        }
        self.lost_unsteady = false;
        let flapping = self.flapping.take()?;
        let since = self.down_since.take().unwrap_or(now);
        Some(Steady {
            flaps: flapping.count,
            unsteady_for: now - since,
        })
    }

    /// An exchange or a connection attempt failed at `now`.
    pub fn failed(&mut self, now: Instant) -> Failure {
        let probe_started = self.probe_started.take();
        let steady = self.good_polls >= STEADY_POLLS;
        let polled_meanwhile = self.good_polls > 0;
        let failure = match self.state {
            LinkState::Online if steady => Failure::Lost,
            LinkState::Online if self.flapping.is_some() => Failure::Flapped,
            LinkState::Online if self.lost_unsteady => Failure::Unsteady,
            LinkState::Online => Failure::Lost,
            LinkState::Connecting => Failure::Unreachable,
            LinkState::Lost | LinkState::NoPlc => Failure::StillDown,
        };
        if matches!(failure, Failure::Lost | Failure::Unreachable) {
            self.down_since = Some(now);
        }
        if failure == Failure::Unsteady {
            self.down_since.get_or_insert(now);
        }
        if self.state != LinkState::NoPlc {
            self.set(LinkState::Lost);
        }
        self.good_polls = 0;
        match failure {
            // A loss is probed again at once (it may have been one lost
            // datagram pair).
            Failure::Lost => {
                self.lost_unsteady = !steady;
                self.pause = self.backoff.0;
                self.next_probe = now;
            }
            // A link that failed before a single good poll waits a pause
            // of its own, longer each time; one that polled meanwhile is
            // probed at once again.
            Failure::Unsteady | Failure::Flapped => {
                let flapping = self.flapping.get_or_insert(Flapping {
                    count: 0,
                    unreported: 0,
                    reported: now,
                    pause: self.backoff.0,
                });
                flapping.count = flapping.count.saturating_add(1);
                if failure == Failure::Flapped {
                    flapping.unreported = flapping.unreported.saturating_add(1);
                }
                if polled_meanwhile {
                    flapping.pause = self.backoff.0;
                    self.next_probe = now;
                } else {
                    self.next_probe = now + flapping.pause;
                    flapping.pause = (flapping.pause * 2).min(FLAP_MAX.max(self.backoff.1));
                }
            }
            // A failed probe waits, longer each time, from its start; one
            // that took longer than its pause is followed soon after.
            Failure::Unreachable | Failure::StillDown => {
                let start = probe_started.unwrap_or(now).min(now);
                let spread = self.jitter(self.pause);
                let due = start + self.pause - spread;
                self.next_probe = if due > now { due } else { now + spread / 2 };
                self.pause = (self.pause * 2).min(self.backoff.1);
            }
        }
        failure
    }

    /// The flaps not logged yet, when the last count is [`FLAP_REPORT`] old.
    pub fn flap_report(&mut self, now: Instant) -> Option<u32> {
        let flapping = self.flapping.as_mut()?;
        if flapping.unreported == 0 || now - flapping.reported < FLAP_REPORT {
            return None;
        }
        flapping.reported = now;
        Some(std::mem::take(&mut flapping.unreported))
    }

    /// The pause before the next reconnection of a flapping link.
    pub fn next_probe_in(&self, now: Instant) -> Duration {
        self.next_probe.saturating_duration_since(now)
    }

    /// A new link (SETCONF): connect to it at once.
    pub fn reset(&mut self, has_plc: bool, now: Instant) {
        self.set(if has_plc {
            LinkState::Connecting
        } else {
            LinkState::NoPlc
        });
        self.pause = self.backoff.0;
        self.next_probe = now;
        self.probe_started = None;
        self.down_since = None;
        self.good_polls = 0;
        self.lost_unsteady = false;
        self.flapping = None;
    }
}

/// A seed for the jitter, different for each link and each run.
fn seed() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
    hasher.write_u64(0x9E37_79B9_7F4A_7C15);
    hasher.finish() | 1
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run of good polls at `now`.
    fn steady(health: &mut Health, now: Instant) -> Option<Steady> {
        (0..STEADY_POLLS).filter_map(|_| health.polled(now)).last()
    }

    /// The pause until the next probe is due after `now`.
    fn pause(health: &Health, now: Instant) -> Duration {
        let mut wait = Duration::ZERO;
        while !health.probe_due(now + wait) {
            wait += Duration::from_millis(50);
        }
        wait
    }

    /// The pause until the next probe is due after `now`, to the
    /// millisecond.
    fn fine_pause(health: &Health, now: Instant) -> Duration {
        let mut step = Duration::from_millis(1024);
        let mut wait = Duration::ZERO;
        while !health.probe_due(now + wait) {
            wait += step;
        }
        // Back to the first due millisecond.
        while step > Duration::from_millis(1) {
            step /= 2;
            if health.probe_due(now + wait - step) {
                wait -= step;
            }
        }
        wait
    }

    #[test]
    fn pauses_run_from_the_start_of_a_probe_with_jitter() {
        let t0 = Instant::now();
        let mut health = Health::new(true, t0);
        health.connected(t0);
        steady(&mut health, t0);
        assert_eq!(health.failed(t0), Failure::Lost);
        // Probes that get no answer within a second (a silent PLC over UDP,
        // EPSTOUT 1 s): the next starts soon after, not a pause later.
        let mut now = t0;
        let mut gaps = Vec::new();
        for _ in 0..40 {
            health.probing(now);
            let end = now + Duration::from_secs(1);
            assert_eq!(health.failed(end), Failure::StillDown);
            let next = end + fine_pause(&health, end);
            gaps.push((next - now).as_millis());
            now = next;
        }
        assert!(
            gaps.iter().all(|gap| (1000..=1100).contains(gap)),
            "{gaps:?}"
        );
        assert!(gaps.windows(2).any(|w| w[0] != w[1]), "no jitter: {gaps:?}");
        // Probes refused at once (a port closed): start to start, at most
        // PROBE_MAX.
        let mut starts = Vec::new();
        for _ in 0..40 {
            health.probing(now);
            starts.push(now);
            let end = now + Duration::from_millis(3);
            assert_eq!(health.failed(end), Failure::StillDown);
            now = end + fine_pause(&health, end);
        }
        let gaps: Vec<u128> = starts
            .windows(2)
            .map(|w| (w[1] - w[0]).as_millis())
            .collect();
        assert!(
            gaps.iter().all(|gap| (800..=1000).contains(gap)),
            "{gaps:?}"
        );
        assert!(gaps.windows(2).any(|w| w[0] != w[1]), "no jitter: {gaps:?}");
        // Two links lost together drift apart.
        let mut other = Health::new(true, t0);
        other.connected(t0);
        steady(&mut other, t0);
        other.failed(t0);
        let mut health = Health::new(true, t0);
        health.connected(t0);
        steady(&mut health, t0);
        health.failed(t0);
        let (mut a, mut b) = (t0, t0);
        for _ in 0..10 {
            health.failed(a);
            a += fine_pause(&health, a);
            other.failed(b);
            b += fine_pause(&other, b);
        }
        assert_ne!(a, b, "in step");
    }

    #[test]
    fn a_link_that_fails_soon_after_connecting_backs_off_until_steady() {
        let t0 = Instant::now();
        let mut health = Health::new(true, t0);
        assert_eq!(health.connected(t0), Connected::First);
        // Lost before a run of good polls: maybe a PLC switched off, or one
        // lost datagram pair; probed at once as any loss.
        assert_eq!(health.failed(t0), Failure::Lost);
        assert!(health.probe_due(t0));
        assert_eq!(health.connected(t0), Connected::Again(Duration::ZERO));
        // Lost again so soon: it flaps.
        assert_eq!(health.failed(t0), Failure::Unsteady);
        let mut now = t0;
        let mut pauses = Vec::new();
        for _ in 0..12 {
            let wait = pause(&health, now);
            pauses.push(wait.as_millis());
            now += wait;
            assert_eq!(health.connected(now), Connected::Retrial);
            assert_eq!(health.failed(now), Failure::Flapped);
        }
        assert_eq!(
            pauses,
            [100, 200, 400, 800, 1600, 3200, 6400, 12800, 25600, 30000, 30000, 30000]
        );
        // The count is logged at most once a minute.
        let reported = health.flap_report(now);
        assert_eq!(reported, Some(12));
        assert_eq!(health.flap_report(now), None);
        let reported_at = now;
        now += pause(&health, now);
        health.connected(now);
        health.failed(now);
        let soon = reported_at + FLAP_REPORT - Duration::from_millis(1);
        assert_eq!(health.flap_report(soon), None);
        assert_eq!(health.flap_report(reported_at + FLAP_REPORT), Some(1));

        // A lossy line: a few good polls between losses are not a run of
        // them (still quiet), but they end the pauses.
        now += pause(&health, now);
        assert_eq!(health.connected(now), Connected::Retrial);
        for _ in 0..STEADY_POLLS - 1 {
            assert_eq!(health.polled(now), None);
        }
        assert_eq!(health.failed(now), Failure::Flapped);
        assert!(health.probe_due(now));
        assert_eq!(health.connected(now), Connected::Retrial);
        assert_eq!(health.failed(now), Failure::Flapped);
        assert_eq!(pause(&health, now).as_millis(), 100);

        // Away for real meanwhile: probed as in any outage, not at the
        // flapping pace, so its return is found within PROBE_MAX.
        now += pause(&health, now);
        for _ in 0..6 {
            assert_eq!(health.failed(now), Failure::StillDown);
            assert!(pause(&health, now) <= PROBE_MAX);
            now += pause(&health, now);
        }
        assert_eq!(health.connected(now), Connected::Retrial);
        // A run of good polls ends the flapping, once; the next loss is a
        // plain one again, probed at once.
        let end = steady(&mut health, now).expect("steady again");
        assert_eq!(end.flaps, 16);
        assert_eq!(end.unsteady_for, now - t0);
        assert_eq!(health.polled(now), None);
        assert_eq!(health.failed(now), Failure::Lost);
        assert!(health.probe_due(now));
        assert_eq!(health.connected(now), Connected::Again(Duration::ZERO));
    }

    #[test]
    fn a_lost_link_is_probed_at_once_then_with_growing_pauses() {
        let t0 = Instant::now();
        let mut health = Health::new(true, t0);
        let shared = health.shared();
        assert_eq!(shared.get(), LinkState::Connecting);
        assert!(health.probe_due(t0));
        assert_eq!(health.connected(t0), Connected::First);
        assert_eq!(shared.get(), LinkState::Online);
        assert!(!health.probe_due(t0), "online: no probes");
        steady(&mut health, t0);

        let t1 = t0 + Duration::from_secs(10);
        assert_eq!(health.failed(t1), Failure::Lost);
        assert_eq!(shared.get(), LinkState::Lost);
        assert!(!shared.get().accepts_requests());
        assert!(health.probe_due(t1), "first probe at once");
        assert_eq!(health.failed(t1), Failure::StillDown);
        // Jitter takes up to a fifth off each pause.
        assert!(!health.probe_due(t1 + Duration::from_millis(79)));
        assert!(health.probe_due(t1 + PROBE_MIN));
        let mut now = t1 + PROBE_MIN;
        let mut pauses = Vec::new();
        for _ in 0..6 {
            assert_eq!(health.failed(now), Failure::StillDown);
            let wait = fine_pause(&health, now);
            pauses.push(wait.as_millis());
            now += wait;
        }
        for (pause, nominal) in pauses.iter().zip([200, 400, 800, 1000, 1000, 1000]) {
            assert!((nominal * 4 / 5..=nominal).contains(pause), "{pauses:?}");
        }
        let back = now + Duration::from_millis(10);
        assert_eq!(health.connected(back), Connected::Again(back - t1));
        assert_eq!(shared.get(), LinkState::Online);
    }

    #[test]
    fn the_backend_chooses_the_pauses() {
        let t0 = Instant::now();
        let mut health = Health::new(true, t0);
        health.set_backoff((Duration::from_secs(1), Duration::from_secs(30)));
        health.connected(t0);
        steady(&mut health, t0);
        assert_eq!(health.failed(t0), Failure::Lost);
        let mut now = t0;
        let mut pauses = Vec::new();
        for _ in 0..7 {
            assert_eq!(health.failed(now), Failure::StillDown);
            let wait = fine_pause(&health, now);
            pauses.push(wait.as_millis());
            now += wait;
        }
        for (pause, nominal) in pauses.iter().zip([1, 2, 4, 8, 16, 30, 30]) {
            let nominal = nominal * 1000;
            assert!((nominal * 4 / 5..=nominal).contains(pause), "{pauses:?}");
        }
    }

    #[test]
    fn first_connection_failures_and_no_plc() {
        let t0 = Instant::now();
        let mut health = Health::new(true, t0);
        assert_eq!(health.failed(t0), Failure::Unreachable);
        assert_eq!(health.failed(t0 + PROBE_MIN), Failure::StillDown);
        let mut none = Health::new(false, t0);
        assert_eq!(none.state(), LinkState::NoPlc);
        assert!(!none.probe_due(t0));
        none.reset(true, t0);
        assert!(none.probe_due(t0));
        assert_eq!(none.state(), LinkState::Connecting);
    }
}
