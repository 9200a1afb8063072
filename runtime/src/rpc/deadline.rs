//! The runtime's RPC deadline thread: every module call has a deadline, and the thread
//! answers a call whose deadline passes with `TIMEOUT`. It needs no executor, so a call
//! blocking a thread of any executor still ends.

use std::cell::Cell;
use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::sync::{Arc, Condvar, Mutex, Weak};
use std::thread::JoinHandle;
use std::time::Instant;

thread_local! {
    static ON_DEADLINE_THREAD: Cell<bool> = const { Cell::new(false) };
}

/// Whether the calling thread is the deadline thread (a blocking call there could never
/// be timed out).
pub(crate) fn on_deadline_thread() -> bool {
    ON_DEADLINE_THREAD.with(Cell::get)
}

/// Something that can be expired.
pub(crate) trait Expire: Send + Sync + 'static {
    /// The deadline passed.
    fn expire(&self);
    /// The runtime shuts down before the deadline.
    fn abandon(&self);
}

struct Entry {
    at: Instant,
    seq: u64,
    call: Weak<dyn Expire>,
}

impl PartialEq for Entry {
    fn eq(&self, other: &Self) -> bool {
        (self.at, self.seq) == (other.at, other.seq)
    }
}
impl Eq for Entry {}
impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Entry {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.at, self.seq).cmp(&(other.at, other.seq))
    }
}

/// Below this many entries the heap is never swept.
const SWEEP_FROM: usize = 1024;

#[derive(Default)]
struct State {
    heap: BinaryHeap<Reverse<Entry>>,
    seq: u64,
    closed: bool,
    /// The heap's size at which answered calls are swept out next.
    sweep_at: usize,
}

#[derive(Default)]
struct Shared {
    state: Mutex<State>,
    wake: Condvar,
}

fn lock(s: &Shared) -> std::sync::MutexGuard<'_, State> {
    s.state.lock().unwrap_or_else(|e| e.into_inner())
}

/// The deadline thread and its queue. A call held only weakly: one answered and dropped
/// costs nothing when its deadline comes.
pub(crate) struct Deadlines {
    shared: Arc<Shared>,
    thread: Mutex<Option<JoinHandle<()>>>,
}

impl Deadlines {
    /// Starts the thread.
    pub(crate) fn start() -> std::io::Result<Deadlines> {
        let shared = Arc::new(Shared::default());
        let s = shared.clone();
        let thread = std::thread::Builder::new()
            .name("aimrt_rpc_deadline".into())
            .spawn(move || {
                ON_DEADLINE_THREAD.with(|c| c.set(true));
                run(&s);
            })?;
        Ok(Deadlines {
            shared,
            thread: Mutex::new(Some(thread)),
        })
    }

    /// Expires `call` at `at`; `false` after [`close`](Self::close).
    pub(crate) fn add(&self, at: Instant, call: Weak<dyn Expire>) -> bool {
        let mut s = lock(&self.shared);
        if s.closed {
            return false;
        }
        s.seq += 1;
        let seq = s.seq;
        let earliest = s.heap.peek().is_none_or(|Reverse(e)| at < e.at);
        s.heap.push(Reverse(Entry { at, seq, call }));
        // An answered call stays in the heap until its deadline, holding its allocation
        // (a weak reference). Sweeping them out whenever the heap doubles keeps it within
        // about twice the calls in flight, at a constant cost per call.
        if s.heap.len() >= s.sweep_at.max(SWEEP_FROM) {
            s.heap.retain(|Reverse(e)| e.call.strong_count() > 0);
            s.sweep_at = 2 * s.heap.len();
        }
        drop(s);
        if earliest {
            self.shared.wake.notify_one();
        }
        true
    }

    /// The entries in the heap (answered calls not swept out yet included).
    #[cfg(test)]
    fn len(&self) -> usize {
        lock(&self.shared).heap.len()
    }

