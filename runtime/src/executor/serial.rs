//! A FIFO queue served by one thread at a time: the `main_thread` executor (served by the
//! thread that runs the runtime) and the `guard_thread` executor (served by its own thread).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Condvar, Mutex};
use std::thread::ThreadId;
use std::time::Instant;

use aimrt_plugin_api::{ExecuteError, Executor, ExecutorStats, RateLimit, Task, TaskOutcome};

/// The executor type of the main thread's queue: served by the thread that runs the
/// runtime, which at shutdown drains it only after the plugins.
pub(crate) const MAIN_THREAD_TYPE: &str = "main_thread";

#[derive(Debug)]
struct State {
    queue: VecDeque<Task>,
    /// Queued plus running (AimRT's guard thread counts the running task against the limit).
    in_flight: u64,
    accepting: bool,
    stop: bool,
    /// The thread serving the queue now (a `spin*` call or the runtime's main loop).
    server: Option<ThreadId>,
    /// `cancel()` was called during the current spin.
    cancel: bool,
}

/// How long one [`SerialQueue::spin`] call serves the queue.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Until {
    /// Stop at this instant: while waiting for work (`wait`), or before starting the next
    /// task (no `wait`).
    pub(crate) deadline: Option<Instant>,
    /// At most this many tasks.
    pub(crate) limit: Limit,
    /// Wait for work when the queue is empty (else return).
    pub(crate) wait: bool,
}

/// How many tasks one spin runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Limit {
    /// No limit.
    None,
    /// One task.
    One,
    /// The tasks queued when the spin began, each once.
    QueuedAtStart,
}

/// A spin was refused: the queue is already being served by `by`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Busy {
    pub(crate) by: Option<ThreadId>,
}

/// A thread-safe, timer-less executor whose queue is served by [`SerialQueue::serve`].
#[derive(Debug)]
pub(crate) struct SerialQueue {
    type_name: &'static str,
    name: String,
    threshold: Option<u64>,
    alarm: RateLimit,
    state: Mutex<State>,
    ready: Condvar,
    submitted: AtomicU64,
    run: AtomicU64,
    refused: AtomicU64,
    panicked: AtomicU64,
}

