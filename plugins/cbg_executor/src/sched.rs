//! The scheduler behind a pool: callback groups, each with its own FIFO, served by one set
//! of threads in arrival order.
//!
//! Every accepted task gets an arrival number. A group is *runnable* when it has queued
//! work and may start it now: a reentrant group always, a mutually exclusive group only
//! while none of its tasks runs. Runnable groups are kept ordered by the arrival number of
//! their oldest task, and a free thread always starts the oldest runnable task. So tasks
//! start in arrival order across all groups, except that a task of an exclusive group
//! whose previous task still runs is passed over — it waits for its own group only, never
//! holding up the tasks behind it.
//!
//! A timed task joins its group's queue when its time comes (its arrival is that moment).
//! The threads sleep until the earliest one; no extra timer thread is needed.

use std::cell::Cell;
use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use aimrt_plugin_api::{
    Error, ExecuteError, ExecutorStats, RateLimit, Task, TaskOutcome, ThreadFactory,
    ThreadSettingsRef,
};

/// A group's index in its scheduler.
pub(crate) type GroupId = usize;

/// What a panicking callback does to the process (seed 001's exception handler).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OnPanic {
    /// Log it (with the group's name), count it, and go on.
    Log,
    /// Log it, then abort the process.
    Abort,
}

/// One group's identity and counters (shared by its handle and the scheduler).
#[derive(Debug)]
pub(crate) struct GroupCore {
    pub(crate) name: String,
    /// Mutually exclusive: never two of its tasks at once.
    pub(crate) exclusive: bool,
    submitted: AtomicU64,
    run: AtomicU64,
    refused: AtomicU64,
    panicked: AtomicU64,
    dropped: AtomicU64,
    alarm: RateLimit,
}

impl GroupCore {
    pub(crate) fn new(name: &str, exclusive: bool) -> Arc<GroupCore> {
        Arc::new(GroupCore {
            name: name.to_owned(),
            exclusive,
            submitted: AtomicU64::new(0),
            run: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            panicked: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            alarm: RateLimit::from_millis(1000),
        })
    }

    /// Drops a refused task, counts it and warns at most once a second.
    pub(crate) fn refuse(&self, type_name: &str, task: Task, err: ExecuteError) -> ExecuteError {
        drop(task);
        let n = self.refused.fetch_add(1, Ordering::Relaxed) + 1;
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(target: "aimrt", "{type_name} executor '{}': task refused: {err} ({} refused since the last report, {n} so far)", self.name, held + 1);
        }
        err
    }
}

/// A task waiting for its time.
struct Timed {
    at: Instant,
    seq: u64,
    gid: GroupId,
    task: Task,
}

impl PartialEq for Timed {
    fn eq(&self, other: &Self) -> bool {
        (self.at, self.seq) == (other.at, other.seq)
    }
}
impl Eq for Timed {}
impl PartialOrd for Timed {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Timed {
    /// Reversed, so that the `BinaryHeap` (a max-heap) yields the earliest first.
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (other.at, other.seq).cmp(&(self.at, self.seq))
    }
}

struct Slot {
    core: Arc<GroupCore>,
    queue: VecDeque<(u64, Task)>,
    running: usize,
    closed: bool,
}

impl Slot {
    /// The arrival number of the task this group could start now, if any.
    fn startable(&self) -> Option<u64> {
        if self.core.exclusive && self.running > 0 {
            return None;
        }
        self.queue.front().map(|(seq, _)| *seq)
    }
}

struct State {
    next_seq: u64,
    /// Runnable groups by the arrival number of their oldest task (each at most once; a
    /// heap in a reused `Vec`, so no allocation per task).
    runnable: BinaryHeap<Reverse<(u64, GroupId)>>,
    slots: Vec<Slot>,
    timers: BinaryHeap<Timed>,
    accepting: bool,
    stop: bool,
    /// Threads waiting for work: a wake-up is a system call, so it is made only for them.
    sleeping: usize,
}

