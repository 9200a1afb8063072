//! The engine of `tbb_thread` and `asio_thread` with two or more workers: `n` threads fed
//! by one lock-free crossbeam channel, an optional in-flight limit, and optional timers.
//!
//! # Protocol
//!
//! * **Submitting**: [`Gate::enter`] counts the task (or refuses it: shut down, or
//!   `queue_threshold` tasks already in flight), then the task goes into the channel.
//! * **Running**: a worker takes a message, runs the task, records it in its own counters
//!   and [`Gate::leave`]s. Tasks leave the channel in FIFO order; with one worker that is
//!   also the running order.
//! * **Timers** (`asio_thread`): a min-heap of deadlines under a mutex. At most one idle
//!   worker is the *leader*: it waits on the channel with the earliest deadline as its
//!   timeout, so a timer wakes one thread, not a timer thread plus a worker. A new earlier
//!   deadline kicks the leader through a one-slot side channel; a new deadline with no
//!   leader sends a `Wake` message that any idle worker takes and becomes leader. A leader
//!   that gets a task, and a worker that pops a due timer while more wait, hands leadership
//!   on (another `Wake`) before running it, so an idle worker always watches the next
//!   deadline while one is idle. Every worker
//!   checks for due timers before it blocks, so a due timer never waits for an idle pool.
//! * **Shutdown**: [`Gate::close`] refuses new work; timers already due are queued, timers
//!   due later are dropped and counted; the call that leaves the gate closed and empty sends
//!   one `Stop` per worker. Everything accepted before the close therefore runs, and no
//!   task can slip in after the workers exit (AimRT's `simple_thread` race).

use std::cmp::Ordering as CmpOrdering;
use std::collections::BinaryHeap;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorStats, Task, TaskOutcome, ThreadFactory,
    ThreadSettingsRef,
};
use crossbeam_channel::{Receiver, Select, Sender};

use crate::common::{worker_name, Accounting, Admission, Clock, LateAlarm, Marker};

enum Msg {
    Task(Task),
    /// Someone should look at the timers.
    Wake,
    /// Exit (sent only when nothing accepted is left).
    Stop,
}

/// How a pool is built.
#[derive(Debug)]
pub(crate) struct PoolSpec<'a> {
    /// `simple_thread`, `tbb_thread` or `asio_thread`.
    pub(crate) type_name: &'static str,
    /// Words for log lines: "simple thread", "tbb thread", "asio thread".
    pub(crate) label: &'static str,
    pub(crate) name: &'a str,
    pub(crate) threads: usize,
    /// In-flight limit (`queue_threshold`); `None`: unbounded.
    pub(crate) limit: Option<u64>,
    /// `threshold_alarm_interval_ms` (negative: silent).
    pub(crate) queue_alarm_ms: i32,
    /// `Some` for a timer-capable pool.
    pub(crate) timers: Option<TimerSpec>,
    pub(crate) clock: Clock,
    pub(crate) sched_policy: &'a str,
    pub(crate) bind_cpu: &'a [u32],
    pub(crate) strict: bool,
}

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

/// The most tasks a worker runs before it settles them with the gate and looks at the
/// timers again.
const BATCH: u64 = 64;

#[derive(Default)]
struct TimerState {
    heap: BinaryHeap<Entry>,
    seq: u64,
    /// The deadline the leader sleeps until, if there is a leader.
    leader: Option<Instant>,
    /// A `Wake` is in the channel and nobody has looked at the timers since.
    wake_sent: bool,
}

struct Timers {
    late: LateAlarm,
    state: Mutex<TimerState>,
    /// Timers in the heap; read without the lock to skip it when there are none.
    pending: AtomicUsize,
    kick_tx: Sender<()>,
    kick_rx: Receiver<()>,
}

impl Timers {
    fn lock(&self) -> std::sync::MutexGuard<'_, TimerState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

struct Shared {
    type_name: &'static str,
    label: &'static str,
    name: String,
    threads: usize,
    admission: Admission,
    tx: Sender<Msg>,
    rx: Receiver<Msg>,
    acct: Accounting,
    clock: Clock,
    timers: Option<Timers>,
}

/// A pool of workers; see the module doc for the protocol.
pub(crate) struct Pool {
    shared: Arc<Shared>,
    handles: Mutex<Vec<JoinHandle<()>>>,
    started: AtomicBool,
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pool")
            .field("type", &self.shared.type_name)
            .field("name", &self.shared.name)
            .field("threads", &self.shared.threads)
            .finish()
    }
}

