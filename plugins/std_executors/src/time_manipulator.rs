//! `time_manipulator`: a timing wheel on scaled time. Its `now()` starts at the system
//! time of its creation and then flows at the time ratio; timed tasks (`execute_at`,
//! `execute_after`, timers, `schedule_after`) fire when *that* time reaches their
//! deadline, on the first tick (`dt_us` of scaled time) at or after it, and run on the
//! bound executor. The ratio is exact (2.5 is 2.5, unlike AimRT, which truncates it),
//! a ratio ≤ 0 pauses, and a change applies at once with `now()` continuous.

use std::sync::Arc;
use std::time::{Instant, SystemTime};

use aimrt_plugin_api::{Error, ExecuteError, Executor, ExecutorArgs, ExecutorStats, Task};
use serde::Deserialize;

use crate::common::options_error;
use crate::time_wheel::{Pace, Setup, TimeWheel};

/// The largest ratio accepted: a million times real time.
pub const MAX_TIME_RATIO: f64 = 1e6;

/// Why a time ratio was refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum TimeRatioError {
    /// NaN or an infinity.
    #[error("time ratio {0} is not a finite number; give a number such as 0.5, 1 or 2.5")]
    NotFinite(f64),
    /// Above [`MAX_TIME_RATIO`] (both in scientific notation: `1e308` would otherwise be
    /// written with its 309 digits).
    #[error("time ratio {ratio:e} is above the limit of {max:e}")]
    TooLarge {
        /// The ratio asked for.
        ratio: f64,
        /// The limit.
        max: f64,
    },
}

/// The options of AimRT's `time_manipulator`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct TimeManipulatorOptions {
    #[serde(default)]
    bind_executor: String,
    #[serde(default = "crate::time_wheel::default_dt_us")]
    dt_us: u64,
    #[serde(default = "default_init_ratio")]
    init_ratio: f64,
    #[serde(default = "crate::time_wheel::default_wheel_size")]
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

fn default_init_ratio() -> f64 {
    1.0
}

/// Checks a time ratio: finite and at most [`MAX_TIME_RATIO`]. Returns the ratio the
/// executor will run at (a negative ratio pauses, as 0).
///
/// ```
/// use aimrt_std_executors::check_time_ratio;
/// assert_eq!(check_time_ratio(2.5), Ok(2.5));
/// assert_eq!(check_time_ratio(-1.0), Ok(0.0));
/// assert!(check_time_ratio(f64::NAN).is_err());
/// assert_eq!(
///     check_time_ratio(2.5e6).unwrap_err().to_string(),
///     "time ratio 2.5e6 is above the limit of 1e6"
/// );
/// ```
pub fn check_time_ratio(ratio: f64) -> Result<f64, TimeRatioError> {
    if !ratio.is_finite() {
        return Err(TimeRatioError::NotFinite(ratio));
    }
    if ratio > MAX_TIME_RATIO {
        return Err(TimeRatioError::TooLarge {
            ratio,
            max: MAX_TIME_RATIO,
        });
    }
    Ok(ratio.max(0.0))
}

/// A `time_manipulator` executor: the handle its plugin's control service uses.
pub struct TimeManipulator {
    wheel: TimeWheel,
}

impl std::fmt::Debug for TimeManipulator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TimeManipulator")
            .field("name", &self.wheel.name())
            .field("time_ratio", &self.time_ratio())
            .finish()
    }
}

