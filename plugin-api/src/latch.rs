//! `DynamicLatch`: a countdown latch whose count can grow until it is closed.
//!
//! Design note. The state is one `AtomicU64`: bit 63 is CLOSED, the low 63 bits the count.
//! `try_add` and `count_down` are CAS loops, so the fast path takes no lock. Waiters sleep
//! on a condvar; whoever moves the count to zero (or closes at zero) takes the mutex before
//! `notify_all`, and waiters re-check the count under the same mutex, so no wake-up is
//! lost. Unlike AimRT, an underflowing `count_down` leaves the state untouched and returns
//! an error, and `close` is idempotent.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

const CLOSED: u64 = 1 << 63;
const COUNT: u64 = CLOSED - 1;

/// `count_down` by more than the current count. The latch is unchanged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("DynamicLatch::count_down({delta}) underflow: the count is {count}")]
pub struct LatchUnderflow {
    /// The requested decrement.
    pub delta: u64,
    /// The count at the time.
    pub count: u64,
}

#[derive(Debug, Default)]
struct Inner {
    state: AtomicU64,
    lock: Mutex<()>,
    zero: Condvar,
}

/// A latch that counts outstanding work: `try_add` before starting some, `count_down` when
/// it is done, `close` when no more will be added, `wait` until the count is zero.
///
/// Cloning gives another handle to the same latch.
///
/// ```
/// use aimrt_plugin_api::DynamicLatch;
/// let latch = DynamicLatch::new();
/// assert!(latch.try_add(2));
/// let l = latch.clone();
/// let t = std::thread::spawn(move || { l.count_down(2).unwrap(); });
/// latch.close_and_wait();
/// t.join().unwrap();
/// assert!(!latch.try_add(1), "closed");
/// ```
#[derive(Debug, Clone, Default)]
pub struct DynamicLatch {
    inner: Arc<Inner>,
}

impl DynamicLatch {
    /// An open latch with count 0.
    pub fn new() -> DynamicLatch {
        DynamicLatch::default()
    }

    /// Adds `delta` unless the latch is closed; returns whether it was added.
    pub fn try_add(&self, delta: u64) -> bool {
        let mut cur = self.inner.state.load(Ordering::Acquire);
        loop {
            if cur & CLOSED != 0 {
                return false;
            }
            let Some(next) = (cur & COUNT).checked_add(delta).filter(|n| *n <= COUNT) else {
                return false;
            };
            match self.inner.state.compare_exchange_weak(
                cur,
                next,
                Ordering::AcqRel,
                Ordering::Acquire,
            ) {
                Ok(_) => return true,
                Err(actual) => cur = actual,
            }
        }
    }

    /// Subtracts `delta`; wakes every waiter when the count reaches zero. Counting down
    /// below zero is an error and changes nothing.
    pub fn count_down(&self, delta: u64) -> Result<(), LatchUnderflow> {
        let mut cur = self.inner.state.load(Ordering::Acquire);
        loop {
            let count = cur & COUNT;
            if count < delta {
                return Err(LatchUnderflow { delta, count });
            }
            let next = (cur & CLOSED) | (count - delta);
            match self.inner.state.compare_exchange_weak(
                cur,
                next,
                Ordering::AcqRel,
                Ordering::Acquire,
            ) {
                Ok(_) => {
                    if count == delta && delta > 0 {
                        self.notify();
                    }
                    return Ok(());
                }
                Err(actual) => cur = actual,
            }
        }
    }

    /// Refuses further `try_add`s (idempotent); wakes waiters if the count is zero.
    pub fn close(&self) {
        let prev = self.inner.state.fetch_or(CLOSED, Ordering::AcqRel);
        if prev & COUNT == 0 {
            self.notify();
        }
    }

    /// Whether `close` was called.
    pub fn is_closed(&self) -> bool {
        self.inner.state.load(Ordering::Acquire) & CLOSED != 0
    }

    /// The current count.
    pub fn count(&self) -> u64 {
        self.inner.state.load(Ordering::Acquire) & COUNT
    }

