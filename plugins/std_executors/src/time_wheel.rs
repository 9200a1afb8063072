//! `time_wheel`: timers on a hierarchical timing wheel ([`Wheel`]) served by one thread,
//! optionally handing due tasks to a bound executor.
//!
//! Tick `k` is the instant `origin + k·dt` (origin: creation). A task for time `at` is due
//! at the first tick at or after `at`, so it never runs early and at most one tick late
//! plus scheduling noise; `now()` is the executor's clock, not rounded to ticks. The thread
//! sleeps until the wheel's next event (or until new work arrives), not every tick.
//! Unbound, `execute` queues the task for the wheel thread, which runs it at once (AimRT
//! waits for the next tick); bound, `execute` goes straight to the bound executor.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorArgs, ExecutorRef, ExecutorStats, Task, ThreadFactory,
    ThreadSettingsRef,
};
use serde::Deserialize;

use crate::common::{execute_error, options_error, Accounting, Clock, Marker};
use crate::wheel::Wheel;

/// The options of AimRT's `time_wheel`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TimeWheelOptions {
    #[serde(default)]
    bind_executor: String,
    #[serde(default = "default_dt_us")]
    dt_us: u64,
    #[serde(default = "default_wheel_size")]
    wheel_size: Vec<u64>,
    #[serde(default)]
    thread_sched_policy: String,
    #[serde(default)]
    thread_bind_cpu: Vec<u32>,
    #[serde(default)]
    thread_policy_strict: bool,
    #[serde(default)]
    use_system_clock: bool,
}

fn default_dt_us() -> u64 {
    100_000
}

fn default_wheel_size() -> Vec<u64> {
    vec![100, 360]
}

struct State {
    wheel: Wheel<Task>,
    immediate: VecDeque<Task>,
    /// The tick the sleeping thread wakes at (`None`: awake, or asleep with nothing due).
    sleeping_until: Option<u64>,
    sleeping: bool,
    stop: bool,
    started: bool,
}

struct Inner {
    name: String,
    bound: Option<ExecutorRef>,
    clock: Clock,
    origin: Instant,
    dt_ns: u64,
    acct: Accounting,
    state: Mutex<State>,
    wake: Condvar,
}

/// A timing-wheel executor.
pub(crate) struct TimeWheel {
    inner: Arc<Inner>,
    factory: ThreadFactory,
    options: TimeWheelOptions,
    handle: Mutex<Option<JoinHandle<()>>>,
}

impl std::fmt::Debug for TimeWheel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TimeWheel")
            .field("name", &self.inner.name)
            .field("options", &self.options)
            .finish()
    }
}

/// Builds a `time_wheel`; `args.bound[0]` is `bind_executor`.
pub(crate) fn create(args: ExecutorArgs<'_>) -> Result<Arc<TimeWheel>, Error> {
    let o: TimeWheelOptions = args.options()?;
    if o.dt_us == 0 {
        return Err(options_error(
            &args,
            "dt_us must be greater than 0 (the tick length in µs)",
        ));
    }
    if o.wheel_size.is_empty() || o.wheel_size.contains(&0) {
        return Err(options_error(
            &args,
            format!(
            "wheel_size must list at least one level and every size must be greater than 0, got {:?}",
            o.wheel_size
        )));
    }
    let bound = args.bound.first().copied().flatten();
    if bound.is_none() && !o.bind_executor.is_empty() {
        return Err(options_error(
            &args,
            format!("bind_executor '{}' was not resolved", o.bind_executor),
        ));
    }
    let inner = Arc::new(Inner {
        name: args.name.to_owned(),
        bound,
        clock: Clock::new(o.use_system_clock),
        origin: Instant::now(),
        dt_ns: o.dt_us.saturating_mul(1000),
        acct: Accounting::new(1),
        state: Mutex::new(State {
            wheel: Wheel::new(&o.wheel_size),
            immediate: VecDeque::new(),
            sleeping_until: None,
            sleeping: false,
            stop: false,
            started: false,
        }),
        wake: Condvar::new(),
    });
    Ok(Arc::new(TimeWheel {
        inner,
        factory: args.threads,
        options: o,
        handle: Mutex::new(None),
    }))
}

impl Inner {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn id(&self) -> usize {
        self as *const Inner as usize
    }

    /// The first tick at or after `due`.
    fn tick_at_or_after(&self, due: Instant) -> u64 {
        let ns = due.saturating_duration_since(self.origin).as_nanos();
        u64::try_from(ns.div_ceil(u128::from(self.dt_ns))).unwrap_or(u64::MAX)
    }

    /// The last tick at or before `now`.
    fn tick_reached(&self, now: Instant) -> u64 {
        let ns = now.saturating_duration_since(self.origin).as_nanos();
        u64::try_from(ns / u128::from(self.dt_ns)).unwrap_or(u64::MAX)
    }

