//! AimRT's `AIMRT_WARN_INTERVAL` as a value: at most one warning per interval.

use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Lets one event through per interval; a negative interval (AimRT's way to silence an
/// alarm) lets nothing through. Used for queue-full and late-timer warnings.
///
/// ```
/// let limit = aimrt_plugin_api::RateLimit::from_millis(60_000);
/// assert!(limit.ready());
/// assert!(!limit.ready());
/// assert!(!aimrt_plugin_api::RateLimit::from_millis(-1).ready());
/// ```
#[derive(Debug)]
pub struct RateLimit {
    interval: Option<Duration>,
    /// When an event last passed, and how many were held back since.
    last: Mutex<(Option<Instant>, u64)>,
}

impl RateLimit {
    /// A limit of one event per `interval_ms` (0: every event; negative: none).
    pub fn from_millis(interval_ms: i32) -> RateLimit {
        RateLimit {
            interval: u64::try_from(interval_ms).ok().map(Duration::from_millis),
            last: Mutex::new((None, 0)),
        }
    }

    /// Whether an event may pass now (and if so, the interval restarts).
    pub fn ready(&self) -> bool {
        self.admit().is_some()
    }

    /// `Some(n)` if an event may pass now, where `n` events were held back since the last
    /// one that passed (the interval restarts); `None` holds this one back and counts it.
    ///
    /// ```
    /// let limit = aimrt_plugin_api::RateLimit::from_millis(60_000);
    /// assert_eq!(limit.admit(), Some(0));
    /// assert_eq!(limit.admit(), None);
    /// assert_eq!(limit.admit(), None);
    /// let every = aimrt_plugin_api::RateLimit::from_millis(0);
    /// assert_eq!(every.admit(), Some(0));
    /// ```
    pub fn admit(&self) -> Option<u64> {
        let mut last = self.last.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        let due = match self.interval {
            Some(interval) => last.0.is_none_or(|l| now.duration_since(l) >= interval),
            None => false,
        };
        if due {
            let held = std::mem::take(&mut last.1);
            last.0 = Some(now);
            Some(held)
        } else {
            last.1 += 1;
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_lets_every_event_through() {
        let every = RateLimit::from_millis(0);
        assert!(every.ready() && every.ready());
    }

    #[test]
    fn held_back_events_are_counted_until_one_passes() {
        let limit = RateLimit::from_millis(20);
        assert_eq!(limit.admit(), Some(0));
        for _ in 0..5 {
            assert_eq!(limit.admit(), None);
        }
        std::thread::sleep(Duration::from_millis(30));
        assert_eq!(limit.admit(), Some(5));
    }
}