    /// Blocks until the count is zero (closing is not required; a latch at zero can be
    /// reused if it is not closed).
    pub fn wait(&self) {
        let mut guard = self.inner.lock.lock().unwrap_or_else(|e| e.into_inner());
        while self.count() != 0 {
            guard = self
                .inner
                .zero
                .wait(guard)
                .unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Like [`wait`](Self::wait) with a limit; returns whether the count reached zero.
    pub fn wait_timeout(&self, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        let mut guard = self.inner.lock.lock().unwrap_or_else(|e| e.into_inner());
        while self.count() != 0 {
            let now = Instant::now();
            if now >= deadline {
                return false;
            }
            guard = self
                .inner
                .zero
                .wait_timeout(guard, deadline - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
        true
    }

    /// `close()` then `wait()`.
    pub fn close_and_wait(&self) {
        self.close();
        self.wait();
    }

    fn notify(&self) {
        let _guard = self.inner.lock.lock().unwrap_or_else(|e| e.into_inner());
        self.inner.zero.notify_all();
    }

    /// A guard that counts down by one when dropped.
    pub(crate) fn count_down_guard(&self) -> CountDownGuard {
        CountDownGuard(self.clone())
    }
}

/// Counts its latch down by one when dropped (run, panicked or dropped unrun alike).
#[derive(Debug)]
pub(crate) struct CountDownGuard(DynamicLatch);

impl Drop for CountDownGuard {
    fn drop(&mut self) {
        let _ = self.0.count_down(1);
    }
}

#[cfg(test)]
mod tests {
    //! AimRT's 17 `DYNAMICLATCH_TEST` cases, re-expressed, plus the fixed edge cases.
    use super::*;
    use std::sync::atomic::{AtomicBool, AtomicUsize};
    use std::thread;

    const LIMIT: Duration = Duration::from_secs(20);

    fn spawn_waiter(l: &DynamicLatch, woken: &Arc<AtomicUsize>) -> thread::JoinHandle<()> {
        let l = l.clone();
        let w = woken.clone();
        thread::spawn(move || {
            assert!(l.wait_timeout(LIMIT), "waiter timed out");
            w.fetch_add(1, Ordering::SeqCst);
        })
    }

    #[test]
    fn base_zero_then_wait_immediate() {
        DynamicLatch::new().wait();
    }

    #[test]
    fn base_add_count_down_simple() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1));
        let woken = Arc::new(AtomicUsize::new(0));
        let h = spawn_waiter(&l, &woken);
        thread::sleep(Duration::from_millis(10));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.count_down(1).unwrap();
        h.join().unwrap();
        assert_eq!(woken.load(Ordering::SeqCst), 1);
    }

    #[test]
    fn count_down_to_zero_notifies_all_waiters() {
        let l = DynamicLatch::new();
        assert!(l.try_add(2));
        let woken = Arc::new(AtomicUsize::new(0));
        let hs: Vec<_> = (0..2).map(|_| spawn_waiter(&l, &woken)).collect();
        thread::sleep(Duration::from_millis(10));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.count_down(1).unwrap();
        thread::sleep(Duration::from_millis(10));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.count_down(1).unwrap();
        hs.into_iter().for_each(|h| h.join().unwrap());
        assert_eq!(woken.load(Ordering::SeqCst), 2);
    }

    #[test]
    fn close_stops_further_add_and_wakes_if_zero() {
        let l = DynamicLatch::new();
        l.close();
        l.wait();
        assert!(!l.try_add(1));
        l.wait();
        assert_eq!(l.count(), 0);
    }

    #[test]
    fn close_with_outstanding_count_wakes_on_zero() {
        let l = DynamicLatch::new();
        assert!(l.try_add(3));
        let woken = Arc::new(AtomicUsize::new(0));
        let h = spawn_waiter(&l, &woken);
        thread::sleep(Duration::from_millis(10));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.close();
        thread::sleep(Duration::from_millis(10));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.count_down(2).unwrap();
        thread::sleep(Duration::from_millis(10));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.count_down(1).unwrap();
        h.join().unwrap();
        assert_eq!(woken.load(Ordering::SeqCst), 1);
    }

    #[test]
    fn concurrency_add_and_count_down() {
        let l = DynamicLatch::new();
        let adders: Vec<_> = (0..12)
            .map(|_| {
                let l = l.clone();
                thread::spawn(move || (0..10_000).for_each(|_| assert!(l.try_add(1))))
            })
            .collect();
        adders.into_iter().for_each(|h| h.join().unwrap());
        assert_eq!(l.count(), 120_000);
        let downs: Vec<_> = (0..12)
            .map(|_| {
                let l = l.clone();
                thread::spawn(move || (0..10_000).for_each(|_| l.count_down(1).unwrap()))
            })
            .collect();
        downs.into_iter().for_each(|h| h.join().unwrap());
        assert!(l.wait_timeout(LIMIT));
    }

    #[test]
    fn count_down_underflow_is_an_error_and_changes_nothing() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1));
        l.count_down(1).unwrap();
        assert_eq!(l.count_down(1), Err(LatchUnderflow { delta: 1, count: 0 }));
        assert_eq!(l.count(), 0);
        assert!(!l.is_closed(), "underflow must not corrupt the state");
        assert!(l.try_add(1));
    }

    #[test]
    fn stress_multi_rounds_workers_and_waiter() {
        for _ in 0..100 {
            let l = DynamicLatch::new();
            let workers: Vec<_> = (0..8)
                .map(|_| {
                    assert!(l.try_add(1));
                    let l = l.clone();
                    thread::spawn(move || {
                        thread::sleep(Duration::from_micros(50));
                        l.count_down(1).unwrap();
                    })
                })
                .collect();
            assert!(l.wait_timeout(LIMIT));
            workers.into_iter().for_each(|h| h.join().unwrap());
        }
    }

    #[test]
    fn stress_interleaved_producers_consumers() {
        let l = DynamicLatch::new();
        let produced = Arc::new(AtomicUsize::new(0));
        let consumed = Arc::new(AtomicUsize::new(0));
        let done = Arc::new(AtomicBool::new(false));
        let producers: Vec<_> = (0..8)
            .map(|i| {
                let (l, p) = (l.clone(), produced.clone());
                thread::spawn(move || {
                    for j in 0..2000u64 {
                        assert!(l.try_add(1));
                        p.fetch_add(1, Ordering::SeqCst);
                        if (i + j) % 97 == 0 {
                            thread::sleep(Duration::from_micros(10));
                        }
                    }
                })
            })
            .collect();
        let consumers: Vec<_> = (0..8)
            .map(|_| {
                let (l, c, d) = (l.clone(), consumed.clone(), done.clone());
                thread::spawn(move || loop {
                    if l.count_down(1).is_ok() {
                        c.fetch_add(1, Ordering::SeqCst);
                    } else if d.load(Ordering::SeqCst) && l.count() == 0 {
                        break;
                    } else {
                        thread::yield_now();
                    }
                })
            })
            .collect();
        producers.into_iter().for_each(|h| h.join().unwrap());
        done.store(true, Ordering::SeqCst);
        consumers.into_iter().for_each(|h| h.join().unwrap());
        assert_eq!(produced.load(Ordering::SeqCst), 16_000);
        assert_eq!(consumed.load(Ordering::SeqCst), 16_000);
        assert!(l.wait_timeout(LIMIT));
    }

    #[test]
    fn add_large_delta_then_count_down() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1_000_000));
        let woken = Arc::new(AtomicUsize::new(0));
        let h = spawn_waiter(&l, &woken);
        for _ in 0..1_000_000 {
            l.count_down(1).unwrap();
        }
        h.join().unwrap();
        assert_eq!(woken.load(Ordering::SeqCst), 1);
    }

    #[test]
    fn many_waiters_wake_on_zero() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1));
        let woken = Arc::new(AtomicUsize::new(0));
        let hs: Vec<_> = (0..64).map(|_| spawn_waiter(&l, &woken)).collect();
        thread::sleep(Duration::from_millis(20));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.count_down(1).unwrap();
        hs.into_iter().for_each(|h| h.join().unwrap());
        assert_eq!(woken.load(Ordering::SeqCst), 64);
    }

    #[test]
    fn close_then_add_ignored_many_times() {
        let l = DynamicLatch::new();
        l.close();
        for _ in 0..100_000 {
            assert!(!l.try_add(1));
        }
        assert_eq!(l.count(), 0);
        l.wait();
    }

    #[test]
    fn close_add_ignored_race_ordering() {
        let l = DynamicLatch::new();
        let closed = Arc::new(AtomicBool::new(false));
        l.close();
        closed.store(true, Ordering::SeqCst);
        let hs: Vec<_> = (0..16)
            .map(|_| {
                let (l, c) = (l.clone(), closed.clone());
                thread::spawn(move || {
                    assert!(c.load(Ordering::SeqCst));
                    assert!(!l.try_add(1));
                })
            })
            .collect();
        hs.into_iter().for_each(|h| h.join().unwrap());
        assert!(l.wait_timeout(LIMIT));
    }

    #[test]
    fn close_then_count_down_wakes_all_waiters_race() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1000));
        let woken = Arc::new(AtomicUsize::new(0));
        let waiters: Vec<_> = (0..32).map(|_| spawn_waiter(&l, &woken)).collect();
        l.close();
        let consumers: Vec<_> = (0..8)
            .map(|_| {
                let l = l.clone();
                thread::spawn(move || (0..125).for_each(|_| l.count_down(1).unwrap()))
            })
            .collect();
        consumers.into_iter().for_each(|h| h.join().unwrap());
        waiters.into_iter().for_each(|h| h.join().unwrap());
        assert_eq!(woken.load(Ordering::SeqCst), 32);
    }

    #[test]
    fn reuse_after_zero_works() {
        let l = DynamicLatch::new();
        assert!(l.try_add(2));
        l.count_down(2).unwrap();
        l.wait();
        let woken = Arc::new(AtomicUsize::new(0));
        assert!(l.try_add(1));
        let h = spawn_waiter(&l, &woken);
        thread::sleep(Duration::from_millis(1));
        assert_eq!(woken.load(Ordering::SeqCst), 0);
        l.count_down(1).unwrap();
        h.join().unwrap();
        assert_eq!(woken.load(Ordering::SeqCst), 1);
    }

    #[test]
    fn many_waiters_close_then_last_count_down_race() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1));
        let woken = Arc::new(AtomicUsize::new(0));
        let waiters: Vec<_> = (0..64).map(|_| spawn_waiter(&l, &woken)).collect();
        let (a, b) = (l.clone(), l.clone());
        let t1 = thread::spawn(move || a.close());
        let t2 = thread::spawn(move || b.count_down(1).unwrap());
        t1.join().unwrap();
        t2.join().unwrap();
        waiters.into_iter().for_each(|h| h.join().unwrap());
        assert_eq!(woken.load(Ordering::SeqCst), 64);
    }

    #[test]
    fn race_add_succeeds_after_close() {
        let l = DynamicLatch::new();
        let adders: Vec<_> = (0..40)
            .map(|_| {
                let l = l.clone();
                thread::spawn(move || {
                    if l.try_add(1) {
                        thread::sleep(Duration::from_micros(1));
                        l.count_down(1).unwrap();
                    }
                })
            })
            .collect();
        l.close();
        adders.into_iter().for_each(|h| h.join().unwrap());
        assert_eq!(l.count(), 0);
        assert!(l.wait_timeout(LIMIT));
    }

    #[test]
    fn double_close_is_idempotent() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1));
        l.close();
        l.close();
        assert!(l.is_closed());
        assert_eq!(l.count(), 1);
        l.count_down(1).unwrap();
        assert!(l.wait_timeout(LIMIT));
    }

    #[test]
    fn wait_timeout_reports_expiry() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1));
        assert!(!l.wait_timeout(Duration::from_millis(5)));
    }

    #[test]
    fn guard_counts_down_on_drop() {
        let l = DynamicLatch::new();
        assert!(l.try_add(1));
        drop(l.count_down_guard());
        assert_eq!(l.count(), 0);
    }
}
