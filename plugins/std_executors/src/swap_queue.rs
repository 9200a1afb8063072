//! The engine of `simple_thread`, `tbb_thread` and `asio_thread`: a mutex-protected queue
//! that workers take tasks from in batches and run outside the lock, as AimRT's
//! `simple_thread` does, with our accounting and optional timers.
//!
//! # Protocol
//!
//! * **Submit**: count the task in at the [`Gate`](crate::common::Gate) (the
//!   `queue_threshold` and shutdown check), push it under the lock, and notify a condvar
//!   only if a worker said it is waiting and no wake-up is on its way already (`waking`).
//!   Those counts are read and written under the lock, so a wake-up cannot be lost; busy
//!   workers cost producers no syscall, and sleeping ones one per batch, not per task.
//! * **Worker**: under the lock, wait while there is nothing to run, then take a batch:
//!   with one worker the whole queue (swapped with its own empty buffer, so a steady state
//!   allocates nothing); with `n` workers a share of it, `len / 2n` tasks but at least 1
//!   and at most [`SHARE`], so that all can work and no task waits long behind a slow
//!   one while another worker idles. A worker that leaves tasks behind while another
//!   waits wakes it (the wake-up a producer skipped). The batch runs in order outside the lock and is counted out of the
//!   gate at once. Before it sleeps, a worker spins, then yields twice, while the gate
//!   shows nothing in flight, so in a burst it is found awake; when a few tasks are
//!   already queued it waits (at most [`ACCUMULATE`]) for [`MIN_BATCH`], so that a burst
//!   is taken in batches instead of a lock handover per task.
//! * **Timers** (when built with a [`TimerSpec`]): a min-heap of deadlines in the same
//!   state. At most one waiting worker is the *leader*: it sleeps on its own condvar until
//!   the earliest deadline, the others without a deadline. A new earlier deadline wakes
//!   the leader; a deadline with no leader wakes an idle worker, which becomes leader; a
//!   leader that takes work hands the lead on to an idle worker. Due timers run before the
//!   tasks taken with them; while timers wait, a worker takes at most [`BATCH`] tasks.
//! * **Shutdown**: close the gate. Timers already due are queued, timers due later are
//!   dropped and counted. The workers run everything accepted; the count-out that
//!   empties a closed gate (a worker's, or `shutdown`'s when nothing was in flight)
//!   stops them. Unlike AimRT, a task accepted just before shutdown is never lost: it was
//!   counted before it was queued, so the workers cannot stop before running it.

use std::cmp::Ordering as CmpOrdering;
use std::collections::{BinaryHeap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorStats, Task, TaskOutcome, ThreadFactory,
    ThreadSettingsRef,
};

use crossbeam_utils::Backoff;

use crate::common::{worker_name, Accounting, Admission, Clock, LateAlarm, Marker};

/// Spins (of up to 64 pauses each) a worker waits for more work before it yields: a few
/// microseconds, which catch the next task of a burst on another core.
const SPINS: u32 = 32;
/// Yields before it sleeps: on a shared core they let the producer fill a batch.
const YIELDS: u32 = 2;
/// Tasks in flight a worker waits for (spinning, at most [`ACCUMULATE`]) before it takes
/// the lock again in a burst.
const MIN_BATCH: u64 = 32;
const ACCUMULATE: Duration = Duration::from_micros(2);
/// The most tasks one worker takes at once while timers wait (one worker).
const BATCH: usize = 64;
/// The most tasks one of several workers takes at once.
const SHARE: usize = 64;

/// Timer options (`asio_thread`).
#[derive(Debug, Clone, Copy)]
pub(crate) struct TimerSpec {
    /// `timeout_alarm_threshold_us`: a timer this late is reported.
    pub(crate) late_threshold: Duration,
    /// `timeout_alarm_interval_ms`.
    pub(crate) late_alarm_ms: i32,
}

impl TimerSpec {
    pub(crate) fn alarm(&self) -> LateAlarm {
        LateAlarm::new(self.late_threshold, self.late_alarm_ms)
    }
}

