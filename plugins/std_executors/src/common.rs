//! Pieces every standard executor shares: the in-flight gate, per-worker counters, the
//! rate-limited warning, the wall-clock-anchored clock and the "which executor runs this
//! thread" markers.

use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant, SystemTime};

use aimrt_plugin_api::{
    Error, ExecuteError, ExecutorArgs, ExecutorStats, RateLimit, Task, TaskOutcome,
};
use crossbeam_utils::CachePadded;

/// The high bit of the gate: set once the executor stops taking work.
const CLOSED: u64 = 1 << 63;

/// Counts tasks in flight (accepted and not yet finished: queued, waiting for their time,
/// or running) and closes for good at shutdown. One relaxed-enough atomic per executor.
///
/// Protocol: a submitter `enter`s before it hands the task over; a worker `leave`s after
/// the task ran (or a timer was dropped). `close` sets [`CLOSED`]; from then on `enter`
/// fails. Because a task is counted before it is queued, "closed and zero" means nothing
/// accepted is left anywhere, and exactly the call that makes it so learns it (`true`),
/// so it can tell the workers to stop.
#[derive(Debug, Default)]
pub(crate) struct Gate {
    count: CachePadded<AtomicU64>,
}

impl Gate {
    /// Counts one more task unless closed or `limit` tasks are already in flight.
    pub(crate) fn enter(&self, limit: u64) -> Result<(), Refusal> {
        let prev = self.count.fetch_add(1, Ordering::AcqRel);
        if prev & CLOSED != 0 {
            return Err(Refusal::ShutDown { last: self.leave() });
        }
        if prev >= limit {
            // Not closed here; a close racing in makes `leave` report the last one.
            return Err(Refusal::QueueFull { last: self.leave() });
        }
        Ok(())
    }

    /// One task finished (or was dropped). `true`: the gate is now closed and empty.
    pub(crate) fn leave(&self) -> bool {
        self.count.fetch_sub(1, Ordering::AcqRel) == CLOSED | 1
    }

    /// `n` tasks finished at once (a worker's batch). `true`: the gate is now closed and
    /// empty.
    pub(crate) fn leave_n(&self, n: u64) -> bool {
        n > 0 && self.count.fetch_sub(n, Ordering::AcqRel) == CLOSED | n
    }

    /// Stops taking work. `true`: nothing was in flight (and this call closed it).
    pub(crate) fn close(&self) -> bool {
        self.count.fetch_or(CLOSED, Ordering::AcqRel) == 0
    }

    /// Whether `close` has been called.
    pub(crate) fn is_closed(&self) -> bool {
        self.count.load(Ordering::Acquire) & CLOSED != 0
    }

    /// Tasks in flight now.
    pub(crate) fn depth(&self) -> u64 {
        self.count.load(Ordering::Acquire) & !CLOSED
    }
}

/// Why [`Gate::enter`] refused; `last` says the refusal's own `leave` emptied a closed gate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Refusal {
    ShutDown { last: bool },
    QueueFull { last: bool },
}

impl Refusal {
    pub(crate) fn error(self) -> ExecuteError {
        match self {
            Refusal::ShutDown { .. } => ExecuteError::ShutDown,
            Refusal::QueueFull { .. } => ExecuteError::QueueFull,
        }
    }

    pub(crate) fn emptied(self) -> bool {
        matches!(
            self,
            Refusal::ShutDown { last: true } | Refusal::QueueFull { last: true }
        )
    }
}

/// What one worker ran; each worker writes only its own (cache-padded) counters.
#[derive(Debug, Default)]
pub(crate) struct WorkerCounters {
    run: AtomicU64,
    panicked: AtomicU64,
}

impl WorkerCounters {
    pub(crate) fn record(&self, outcome: TaskOutcome) {
        self.record_batch(1, u64::from(outcome == TaskOutcome::Panicked));
    }

