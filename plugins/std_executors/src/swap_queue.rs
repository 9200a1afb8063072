//! `simple_thread`: one worker over a mutex-protected queue that it swaps out whole and
//! runs outside the lock, as AimRT's `simple_thread` does, with our accounting.
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
//! * **Shutdown**: close the gate. The worker runs everything accepted; the count-out that
//!   empties a closed gate (the worker's, or `shutdown`'s when nothing was in flight)
//!   stops it. Unlike AimRT, a task accepted just before shutdown is never lost: it was
//!   counted before it was queued, so the worker cannot stop before running it.

use std::collections::VecDeque;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::SystemTime;

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorStats, Task, TaskOutcome, ThreadFactory,
    ThreadSettingsRef,
};

use crossbeam_utils::Backoff;

use crate::common::{Accounting, Admission, Clock, Marker};

/// Spins (of up to 64 pauses each) the worker waits for more work before it yields: a
/// few microseconds, which catch the next task of a burst on another core.
const SPINS: u32 = 32;
/// Yields before it sleeps: on a shared core they let the producer fill a batch.
const YIELDS: u32 = 2;

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
}

struct State {
    queue: VecDeque<Task>,
    /// The worker waits on the condvar (set and cleared by it, under the lock).
    waiting: bool,
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

    /// Tells the worker to return (the gate is closed and empty).
    fn stop(&self) {
        self.lock().stop = true;
        self.ready.notify_one();
    }

    fn serve(&self) {
        let _mark = Marker::Worker.set(self.id());
        let counters = self.acct.worker(0);
        let mut batch = VecDeque::new();
        loop {
            {
                let mut st = self.lock();
                while st.queue.is_empty() {
                    if st.stop {
                        return;
                    }
                    st.waiting = true;
                    st = self.ready.wait(st).unwrap_or_else(|e| e.into_inner());
                    st.waiting = false;
                }
                std::mem::swap(&mut st.queue, &mut batch);
            }
            let n = batch.len() as u64;
            let mut panicked = 0;
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
            // it is queued, so this reads no lock.
            let backoff = Backoff::new();
            for _ in 0..SPINS {
                if self.acct.gate.depth() > 0 {
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
            clock: Clock::new(false),
            state: Mutex::new(State {
                queue: VecDeque::new(),
                waiting: false,
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
        false
    }

    fn now(&self) -> SystemTime {
        self.shared.clock.now()
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        let s = &self.shared;
        let task =
            s.acct
                .admit(task, &s.admission, s.label, &s.name)
                .map_err(|(err, emptied)| {
                    if emptied {
                        s.stop();
                    }
                    err
                })?;
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

    fn execute_at(&self, _at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        drop(task);
        self.shared.acct.refuse();
        Err(ExecuteError::NoTimerSupport)
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
        if !s.acct.gate.is_closed() && s.acct.gate.close() {
            s.stop();
        }
        let handle = self.handle.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            if h.thread().id() != std::thread::current().id() {
                let _ = h.join();
            }
        }
    }
}
