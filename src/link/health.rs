//! Link health: whether the PLC answers, when to probe it again while it does
//! not, and what to log. Pure: the link tells it what happened and when.
//!
//! Rules (the link applies them):
//! - the PLC is lost when an exchange fails after its one retry, that is
//!   within EPSTOUT + (EPSTOUT + EPSTOUT_STEP) of going silent (2.5 s at the
//!   vendor's defaults); the loss is logged once;
//! - while it is lost, requests are answered with the link error at once
//!   (the handle refuses them without queueing) and one probe at a time
//!   looks for its return, [`PROBE_MIN`] doubling to [`PROBE_MAX`] apart
//!   (the backend may choose other bounds: a Modbus device 1 s to 30 s);
//! - a failed first connection is logged once too, then retried the same
//!   way; the return is logged with the outage's length.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::time::Instant;

/// Pause after the first failed probe; doubles up to [`PROBE_MAX`].
pub const PROBE_MIN: Duration = Duration::from_millis(100);
/// Longest pause between probes: with a probe taking at most EPSTOUT plus a
/// retry, a PLC that returns is found again within about a second.
pub const PROBE_MAX: Duration = Duration::from_secs(1);

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
}

#[derive(Debug)]
pub struct Health {
    state: LinkState,
    shared: SharedState,
    pause: Duration,
    /// The first pause of an outage and the longest it doubles to.
    backoff: (Duration, Duration),
    next_probe: Instant,
    /// Since when the PLC has not answered.
    down_since: Option<Instant>,
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
            down_since: None,
        }
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

    /// The PLC answered a connection attempt. Returns how long it had been
    /// away (`None` at the first connection).
    pub fn connected(&mut self, now: Instant) -> Option<Duration> {
        self.set(LinkState::Online);
        self.pause = self.backoff.0;
        self.down_since.take().map(|since| now - since)
    }

    /// An exchange or a connection attempt failed at `now`.
    pub fn failed(&mut self, now: Instant) -> Failure {
        let failure = match self.state {
            LinkState::Online => Failure::Lost,
            LinkState::Connecting => Failure::Unreachable,
            LinkState::Lost | LinkState::NoPlc => Failure::StillDown,
        };
        if failure != Failure::StillDown {
            self.down_since = Some(now);
        }
        if self.state != LinkState::NoPlc {
            self.set(LinkState::Lost);
        }
        // A loss is probed again at once (it may have been one lost
        // datagram pair); a failed probe waits, longer each time.
        if failure == Failure::Lost {
            self.pause = self.backoff.0;
            self.next_probe = now;
        } else {
            self.next_probe = now + self.pause;
            self.pause = (self.pause * 2).min(self.backoff.1);
        }
        failure
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
        self.down_since = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lost_link_is_probed_at_once_then_with_growing_pauses() {
        let t0 = Instant::now();
        let mut health = Health::new(true, t0);
        let shared = health.shared();
        assert_eq!(shared.get(), LinkState::Connecting);
        assert!(health.probe_due(t0));
        assert_eq!(health.connected(t0), None);
        assert_eq!(shared.get(), LinkState::Online);
        assert!(!health.probe_due(t0), "online: no probes");

        let t1 = t0 + Duration::from_secs(10);
        assert_eq!(health.failed(t1), Failure::Lost);
        assert_eq!(shared.get(), LinkState::Lost);
        assert!(!shared.get().accepts_requests());
        assert!(health.probe_due(t1), "first probe at once");
        assert_eq!(health.failed(t1), Failure::StillDown);
        assert!(!health.probe_due(t1 + Duration::from_millis(99)));
        assert!(health.probe_due(t1 + PROBE_MIN));
        let mut now = t1 + PROBE_MIN;
        let mut pauses = Vec::new();
        for _ in 0..6 {
            assert_eq!(health.failed(now), Failure::StillDown);
            let mut wait = Duration::ZERO;
            while !health.probe_due(now + wait) {
                wait += Duration::from_millis(50);
            }
            pauses.push(wait.as_millis());
            now += wait;
        }
        assert_eq!(pauses, [200, 400, 800, 1000, 1000, 1000]);
        let back = now + Duration::from_millis(10);
        assert_eq!(health.connected(back), Some(back - t1));
        assert_eq!(shared.get(), LinkState::Online);
    }

    #[test]
    fn the_backend_chooses_the_pauses() {
        let t0 = Instant::now();
        let mut health = Health::new(true, t0);
        health.set_backoff((Duration::from_secs(1), Duration::from_secs(30)));
        health.connected(t0);
        assert_eq!(health.failed(t0), Failure::Lost);
        let mut now = t0;
        let mut pauses = Vec::new();
        for _ in 0..7 {
            assert_eq!(health.failed(now), Failure::StillDown);
            let mut wait = Duration::ZERO;
            while !health.probe_due(now + wait) {
                wait += Duration::from_millis(500);
            }
            pauses.push(wait.as_secs());
            now += wait;
        }
        assert_eq!(pauses, [1, 2, 4, 8, 16, 30, 30]);
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
