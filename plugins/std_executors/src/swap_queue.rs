//! The one-worker engine of `simple_thread`, and of `asio_thread` and `tbb_thread` with
//! `thread_num: 1`: a mutex-protected queue that the worker swaps out whole and runs
//! outside the lock, as AimRT's `simple_thread` does, with our accounting, and optional
//! timers.
//!
//! # Protocol
//!
//! * **Submit**: count the task in at the [`Gate`](crate::common::Gate) (the
//!   `queue_threshold` and shutdown check), push it under the lock, and notify the
//!   condvar only if the worker said it is waiting. The flag is read and written under
//!   the lock, so a wake-up cannot be lost, and a busy worker costs producers no syscall.
//! * **Worker**: under the lock, wait while the queue is empty (flag set), then swap the
//!   queue with its own empty buffer; run the batch in order outside the lock; then count
//!   the whole batch out of the gate at once. The buffers are swapped back and forth, so
//!   a steady state allocates nothing. Before it sleeps, the worker spins, then yields
//!   twice, while the gate shows nothing in flight, so in a burst it is found awake.
//! * **Timers** (when built with a [`TimerSpec`]): a min-heap of deadlines in the same
//!   state. A waiting worker sleeps on the condvar until the earliest deadline; a new
//!   earlier deadline wakes it. Due timers run before the tasks taken with them; while
//!   timers wait, the worker takes at most [`BATCH`] tasks at a time, so a long backlog
//!   cannot hold a due timer back by more than a batch.
//! * **Shutdown**: close the gate. Timers already due are queued, timers due later are
//!   dropped and counted. The worker runs everything accepted; the count-out that
//!   empties a closed gate (the worker's, or `shutdown`'s when nothing was in flight)
//!   stops it. Unlike AimRT, a task accepted just before shutdown is never lost: it was
//!   counted before it was queued, so the worker cannot stop before running it.

use std::collections::{BinaryHeap, VecDeque};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Instant, SystemTime};

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorStats, Task, TaskOutcome, ThreadFactory,
    ThreadSettingsRef,
};

use crossbeam_utils::Backoff;

use crate::common::{Accounting, Admission, Clock, LateAlarm, Marker};
use crate::pool::{Entry, TimerSpec};

/// Spins (of up to 64 pauses each) the worker waits for more work before it yields: a
/// few microseconds, which catch the next task of a burst on another core.
const SPINS: u32 = 32;
/// Yields before it sleeps: on a shared core they let the producer fill a batch.
const YIELDS: u32 = 2;
/// Queued tasks the worker waits for (spinning, at most [`ACCUMULATE`]) before it takes
/// the lock again in a burst.
const MIN_BATCH: u64 = 32;
const ACCUMULATE: std::time::Duration = std::time::Duration::from_micros(2);
/// The most tasks the worker takes at once while timers wait.
const BATCH: usize = 64;

/// What [`SwapQueue::new`] needs.
pub(crate) struct SwapSpec<'a> {
    pub(crate) type_name: &'static str,
    /// For log lines, e.g. `simple thread`.
    pub(crate) label: &'static str,
    pub(crate) name: &'a str,
    pub(crate) admission: Admission,
    pub(crate) sched_policy: &'a str,
    pub(crate) bind_cpu: &'a [u32],
    pub(crate) strict: bool,
    /// `Some` for a timer-capable executor.
    pub(crate) timers: Option<TimerSpec>,
    pub(crate) clock: Clock,
}

struct State {
    queue: VecDeque<Task>,
    /// Timed tasks not yet due, earliest on top.
    timers: BinaryHeap<Entry>,
    seq: u64,
    /// The worker waits on the condvar (set and cleared by it, under the lock).
    waiting: bool,
    /// While it waits: the deadline it sleeps until, if any.
    until: Option<Instant>,
    /// The gate is closed and empty: the worker returns.
    stop: bool,
}

struct Shared {
    type_name: &'static str,
    label: &'static str,
    name: String,
    admission: Admission,
    acct: Accounting,
    clock: Clock,
    /// `Some` for a timer-capable executor.
    late: Option<LateAlarm>,
    state: Mutex<State>,
    ready: Condvar,
}

