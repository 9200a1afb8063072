//! Periodic timers on any executor with timer support (AimRT's `CreateTimer`).
//!
//! A timer runs its task every `period` on its executor's clock. The first run is one
//! period after start (or [`Timer::reset`]). A run that starts late, or a task that takes
//! longer than a period, never causes catch-up runs: the next run is the first point of the
//! original grid (`start + k·period`) that is not in the past. With a 1000 ms period and a
//! task taking 1500 ms, runs start at 0, 2000, 4000 ms after the first.
//!
//! Runs of one timer never overlap, also on a multi-threaded executor: the next run is
//! scheduled only after the task returns. A panicking task is logged (with the timer's
//! executor) and the timer goes on.
//!
//! **Lifetime** (as AimRT): a timer keeps running until [`Timer::cancel`], also when every
//! [`Timer`] handle is dropped — the scheduled run holds it. It also ends when its executor
//! refuses or drops a run (queue full, shut down); [`Timer::is_cancelled`] then reports
//! `true`.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime};

use crate::error::{Error, ExecuteError};
use crate::executor::ExecutorRef;

type TimerTask = Box<dyn FnMut(&Timer) + Send>;

/// A handle to a periodic timer; clones refer to the same timer.
///
/// ```no_run
/// # fn demo(exec: aimrt_plugin_api::ExecutorRef) -> Result<(), aimrt_plugin_api::Error> {
/// use std::time::Duration;
/// let mut runs = 0;
/// let timer = aimrt_plugin_api::create_timer(exec, Duration::from_millis(100), move |timer| {
///     runs += 1;
///     tracing::info!("run {runs}");
///     if runs == 10 {
///         timer.cancel();
///     }
/// }, true)?;
/// # Ok(()) }
/// ```
#[derive(Clone)]
pub struct Timer {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Timer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let state = self.inner.state();
        f.debug_struct("Timer")
            .field("executor", &self.inner.executor.name())
            .field("period", &self.inner.period)
            .field("cancelled", &state.cancelled)
            .field("next_call_time", &state.next)
            .finish()
    }
}

struct Inner {
    executor: ExecutorRef,
    period: Duration,
    state: Mutex<State>,
    task: Mutex<TimerTask>,
}

struct State {
    cancelled: bool,
    next: SystemTime,
    /// Bumped by every reset and cancel: a scheduled run of an older generation does
    /// nothing, so a reset never fires twice.
    generation: u64,
}