impl State {
    fn push(&mut self, gid: GroupId, task: Task) {
        let seq = self.next_seq;
        self.next_seq += 1;
        let slot = &mut self.slots[gid];
        slot.queue.push_back((seq, task));
        // Newly non-empty and allowed to start: it becomes runnable with this task.
        if slot.queue.len() == 1 && slot.startable().is_some() {
            self.runnable.push(Reverse((seq, gid)));
        }
    }

    /// Moves every timed task whose time has come into its group's queue.
    fn release_due(&mut self, now: Instant) {
        while self.timers.peek().is_some_and(|t| t.at <= now) {
            let Some(t) = self.timers.pop() else { break };
            if self.slots[t.gid].closed || !self.accepting {
                self.slots[t.gid]
                    .core
                    .dropped
                    .fetch_add(1, Ordering::Relaxed);
                continue;
            }
            self.push(t.gid, t.task);
        }
    }

    /// Takes the oldest startable task.
    fn take(&mut self) -> Option<(GroupId, Arc<GroupCore>, Task)> {
        let Reverse((_, gid)) = self.runnable.pop()?;
        let slot = &mut self.slots[gid];
        let (_, task) = slot.queue.pop_front()?;
        slot.running += 1;
        let core = slot.core.clone();
        if let Some(seq) = slot.startable() {
            self.runnable.push(Reverse((seq, gid)));
        }
        Some((gid, core, task))
    }

    /// A task of `gid` finished; an exclusive group may start its next one.
    fn finish(&mut self, gid: GroupId) {
        let slot = &mut self.slots[gid];
        slot.running -= 1;
        if slot.core.exclusive {
            if let Some(seq) = slot.startable() {
                self.runnable.push(Reverse((seq, gid)));
            }
        }
    }

    fn idle(&self, gid: GroupId) -> bool {
        let slot = &self.slots[gid];
        slot.queue.is_empty() && slot.running == 0
    }
}

thread_local! {
    /// The (scheduler, group) whose task runs on this thread now.
    static CURRENT: Cell<(usize, GroupId)> = const { Cell::new((0, usize::MAX)) };
}

/// Settings of the scheduler's threads.
#[derive(Debug, Clone, Default)]
pub(crate) struct ThreadSpec {
    pub(crate) count: usize,
    pub(crate) sched_policy: String,
    pub(crate) bind_cpu: Vec<u32>,
    pub(crate) strict: bool,
}

/// A pool of threads serving callback groups; group 0 is the pool's own (reentrant).
pub(crate) struct Scheduler {
    name: String,
    type_name: &'static str,
    on_panic: OnPanic,
    spec: ThreadSpec,
    state: Mutex<State>,
    work: Condvar,
    idle: Condvar,
    threads: Mutex<Vec<JoinHandle<()>>>,
    anchor: (SystemTime, Instant),
}

impl std::fmt::Debug for Scheduler {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scheduler")
            .field("name", &self.name)
            .field("threads", &self.spec.count)
            .finish_non_exhaustive()
    }
}

