//! `time_wheel`: timers on a hierarchical timing wheel ([`Wheel`]) served by one thread,
//! optionally handing due tasks to a bound executor.
//!
//! Tick `k` is the instant `origin + k·dt` (origin: creation). A task for time `at` is due
//! at the first tick at or after `at`, so it never runs early and at most one tick late
//! plus scheduling noise; `now()` is the executor's clock, not rounded to ticks. The thread
//! sleeps until the wheel's next event (or until new work arrives), not every tick.
//! Unbound, `execute` queues the task for the wheel thread, which runs it at once (AimRT
//! waits for the next tick); bound, `execute` goes straight to the bound executor.
//!
//! The same wheel serves `time_manipulator` ([`crate::TimeManipulator`]): there the
//! timeline is scaled time ([`Pace::Scaled`]) instead of real time.

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
#[derive(Debug, Deserialize, serde::Serialize)]
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

/// The most levels a wheel may have.
pub(crate) const MAX_WHEEL_LEVELS: usize = 8;
/// The most slots a wheel may have, summed over its levels (each slot is a list head).
pub(crate) const MAX_WHEEL_SLOTS: u64 = 4_000_000;

pub(crate) fn default_dt_us() -> u64 {
    100_000
}

pub(crate) fn default_wheel_size() -> Vec<u64> {
    vec![100, 360]
}

/// How the wheel's timeline (nanoseconds since the origin) relates to real time.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Pace {
    /// Real time (`time_wheel`).
    Real,
    /// `ratio` × real time since `base_real`, where the timeline was at `base_pos`
    /// (`time_manipulator`). A ratio of 0 stands still.
    Scaled {
        ratio: f64,
        base_real: Instant,
        base_pos: u64,
    },
}

impl Pace {
    /// The timeline position at real instant `now`.
    fn position(&self, origin: Instant, now: Instant) -> u64 {
        match *self {
            Pace::Real => saturating_ns(now.saturating_duration_since(origin)),
            Pace::Scaled {
                ratio,
                base_real,
                base_pos,
            } => {
                let real = now.saturating_duration_since(base_real).as_nanos() as f64;
                // `as` saturates; the product is never negative.
                base_pos.saturating_add((real * ratio) as u64)
            }
        }
    }

    /// The first real instant at which the timeline is at `pos` or later (`None`: never,
    /// the timeline stands still).
    fn instant_of(&self, origin: Instant, pos: u64) -> Option<Instant> {
        match *self {
            Pace::Real => origin.checked_add(Duration::from_nanos(pos)),
            Pace::Scaled {
                ratio,
                base_real,
                base_pos,
            } => {
                if pos <= base_pos {
                    return Some(base_real);
                }
                if ratio <= 0.0 {
                    return None;
                }
                // Rounded up, plus 1 µs for the rounding of the division: the thread never
                // wakes before the timeline got there.
                let real = ((pos - base_pos) as f64 / ratio).ceil() as u64;
                base_real.checked_add(Duration::from_nanos(real.saturating_add(1000)))
            }
        }
    }
}

fn saturating_ns(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

struct State {
    pace: Pace,
    wheel: Wheel<Task>,
    immediate: VecDeque<Task>,
    /// The tick the sleeping thread wakes at (`None`: awake, or asleep with nothing due).
    sleeping_until: Option<u64>,
    sleeping: bool,
    stop: bool,
    started: bool,
}

struct Inner {
    type_name: &'static str,
    name: String,
    bound: Option<ExecutorRef>,
    clock: Clock,
    /// Where the timeline starts: the clock's anchor.
    origin: Instant,
    /// Whether the timeline is scaled time (set at creation, never changes).
    scaled: bool,
    dt_ns: u64,
    acct: Accounting,
    state: Mutex<State>,
    wake: Condvar,
}

/// What differs between the two wheel executors.
pub(crate) struct Setup<'a> {
    pub(crate) type_name: &'static str,
    pub(crate) bound: Option<ExecutorRef>,
    pub(crate) dt_us: u64,
    pub(crate) wheel_size: &'a [u64],
    pub(crate) use_system_clock: bool,
    pub(crate) pace: Pace,
    pub(crate) thread_sched_policy: String,
    pub(crate) thread_bind_cpu: Vec<u32>,
    pub(crate) thread_policy_strict: bool,
}

/// A timing-wheel executor.
pub(crate) struct TimeWheel {
    inner: Arc<Inner>,
    factory: ThreadFactory,
    thread_sched_policy: String,
    thread_bind_cpu: Vec<u32>,
    thread_policy_strict: bool,
    handle: Mutex<Option<JoinHandle<()>>>,
}

impl std::fmt::Debug for TimeWheel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TimeWheel")
            .field("type", &self.inner.type_name)
            .field("name", &self.inner.name)
            .finish_non_exhaustive()
    }
}