/// A one-worker executor; see the module doc for the protocol.
pub(crate) struct SwapQueue {
    shared: Arc<Shared>,
    handle: Mutex<Option<JoinHandle<()>>>,
    started: AtomicBool,
}

impl std::fmt::Debug for SwapQueue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SwapQueue")
            .field("type", &self.shared.type_name)
            .field("name", &self.shared.name)
            .finish()
    }
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn id(&self) -> usize {
        self as *const Shared as usize
    }

    /// Counts the task in, or refuses it (counted, rate-limited warning, task dropped).
    fn admit(&self, task: Task) -> Result<Task, ExecuteError> {
        self.acct
            .admit(task, &self.admission, self.label, &self.name)
            .map_err(|(err, emptied)| {
                if emptied {
                    self.stop();
                }
                err
            })
    }

    /// At shutdown: queues the timers already due and drops (and counts) the others.
    /// Returns whether a drop emptied the closed gate.
    fn settle_timers(&self) -> bool {
        let entries = std::mem::take(&mut self.lock().timers);
        if entries.is_empty() {
            return false;
        }
        let now = Instant::now();
        let (due, later): (Vec<Entry>, Vec<Entry>) = entries.into_iter().partition(|e| e.due <= now);
        let wake = {
            let mut st = self.lock();
            st.queue.extend(due.into_iter().map(|e| e.task));
            st.waiting
        };
        if wake {
            self.ready.notify_one();
        }
        let mut emptied = false;
        let dropped = later.len();
        for e in later {
            drop(e.task);
            self.acct.drop_at_shutdown();
            emptied |= self.acct.gate.leave();
        }
        if dropped > 0 {
            tracing::info!(target: "aimrt", "{} executor '{}' shut down with {dropped} timed task(s) not yet due (a cancelled timer leaves one); they were dropped without running", self.label, self.name);
        }
        emptied
    }

    /// Tells the worker to return (the gate is closed and empty).
    fn stop(&self) {
        self.lock().stop = true;
        self.ready.notify_one();
    }

    fn serve(&self) {
        let _mark = Marker::Worker.set(self.id());
        if self.late.is_some() {
            crate::common::precise_timed_waits();
        }
        let counters = self.acct.worker(0);
        let mut batch = VecDeque::new();
        let mut due = Vec::new();
        loop {
            {
                let mut st = self.lock();
                loop {
                    if !st.timers.is_empty() {
                        let now = Instant::now();
                        while st.timers.peek().is_some_and(|e| e.due <= now) {
                            due.extend(st.timers.pop());
                        }
                    }
                    if !st.queue.is_empty() || !due.is_empty() {
                        break;
                    }
                    if st.stop {
                        return;
                    }
                    let next = st.timers.peek().map(|e| e.due);
                    st.waiting = true;
                    st.until = next;
                    st = match next {
                        Some(d) => {
                            let left = d.saturating_duration_since(Instant::now());
                            self.ready
                                .wait_timeout(st, left)
                                .unwrap_or_else(|e| e.into_inner())
                                .0
                        }
                        None => self.ready.wait(st).unwrap_or_else(|e| e.into_inner()),
                    };
                    st.waiting = false;
                    st.until = None;
                }
                if st.timers.is_empty() || st.queue.len() <= BATCH {
                    std::mem::swap(&mut st.queue, &mut batch);
                } else {
                    batch.extend(st.queue.drain(..BATCH));
                }
            }
            let n = (due.len() + batch.len()) as u64;
            let mut panicked = 0;
            for e in due.drain(..) {
                if let Some(late) = &self.late {
                    late.check(self.label, &self.name, e.due);
                }
                panicked += u64::from(e.task.run(&self.name) == TaskOutcome::Panicked);
            }
            for task in batch.drain(..) {
                panicked += u64::from(task.run(&self.name) == TaskOutcome::Panicked);
            }
            // Counted as run before they leave the gate, so `stats` never misses one.
            counters.record_batch(n, panicked);
            if self.acct.gate.leave_n(n) {
                return;
            }
            // Before sleeping, spin and then yield twice while nothing new is in flight: a
            // producer in a burst then finds the worker awake and skips the wake-up
            // syscall, and on a shared core the yields let the producer fill a batch
            // instead of waking the worker once per task. The gate counts a task before
            // it is queued, so this reads no lock. When a few tasks are already queued,
            // the spin goes on for up to ACCUMULATE while fewer than MIN_BATCH are: in a
            // burst, taking the lock for every task or two would bounce it (and the
            // queue's buffer) between the producer's core and this one.
            let backoff = Backoff::new();
            let mut first_seen: Option<Instant> = None;
            for _ in 0..SPINS {
                let depth = self.acct.gate.depth();
                if depth >= MIN_BATCH {
                    break;
                }
                if depth > 0 && first_seen.get_or_insert_with(Instant::now).elapsed() >= ACCUMULATE {
                    break;
                }
                backoff.spin();
            }
            for _ in 0..YIELDS {
                if self.acct.gate.depth() > 0 {
                    break;
                }
                std::thread::yield_now();
            }
        }
    }
}