/// A timed task: due at `due`; `seq` keeps equal deadlines in submission order.
pub(crate) struct Entry {
    pub(crate) due: Instant,
    pub(crate) seq: u64,
    pub(crate) task: Task,
}

impl PartialEq for Entry {
    fn eq(&self, other: &Self) -> bool {
        (self.due, self.seq) == (other.due, other.seq)
    }
}
impl Eq for Entry {}
impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<CmpOrdering> {
        Some(self.cmp(other))
    }
}
impl Ord for Entry {
    // Reversed: `BinaryHeap` is a max-heap and we want the earliest deadline on top.
    fn cmp(&self, other: &Self) -> CmpOrdering {
        (other.due, other.seq).cmp(&(self.due, self.seq))
    }
}

/// What [`SwapQueue::new`] needs.
pub(crate) struct SwapSpec<'a> {
    /// `simple_thread`, `tbb_thread` or `asio_thread`.
    pub(crate) type_name: &'static str,
    /// Words for log lines: "simple thread", "tbb thread", "asio thread".
    pub(crate) label: &'static str,
    pub(crate) name: &'a str,
    pub(crate) threads: usize,
    /// `queue_threshold` and its warning.
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
    /// Workers waiting on `ready` (no deadline).
    idle: usize,
    /// Wake-ups sent for queued tasks that no woken worker has come back from yet.
    waking: usize,
    /// While the leader waits on `lead`: the deadline it sleeps until.
    leader: Option<Instant>,
    /// The gate is closed and empty: the workers return.
    stop: bool,
}

struct Shared {
    type_name: &'static str,
    label: &'static str,
    name: String,
    threads: usize,
    admission: Admission,
    acct: Accounting,
    clock: Clock,
    /// `Some` for a timer-capable executor.
    late: Option<LateAlarm>,
    /// Timers in the heap (kept under the lock, read without it by `linger`).
    timers_waiting: AtomicUsize,
    state: Mutex<State>,
    /// Idle workers wait here.
    ready: Condvar,
    /// The leader waits here, until the earliest deadline.
    lead: Condvar,
}

/// An executor of `threads` workers; see the module doc for the protocol.
pub(crate) struct SwapQueue {
    shared: Arc<Shared>,
    handles: Mutex<Vec<JoinHandle<()>>>,
    started: AtomicBool,
}