/// Builds a `time_wheel`; `args.bound[0]` is `bind_executor`.
pub(crate) fn create(args: ExecutorArgs<'_>) -> Result<Arc<TimeWheel>, Error> {
    let o: TimeWheelOptions = args.read_options()?;
    let bound = args.bound.first().copied().flatten();
    if bound.is_none() && !o.bind_executor.is_empty() {
        return Err(options_error(
            &args,
            format!("bind_executor '{}' was not resolved", o.bind_executor),
        ));
    }
    let setup = Setup {
        type_name: "time_wheel",
        bound,
        dt_us: o.dt_us,
        wheel_size: &o.wheel_size,
        use_system_clock: o.use_system_clock,
        pace: Pace::Real,
        thread_sched_policy: o.thread_sched_policy,
        thread_bind_cpu: o.thread_bind_cpu,
        thread_policy_strict: o.thread_policy_strict,
    };
    TimeWheel::new(&args, setup).map(Arc::new)
}

impl TimeWheel {
    /// A wheel executor of either kind; checks `dt_us` and `wheel_size`.
    pub(crate) fn new(args: &ExecutorArgs<'_>, s: Setup<'_>) -> Result<TimeWheel, Error> {
        if s.dt_us == 0 {
            return Err(options_error(
                args,
                "dt_us must be greater than 0 (the tick length in µs)",
            ));
        }
        if s.wheel_size.is_empty() || s.wheel_size.contains(&0) {
            return Err(options_error(
                args,
                format!(
                    "wheel_size must list at least one level and every size must be greater than 0, got {:?}",
                    s.wheel_size
                ),
            ));
        }
        let total = s.wheel_size.iter().fold(0u64, |a, &n| a.saturating_add(n));
        if s.wheel_size.len() > MAX_WHEEL_LEVELS || total > MAX_WHEEL_SLOTS {
            return Err(options_error(
                args,
                format!(
                    "wheel_size {:?} is over the limit: at most {MAX_WHEEL_LEVELS} levels and {MAX_WHEEL_SLOTS} slots in all (AimRT's default is [1000, 600])",
                    s.wheel_size
                ),
            ));
        }
        let clock = Clock::new(s.use_system_clock);
        let scaled = matches!(s.pace, Pace::Scaled { .. });
        let inner = Arc::new(Inner {
            type_name: s.type_name,
            name: args.name.to_owned(),
            bound: s.bound,
            origin: clock.origin(),
            clock,
            scaled,
            dt_ns: s.dt_us.saturating_mul(1000),
            acct: Accounting::new(1),
            state: Mutex::new(State {
                pace: s.pace,
                wheel: Wheel::new(s.wheel_size),
                immediate: VecDeque::new(),
                sleeping_until: None,
                sleeping: false,
                stop: false,
                started: false,
            }),
            wake: Condvar::new(),
        });
        Ok(TimeWheel {
            inner,
            factory: args.threads,
            thread_sched_policy: s.thread_sched_policy,
            thread_bind_cpu: s.thread_bind_cpu,
            thread_policy_strict: s.thread_policy_strict,
            handle: Mutex::new(None),
        })
    }

    /// Changes the pace of a scaled timeline at once: the timeline goes on from where it
    /// is now (continuous, never backwards) at `ratio` (≤ 0 stands still).
    pub(crate) fn set_ratio(&self, ratio: f64) {
        let inner = &self.inner;
        let mut st = inner.lock();
        let now = Instant::now();
        let base_pos = st.pace.position(inner.origin, now);
        st.pace = Pace::Scaled {
            ratio: ratio.max(0.0),
            base_real: now,
            base_pos,
        };
        drop(st);
        inner.wake.notify_all();
    }

    /// The ratio of a scaled timeline (1 for real time).
    pub(crate) fn ratio(&self) -> f64 {
        match self.inner.lock().pace {
            Pace::Real => 1.0,
            Pace::Scaled { ratio, .. } => ratio,
        }
    }
}

impl Inner {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn id(&self) -> usize {
        self as *const Inner as usize
    }

    /// The timeline position of the executor time `at` (0 if before the origin).
    fn position_of(&self, at: SystemTime) -> u64 {
        if self.scaled {
            saturating_ns(self.clock.offset_of(at))
        } else {
            saturating_ns(
                self.clock
                    .instant_of(at)
                    .saturating_duration_since(self.origin),
            )
        }
    }

    /// The first tick at or after timeline position `pos`.
    fn tick_at_or_after(&self, pos: u64) -> u64 {
        pos.div_ceil(self.dt_ns)
    }

    /// The last tick the timeline reached at real instant `now`.
    fn tick_reached(&self, st: &State, now: Instant) -> u64 {
        st.pace.position(self.origin, now) / self.dt_ns
    }

    /// The real instant at which the timeline reaches `tick` (`None`: never, it stands
    /// still).
    fn instant_of_tick(&self, st: &State, tick: u64) -> Option<Instant> {
        st.pace
            .instant_of(self.origin, tick.saturating_mul(self.dt_ns))
    }

