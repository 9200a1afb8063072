//! `asio_strand`: a serialised executor on the threads of an `asio_thread`.
//!
//! # Protocol
//!
//! Tasks go into a queue under a mutex, beside an `owned` flag. The submitter that finds
//! the strand not owned takes ownership and posts one *drain* task to the bound pool. The
//! drain takes everything queued at once (swapping the queue with its own empty buffer,
//! which it takes from the state's `spare` and leaves there when it stops, so a steady
//! state allocates nothing across drains either), runs it in order outside the lock,
//! counts it out of the gate at once, and comes back for more; when it finds the queue
//! empty it releases ownership under the same lock. Only the owner runs tasks, so no two overlap, and they
//! run in push order. After [`SLICE`] of running the drain re-posts itself, so that a busy
//! strand does not hold one pool thread for ever.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime};

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorArgs, ExecutorRef, ExecutorStats, Task, TaskOutcome,
};
use serde::Deserialize;

use crate::common::{execute_error, options_error, Accounting, Clock, LateAlarm, Marker};

/// How long one drain may hold its pool thread before it re-posts itself.
const SLICE: Duration = Duration::from_micros(500);

/// The options of AimRT's `asio_strand`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct AsioStrandOptions {
    #[serde(default)]
    bind_asio_thread_executor_name: String,
    #[serde(default = "crate::default_timeout_alarm_threshold_us")]
    timeout_alarm_threshold_us: u64,
    #[serde(default = "crate::default_alarm_interval")]
    timeout_alarm_interval_ms: i32,
    #[serde(default)]
    use_system_clock: bool,
}

struct Inner {
    name: String,
    bound: ExecutorRef,
    clock: Clock,
    late: LateAlarm,
    queue: Mutex<Queue>,
    acct: Accounting,
    idle: Mutex<()>,
    idle_cv: Condvar,
}

/// The state under the strand's lock.
#[derive(Default)]
struct Queue {
    tasks: VecDeque<Task>,
    /// Whether a drain owns the strand.
    owned: bool,
    /// The drains' swap buffer, kept with its capacity between drains.
    spare: VecDeque<Task>,
}

/// A strand over an `asio_thread`.
pub(crate) struct Strand {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Strand {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Strand")
            .field("name", &self.inner.name)
            .field("bound", &self.inner.bound.name())
            .finish()
    }
}

/// Builds an `asio_strand`; `args.bound[0]` is `bind_asio_thread_executor_name`.
pub(crate) fn create(args: ExecutorArgs<'_>) -> Result<Arc<Strand>, Error> {
    let o: AsioStrandOptions = args.read_options()?;
    let Some(bound) = args.bound.first().copied().flatten() else {
        return Err(options_error(
            &args,
            format!(
            "bind_asio_thread_executor_name is required (got '{}'): the name of an asio_thread executor",
            o.bind_asio_thread_executor_name
        )));
    };
    if bound.type_name() != "asio_thread" {
        return Err(options_error(
            &args,
            format!(
            "bind_asio_thread_executor_name names '{}', which is a {}; a strand needs an asio_thread",
            bound.name(),
            bound.type_name()
        )));
    }
    Ok(Arc::new(Strand {
        inner: Arc::new(Inner {
            name: args.name.to_owned(),
            bound,
            clock: Clock::new(o.use_system_clock),
            late: LateAlarm::new(
                Duration::from_micros(o.timeout_alarm_threshold_us),
                o.timeout_alarm_interval_ms,
            ),
            queue: Mutex::new(Queue::default()),
            acct: Accounting::new(1),
            idle: Mutex::new(()),
            idle_cv: Condvar::new(),
        }),
    }))
}

impl Inner {
    fn id(&self) -> usize {
        self as *const Inner as usize
    }

    fn refuse(&self, task: Task, err: ExecuteError) -> ExecuteError {
        self.acct
            .refuse_task(Some(task), err, "asio strand", &self.name, &"task refused")
    }