    /// `run` tasks ran, `panicked` of them panicked (a worker's batch, counted at once).
    pub(crate) fn record_batch(&self, run: u64, panicked: u64) {
        self.run.fetch_add(run, Ordering::Relaxed);
        if panicked > 0 {
            self.panicked.fetch_add(panicked, Ordering::Relaxed);
        }
    }
}

/// The late-timer check of a timer-capable executor: `timeout_alarm_threshold_us` and the
/// rate limit of its warning (`timeout_alarm_interval_ms`).
#[derive(Debug)]
pub(crate) struct LateAlarm {
    threshold: Duration,
    alarm: RateLimit,
}

impl LateAlarm {
    pub(crate) fn new(threshold: Duration, interval_ms: i32) -> LateAlarm {
        LateAlarm {
            threshold,
            alarm: RateLimit::from_millis(interval_ms),
        }
    }

    /// Warns (rate-limited) if a timer due at `due` runs now, past the threshold.
    pub(crate) fn check(&self, label: &str, name: &str, due: Instant) {
        let late = due.elapsed();
        if late > self.threshold {
            if let Some(held) = self.alarm.admit() {
                warn_late(label, name, late, self.threshold, held);
            }
        }
    }
}

/// AimRT's late-timer warning, with how late in milliseconds and how many late timers
/// went unreported since the last warning (the warning is rate-limited by
/// `timeout_alarm_interval_ms`).
pub(crate) fn warn_late(label: &str, name: &str, late: Duration, threshold: Duration, held: u64) {
    tracing::warn!(target: "aimrt", "{}", late_message(label, name, late, threshold, held));
}

fn late_message(label: &str, name: &str, late: Duration, threshold: Duration, held: u64) -> String {
    let also = if held > 0 {
        format!(" ({held} more late timer(s) since the last warning)")
    } else {
        String::new()
    };
    format!("{label} executor '{name}' timer delay too much, error time value '{}', require '{}': a timer ran {:.3} ms late, over timeout_alarm_threshold_us. Perhaps the CPU load is too high{also}", late.as_micros(), threshold.as_micros(), late.as_secs_f64() * 1e3)
}

/// An executor's `queue_threshold` and the warning that comes before it.
#[derive(Debug)]
pub(crate) struct Admission {
    /// Tasks in flight at most (`u64::MAX`: no limit).
    pub(crate) limit: u64,
    /// AimRT warns above 95 % of the limit.
    pub(crate) warn_at: u64,
    /// `threshold_alarm_interval_ms` (negative: silent).
    pub(crate) alarm: RateLimit,
}

impl Admission {
    /// `limit` tasks in flight (`None`: no limit), warning once per `alarm_ms` above 95 %.
    pub(crate) fn new(limit: Option<u64>, alarm_ms: i32) -> Admission {
        let limit = limit.unwrap_or(u64::MAX);
        Admission {
            limit,
            warn_at: limit / 100 * 95 + limit % 100 * 95 / 100,
            alarm: RateLimit::from_millis(alarm_ms),
        }
    }
}

/// Work accounting of one executor: the gate, per-worker counters, and the cold counters.
#[derive(Debug)]
pub(crate) struct Accounting {
    pub(crate) gate: Gate,
    workers: Box<[CachePadded<WorkerCounters>]>,
    refused: AtomicU64,
    dropped: AtomicU64,
    refusal_alarm: RateLimit,
}

impl Accounting {
    pub(crate) fn new(workers: usize) -> Accounting {
        Accounting {
            gate: Gate::default(),
            workers: (0..workers.max(1)).map(|_| Default::default()).collect(),
            refused: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            refusal_alarm: RateLimit::from_millis(1000),
        }
    }

    pub(crate) fn worker(&self, i: usize) -> &WorkerCounters {
        &self.workers[i % self.workers.len()]
    }

    /// Counts a refused task; returns how many were refused so far.
    pub(crate) fn refuse(&self) -> u64 {
        self.refused.fetch_add(1, Ordering::Relaxed) + 1
    }