/// Builds a `time_manipulator` (not started); `args.bound[0]` is the required
/// `bind_executor`.
///
/// ```
/// use aimrt_plugin_api::{Executor, ExecutorArgs, ThreadFactory};
/// let pool = aimrt_std_executors::create_executor("simple_thread", ExecutorArgs {
///     name: "pool", options_json: "null", location: "example",
///     bound: Vec::new(), threads: ThreadFactory::plain(),
/// }).unwrap();
/// let sim = aimrt_std_executors::create_time_manipulator(ExecutorArgs {
///     name: "sim", options_json: r#"{"bind_executor": "pool", "init_ratio": 2.5}"#,
///     location: "example", bound: vec![Some(pool)], threads: ThreadFactory::plain(),
/// }).unwrap();
/// assert_eq!(sim.time_ratio(), 2.5);
/// assert_eq!(sim.set_time_ratio(-3.0), Ok(0.0)); // paused
/// assert!(sim.set_time_ratio(f64::INFINITY).is_err());
/// assert_eq!(sim.time_ratio(), 0.0);
/// sim.shutdown();
/// pool.raw().shutdown();
/// ```
pub fn create_time_manipulator(args: ExecutorArgs<'_>) -> Result<Arc<TimeManipulator>, Error> {
    let o: TimeManipulatorOptions = args.read_options()?;
    if o.bind_executor.is_empty() {
        return Err(options_error(
            &args,
            "bind_executor is required: name the executor that runs the tasks (e.g. an asio_thread)",
        ));
    }
    let Some(bound) = args.bound.first().copied().flatten() else {
        return Err(options_error(
            &args,
            format!("bind_executor '{}' was not resolved", o.bind_executor),
        ));
    };
    let ratio = check_time_ratio(o.init_ratio)
        .map_err(|e| options_error(&args, format!("init_ratio: {e}")))?;
    if o.use_system_clock {
        tracing::warn!(target: "aimrt", "time_manipulator executor '{}': use_system_clock: true has no effect; its time starts at the system time of its creation and flows at the time ratio", args.name);
    }
    let wheel = TimeWheel::new(
        &args,
        Setup {
            type_name: "time_manipulator",
            bound: Some(bound),
            dt_us: o.dt_us,
            wheel_size: &o.wheel_size,
            use_system_clock: false,
            pace: Pace::Scaled {
                ratio,
                base_real: Instant::now(),
                base_pos: 0,
            },
            thread_sched_policy: o.thread_sched_policy,
            thread_bind_cpu: o.thread_bind_cpu,
            thread_policy_strict: o.thread_policy_strict,
        },
    )?;
    Ok(Arc::new(TimeManipulator { wheel }))
}

impl TimeManipulator {
    /// Sets the time ratio at once: `now()` goes on from where it is, at `ratio` × real
    /// time (≤ 0 pauses). NaN, infinities and ratios above [`MAX_TIME_RATIO`] are refused
    /// and the ratio stays. Returns the ratio now in effect.
    pub fn set_time_ratio(&self, ratio: f64) -> Result<f64, TimeRatioError> {
        let ratio = check_time_ratio(ratio)?;
        self.wheel.set_ratio(ratio);
        Ok(ratio)
    }

    /// Pauses time (ratio 0): `now()` stands still and no timed task fires.
    pub fn pause(&self) {
        self.wheel.set_ratio(0.0);
    }

    /// The time ratio in effect (0 while paused).
    pub fn time_ratio(&self) -> f64 {
        self.wheel.ratio()
    }
}