    /// The executor's time now.
    fn now(&self) -> SystemTime {
        if self.scaled {
            let pos = self.lock().pace.position(self.origin, Instant::now());
            self.clock.at_offset(Duration::from_nanos(pos))
        } else {
            self.clock.now()
        }
    }

    fn refuse(&self, task: Task, err: ExecuteError) -> ExecuteError {
        self.acct
            .refuse_task(Some(task), err, self.type_name, &self.name, &"task refused")
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
                        self.type_name,
                        &self.name,
                        &"the bound executor refused a due task",
                    );
                }
            },
        }
        self.acct.gate.leave();
    }

    /// The wheel thread.
    fn serve(&self) {
        let _mark = Marker::Worker.set(self.id());
        crate::common::precise_timed_waits();
        let mut due = Vec::new();
        loop {
            let mut st = self.lock();
            loop {
                if !st.immediate.is_empty() || st.stop {
                    break;
                }
                let now = Instant::now();
                if st.wheel.current() < self.tick_reached(&st, now) {
                    break;
                }
                st.sleeping = true;
                let next = st
                    .wheel
                    .next_event()
                    .and_then(|tick| Some((tick, self.instant_of_tick(&st, tick)?)));
                st = match next {
                    Some((tick, at)) => {
                        st.sleeping_until = Some(tick);
                        let wait = at.saturating_duration_since(now);
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
            let reached = self.tick_reached(&st, Instant::now());
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
        tracing::info!(target: "aimrt", "{} executor '{}' shut down with {n} task(s) not yet due or never run (a cancelled timer leaves one); they were dropped without running", self.type_name, self.name);
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
        self.inner.type_name
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
        self.inner.now()
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
        let target = inner.tick_at_or_after(inner.position_of(at));
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
                "{} executor '{}' can only be started once, before shutdown",
                self.inner.type_name, self.inner.name
            )));
        }
        let inner = self.inner.clone();
        *handle = Some(self.factory.spawn(
            ThreadSettingsRef {
                name: &self.inner.name,
                sched_policy: &self.thread_sched_policy,
                bind_cpu: &self.thread_bind_cpu,
                strict: self.thread_policy_strict,
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
        let st = i.lock();
        let at = |us: u64| i.origin + Duration::from_micros(us);
        let pos = |us: u64| us * 1000;
        assert_eq!(i.tick_at_or_after(pos(0)), 0);
        assert_eq!(i.tick_at_or_after(pos(1)), 1);
        assert_eq!(i.tick_at_or_after(pos(1000)), 1);
        assert_eq!(i.tick_at_or_after(pos(1001)), 2);
        assert_eq!(i.tick_reached(&st, at(999)), 0);
        assert_eq!(i.tick_reached(&st, at(1000)), 1);
        // Never early: a tick is processed only once its instant is reached, and that
        // instant is at or after every deadline mapped to it.
        for us in [1u64, 999, 1000, 1001, 12_345, 987_654] {
            let tick = i.tick_at_or_after(pos(us));
            let when = i.instant_of_tick(&st, tick).unwrap();
            assert!(when >= at(us), "{us}");
            assert!(when < at(us) + Duration::from_millis(1), "{us}");
        }
        // Deadlines before the origin are due at once.
        let before = i.clock.now() - Duration::from_secs(3600);
        assert_eq!(i.tick_at_or_after(i.position_of(before)), 0);
        drop(st);
        w.shutdown();
    }

    /// A scaled timeline: continuous across ratio changes, still when paused, and the
    /// real instant of a position is never before the timeline reaches it.
    #[test]
    fn a_scaled_timeline_is_continuous_and_never_early() {
        let origin = Instant::now();
        let real = |ms: u64| origin + Duration::from_millis(ms);
        let mut pace = Pace::Scaled {
            ratio: 2.5,
            base_real: origin,
            base_pos: 0,
        };
        assert_eq!(pace.position(origin, real(1000)), 2_500_000_000);
        // Change to 0.5 at 1 s: the position goes on from 2.5 s.
        let base_pos = pace.position(origin, real(1000));
        pace = Pace::Scaled {
            ratio: 0.5,
            base_real: real(1000),
            base_pos,
        };
        assert_eq!(pace.position(origin, real(1000)), 2_500_000_000);
        assert_eq!(pace.position(origin, real(3000)), 3_500_000_000);
        for target in [2_500_000_001u64, 3_000_000_000, 3_123_456_789] {
            let at = pace.instant_of(origin, target).unwrap();
            assert!(pace.position(origin, at) >= target, "{target}");
            assert!(at < real(1000) + Duration::from_secs(2 * 2), "{target}");
        }
        // Paused: stands still, never reaches a later position.
        pace = Pace::Scaled {
            ratio: 0.0,
            base_real: real(3000),
            base_pos: 3_500_000_000,
        };
        assert_eq!(pace.position(origin, real(9000)), 3_500_000_000);
        assert!(pace.instant_of(origin, 3_500_000_001).is_none());
        assert_eq!(pace.instant_of(origin, 3_000_000_000), Some(real(3000)));
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