    /// Drops a refused task, counts it and warns at most once a second, on a limiter of
    /// its own (threshold warnings cannot hide refusals):
    /// `<label> executor '<name>': <what>: <err> (<k> refused since the last report, <n> so far)`.
    pub(crate) fn refuse_task(
        &self,
        task: Option<Task>,
        err: ExecuteError,
        label: &str,
        name: &str,
        what: &dyn std::fmt::Display,
    ) -> ExecuteError {
        drop(task);
        let n = self.refuse();
        if let Some(held) = self.refusal_alarm.admit() {
            tracing::warn!(target: "aimrt", "{label} executor '{name}': {what}: {err} ({} refused since the last report, {n} so far)", held + 1);
        }
        err
    }

    /// Counts `task` in, or refuses it (dropped, counted, a rate-limited line). Above
    /// `warn_at` tasks in flight, `alarm` lets AimRT's "about to reach queue_threshold"
    /// warning through. `Err((error, emptied))`: `emptied` says this refusal's own count
    /// emptied a closed gate, so the caller must tell its workers to stop.
    pub(crate) fn admit(
        &self,
        task: Task,
        limits: &Admission,
        label: &str,
        name: &str,
    ) -> Result<Task, (ExecuteError, bool)> {
        match self.gate.enter(limits.limit) {
            Ok(()) => {
                if limits.limit != u64::MAX
                    && self.gate.depth() > limits.warn_at
                    && limits.alarm.ready()
                {
                    tracing::warn!(target: "aimrt", "{label} executor '{name}': tasks in flight are about to reach queue_threshold: '{} / {}'.", self.gate.depth(), limits.limit);
                }
                Ok(task)
            }
            Err(refusal) => {
                let err = refusal.error();
                // Formatted only if the line is written: a flood of refusals allocates nothing.
                let limit = limits.limit;
                let err = match err {
                    ExecuteError::QueueFull => self.refuse_task(
                        Some(task),
                        err,
                        label,
                        name,
                        &format_args!("queue_threshold '{limit}' reached, task refused"),
                    ),
                    _ => self.refuse_task(Some(task), err, label, name, &"task refused"),
                };
                Err((err, refusal.emptied()))
            }
        }
    }

    /// `start` of an executor whose threads already run: allowed once, never after
    /// shutdown; `started` remembers the first.
    pub(crate) fn start_once(
        &self,
        started: &std::sync::atomic::AtomicBool,
        label: &str,
        name: &str,
    ) -> Result<(), Error> {
        if self.gate.is_closed() || started.swap(true, Ordering::AcqRel) {
            return Err(Error::msg(format!(
                "{label} executor '{name}' can only be started once, before shutdown"
            )));
        }
        Ok(())
    }

    /// Counts a timed task dropped at shutdown.
    pub(crate) fn drop_at_shutdown(&self) {
        self.dropped.fetch_add(1, Ordering::Relaxed);
    }

    pub(crate) fn stats(&self) -> ExecutorStats {
        let (mut run, mut panicked) = (0, 0);
        for w in self.workers.iter() {
            run += w.run.load(Ordering::Relaxed);
            panicked += w.panicked.load(Ordering::Relaxed);
        }
        let depth = self.gate.depth();
        let dropped = self.dropped.load(Ordering::Relaxed);
        ExecutorStats {
            submitted: run + depth + dropped,
            run,
            refused: self.refused.load(Ordering::Relaxed),
            panicked,
            queue_depth: depth,
            dropped_at_shutdown: dropped,
            ..ExecutorStats::default()
        }
    }
}

/// An executor's clock: `use_system_clock: false` (the default) is the system time taken at
/// creation plus monotonic time since, so it never jumps; `true` follows the system clock.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Clock {
    system: bool,
    anchor_sys: SystemTime,
    anchor_mono: Instant,
}

impl Clock {
    pub(crate) fn new(use_system_clock: bool) -> Clock {
        Clock {
            system: use_system_clock,
            anchor_sys: SystemTime::now(),
            anchor_mono: Instant::now(),
        }
    }