impl Executor for TimeManipulator {
    fn type_name(&self) -> &str {
        self.wheel.type_name()
    }
    fn name(&self) -> &str {
        self.wheel.name()
    }
    fn thread_safe(&self) -> bool {
        self.wheel.thread_safe()
    }
    fn is_in_current_executor(&self) -> bool {
        self.wheel.is_in_current_executor()
    }
    fn supports_timer_schedule(&self) -> bool {
        true
    }
    fn now(&self) -> SystemTime {
        self.wheel.now()
    }
    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        self.wheel.execute(task)
    }
    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        self.wheel.execute_at(at, task)
    }
    fn start(&self) -> Result<(), Error> {
        self.wheel.start()
    }
    fn shutdown(&self) {
        self.wheel.shutdown();
    }
    fn stats(&self) -> ExecutorStats {
        self.wheel.stats()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use aimrt_plugin_api::{ExecutorRef, ThreadFactory};
    use std::sync::mpsc;
    use std::time::Duration;

    fn sim(init_ratio: f64) -> (Arc<TimeManipulator>, ExecutorRef, ExecutorRef) {
        let pool = crate::create_executor(
            "simple_thread",
            ExecutorArgs {
                name: "pool",
                options_json: "null",
                location: "test",
                bound: Vec::new(),
                threads: ThreadFactory::plain(),
            },
        )
        .unwrap();
        let tm = create_time_manipulator(ExecutorArgs {
            name: "sim",
            options_json: &format!(
                r#"{{"bind_executor": "pool", "dt_us": 1000, "init_ratio": {init_ratio}}}"#
            ),
            location: "test",
            bound: vec![Some(pool)],
            threads: ThreadFactory::plain(),
        })
        .unwrap();
        tm.start().unwrap();
        let r = ExecutorRef::leak(tm.clone());
        (tm, r, pool)
    }

    #[test]
    fn timed_work_follows_scaled_time_and_stops_while_paused() {
        let (tm, exec, pool) = sim(10.0);
        // 500 ms of simulated time at ratio 10: about 50 ms of real time.
        let (tx, rx) = mpsc::channel();
        let t0 = Instant::now();
        let tx1 = tx.clone();
        exec.execute_after(Duration::from_millis(500), move || {
            tx1.send(()).unwrap();
        })
        .unwrap();
        rx.recv_timeout(Duration::from_secs(5)).unwrap();
        let real = t0.elapsed();
        assert!(
            real >= Duration::from_millis(45) && real < Duration::from_millis(450),
            "{real:?}"
        );
        // Paused: now() stands still and nothing timed runs.
        tm.pause();
        let frozen = exec.now();
        exec.execute_after(Duration::from_millis(10), move || {
            tx.send(()).unwrap();
        })
        .unwrap();
        assert!(rx.recv_timeout(Duration::from_millis(300)).is_err());
        assert_eq!(exec.now(), frozen);
        // Resumed: the task runs and time goes on from where it stood.
        assert_eq!(tm.set_time_ratio(1.0), Ok(1.0));
        rx.recv_timeout(Duration::from_secs(5)).unwrap();
        let gained = exec.now().duration_since(frozen).unwrap();
        assert!(gained < Duration::from_millis(200), "{gained:?}");
        tm.shutdown();
        pool.raw().shutdown();
    }

    #[test]
    fn now_is_continuous_across_ratio_changes() {
        let (tm, exec, pool) = sim(1.0);
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let changer = {
            let (tm, stop) = (tm.clone(), stop.clone());
            std::thread::spawn(move || {
                for r in [3.0, 0.0, 0.25, 1e6, 0.5, -1.0, 2.5].iter().cycle() {
                    if stop.load(std::sync::atomic::Ordering::SeqCst) {
                        break;
                    }
                    tm.set_time_ratio(*r).unwrap();
                    std::thread::sleep(Duration::from_micros(300));
                }
            })
        };
        let mut last = exec.now();
        let end = Instant::now() + Duration::from_millis(300);
        while Instant::now() < end {
            let now = exec.now();
            assert!(now >= last, "now() went backwards: {last:?} -> {now:?}");
            last = now;
        }
        stop.store(true, std::sync::atomic::Ordering::SeqCst);
        changer.join().unwrap();
        tm.shutdown();
        pool.raw().shutdown();
    }

    #[test]
    fn refused_ratios_change_nothing() {
        let (tm, _exec, pool) = sim(2.5);
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e6 + 1.0] {
            assert!(tm.set_time_ratio(bad).is_err(), "{bad}");
            assert_eq!(tm.time_ratio(), 2.5);
        }
        assert_eq!(tm.set_time_ratio(1e6), Ok(1e6));
        assert_eq!(tm.set_time_ratio(-0.5), Ok(0.0));
        assert_eq!(tm.time_ratio(), 0.0);
        tm.shutdown();
        pool.raw().shutdown();
    }

    #[test]
    fn shutdown_while_paused_is_prompt_and_counts_what_was_pending() {
        let (tm, exec, pool) = sim(0.0);
        exec.execute_after(Duration::from_millis(1), || {}).unwrap();
        let t0 = Instant::now();
        tm.shutdown();
        assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
        assert_eq!(tm.stats().dropped_at_shutdown, 1);
        pool.raw().shutdown();
    }

    #[test]
    fn options_are_checked() {
        let args = |options: &'static str, bound: Vec<Option<ExecutorRef>>| ExecutorArgs {
            name: "sim",
            options_json: options,
            location: "test",
            bound,
            threads: ThreadFactory::plain(),
        };
        let err = create_time_manipulator(args("{}", vec![None])).unwrap_err();
        assert!(
            err.to_string().contains("bind_executor is required"),
            "{err}"
        );
        let err =
            create_time_manipulator(args(r#"{"bind_executor": "x"}"#, vec![None])).unwrap_err();
        assert!(err.to_string().contains("not resolved"), "{err}");
    }
}