impl SerialQueue {
    /// A queue; `threshold` limits tasks in flight, and refusals are warned about at most
    /// once per `alarm_interval_ms` (negative: silently, but still refused and counted).
    pub(crate) fn new(
        type_name: &'static str,
        name: &str,
        threshold: Option<u64>,
        alarm_interval_ms: i32,
    ) -> SerialQueue {
        SerialQueue {
            type_name,
            name: name.to_owned(),
            threshold,
            alarm: RateLimit::from_millis(alarm_interval_ms),
            state: Mutex::new(State {
                queue: VecDeque::new(),
                in_flight: 0,
                accepting: true,
                stop: false,
                server: None,
                cancel: false,
            }),
            ready: Condvar::new(),
            submitted: AtomicU64::new(0),
            run: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            panicked: AtomicU64::new(0),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Serves the queue on the calling thread until `request_stop` or `deadline`.
    pub(crate) fn serve(&self, deadline: Option<Instant>) {
        let until = Until {
            deadline,
            limit: Limit::None,
            wait: true,
        };
        // Only this loop serves the runtime's own queues; a refusal cannot happen here.
        let _ = self.spin(until);
    }

    /// Serves the queue on the calling thread as `until` says, or until [`Self::cancel`]
    /// (or, when waiting, `request_stop`). Returns how many tasks ran; refuses if another
    /// spin is running (on any thread, including this one: a task that spins).
    pub(crate) fn spin(&self, until: Until) -> Result<usize, Busy> {
        let mut st = self.lock();
        if st.server.is_some() {
            return Err(Busy { by: st.server });
        }
        st.server = Some(std::thread::current().id());
        st.cancel = false;
        let limit = match until.limit {
            Limit::None => usize::MAX,
            Limit::One => 1,
            Limit::QueuedAtStart => st.queue.len(),
        };
        let mut ran = 0;
        loop {
            if st.cancel || ran >= limit {
                break;
            }
            let late = until.deadline.is_some_and(|d| Instant::now() >= d);
            if late && !until.wait {
                break;
            }
            if let Some(task) = st.queue.pop_front() {
                drop(st);
                self.run_one(task);
                ran += 1;
                st = self.lock();
                continue;
            }
            if !until.wait || st.stop || late {
                break;
            }
            st = match until.deadline {
                Some(d) => {
                    self.ready
                        .wait_timeout(st, d.saturating_duration_since(Instant::now()))
                        .unwrap_or_else(|e| e.into_inner())
                        .0
                }
                None => self.ready.wait(st).unwrap_or_else(|e| e.into_inner()),
            };
        }
        st.server = None;
        st.cancel = false;
        Ok(ran)
    }

    /// Makes the running spin return after its current task; `false` if none runs.
    pub(crate) fn cancel(&self) -> bool {
        let mut st = self.lock();
        if st.server.is_none() {
            return false;
        }
        st.cancel = true;
        drop(st);
        self.ready.notify_all();
        true
    }

    /// Whether a spin serves the queue now.
    pub(crate) fn is_spinning(&self) -> bool {
        self.lock().server.is_some()
    }

    fn run_one(&self, task: Task) {
        if task.run(&self.name) == TaskOutcome::Panicked {
            self.panicked.fetch_add(1, Ordering::Relaxed);
        }
        self.run.fetch_add(1, Ordering::Relaxed);
        self.lock().in_flight -= 1;
    }

    fn refuse(&self, task: Task, err: ExecuteError) -> Result<(), ExecuteError> {
        drop(task);
        let n = self.refused.fetch_add(1, Ordering::Relaxed) + 1;
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(target: "aimrt", "{} executor '{}': task refused: {err} ({} refused since the last report, {n} so far)", self.type_name, self.name, held + 1);
        }
        Err(err)
    }

    /// Makes `serve` return once the queue is empty.
    pub(crate) fn request_stop(&self) {
        self.lock().stop = true;
        self.ready.notify_all();
    }

    /// Stops taking work and runs what is queued on the calling thread (when nobody
    /// serves the queue any more).
    pub(crate) fn close_and_drain(&self) {
        let tasks: Vec<Task> = {
            let mut st = self.lock();
            st.accepting = false;
            st.queue.drain(..).collect()
        };
        for t in tasks {
            self.run_one(t);
        }
    }
}

impl Executor for SerialQueue {
    fn type_name(&self) -> &str {
        self.type_name
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn thread_safe(&self) -> bool {
        true
    }

    fn is_in_current_executor(&self) -> bool {
        self.lock().server == Some(std::thread::current().id())
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        let mut st = self.lock();
        if !st.accepting {
            drop(st);
            return self.refuse(task, ExecuteError::ShutDown);
        }
        if self.threshold.is_some_and(|t| st.in_flight >= t) {
            drop(st);
            return self.refuse(task, ExecuteError::QueueFull);
        }
        st.in_flight += 1;
        st.queue.push_back(task);
        drop(st);
        self.submitted.fetch_add(1, Ordering::Relaxed);
        self.ready.notify_one();
        Ok(())
    }

    fn shutdown(&self) {
        self.request_stop();
        self.close_and_drain();
    }

    fn stats(&self) -> ExecutorStats {
        ExecutorStats {
            submitted: self.submitted.load(Ordering::Relaxed),
            run: self.run.load(Ordering::Relaxed),
            refused: self.refused.load(Ordering::Relaxed),
            panicked: self.panicked.load(Ordering::Relaxed),
            queue_depth: self.lock().in_flight,
            ..ExecutorStats::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use std::time::Duration;

    #[test]
    fn serves_in_fifo_order_and_stops() {
        let q = Arc::new(SerialQueue::new("main_thread", "m", None, 1000));
        let seen = Arc::new(Mutex::new(Vec::new()));
        for i in 0..5 {
            let s = seen.clone();
            q.execute(Task::new(move || s.lock().unwrap().push(i)))
                .unwrap();
        }
        let q2 = q.clone();
        q.execute(Task::new(move || q2.request_stop())).unwrap();
        q.serve(Some(Instant::now() + Duration::from_secs(10)));
        assert_eq!(*seen.lock().unwrap(), vec![0, 1, 2, 3, 4]);
        assert_eq!(q.stats().run, 6);
    }

    #[test]
    fn refuses_after_shutdown_and_over_threshold() {
        let q = SerialQueue::new("guard_thread", "g", Some(1), -1);
        q.execute(Task::new(|| {})).unwrap();
        assert_eq!(q.execute(Task::new(|| {})), Err(ExecuteError::QueueFull));
        q.shutdown();
        assert_eq!(q.stats().run, 1, "queued work runs at shutdown");
        assert_eq!(q.execute(Task::new(|| {})), Err(ExecuteError::ShutDown));
        assert_eq!(q.stats().refused, 2);
    }
}