impl std::fmt::Debug for SwapQueue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SwapQueue")
            .field("type", &self.shared.type_name)
            .field("name", &self.shared.name)
            .field("threads", &self.shared.threads)
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

    /// Queues a task to run now and wakes a waiting worker (an idle one before the
    /// leader), unless a wake-up is already on its way: the woken worker wakes the next if
    /// it leaves tasks behind, so a producer pays at most one wake-up syscall per batch,
    /// not one per task (a publisher with two subscribers on a sleeping pool posts two).
    fn push(&self, task: Task) {
        let mut st = self.lock();
        st.queue.push_back(task);
        let wake = if st.waking > 0 {
            None
        } else if st.idle > 0 {
            Some(&self.ready)
        } else if st.leader.is_some() {
            Some(&self.lead)
        } else {
            None
        };
        if wake.is_some() {
            st.waking += 1;
        }
        drop(st);
        if let Some(cv) = wake {
            cv.notify_one();
        }
    }

    /// At shutdown: queues the timers already due and drops (and counts) the others.
    /// Returns whether a drop emptied the closed gate.
    fn settle_timers(&self) -> bool {
        let entries = {
            let mut st = self.lock();
            self.timers_waiting.store(0, Ordering::Relaxed);
            std::mem::take(&mut st.timers)
        };
        if entries.is_empty() {
            return false;
        }
        let now = Instant::now();
        let (due, later): (Vec<Entry>, Vec<Entry>) =
            entries.into_iter().partition(|e| e.due <= now);
        self.lock().queue.extend(due.into_iter().map(|e| e.task));
        self.ready.notify_all();
        self.lead.notify_all();
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

    /// Tells the workers to return (the gate is closed and empty).
    fn stop(&self) {
        self.lock().stop = true;
        self.ready.notify_all();
        self.lead.notify_all();
    }

    /// Waits until there is something to run, moves due timers to `due` and a batch of
    /// tasks to `batch`. `false`: stop.
    fn take(&self, due: &mut Vec<Entry>, batch: &mut VecDeque<Task>) -> bool {
        let mut st = self.lock();
        loop {
            if !st.timers.is_empty() {
                let now = Instant::now();
                while st.timers.peek().is_some_and(|e| e.due <= now) {
                    due.extend(st.timers.pop());
                    self.timers_waiting.fetch_sub(1, Ordering::Relaxed);
                }
            }
            if !st.queue.is_empty() || !due.is_empty() {
                break;
            }
            if st.stop {
                return false;
            }
            match (st.leader, st.timers.peek().map(|e| e.due)) {
                (None, Some(deadline)) => {
                    st.leader = Some(deadline);
                    let left = deadline.saturating_duration_since(Instant::now());
                    st = self
                        .lead
                        .wait_timeout(st, left)
                        .unwrap_or_else(|e| e.into_inner())
                        .0;
                    st.leader = None;
                    st.waking = st.waking.saturating_sub(1);
                }
                _ => {
                    st.idle += 1;
                    st = self.ready.wait(st).unwrap_or_else(|e| e.into_inner());
                    st.idle -= 1;
                    st.waking = st.waking.saturating_sub(1);
                }
            }
        }
        let len = st.queue.len();
        let take = if self.threads == 1 {
            if st.timers.is_empty() {
                len
            } else {
                len.min(BATCH)
            }
        } else {
            (len / (2 * self.threads)).clamp(1, SHARE).min(len)
        };
        if take == len {
            std::mem::swap(&mut st.queue, batch);
        } else {
            batch.extend(st.queue.drain(..take));
        }
        // Someone idle must help with what is left (unless one is already on its way),
        // and watch the deadlines if nobody leads (this worker may have been the leader).
        let help = !st.queue.is_empty() && st.waking == 0;
        let watch = st.leader.is_none() && !st.timers.is_empty();
        let wake = st.idle > 0 && (help || watch);
        if wake {
            st.waking += 1;
        }
        drop(st);
        if wake {
            self.ready.notify_one();
        }
        true
    }

    fn serve(&self, worker: usize) {
        let _mark = Marker::Worker.set(self.id());
        if self.late.is_some() {
            crate::common::precise_timed_waits();
        }
        let counters = self.acct.worker(worker);
        let mut batch = VecDeque::new();
        let mut due = Vec::new();
        while self.take(&mut due, &mut batch) {
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
                self.stop();
                return;
            }
            self.linger();
        }
    }

    /// Before sleeping, spin and then yield twice while nothing new is in flight: a
    /// producer in a burst then finds the worker awake and skips the wake-up syscall, and
    /// on a shared core the yields let the producer fill a batch instead of waking the
    /// worker once per task. The gate counts a task before it is queued, so this reads no
    /// lock. When a few tasks are in flight already, it yields on (at most
    /// [`ACCUMULATE`]) while fewer than [`MIN_BATCH`] are: in a burst, taking the lock for
    /// every task or two would bounce it, and the queue's buffer, between the producer's
    /// core and this one. With timers waiting it does neither and goes back to them.
    fn linger(&self) {
        // With timers waiting, `take` sleeps until the earliest: no spinning or yielding
        // (a yield can hand the core to another thread for a whole time slice).
        if self.timers_waiting.load(Ordering::Relaxed) > 0 {
            return;
        }
        let backoff = Backoff::new();
        let mut first_seen: Option<Instant> = None;
        for _ in 0..SPINS {
            let depth = self.acct.gate.depth();
            if depth == 0 {
                backoff.spin();
                continue;
            }
            if depth >= MIN_BATCH
                || first_seen.get_or_insert_with(Instant::now).elapsed() >= ACCUMULATE
            {
                return;
            }
            // Yield rather than spin: a producer on this core gets to queue more.
            std::thread::yield_now();
        }
        for _ in 0..YIELDS {
            if self.acct.gate.depth() > 0 {
                return;
            }
            std::thread::yield_now();
        }
    }
}