impl SwapQueue {
    /// Starts the worker, named `name` (as AimRT's, which runs tasks before `start`).
    pub(crate) fn new(spec: SwapSpec<'_>, factory: ThreadFactory) -> Result<SwapQueue, Error> {
        let shared = Arc::new(Shared {
            type_name: spec.type_name,
            label: spec.label,
            name: spec.name.to_owned(),
            admission: spec.admission,
            acct: Accounting::new(1),
            clock: spec.clock,
            late: spec.timers.map(|t| t.alarm()),
            state: Mutex::new(State {
                queue: VecDeque::new(),
                timers: BinaryHeap::new(),
                seq: 0,
                waiting: false,
                until: None,
                stop: false,
            }),
            ready: Condvar::new(),
        });
        let worker = shared.clone();
        let settings = ThreadSettingsRef {
            name: spec.name,
            sched_policy: spec.sched_policy,
            bind_cpu: spec.bind_cpu,
            strict: spec.strict,
        };
        let handle = factory.spawn(settings, move || worker.serve())?;
        Ok(SwapQueue {
            shared,
            handle: Mutex::new(Some(handle)),
            started: AtomicBool::new(false),
        })
    }
}

impl Executor for SwapQueue {
    fn type_name(&self) -> &str {
        self.shared.type_name
    }

    fn name(&self) -> &str {
        &self.shared.name
    }

    /// One worker: no two tasks ever overlap.
    fn thread_safe(&self) -> bool {
        true
    }

    fn is_in_current_executor(&self) -> bool {
        Marker::Worker.is(self.shared.id())
    }

    fn supports_timer_schedule(&self) -> bool {
        self.shared.late.is_some()
    }

    fn now(&self) -> SystemTime {
        self.shared.clock.now()
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        let s = &self.shared;
        let task = s.admit(task)?;
        let wake = {
            let mut st = s.lock();
            st.queue.push_back(task);
            st.waiting
        };
        if wake {
            s.ready.notify_one();
        }
        Ok(())
    }

    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        let s = &self.shared;
        if s.late.is_none() {
            drop(task);
            s.acct.refuse();
            return Err(ExecuteError::NoTimerSupport);
        }
        let task = s.admit(task)?;
        let due = s.clock.instant_of(at);
        let wake = {
            let mut st = s.lock();
            if due <= Instant::now() {
                st.queue.push_back(task);
                st.waiting
            } else {
                st.seq += 1;
                let seq = st.seq;
                st.timers.push(Entry { due, seq, task });
                // Woken only if it sleeps past this deadline.
                st.waiting && st.until.is_none_or(|u| due < u)
            }
        };
        if wake {
            s.ready.notify_one();
        }
        Ok(())
    }

    /// The worker already runs; `start` only checks the state: once, never after
    /// shutdown.
    fn start(&self) -> Result<(), Error> {
        let s = &self.shared;
        s.acct.start_once(&self.started, s.label, &s.name)
    }

    fn stats(&self) -> ExecutorStats {
        self.shared.acct.stats()
    }

    /// Stops taking work, runs what was accepted and joins the worker. Idempotent; from a
    /// task of this executor it does not wait for its own thread.
    fn shutdown(&self) {
        let s = &self.shared;
        if !s.acct.gate.is_closed() {
            let emptied = s.acct.gate.close();
            if emptied | s.settle_timers() {
                s.stop();
            }
        }
        let handle = self.handle.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            if h.thread().id() != std::thread::current().id() {
                let _ = h.join();
            }
        }
    }
}