impl Scheduler {
    /// A scheduler whose group 0 is `own`; threads start with [`Scheduler::start`].
    pub(crate) fn new(
        name: &str,
        type_name: &'static str,
        spec: ThreadSpec,
        on_panic: OnPanic,
        own: Arc<GroupCore>,
    ) -> Arc<Scheduler> {
        Arc::new(Scheduler {
            name: name.to_owned(),
            type_name,
            on_panic,
            spec,
            state: Mutex::new(State {
                next_seq: 0,
                runnable: BinaryHeap::new(),
                slots: vec![Slot {
                    core: own,
                    queue: VecDeque::new(),
                    running: 0,
                    closed: false,
                }],
                timers: BinaryHeap::new(),
                accepting: true,
                stop: false,
                sleeping: 0,
            }),
            work: Condvar::new(),
            idle: Condvar::new(),
            threads: Mutex::new(Vec::new()),
            anchor: (SystemTime::now(), Instant::now()),
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(crate) fn on_panic(&self) -> OnPanic {
        self.on_panic
    }

    pub(crate) fn thread_count(&self) -> usize {
        self.spec.count
    }

    /// Adds a group served by these threads.
    pub(crate) fn add_group(&self, core: Arc<GroupCore>) -> GroupId {
        let mut st = self.lock();
        st.slots.push(Slot {
            core,
            queue: VecDeque::new(),
            running: 0,
            closed: false,
        });
        st.slots.len() - 1
    }

    /// Starts the threads (`<name>` for one, `<name>.<i>` for several).
    pub(crate) fn start(self: &Arc<Self>, factory: ThreadFactory) -> Result<(), Error> {
        let mut threads = self.threads.lock().unwrap_or_else(|e| e.into_inner());
        if !threads.is_empty() {
            return Ok(());
        }
        for i in 0..self.spec.count {
            let name = if self.spec.count == 1 {
                self.name.clone()
            } else {
                format!("{}.{i}", self.name)
            };
            let me = self.clone();
            let settings = ThreadSettingsRef {
                name: &name,
                sched_policy: &self.spec.sched_policy,
                bind_cpu: &self.spec.bind_cpu,
                strict: self.spec.strict,
            };
            threads.push(factory.spawn(settings, move || me.work_loop())?);
        }
        Ok(())
    }

    /// The clock: the system time at creation plus monotonic time since (never jumps).
    pub(crate) fn now(&self) -> SystemTime {
        self.anchor.0 + self.anchor.1.elapsed()
    }

    fn instant_of(&self, at: SystemTime) -> Instant {
        let (sys, mono) = self.anchor;
        match at.duration_since(sys) {
            Ok(ahead) => mono
                .checked_add(ahead)
                .unwrap_or_else(|| Instant::now() + Duration::from_secs(1 << 32)),
            Err(behind) => mono.checked_sub(behind.duration()).unwrap_or(mono),
        }
    }

    /// Queues `task` on group `gid`.
    pub(crate) fn submit(&self, gid: GroupId, task: Task) -> Result<(), ExecuteError> {
        self.accept(gid, task, State::push)
    }

    /// Queues `task` on group `gid` once the clock reads `at`.
    pub(crate) fn submit_at(
        &self,
        gid: GroupId,
        at: SystemTime,
        task: Task,
    ) -> Result<(), ExecuteError> {
        let at = self.instant_of(at);
        // A sleeping thread woken by `accept` re-reads the earliest deadline.
        self.accept(gid, task, |st, gid, task| {
            let seq = st.next_seq;
            st.next_seq += 1;
            st.timers.push(Timed { at, seq, gid, task });
        })
    }

    /// Refuses `task` if the group or the scheduler is shut down; else `place`s it,
    /// counts it and wakes a sleeping thread.
    fn accept(
        &self,
        gid: GroupId,
        task: Task,
        place: impl FnOnce(&mut State, GroupId, Task),
    ) -> Result<(), ExecuteError> {
        let mut st = self.lock();
        let core = st.slots[gid].core.clone();
        if !st.accepting || st.slots[gid].closed {
            drop(st);
            return Err(core.refuse(self.type_name, task, ExecuteError::ShutDown));
        }
        place(&mut st, gid, task);
        let wake = st.sleeping > 0;
        drop(st);
        core.submitted.fetch_add(1, Ordering::Relaxed);
        if wake {
            self.work.notify_one();
        }
        Ok(())
    }

    /// Whether the calling thread runs a task of group `gid` now.
    pub(crate) fn in_group(&self, gid: GroupId) -> bool {
        CURRENT.with(|c| c.get() == (self as *const Self as usize, gid))
    }

    /// Runs one task of group `gid` as that group (counted; `on_panic` applied).
    fn run_task(&self, gid: GroupId, core: &GroupCore, task: Task) {
        let prev = CURRENT.with(|c| c.replace((self as *const Self as usize, gid)));
        let outcome = task.run(&core.name);
        CURRENT.with(|c| c.set(prev));
        core.run.fetch_add(1, Ordering::Relaxed);
        if outcome == TaskOutcome::Panicked {
            core.panicked.fetch_add(1, Ordering::Relaxed);
            if self.on_panic == OnPanic::Abort {
                tracing::error!(target: "aimrt", "{} executor '{}': a callback panicked and on_panic is 'abort'; aborting the process", self.type_name, core.name);
                std::process::abort();
            }
        }
    }

    fn work_loop(&self) {
        let mut st = self.lock();
        loop {
            if !st.timers.is_empty() {
                st.release_due(Instant::now());
            }
            if let Some((gid, core, task)) = st.take() {
                if !st.runnable.is_empty() && st.sleeping > 0 {
                    // More is startable: let a sleeping thread take it.
                    self.work.notify_one();
                }
                drop(st);
                self.run_task(gid, &core, task);
                st = self.lock();
                st.finish(gid);
                if st.idle(gid) {
                    self.idle.notify_all();
                }
                continue;
            }
            if st.stop {
                break;
            }
            st.sleeping += 1;
            st = match st.timers.peek().map(|t| t.at) {
                Some(at) => {
                    let wait = at.saturating_duration_since(Instant::now());
                    self.work
                        .wait_timeout(st, wait)
                        .unwrap_or_else(|e| e.into_inner())
                        .0
                }
                None => self.work.wait(st).unwrap_or_else(|e| e.into_inner()),
            };
            st.sleeping -= 1;
        }
    }

    /// Runs every queued task on the calling thread (when no thread serves the queues).
    fn drain_here(&self) {
        loop {
            let next = self.lock().take();
            let Some((gid, core, task)) = next else { break };
            self.run_task(gid, &core, task);
            self.lock().finish(gid);
        }
    }

    /// Stops group `gid` taking work, drops its timed tasks and waits until what it has
    /// queued has run (on the calling thread if the scheduler no longer runs).
    pub(crate) fn close_group(&self, gid: GroupId) {
        let mut st = self.lock();
        if st.slots[gid].closed {
            return;
        }
        st.slots[gid].closed = true;
        let before = st.timers.len();
        st.timers.retain(|t| t.gid != gid);
        let dropped = (before - st.timers.len()) as u64;
        st.slots[gid]
            .core
            .dropped
            .fetch_add(dropped, Ordering::Relaxed);
        let served = !st.stop && !self.threads_empty();
        if !served {
            drop(st);
            self.drain_here();
            return;
        }
        // A task of this group closing its own group cannot wait for itself.
        let own = self.in_group(gid);
        while !own && !st.idle(gid) {
            st = self.idle.wait(st).unwrap_or_else(|e| e.into_inner());
        }
    }

    fn threads_empty(&self) -> bool {
        self.threads
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .is_empty()
    }

    /// Stops taking work, drops timed tasks whose time has not come, lets the threads run
    /// what is queued and joins them. Idempotent; from one of its own threads it does not
    /// join that thread.
    pub(crate) fn shutdown(&self) {
        {
            let mut st = self.lock();
            st.accepting = false;
            st.stop = true;
            for t in std::mem::take(&mut st.timers).into_vec() {
                st.slots[t.gid].core.dropped.fetch_add(1, Ordering::Relaxed);
            }
            for slot in &mut st.slots {
                slot.closed = true;
            }
        }
        self.work.notify_all();
        let me = std::thread::current().id();
        let threads = std::mem::take(&mut *self.threads.lock().unwrap_or_else(|e| e.into_inner()));
        for handle in threads {
            if handle.thread().id() != me {
                let _ = handle.join();
            }
        }
        self.drain_here();
        self.idle.notify_all();
    }

    /// Group `gid`'s counters.
    pub(crate) fn stats(&self, gid: GroupId) -> ExecutorStats {
        let (core, depth) = {
            let st = self.lock();
            let slot = &st.slots[gid];
            let timed = st.timers.iter().filter(|t| t.gid == gid).count();
            (
                slot.core.clone(),
                (slot.queue.len() + slot.running + timed) as u64,
            )
        };
        ExecutorStats {
            submitted: core.submitted.load(Ordering::Relaxed),
            run: core.run.load(Ordering::Relaxed),
            refused: core.refused.load(Ordering::Relaxed),
            panicked: core.panicked.load(Ordering::Relaxed),
            queue_depth: depth,
            dropped_at_shutdown: core.dropped.load(Ordering::Relaxed),
            ..ExecutorStats::default()
        }
    }
}