impl Pool {
    /// Starts the workers (as AimRT does at Initialize: tasks run before `start`).
    pub(crate) fn new(spec: PoolSpec<'_>, factory: ThreadFactory) -> Result<Pool, Error> {
        let (tx, rx) = crossbeam_channel::unbounded();
        let timers = spec.timers.map(|t| {
            let (kick_tx, kick_rx) = crossbeam_channel::bounded(1);
            Timers {
                late: t.alarm(),
                state: Mutex::new(TimerState::default()),
                pending: AtomicUsize::new(0),
                kick_tx,
                kick_rx,
            }
        });
        let shared = Arc::new(Shared {
            type_name: spec.type_name,
            label: spec.label,
            name: spec.name.to_owned(),
            threads: spec.threads,
            admission: Admission::new(spec.limit, spec.queue_alarm_ms),
            tx,
            rx,
            acct: Accounting::new(spec.threads),
            clock: spec.clock,
            timers,
        });
        let pool = Pool {
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
                Ok(h) => pool.lock_handles().push(h),
                Err(e) => {
                    pool.shutdown();
                    return Err(e);
                }
            }
        }
        Ok(pool)
    }

    fn lock_handles(&self) -> std::sync::MutexGuard<'_, Vec<JoinHandle<()>>> {
        self.handles.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Executor for Pool {
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
        self.shared.timers.is_some()
    }

    fn now(&self) -> SystemTime {
        self.shared.clock.now()
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        self.shared.admit(task).map(|task| self.shared.post(task))
    }

    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        let s = &self.shared;
        let Some(timers) = &s.timers else {
            drop(task);
            s.acct.refuse();
            return Err(ExecuteError::NoTimerSupport);
        };
        let task = s.admit(task)?;
        let due = s.clock.instant_of(at);
        if due <= Instant::now() {
            s.post(task);
            return Ok(());
        }
        let mut st = timers.lock();
        st.seq += 1;
        let seq = st.seq;
        st.heap.push(Entry { due, seq, task });
        timers.pending.fetch_add(1, Ordering::Release);
        match st.leader {
            Some(d) if due < d => {
                drop(st);
                let _ = timers.kick_tx.try_send(());
            }
            Some(_) => {}
            None if st.wake_sent => {}
            None => {
                st.wake_sent = true;
                drop(st);
                let _ = s.tx.send(Msg::Wake);
            }
        }
        Ok(())
    }

    /// Workers already run (AimRT starts them at Initialize); `start` only checks the state:
    /// once, and never after shutdown.
    fn start(&self) -> Result<(), Error> {
        let s = &self.shared;
        s.acct.start_once(&self.started, s.label, &s.name)
    }

    fn stats(&self) -> ExecutorStats {
        self.shared.acct.stats()
    }

    /// Stops taking work, runs what was accepted (timers due later are dropped and
    /// counted) and joins the workers. Idempotent; from a worker of this pool it does not
    /// wait for that worker.
    fn shutdown(&self) {
        let s = &self.shared;
        if !s.acct.gate.is_closed() {
            let mut emptied = s.acct.gate.close();
            if let Some(timers) = &s.timers {
                let entries = {
                    let mut st = timers.lock();
                    timers.pending.store(0, Ordering::Release);
                    std::mem::take(&mut st.heap)
                };
                let now = Instant::now();
                let mut dropped = 0u64;
                for e in entries {
                    if e.due <= now {
                        let _ = s.tx.send(Msg::Task(e.task));
                    } else {
                        drop(e.task);
                        s.acct.drop_at_shutdown();
                        dropped += 1;
                        emptied |= s.acct.gate.leave();
                    }
                }
                if dropped > 0 {
                    tracing::info!(target: "aimrt", "{} executor '{}' shut down with {dropped} timed task(s) not yet due (a cancelled timer leaves one); they were dropped without running", s.label, s.name);
                }
            }
            if emptied {
                s.stop_all();
            }
        }
        let handles = std::mem::take(&mut *self.lock_handles());
        let me = std::thread::current().id();
        for h in handles {
            if h.thread().id() != me {
                let _ = h.join();
            }
        }
    }
}

impl Shared {
    fn id(&self) -> usize {
        self as *const Shared as usize
    }

    /// Counts the task in, or refuses it (counted, rate-limited warning, task dropped).
    fn admit(&self, task: Task) -> Result<Task, ExecuteError> {
        self.acct
            .admit(task, &self.admission, self.label, &self.name)
            .map_err(|(err, emptied)| {
                if emptied {
                    self.stop_all();
                }
                err
            })
    }

    fn post(&self, task: Task) {
        // The channel lives as long as `self`: sending cannot fail.
        let _ = self.tx.send(Msg::Task(task));
    }

    fn stop_all(&self) {
        for _ in 0..self.threads {
            let _ = self.tx.send(Msg::Stop);
        }
    }