    pub(crate) fn now(&self) -> SystemTime {
        if self.system {
            SystemTime::now()
        } else {
            self.anchor_sys + self.anchor_mono.elapsed()
        }
    }

    /// The monotonic instant the clock was anchored at.
    pub(crate) fn origin(&self) -> Instant {
        self.anchor_mono
    }

    /// How far `at` is past the anchor's system time (zero if before it).
    pub(crate) fn offset_of(&self, at: SystemTime) -> Duration {
        at.duration_since(self.anchor_sys).unwrap_or_default()
    }

    /// The system time `d` past the anchor.
    pub(crate) fn at_offset(&self, d: Duration) -> SystemTime {
        self.anchor_sys + d
    }

    /// The monotonic instant at which this clock reads `at` (now, if `at` is past).
    pub(crate) fn instant_of(&self, at: SystemTime) -> Instant {
        let (sys, mono) = if self.system {
            (SystemTime::now(), Instant::now())
        } else {
            (self.anchor_sys, self.anchor_mono)
        };
        match at.duration_since(sys) {
            Ok(ahead) => mono.checked_add(ahead).unwrap_or_else(far_future),
            Err(behind) => mono
                .checked_sub(behind.duration())
                .unwrap_or_else(Instant::now),
        }
    }
}

/// An instant no timer reaches (a deadline beyond what `Instant` holds).
fn far_future() -> Instant {
    Instant::now() + Duration::from_secs(100 * 365 * 24 * 3600)
}

thread_local! {
    /// The executor whose thread this is (pool worker or wheel thread), by address.
    static WORKER_OF: Cell<usize> = const { Cell::new(0) };
    /// The strand whose task runs on this thread now, by address.
    static STRAND: Cell<usize> = const { Cell::new(0) };
}

/// Which marker a [`Mark`] sets.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Marker {
    Worker,
    Strand,
}

impl Marker {
    fn cell(self) -> &'static std::thread::LocalKey<Cell<usize>> {
        match self {
            Marker::Worker => &WORKER_OF,
            Marker::Strand => &STRAND,
        }
    }

    /// Whether the calling thread is marked with `id`.
    pub(crate) fn is(self, id: usize) -> bool {
        self.cell().with(|c| c.get() == id)
    }

    /// Marks the calling thread with `id` until the guard drops (then restores the old).
    pub(crate) fn set(self, id: usize) -> Mark {
        let prev = self.cell().with(|c| c.replace(id));
        Mark { marker: self, prev }
    }
}

/// Restores a thread marker on drop.
#[derive(Debug)]
pub(crate) struct Mark {
    marker: Marker,
    prev: usize,
}

impl Drop for Mark {
    fn drop(&mut self) {
        let prev = self.prev;
        self.marker.cell().with(|c| c.set(prev));
    }
}

/// AimRT's thread naming: `name` for one thread, `name.0`, `name.1`, … for several.
pub(crate) fn worker_name(name: &str, index: usize, count: usize) -> String {
    if count == 1 {
        name.to_owned()
    } else {
        format!("{name}.{index}")
    }
}

/// The error for invalid options of the executor `args` describes.
pub(crate) fn options_error(args: &ExecutorArgs<'_>, message: impl Into<String>) -> Error {
    Error::Options {
        what: format!("options of executor '{}' at {}", args.name, args.location),
        message: message.into(),
    }
}

/// Why another executor refused a task, from the error its handle returned.
pub(crate) fn execute_error(e: Error) -> ExecuteError {
    match e {
        Error::Execute { source, .. } => source,
        _ => ExecuteError::Refused(0),
    }
}

/// Asks the kernel to end this thread's timed waits at their deadline instead of up to
/// 50 µs later (the default timer slack). Threads that wait for timer deadlines call it;
/// a refusal changes nothing but precision, so it is ignored.
pub(crate) fn precise_timed_waits() {
    let _ = nix::sys::prctl::set_timerslack(1);
}