    fn lock(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues an admitted task; the submitter that finds the strand idle starts a drain.
    fn enqueue(self: &Arc<Self>, task: Task) {
        if self.push(task) {
            self.post_drain();
        }
    }

    /// Queues an admitted task; `true`: the strand was idle and the caller now owns it
    /// (it must drain, here or on the pool).
    fn push(&self, task: Task) -> bool {
        let mut q = self.lock();
        q.tasks.push_back(task);
        !std::mem::replace(&mut q.owned, true)
    }

    fn post_drain(self: &Arc<Self>) {
        let me = self.clone();
        if let Err(e) = self.bound.execute(move || me.drain()) {
            // The pool is gone: nothing will run the queue. Drop it, counted and logged.
            let dropped = {
                let mut q = self.lock();
                q.owned = false;
                std::mem::take(&mut q.tasks)
            };
            let n = dropped.len() as u64;
            drop(dropped);
            for _ in 0..n {
                self.acct.drop_at_shutdown();
            }
            self.finish(n);
            tracing::warn!(target: "aimrt", "asio strand executor '{}': its asio_thread '{}' refused work ({e}); {n} queued task(s) dropped", self.name, self.bound.name());
        }
    }

    /// `n` tasks left the strand; the one that empties a closed gate wakes `shutdown`.
    fn finish(&self, n: u64) {
        if self.acct.gate.leave_n(n) {
            let _guard = self.idle.lock().unwrap_or_else(|e| e.into_inner());
            self.idle_cv.notify_all();
        }
    }

    /// Runs queued tasks while this drain owns the strand.
    fn drain(self: &Arc<Self>) {
        let _mark = Marker::Strand.set(self.id());
        let mut since = Instant::now();
        let mut batch = std::mem::take(&mut self.lock().spare);
        loop {
            {
                let mut q = self.lock();
                if q.tasks.is_empty() {
                    q.owned = false;
                    q.spare = batch;
                    return;
                }
                std::mem::swap(&mut q.tasks, &mut batch);
            }
            let n = batch.len() as u64;
            let mut panicked = 0u64;
            for task in batch.drain(..) {
                panicked += u64::from(task.run(&self.name) == TaskOutcome::Panicked);
            }
            self.acct.worker(0).record_batch(n, panicked);
            self.finish(n);
            if since.elapsed() >= SLICE {
                // The next drain takes the buffer back (this one still owns the strand).
                self.lock().spare = std::mem::take(&mut batch);
                let me = self.clone();
                if self.bound.execute(move || me.drain()).is_ok() {
                    return;
                }
                // The pool no longer takes work: keep draining on this thread.
                since = Instant::now();
            }
        }
    }
}

impl Executor for Strand {
    fn type_name(&self) -> &str {
        "asio_strand"
    }

    fn name(&self) -> &str {
        &self.inner.name
    }

    fn thread_safe(&self) -> bool {
        true
    }

    /// True inside this strand's tasks (AimRT always answers false).
    fn is_in_current_executor(&self) -> bool {
        Marker::Strand.is(self.inner.id())
    }

    fn supports_timer_schedule(&self) -> bool {
        true
    }

    fn now(&self) -> SystemTime {
        self.inner.clock.now()
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        let inner = &self.inner;
        if let Err(r) = inner.acct.gate.enter(u64::MAX) {
            return Err(inner.refuse(task, r.error()));
        }
        inner.enqueue(task);
        Ok(())
    }

    /// A timer on the bound pool whose handler enters the strand. A timer that comes due
    /// after the strand shut down is dropped and counted.
    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        let inner = &self.inner;
        if inner.acct.gate.is_closed() {
            return Err(inner.refuse(task, ExecuteError::ShutDown));
        }
        let delay = at
            .duration_since(inner.clock.now())
            .unwrap_or(Duration::ZERO);
        let due = Instant::now() + delay;
        let me = inner.clone();
        let on_time = move || {
            me.late.check("asio strand", &me.name, due);
            if me.acct.gate.enter(u64::MAX).is_ok() {
                // On a pool thread already: an idle strand runs here, without a second
                // hop through the pool.
                if me.push(task) {
                    me.drain();
                }
            } else {
                drop(task);
                me.acct.drop_at_shutdown();
            }
        };
        let bound_at = inner.bound.now() + delay;
        inner.bound.execute_at(bound_at, on_time).map_err(|e| {
            let what = format!("timer refused by '{}'", inner.bound.name());
            inner
                .acct
                .refuse_task(None, execute_error(e), "asio strand", &inner.name, &what)
        })
    }

    /// Stops taking work and waits until the queued tasks have run on the pool (not from
    /// inside one of its own tasks, which would wait for itself).
    fn shutdown(&self) {
        let inner = &self.inner;
        if inner.acct.gate.close() || self.is_in_current_executor() {
            return;
        }
        let mut guard = inner.idle.lock().unwrap_or_else(|e| e.into_inner());
        while inner.acct.gate.depth() > 0 {
            guard = inner
                .idle_cv
                .wait_timeout(guard, Duration::from_millis(100))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    fn stats(&self) -> ExecutorStats {
        self.inner.acct.stats()
    }
}
