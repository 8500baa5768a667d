//! Warnings that a client can trigger at will (refused connections, refused
//! file names, a flood at the descriptor limit) are logged at most once per
//! interval, with how many were left out since, so nobody can fill the log.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// One kind of warning.
pub struct RateLimited {
    interval: Duration,
    last: Mutex<Option<Instant>>,
    quiet: AtomicU64,
}

impl RateLimited {
    pub const fn new(interval: Duration) -> RateLimited {
        RateLimited {
            interval,
            last: Mutex::new(None),
            quiet: AtomicU64::new(0),
        }
    }

    /// `Some(n)` when this occurrence is to be logged, `n` being how many
    /// were not logged since the last one; `None` to stay quiet.
    pub fn admit(&self) -> Option<u64> {
        let now = Instant::now();
        let mut last = self.last.lock().unwrap_or_else(|p| p.into_inner());
        if last.is_some_and(|at| now.duration_since(at) < self.interval) {
            self.quiet.fetch_add(1, Ordering::Relaxed);
            return None;
        }
        *last = Some(now);
        Some(self.quiet.swap(0, Ordering::Relaxed))
    }
}

/// ` (N more since the last message)` when some were left out.
pub fn more(quiet: u64) -> String {
    if quiet == 0 {
        String::new()
    } else {
        format!(" ({quiet} more since the last message)")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_message_an_interval_with_the_count_of_the_rest() {
        let limit = RateLimited::new(Duration::from_millis(200));
        assert_eq!(limit.admit(), Some(0));
        for _ in 0..5 {
            assert_eq!(limit.admit(), None);
        }
        std::thread::sleep(Duration::from_millis(250));
        assert_eq!(limit.admit(), Some(5));
        assert_eq!(more(5), " (5 more since the last message)");
        assert_eq!(more(0), "");
    }
}