    fn instant_of_tick(&self, tick: u64) -> Instant {
        let ns = u128::from(tick) * u128::from(self.dt_ns);
        let ns = u64::try_from(ns).unwrap_or(u64::MAX);
        self.origin
            .checked_add(Duration::from_nanos(ns))
            .unwrap_or_else(|| Instant::now() + Duration::from_secs(3600 * 24 * 365))
    }

    fn refuse(&self, task: Task, err: ExecuteError) -> ExecuteError {
        self.acct
            .refuse_task(Some(task), err, "time wheel", &self.name, "task refused")
    }

    /// Runs a due task here (unbound) or hands it to the bound executor.
    fn dispatch(&self, task: Task) {
        match self.bound {
            None => self.acct.worker(0).record(task.run(&self.name)),
            Some(bound) => match bound.execute_task(task) {
                Ok(()) => self
                    .acct
                    .worker(0)
                    .record(aimrt_plugin_api::TaskOutcome::Completed),
                Err(e) => {
                    self.acct.refuse_task(
                        None,
                        execute_error(e),
                        "time wheel",
                        &self.name,
                        "the bound executor refused a due task",
                    );
                }
            },
        }
        self.acct.gate.leave();
    }

    /// The wheel thread.
    fn serve(&self) {
        let _mark = Marker::Worker.set(self.id());
        let mut due = Vec::new();
        loop {
            let mut st = self.lock();
            loop {
                if !st.immediate.is_empty() || st.stop {
                    break;
                }
                let now = Instant::now();
                if st.wheel.current() < self.tick_reached(now) {
                    break;
                }
                st.sleeping = true;
                st = match st.wheel.next_event() {
                    Some(tick) => {
                        st.sleeping_until = Some(tick);
                        let wait = self.instant_of_tick(tick).saturating_duration_since(now);
                        self.wake
                            .wait_timeout(st, wait)
                            .unwrap_or_else(|e| e.into_inner())
                            .0
                    }
                    None => {
                        st.sleeping_until = None;
                        self.wake.wait(st).unwrap_or_else(|e| e.into_inner())
                    }
                };
                st.sleeping = false;
            }
            let immediate = std::mem::take(&mut st.immediate);
            let reached = self.tick_reached(Instant::now());
            st.wheel.advance(reached, &mut due);
            let stop = st.stop;
            let dropped = if stop { st.wheel.drain() } else { Vec::new() };
            drop(st);
            for task in immediate {
                self.acct.worker(0).record(task.run(&self.name));
                self.acct.gate.leave();
            }
            for task in due.drain(..) {
                self.dispatch(task);
            }
            if stop {
                self.drop_pending(dropped);
                return;
            }
        }
    }

    fn drop_pending(&self, tasks: Vec<Task>) {
        if tasks.is_empty() {
            return;
        }
        let n = tasks.len();
        for task in tasks {
            drop(task);
            self.acct.drop_at_shutdown();
            self.acct.gate.leave();
        }
        tracing::info!(target: "aimrt", "time wheel executor '{}' shut down with {n} task(s) not yet due or never run (a cancelled timer leaves one); they were dropped without running", self.name);
    }

    /// Wakes the wheel thread if it sleeps past `tick` (or without a deadline).
    fn wake_for(&self, st: &State, tick: Option<u64>) {
        let later = match (st.sleeping_until, tick) {
            (_, None) | (None, _) => true,
            (Some(until), Some(t)) => t < until,
        };
        if st.sleeping && later {
            self.wake.notify_one();
        }
    }
}

impl Executor for TimeWheel {
    fn type_name(&self) -> &str {
        "time_wheel"
    }

    fn name(&self) -> &str {
        &self.inner.name
    }

    fn thread_safe(&self) -> bool {
        self.inner.bound.is_none_or(|b| b.thread_safe())
    }

    fn is_in_current_executor(&self) -> bool {
        match self.inner.bound {
            Some(b) => b.is_in_current_executor(),
            None => Marker::Worker.is(self.inner.id()),
        }
    }

    fn supports_timer_schedule(&self) -> bool {
        true
    }