#[cfg(test)]
mod tests {

    #[test]
    fn a_late_timer_warning_says_how_late_and_what_was_left_out() {
        let m = late_message(
            "asio thread",
            "pool",
            Duration::from_micros(12_345),
            Duration::from_micros(10_000),
            0,
        );
        assert!(
            m.contains("error time value '12345', require '10000': a timer ran 12.345 ms late"),
            "{m}"
        );
        let m = late_message(
            "asio strand",
            "s",
            Duration::from_secs(2),
            Duration::from_secs(1),
            7,
        );
        assert!(
            m.ends_with("(7 more late timer(s) since the last warning)"),
            "{m}"
        );
    }

    use super::*;

    #[test]
    fn gate_counts_refuses_and_reports_the_last_leave() {
        let g = Gate::default();
        g.enter(2).unwrap();
        g.enter(2).unwrap();
        assert_eq!(g.enter(2), Err(Refusal::QueueFull { last: false }));
        assert_eq!(g.depth(), 2);
        assert!(!g.close());
        assert!(g.is_closed());
        assert_eq!(g.enter(10), Err(Refusal::ShutDown { last: false }));
        assert!(!g.leave());
        assert!(g.leave());
        assert_eq!(g.enter(10), Err(Refusal::ShutDown { last: true }));
        assert_eq!(g.depth(), 0);
        let empty = Gate::default();
        assert!(empty.close());
        assert_eq!(
            Gate::default().enter(0),
            Err(Refusal::QueueFull { last: false })
        );
    }

    #[test]
    fn gate_under_contention_never_loses_the_last_leave() {
        for _ in 0..50 {
            let g = std::sync::Arc::new(Gate::default());
            let lasts = std::sync::Arc::new(AtomicU64::new(0));
            let threads: Vec<_> = (0..4)
                .map(|_| {
                    let (g, lasts) = (g.clone(), lasts.clone());
                    std::thread::spawn(move || {
                        for _ in 0..1000 {
                            match g.enter(u64::MAX >> 2) {
                                Ok(()) => {
                                    if g.leave() {
                                        lasts.fetch_add(1, Ordering::SeqCst);
                                    }
                                }
                                Err(r) => {
                                    if r.emptied() {
                                        lasts.fetch_add(1, Ordering::SeqCst);
                                    }
                                }
                            }
                        }
                    })
                })
                .collect();
            let closed_empty = g.close();
            for t in threads {
                t.join().unwrap();
            }
            // Exactly the transitions to "closed and empty" were reported: at least one.
            assert_eq!(g.depth(), 0);
            assert!(closed_empty || lasts.load(Ordering::SeqCst) >= 1);
        }
    }

    #[test]
    fn clock_is_wall_anchored_and_maps_back_to_instants() {
        let c = Clock::new(false);
        let drift = c
            .now()
            .duration_since(SystemTime::now())
            .unwrap_or_else(|e| e.duration());
        assert!(drift < Duration::from_millis(50));
        let at = c.now() + Duration::from_millis(300);
        let due = c.instant_of(at);
        let ahead = due.duration_since(Instant::now());
        assert!(ahead > Duration::from_millis(200) && ahead <= Duration::from_millis(300));
        let past = c.instant_of(c.now() - Duration::from_secs(5));
        assert!(past <= Instant::now());
    }

    #[test]
    fn markers_nest_and_restore() {
        assert!(Marker::Worker.is(0));
        {
            let _a = Marker::Worker.set(7);
            assert!(Marker::Worker.is(7));
            {
                let _b = Marker::Strand.set(9);
                assert!(Marker::Strand.is(9) && Marker::Worker.is(7));
            }
            assert!(Marker::Strand.is(0));
        }
        assert!(Marker::Worker.is(0));
    }

    #[test]
    fn workers_are_named_like_aimrt() {
        assert_eq!(worker_name("pool", 0, 1), "pool");
        assert_eq!(worker_name("pool", 1, 2), "pool.1");
    }
}