    fn run(&self, worker: usize, task: Task) {
        self.acct.worker(worker).record(task.run(&self.name));
        if self.acct.gate.leave() {
            self.stop_all();
        }
    }

    fn run_timer(&self, worker: usize, timers: &Timers, e: Entry) {
        timers.late.check(self.label, &self.name, e.due);
        self.run(worker, e.task);
    }

    /// A worker's loop.
    fn serve(&self, worker: usize) {
        let _mark = Marker::Worker.set(self.id());
        if self.timers.is_some() {
            crate::common::precise_timed_waits();
        }
        loop {
            let mut lead = None;
            if let Some(timers) = &self.timers {
                if timers.pending.load(Ordering::Acquire) > 0 {
                    let mut st = timers.lock();
                    st.wake_sent = false;
                    if st.heap.peek().is_some_and(|e| e.due <= Instant::now()) {
                        let entry = st.heap.pop();
                        timers.pending.fetch_sub(1, Ordering::Release);
                        // This worker is busy with the timer from now on: if more timers
                        // wait and nobody leads, an idle worker must take the lead, or the
                        // next timer would wait for this one to finish.
                        let hand_over = self.threads > 1
                            && !st.heap.is_empty()
                            && st.leader.is_none()
                            && !st.wake_sent;
                        if hand_over {
                            st.wake_sent = true;
                        }
                        drop(st);
                        if hand_over {
                            let _ = self.tx.send(Msg::Wake);
                        }
                        if let Some(e) = entry {
                            self.run_timer(worker, timers, e);
                        }
                        continue;
                    }
                    if st.leader.is_none() {
                        if let Some(due) = st.heap.peek().map(|e| e.due) {
                            st.leader = Some(due);
                            lead = Some((timers, due));
                        }
                    }
                }
            }
            let msg = match lead {
                None => self.rx.recv(),
                Some((timers, due)) => match self.lead(timers, due) {
                    Some(msg) => msg,
                    None => continue,
                },
            };
            match msg {
                Ok(Msg::Task(task)) => {
                    if !self.run_batch(worker, task) {
                        break;
                    }
                }
                Ok(Msg::Wake) => {}
                Ok(Msg::Stop) | Err(_) => break,
            }
        }
    }

    /// Runs `first` and then, without blocking and while no timer waits, up to [`BATCH`]
    /// tasks in all, and counts them out of the gate at once (one shared-counter update
    /// per batch, not per task). Returns `false` if a `Stop` came (the batch is counted
    /// out first).
    fn run_batch(&self, worker: usize, first: Task) -> bool {
        let counters = self.acct.worker(worker);
        let (mut run, mut panicked) = (1u64, 0u64);
        panicked += u64::from(first.run(&self.name) == TaskOutcome::Panicked);
        let mut go_on = true;
        // With timers waiting, go back to them after every task, as before batching.
        let timers_wait = || {
            self.timers
                .as_ref()
                .is_some_and(|t| t.pending.load(Ordering::Acquire) > 0)
        };
        while run < BATCH && !timers_wait() {
            match self.rx.try_recv() {
                Ok(Msg::Task(task)) => {
                    run += 1;
                    panicked += u64::from(task.run(&self.name) == TaskOutcome::Panicked);
                }
                // A wake-up is about timers: end the batch so that they are looked at.
                Ok(Msg::Wake) => break,
                Ok(Msg::Stop) => {
                    go_on = false;
                    break;
                }
                Err(_) => break,
            }
        }
        counters.record_batch(run, panicked);
        if self.acct.gate.leave_n(run) {
            self.stop_all();
        }
        go_on
    }

    /// The leader waits for a message, a kick or the deadline; `None`: look at the timers.
    fn lead(
        &self,
        timers: &Timers,
        due: Instant,
    ) -> Option<Result<Msg, crossbeam_channel::RecvError>> {
        let mut sel = Select::new();
        let on_msg = sel.recv(&self.rx);
        sel.recv(&timers.kick_rx);
        let got = match sel.select_deadline(due) {
            Ok(op) if op.index() == on_msg => Some(op.recv(&self.rx)),
            Ok(op) => {
                let _ = op.recv(&timers.kick_rx);
                None
            }
            Err(_) => None,
        };
        let mut st = timers.lock();
        st.leader = None;
        let hand_over = matches!(got, Some(Ok(Msg::Task(_))))
            && self.threads > 1
            && !st.heap.is_empty()
            && !st.wake_sent;
        if hand_over {
            st.wake_sent = true;
        }
        drop(st);
        if hand_over {
            let _ = self.tx.send(Msg::Wake);
        }
        got
    }
}