    /// Stops the thread and abandons every call still waiting (they are answered).
    pub(crate) fn close(&self) {
        let left = {
            let mut s = lock(&self.shared);
            s.closed = true;
            std::mem::take(&mut s.heap)
        };
        self.shared.wake.notify_one();
        let handle = self.thread.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            let _ = h.join();
        }
        for Reverse(e) in left {
            if let Some(call) = e.call.upgrade() {
                call.abandon();
            }
        }
    }
}

fn run(shared: &Shared) {
    let mut s = lock(shared);
    loop {
        if s.closed {
            return;
        }
        let now = Instant::now();
        match s.heap.peek() {
            Some(Reverse(e)) if e.at <= now => {
                let Some(Reverse(e)) = s.heap.pop() else {
                    continue;
                };
                drop(s);
                if let Some(call) = e.call.upgrade() {
                    call.expire();
                }
                s = lock(shared);
            }
            Some(Reverse(e)) => {
                let wait = e.at - now;
                s = shared
                    .wake
                    .wait_timeout(s, wait)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
            None => s = shared.wake.wait(s).unwrap_or_else(|e| e.into_inner()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU32, Ordering};
    use std::time::Duration;

    #[derive(Default)]
    struct Probe {
        expired: AtomicU32,
        abandoned: AtomicU32,
        on_thread: AtomicU32,
    }
    impl Expire for Probe {
        fn expire(&self) {
            self.expired.fetch_add(1, Ordering::SeqCst);
            if on_deadline_thread() {
                self.on_thread.fetch_add(1, Ordering::SeqCst);
            }
        }
        fn abandon(&self) {
            self.abandoned.fetch_add(1, Ordering::SeqCst);
        }
    }

    #[test]
    fn answered_calls_do_not_pile_up_until_their_deadlines() {
        let d = Deadlines::start().unwrap();
        let far = Instant::now() + Duration::from_secs(600);
        let in_flight: Vec<Arc<Probe>> = (0..100).map(|_| Arc::new(Probe::default())).collect();
        for p in &in_flight {
            assert!(d.add(far, Arc::downgrade(p) as Weak<dyn Expire>));
        }
        // 100 000 calls answered at once (dropped), as a busy client makes them.
        for _ in 0..100_000 {
            let answered = Arc::new(Probe::default());
            assert!(d.add(far, Arc::downgrade(&answered) as Weak<dyn Expire>));
        }
        assert!(d.len() <= 2 * SWEEP_FROM, "{} entries", d.len());
        // The calls still in flight are kept.
        d.close();
        for p in &in_flight {
            assert_eq!(p.abandoned.load(Ordering::SeqCst), 1);
        }
    }

    #[test]
    fn expires_in_deadline_order_skips_dropped_calls_and_abandons_the_rest_on_close() {
        let d = Deadlines::start().unwrap();
        let now = Instant::now();
        let soon = Arc::new(Probe::default());
        let dropped = Arc::new(Probe::default());
        let late = Arc::new(Probe::default());
        let weak = |p: &Arc<Probe>| Arc::downgrade(p) as Weak<dyn Expire>;
        assert!(d.add(now + Duration::from_secs(600), weak(&late)));
        assert!(d.add(now + Duration::from_millis(20), weak(&soon)));
        assert!(d.add(now + Duration::from_millis(10), weak(&dropped)));
        let dropped_probe = Arc::downgrade(&dropped);
        drop(dropped);
        let until = Instant::now() + Duration::from_secs(10);
        while soon.expired.load(Ordering::SeqCst) == 0 && Instant::now() < until {
            std::thread::sleep(Duration::from_millis(2));
        }
        assert_eq!(soon.expired.load(Ordering::SeqCst), 1);
        assert_eq!(soon.on_thread.load(Ordering::SeqCst), 1);
        assert!(dropped_probe.upgrade().is_none());
        assert!(!on_deadline_thread());
        d.close();
        assert_eq!(late.abandoned.load(Ordering::SeqCst), 1);
        assert_eq!(late.expired.load(Ordering::SeqCst), 0);
        assert!(!d.add(now, weak(&late)), "closed: refused");
    }
}