impl Inner {
    fn state(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Creates a timer that runs `task` every `period` on `executor`; with `auto_start` it
/// starts now (first run one period from now), else it waits, cancelled, for
/// [`Timer::reset`]. The task gets the timer, e.g. to cancel itself.
///
/// Fails if the executor does not support timers, or refuses the first run.
pub fn create_timer(
    executor: ExecutorRef,
    period: Duration,
    task: impl FnMut(&Timer) + Send + 'static,
    auto_start: bool,
) -> Result<Timer, Error> {
    if !executor.supports_timer_schedule() {
        return Err(Error::Execute {
            executor: executor.name().to_owned(),
            source: ExecuteError::NoTimerSupport,
        });
    }
    let timer = Timer {
        inner: Arc::new(Inner {
            executor,
            period,
            state: Mutex::new(State {
                cancelled: true,
                next: SystemTime::UNIX_EPOCH,
                generation: 0,
            }),
            task: Mutex::new(Box::new(task)),
        }),
    };
    if auto_start {
        timer.reset()?;
    }
    Ok(timer)
}

impl Timer {
    /// (Re)starts the timer: the next run is one period from now on the executor's clock,
    /// and any run scheduled before is void. Also after [`cancel`](Timer::cancel).
    pub fn reset(&self) -> Result<(), Error> {
        let (generation, next) = {
            let mut state = self.inner.state();
            state.cancelled = false;
            state.next = self.inner.executor.now() + self.inner.period;
            state.generation += 1;
            (state.generation, state.next)
        };
        self.arm(generation, next)
    }

    /// Stops the timer: no run starts after this returns (a run in progress finishes).
    pub fn cancel(&self) {
        let mut state = self.inner.state();
        state.cancelled = true;
        state.generation += 1;
    }

    /// Runs the task once now, on the calling thread (the schedule is not changed). Not
    /// from inside the task itself: runs never overlap, so that call would wait forever.
    pub fn execute_task(&self) {
        let mut task = self.inner.task.lock().unwrap_or_else(|e| e.into_inner());
        task(self);
    }

    /// Whether the timer is stopped: not started, cancelled, or its executor refused a run.
    pub fn is_cancelled(&self) -> bool {
        self.inner.state().cancelled
    }

    /// The period.
    pub fn period(&self) -> Duration {
        self.inner.period
    }

    /// When the next run is due, on the executor's clock (the Unix epoch before the first
    /// start).
    pub fn next_call_time(&self) -> SystemTime {
        self.inner.state().next
    }

    /// How long until the next run is due; zero when it is due or overdue.
    pub fn time_until_next_call(&self) -> Duration {
        let next = self.next_call_time();
        next.duration_since(self.inner.executor.now())
            .unwrap_or(Duration::ZERO)
    }

    /// The executor the timer runs on.
    pub fn executor(&self) -> ExecutorRef {
        self.inner.executor
    }

    fn arm(&self, generation: u64, at: SystemTime) -> Result<(), Error> {
        let timer = self.clone();
        let result = self
            .inner
            .executor
            .execute_at(at, move || timer.fire(generation));
        if result.is_err() {
            self.stop_if_current(generation);
        }
        result
    }

    /// A refused run ends the chain; the timer reports itself cancelled.
    fn stop_if_current(&self, generation: u64) {
        let mut state = self.inner.state();
        if state.generation == generation {
            state.cancelled = true;
        }
    }

    fn fire(&self, generation: u64) {
        if self.inner.state().generation != generation {
            return;
        }
        {
            let mut task = self.inner.task.lock().unwrap_or_else(|e| e.into_inner());
            if let Err(message) = crate::panic::contain(|| task(self)) {
                let executor = self.inner.executor.name();
                crate::panic::log_panic(
                    &format!("timer task on executor '{executor}'"),
                    executor,
                    &message,
                );
            }
        }
        let next = {
            let mut state = self.inner.state();
            // Cancelled or reset by the task (or meanwhile): that decides what comes next.
            if state.generation != generation {
                return;
            }
            let period = self.inner.period;
            let now = self.inner.executor.now();
            let mut next = state.next + period;
            if next < now {
                // Missed periods are skipped: the first grid point not in the past.
                next = if period.is_zero() {
                    now
                } else {
                    let behind = now.duration_since(next).unwrap_or_default();
                    let periods = behind.as_nanos().div_ceil(period.as_nanos());
                    next + period.saturating_mul(u32::try_from(periods).unwrap_or(u32::MAX))
                };
            }
            state.next = next;
            next
        };
        // A refusal (executor shut down) ends the chain; the executor has logged why.
        let _ = self.arm(generation, next);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Executor, Task};
    use std::collections::BinaryHeap;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Condvar;

    /// A manual-clock executor: tasks run when the test advances time.
    #[derive(Default)]
    struct ManualClock {
        inner: Mutex<Manual>,
        refuse: AtomicBool,
        changed: Condvar,
    }

    #[derive(Default)]
    struct Manual {
        now_ms: u64,
        seq: u64,
        queue: BinaryHeap<std::cmp::Reverse<(u64, u64, usize)>>,
        tasks: Vec<Option<Task>>,
    }

    impl ManualClock {
        fn advance_to(&self, ms: u64) {
            loop {
                let task = {
                    let mut m = self.inner.lock().unwrap();
                    match m.queue.peek() {
                        Some(std::cmp::Reverse((at, _, _))) if *at <= ms => {
                            let std::cmp::Reverse((at, _, idx)) = m.queue.pop().unwrap();
                            m.now_ms = m.now_ms.max(at);
                            m.tasks[idx].take()
                        }
                        _ => {
                            m.now_ms = ms;
                            None
                        }
                    }
                };
                match task {
                    Some(t) => {
                        t.run("manual");
                    }
                    None => return,
                }
            }
        }

        fn set_now(&self, ms: u64) {
            self.inner.lock().unwrap().now_ms = ms;
        }

        fn pending(&self) -> usize {
            self.inner.lock().unwrap().queue.len()
        }
    }

    impl Executor for ManualClock {
        fn type_name(&self) -> &str {
            "manual"
        }
        fn name(&self) -> &str {
            "manual"
        }
        fn thread_safe(&self) -> bool {
            true
        }
        fn is_in_current_executor(&self) -> bool {
            false
        }
        fn supports_timer_schedule(&self) -> bool {
            true
        }
        fn execute(&self, task: Task) -> Result<(), ExecuteError> {
            let now =
                SystemTime::UNIX_EPOCH + Duration::from_millis(self.inner.lock().unwrap().now_ms);
            self.execute_at(now, task)
        }
        fn now(&self) -> SystemTime {
            SystemTime::UNIX_EPOCH + Duration::from_millis(self.inner.lock().unwrap().now_ms)
        }
        fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
            if self.refuse.load(Ordering::SeqCst) {
                return Err(ExecuteError::ShutDown);
            }
            let at = at
                .duration_since(SystemTime::UNIX_EPOCH)
                .unwrap()
                .as_millis() as u64;
            let mut m = self.inner.lock().unwrap();
            let idx = m.tasks.len();
            m.tasks.push(Some(task));
            m.seq += 1;
            let seq = m.seq;
            m.queue.push(std::cmp::Reverse((at, seq, idx)));
            self.changed.notify_all();
            Ok(())
        }
        fn shutdown(&self) {}
    }

    fn manual() -> (Arc<ManualClock>, ExecutorRef) {
        let exec = Arc::new(ManualClock::default());
        let r = ExecutorRef::leak(exec.clone());
        (exec, r)
    }

    fn ms(t: SystemTime) -> u64 {
        t.duration_since(SystemTime::UNIX_EPOCH)
            .unwrap()
            .as_millis() as u64
    }

    /// A timer recording the clock at each run.
    fn recording(
        exec: ExecutorRef,
        period: u64,
        auto: bool,
        work: impl Fn(&Timer, usize) + Send + 'static,
    ) -> (Timer, Arc<Mutex<Vec<u64>>>) {
        let runs = Arc::new(Mutex::new(Vec::new()));
        let r = runs.clone();
        let timer = create_timer(
            exec,
            Duration::from_millis(period),
            move |t| {
                let n = {
                    let mut v = r.lock().unwrap();
                    v.push(ms(t.executor().now()));
                    v.len()
                };
                work(t, n);
            },
            auto,
        )
        .unwrap();
        (timer, runs)
    }

    #[test]
    fn first_run_is_one_period_after_start_then_every_period() {
        let (clock, exec) = manual();
        let (timer, runs) = recording(exec, 100, true, |_, _| {});
        assert_eq!(ms(timer.next_call_time()), 100);
        assert_eq!(timer.time_until_next_call(), Duration::from_millis(100));
        clock.advance_to(1000);
        assert_eq!(
            *runs.lock().unwrap(),
            [100, 200, 300, 400, 500, 600, 700, 800, 900, 1000]
        );
        assert_eq!(timer.period(), Duration::from_millis(100));
        assert!(!timer.is_cancelled());
    }

    #[test]
    fn missed_periods_are_skipped_on_the_grid() {
        // The docs' example: period 1000 ms, a task taking 1500 ms → 0, 2000, 4000 after the first.
        let (clock, exec) = manual();
        let c = clock.clone();
        let (_timer, runs) = recording(exec, 1000, true, move |t, _| {
            c.set_now(ms(t.executor().now()) + 1500);
        });
        clock.advance_to(7500);
        assert_eq!(*runs.lock().unwrap(), [1000, 3000, 5000, 7000]);
    }

    #[test]
    fn cancel_stops_and_reset_restarts_from_now() {
        let (clock, exec) = manual();
        let (timer, runs) = recording(exec, 100, true, |_, _| {});
        clock.advance_to(250);
        timer.cancel();
        assert!(timer.is_cancelled());
        clock.advance_to(1000);
        assert_eq!(*runs.lock().unwrap(), [100, 200]);
        timer.reset().unwrap();
        assert!(!timer.is_cancelled());
        clock.advance_to(1250);
        assert_eq!(*runs.lock().unwrap(), [100, 200, 1100, 1200]);
    }

    #[test]
    fn reset_replaces_the_schedule_without_double_firing() {
        let (clock, exec) = manual();
        let (timer, runs) = recording(exec, 100, true, |_, _| {});
        clock.advance_to(350);
        timer.reset().unwrap(); // old chain due at 400 is void; new at 450
        clock.advance_to(600);
        timer.reset().unwrap(); // new at 700
        clock.advance_to(900);
        assert_eq!(
            *runs.lock().unwrap(),
            [100, 200, 300, 450, 550, 700, 800, 900]
        );
    }

    #[test]
    fn the_task_can_cancel_or_reset_its_own_timer() {
        let (clock, exec) = manual();
        let (_timer, runs) = recording(exec, 100, true, |t, n| {
            if n == 3 {
                t.cancel();
            }
        });
        clock.advance_to(1000);
        assert_eq!(*runs.lock().unwrap(), [100, 200, 300]);
        assert_eq!(
            clock.pending(),
            0,
            "a cancelled timer leaves nothing scheduled"
        );

        let (clock, exec) = manual();
        let (_timer, runs) = recording(exec, 100, true, |t, n| {
            if n == 2 {
                t.reset().unwrap(); // next run one period after the reset
            }
        });
        clock.advance_to(500);
        assert_eq!(*runs.lock().unwrap(), [100, 200, 300, 400, 500]);
    }

    #[test]
    fn not_started_until_reset() {
        let (clock, exec) = manual();
        let (timer, runs) = recording(exec, 100, false, |_, _| {});
        assert!(timer.is_cancelled());
        assert_eq!(timer.next_call_time(), SystemTime::UNIX_EPOCH);
        clock.advance_to(1000);
        assert!(runs.lock().unwrap().is_empty());
        timer.execute_task();
        assert_eq!(*runs.lock().unwrap(), [1000]);
    }

    #[test]
    fn dropping_every_handle_keeps_it_running_until_cancelled() {
        let (clock, exec) = manual();
        let (timer, runs) = recording(exec, 100, true, |t, n| {
            if n == 5 {
                t.cancel();
            }
        });
        drop(timer);
        clock.advance_to(1000);
        assert_eq!(runs.lock().unwrap().len(), 5);
    }

    #[test]
    fn period_zero_reruns_back_to_back() {
        let (clock, exec) = manual();
        let (_timer, runs) = recording(exec, 0, true, |t, n| {
            if n == 50 {
                t.cancel();
            }
        });
        clock.advance_to(0);
        assert_eq!(runs.lock().unwrap().len(), 50);
    }

    #[test]
    fn refused_run_ends_the_timer() {
        let (clock, exec) = manual();
        let (timer, runs) = recording(exec, 100, true, |_, _| {});
        clock.advance_to(200);
        clock.refuse.store(true, Ordering::SeqCst);
        clock.advance_to(1000); // the run at 300 cannot re-arm
        assert_eq!(*runs.lock().unwrap(), [100, 200, 300]);
        assert!(timer.is_cancelled());
        assert!(timer.reset().is_err());
    }

    #[test]
    fn panicking_task_is_contained_and_the_timer_goes_on() {
        let (clock, exec) = manual();
        let (_timer, runs) = recording(exec, 100, true, |t, n| {
            if n == 2 {
                panic!("boom");
            }
            if n == 4 {
                t.cancel();
            }
        });
        clock.advance_to(1000);
        assert_eq!(*runs.lock().unwrap(), [100, 200, 300, 400]);
    }

    #[test]
    fn executor_without_timers_is_an_error() {
        let exec = crate::test_util::inline();
        let err = create_timer(exec, Duration::from_millis(1), |_| {}, true).unwrap_err();
        assert!(err.to_string().contains("does not support timer"), "{err}");
    }
}
