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
    last: Mutex<Option<Instant>>,
}

impl RateLimit {
    /// A limit of one event per `interval_ms` (0: every event; negative: none).
    pub fn from_millis(interval_ms: i32) -> RateLimit {
        RateLimit {
            interval: u64::try_from(interval_ms).ok().map(Duration::from_millis),
            last: Mutex::new(None),
        }
    }

    /// Whether an event may pass now (and if so, the interval restarts).
    pub fn ready(&self) -> bool {
        let Some(interval) = self.interval else {
            return false;
        };
        let mut last = self.last.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        if last.is_none_or(|l| now.duration_since(l) >= interval) {
            *last = Some(now);
            true
        } else {
            false
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
}