    fn now(&self) -> SystemTime {
        self.inner.clock.now()
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        let inner = &self.inner;
        if let Some(bound) = inner.bound {
            if inner.acct.gate.is_closed() {
                return Err(inner.refuse(task, ExecuteError::ShutDown));
            }
            return bound.execute_task(task).map_err(execute_error);
        }
        if let Err(r) = inner.acct.gate.enter(u64::MAX) {
            return Err(inner.refuse(task, r.error()));
        }
        let mut st = inner.lock();
        st.immediate.push_back(task);
        inner.wake_for(&st, None);
        Ok(())
    }

    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        let inner = &self.inner;
        if let Err(r) = inner.acct.gate.enter(u64::MAX) {
            return Err(inner.refuse(task, r.error()));
        }
        let target = inner.tick_at_or_after(inner.clock.instant_of(at));
        let mut st = inner.lock();
        match st.wheel.insert(target, task) {
            Ok(()) => inner.wake_for(&st, Some(target)),
            Err(task) if inner.bound.is_some() => {
                drop(st);
                inner.dispatch(task);
            }
            Err(task) => {
                st.immediate.push_back(task);
                inner.wake_for(&st, None);
            }
        }
        Ok(())
    }

    /// Starts the wheel thread (as AimRT: at start, not at creation).
    fn start(&self) -> Result<(), Error> {
        let mut handle = self.handle.lock().unwrap_or_else(|e| e.into_inner());
        if handle.is_some() || self.inner.acct.gate.is_closed() {
            return Err(Error::msg(format!(
                "time wheel executor '{}' can only be started once, before shutdown",
                self.inner.name
            )));
        }
        let inner = self.inner.clone();
        let o = &self.options;
        *handle = Some(self.factory.spawn(
            ThreadSettingsRef {
                name: &self.inner.name,
                sched_policy: &o.thread_sched_policy,
                bind_cpu: &o.thread_bind_cpu,
                strict: o.thread_policy_strict,
            },
            move || inner.serve(),
        )?);
        self.inner.lock().started = true;
        Ok(())
    }

    /// Stops taking work; the thread runs what is queued and due, drops the timed tasks
    /// not yet due (counted, logged) and exits. Idempotent.
    fn shutdown(&self) {
        let inner = &self.inner;
        inner.acct.gate.close();
        inner.lock().stop = true;
        inner.wake.notify_all();
        let handle = self.handle.lock().unwrap_or_else(|e| e.into_inner()).take();
        match handle {
            Some(h) if h.thread().id() != std::thread::current().id() => {
                let _ = h.join();
            }
            Some(_) => {}
            None => {
                let mut st = inner.lock();
                if st.started {
                    return;
                }
                // Never started: nothing will run what is queued.
                let mut pending: Vec<Task> = st.immediate.drain(..).collect();
                pending.extend(st.wheel.drain());
                drop(st);
                inner.drop_pending(pending);
            }
        }
    }

    fn stats(&self) -> ExecutorStats {
        self.inner.acct.stats()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use aimrt_plugin_api::ThreadFactory;

    fn wheel(dt_us: u64) -> Arc<TimeWheel> {
        create(ExecutorArgs {
            name: "w",
            options_json: &format!(r#"{{"dt_us": {dt_us}, "wheel_size": [10, 4]}}"#),
            location: "test",
            bound: Vec::new(),
            threads: ThreadFactory::plain(),
        })
        .unwrap()
    }

    /// The time-to-tick mapping, driven by synthetic instants (the injected clock).
    #[test]
    fn a_deadline_maps_to_the_first_tick_at_or_after_it() {
        let w = wheel(1000);
        let i = &w.inner;
        let at = |us: u64| i.origin + Duration::from_micros(us);
        assert_eq!(i.tick_at_or_after(at(0)), 0);
        assert_eq!(i.tick_at_or_after(at(1)), 1);
        assert_eq!(i.tick_at_or_after(at(1000)), 1);
        assert_eq!(i.tick_at_or_after(at(1001)), 2);
        assert_eq!(i.tick_reached(at(999)), 0);
        assert_eq!(i.tick_reached(at(1000)), 1);
        // Never early: a tick is processed only once its instant is reached, and that
        // instant is at or after every deadline mapped to it.
        for us in [1u64, 999, 1000, 1001, 12_345, 987_654] {
            let tick = i.tick_at_or_after(at(us));
            assert!(i.instant_of_tick(tick) >= at(us), "{us}");
            assert!(
                i.instant_of_tick(tick) < at(us) + Duration::from_millis(1),
                "{us}"
            );
        }
        // Deadlines before the origin are due at once.
        let before = i
            .origin
            .checked_sub(Duration::from_secs(1))
            .unwrap_or(i.origin);
        assert_eq!(i.tick_at_or_after(before), 0);
        w.shutdown();
    }

    #[test]
    fn shutdown_before_start_drops_and_counts_what_was_queued() {
        let w = wheel(1000);
        w.execute(Task::new(|| {})).unwrap();
        w.execute_at(w.now() + Duration::from_secs(60), Task::new(|| {}))
            .unwrap();
        w.shutdown();
        let s = w.stats();
        assert_eq!((s.run, s.dropped_at_shutdown, s.queue_depth), (0, 2, 0));
    }
}