impl SwapQueue {
    /// Starts the workers, named as AimRT names them (`name`, or `name.i` for several);
    /// as AimRT's, they run tasks before `start`.
    pub(crate) fn new(spec: SwapSpec<'_>, factory: ThreadFactory) -> Result<SwapQueue, Error> {
        let shared = Arc::new(Shared {
            type_name: spec.type_name,
            label: spec.label,
            name: spec.name.to_owned(),
            threads: spec.threads,
            admission: spec.admission,
            acct: Accounting::new(spec.threads),
            clock: spec.clock,
            late: spec.timers.map(|t| t.alarm()),
            timers_waiting: AtomicUsize::new(0),
            state: Mutex::new(State {
                queue: VecDeque::new(),
                timers: BinaryHeap::new(),
                seq: 0,
                idle: 0,
                waking: 0,
                leader: None,
                stop: false,
            }),
            ready: Condvar::new(),
            lead: Condvar::new(),
        });
        let queue = SwapQueue {
            shared: shared.clone(),
            handles: Mutex::new(Vec::with_capacity(spec.threads)),
            started: AtomicBool::new(false),
        };
        for i in 0..spec.threads {
            let worker = shared.clone();
            let thread = worker_name(spec.name, i, spec.threads);
            let settings = ThreadSettingsRef {
                name: &thread,
                sched_policy: spec.sched_policy,
                bind_cpu: spec.bind_cpu,
                strict: spec.strict,
            };
            match factory.spawn(settings, move || worker.serve(i)) {
                Ok(h) => queue.lock_handles().push(h),
                Err(e) => {
                    queue.shutdown();
                    return Err(e);
                }
            }
        }
        Ok(queue)
    }

    fn lock_handles(&self) -> MutexGuard<'_, Vec<JoinHandle<()>>> {
        self.handles.lock().unwrap_or_else(|e| e.into_inner())
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
        self.shared.threads == 1
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
        s.push(s.admit(task)?);
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
        if due <= Instant::now() {
            s.push(task);
            return Ok(());
        }
        let mut st = s.lock();
        st.seq += 1;
        let seq = st.seq;
        st.timers.push(Entry { due, seq, task });
        s.timers_waiting.fetch_add(1, Ordering::Relaxed);
        // The leader is woken only if it sleeps past this deadline; with no leader, an
        // idle worker becomes one.
        let (lead, ready) = match st.leader {
            Some(until) => (due < until, false),
            None => (false, st.idle > 0),
        };
        drop(st);
        if lead {
            s.lead.notify_one();
        } else if ready {
            s.ready.notify_one();
        }
        Ok(())
    }

    /// The workers already run; `start` only checks the state: once, never after
    /// shutdown.
    fn start(&self) -> Result<(), Error> {
        let s = &self.shared;
        s.acct.start_once(&self.started, s.label, &s.name)
    }

    fn stats(&self) -> ExecutorStats {
        self.shared.acct.stats()
    }

    /// Stops taking work, runs what was accepted (timers due later are dropped and
    /// counted) and joins the workers. Idempotent; from a task of this executor it does
    /// not wait for its own thread.
    fn shutdown(&self) {
        let s = &self.shared;
        if !s.acct.gate.is_closed() {
            let emptied = s.acct.gate.close();
            if emptied | s.settle_timers() {
                s.stop();
            }
        }
        let handles = std::mem::take(&mut *self.lock_handles());
        let me = std::thread::current().id();
        for h in handles {
            if h.thread().id() != me {
                let _ = h.join();
            }
        }
        // The runtime keeps a shut-down executor for the process's life: give back what
        // its queues grew to (what is still queued, when called from a task, stays).
        let mut state = s.lock();
        state.queue.shrink_to_fit();
        state.timers.shrink_to_fit();
    }
}
