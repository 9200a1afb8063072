//! Scenario 2: wake-up latency of an idle executor, and scenario 3: timer overshoot.

use std::collections::BinaryHeap;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use crate::pools::{self, Target, Variant};
use crate::stats::percentile;

/// Percentiles in microseconds.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub(crate) struct Percentiles {
    pub(crate) p50: f64,
    pub(crate) p99: f64,
    pub(crate) p999: f64,
    pub(crate) max: f64,
    pub(crate) min: f64,
}

pub(crate) fn percentiles(mut v: Vec<f64>) -> Percentiles {
    v.sort_by(f64::total_cmp);
    Percentiles {
        p50: percentile(&v, 50.0),
        p99: percentile(&v, 99.0),
        p999: percentile(&v, 99.9),
        max: v.last().copied().unwrap_or(f64::NAN),
        min: v.first().copied().unwrap_or(f64::NAN),
    }
}

/// Posts one task `samples` times, 200 µs apart, to an idle target; µs from post to start.
pub(crate) fn wake(variant: &Variant, samples: usize) -> Percentiles {
    let target = (variant.make)();
    let (tx, rx) = crossbeam_channel::bounded::<Instant>(1);
    let mut out = Vec::with_capacity(samples);
    for i in 0..samples + 100 {
        std::thread::sleep(Duration::from_micros(200));
        let tx = tx.clone();
        let posted = Instant::now();
        target.submit(move || {
            let _ = tx.send(Instant::now());
        });
        let started = rx
            .recv_timeout(Duration::from_secs(10))
            .unwrap_or_else(|_| panic!("{}: a posted task did not run within 10 s", variant.name));
        if i >= 100 {
            out.push(started.duration_since(posted).as_secs_f64() * 1e6);
        }
    }
    target.stop();
    percentiles(out)
}

/// Whether `name` (a wake or timer variant) is one of our executors, not a baseline.
pub(crate) fn is_executor(name: &str) -> bool {
    matches!(
        name,
        "simple_thread" | "asio_thread(1)" | "asio_thread(2)" | "tbb_thread(2)" | "asio_strand"
    ) || name.starts_with("time_wheel")
}

pub(crate) fn wake_variants() -> Vec<Variant> {
    vec![
        Variant {
            name: "condvar(1)",
            workers: 1,
            make: pools::condvar1,
        },
        Variant {
            name: "crossbeam(1)",
            workers: 1,
            make: pools::crossbeam1,
        },
        Variant {
            name: "simple_thread",
            workers: 1,
            make: pools::simple_thread,
        },
        Variant {
            name: "asio_thread(2)",
            workers: 2,
            make: pools::asio_thread2,
        },
        Variant {
            name: "tbb_thread(2)",
            workers: 2,
            make: pools::tbb_thread2,
        },
        Variant {
            name: "asio_strand",
            workers: 1,
            make: pools::asio_strand,
        },
    ]
}

/// Deadlines (earliest first), the jobs by id, and the stop flag.
type HeapState = (
    BinaryHeap<std::cmp::Reverse<(Instant, u64)>>,
    Vec<Option<Box<dyn FnOnce() + Send>>>,
    bool,
);

/// A thread serving a binary heap of deadlines with a condvar: the timer baseline.
pub(crate) struct HeapTimer {
    shared: Arc<(Mutex<HeapState>, Condvar)>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl HeapTimer {
    fn new() -> HeapTimer {
        let shared: Arc<(Mutex<HeapState>, Condvar)> = Arc::new((
            Mutex::new((BinaryHeap::new(), Vec::new(), false)),
            Condvar::new(),
        ));
        let s = shared.clone();
        let thread = std::thread::spawn(move || {
            let (m, cv) = &*s;
            let mut g = m.lock().unwrap_or_else(|e| e.into_inner());
            loop {
                if g.2 {
                    return;
                }
                let now = Instant::now();
                match g.0.peek().copied() {
                    Some(std::cmp::Reverse((at, id))) if at <= now => {
                        g.0.pop();
                        let job = g.1[id as usize].take();
                        drop(g);
                        if let Some(job) = job {
                            job();
                        }
                        g = m.lock().unwrap_or_else(|e| e.into_inner());
                    }
                    Some(std::cmp::Reverse((at, _))) => {
                        g = cv
                            .wait_timeout(g, at - now)
                            .unwrap_or_else(|e| e.into_inner())
                            .0;
                    }
                    None => g = cv.wait(g).unwrap_or_else(|e| e.into_inner()),
                }
            }
        });
        HeapTimer {
            shared,
            thread: Some(thread),
        }
    }

    fn after(&self, d: Duration, f: impl FnOnce() + Send + 'static) {
        let (m, cv) = &*self.shared;
        let mut g = m.lock().unwrap_or_else(|e| e.into_inner());
        let id = g.1.len() as u64;
        g.1.push(Some(Box::new(f)));
        g.0.push(std::cmp::Reverse((Instant::now() + d, id)));
        cv.notify_one();
    }
}

impl Drop for HeapTimer {
    fn drop(&mut self) {
        let (m, cv) = &*self.shared;
        m.lock().unwrap_or_else(|e| e.into_inner()).2 = true;
        cv.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The state of [`TimerfdTimer`]: deadlines, jobs, the deadline the timerfd is armed
/// for, and the stop flag.
struct TimerfdState {
    heap: BinaryHeap<std::cmp::Reverse<(Instant, u64)>>,
    jobs: Vec<Option<Box<dyn FnOnce() + Send>>>,
    armed: Option<Instant>,
    stop: bool,
}

/// A thread that sleeps in `read` on a timerfd armed (absolute, `CLOCK_MONOTONIC`) for the
/// earliest deadline of a binary heap: what asio's `steady_timer` does under epoll. A new
/// earlier deadline re-arms the timerfd from the submitting thread, so no second wake-up
/// channel is needed.
pub(crate) struct TimerfdTimer {
    shared: Arc<(Mutex<TimerfdState>, nix::sys::timerfd::TimerFd)>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// `at` as an absolute `CLOCK_MONOTONIC` time (what `Instant` measures on Linux).
fn monotonic(at: Instant) -> nix::sys::time::TimeSpec {
    use nix::sys::time::TimeValLike;
    let now_ts = nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
        .unwrap_or_else(|_| nix::sys::time::TimeSpec::zero());
    let now = Instant::now();
    let ahead = at.saturating_duration_since(now).as_nanos() as i64;
    now_ts + nix::sys::time::TimeSpec::nanoseconds(ahead)
}

fn arm(fd: &nix::sys::timerfd::TimerFd, at: Instant) {
    use nix::sys::timerfd::{Expiration, TimerSetTimeFlags};
    // A zero value would disarm: fire at least one nanosecond after the epoch.
    let ts = monotonic(at).max(nix::sys::time::TimeSpec::new(0, 1));
    let _ = fd.set(
        Expiration::OneShot(ts),
        TimerSetTimeFlags::TFD_TIMER_ABSTIME,
    );
}

impl TimerfdTimer {
    fn new() -> TimerfdTimer {
        use nix::sys::timerfd::{ClockId, TimerFd, TimerFlags};
        let fd =
            TimerFd::new(ClockId::CLOCK_MONOTONIC, TimerFlags::empty()).expect("a timerfd (Linux)");
        let shared = Arc::new((
            Mutex::new(TimerfdState {
                heap: BinaryHeap::new(),
                jobs: Vec::new(),
                armed: None,
                stop: false,
            }),
            fd,
        ));
        let s = shared.clone();
        let thread = std::thread::spawn(move || {
            let (m, fd) = &*s;
            loop {
                let _ = fd.wait();
                let mut due = Vec::new();
                {
                    let mut g = m.lock().unwrap_or_else(|e| e.into_inner());
                    if g.stop {
                        return;
                    }
                    let now = Instant::now();
                    while let Some(std::cmp::Reverse((at, id))) = g.heap.peek().copied() {
                        if at > now {
                            break;
                        }
                        g.heap.pop();
                        due.extend(g.jobs[id as usize].take());
                    }
                    g.armed = g.heap.peek().map(|std::cmp::Reverse((at, _))| *at);
                    if let Some(at) = g.armed {
                        arm(fd, at);
                    }
                }
                for job in due {
                    job();
                }
            }
        });
        TimerfdTimer {
            shared,
            thread: Some(thread),
        }
    }

    fn after(&self, d: Duration, f: impl FnOnce() + Send + 'static) {
        let (m, fd) = &*self.shared;
        let mut g = m.lock().unwrap_or_else(|e| e.into_inner());
        let at = Instant::now() + d;
        let id = g.jobs.len() as u64;
        g.jobs.push(Some(Box::new(f)));
        g.heap.push(std::cmp::Reverse((at, id)));
        if g.armed.is_none_or(|armed| at < armed) {
            g.armed = Some(at);
            arm(fd, at);
        }
    }
}

impl Drop for TimerfdTimer {
    fn drop(&mut self) {
        let (m, fd) = &*self.shared;
        m.lock().unwrap_or_else(|e| e.into_inner()).stop = true;
        arm(fd, Instant::now());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// How a timer variant schedules `f` after `d`.
pub(crate) enum TimerTarget {
    Executor(Target),
    Heap(HeapTimer),
    Timerfd(TimerfdTimer),
    Tokio(tokio::runtime::Runtime),
}

impl TimerTarget {
    fn after(&self, d: Duration, f: impl FnOnce() + Send + 'static) {
        match self {
            TimerTarget::Executor(t) => {
                let e = t.executor().expect("timer variants are executors");
                if e.execute_after(d, f).is_err() {
                    crate::pools::REFUSED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
            }
            TimerTarget::Heap(h) => h.after(d, f),
            TimerTarget::Timerfd(t) => t.after(d, f),
            TimerTarget::Tokio(rt) => {
                rt.spawn(async move {
                    tokio::time::sleep(d).await;
                    f();
                });
            }
        }
    }

    fn stop(self) {
        match self {
            TimerTarget::Executor(t) => t.stop(),
            TimerTarget::Heap(h) => drop(h),
            TimerTarget::Timerfd(t) => drop(t),
            TimerTarget::Tokio(rt) => rt.shutdown_background(),
        }
    }
}

pub(crate) struct TimerVariant {
    pub(crate) name: &'static str,
    pub(crate) make: fn() -> TimerTarget,
}

/// How each timer baseline works, printed with the results.
pub(crate) const TIMER_BASELINES: &str = "\
Baselines: heap timer thread: a binary heap of deadlines and one thread in `Condvar::wait_timeout` (kernel default timer slack); \
timerfd timer thread: the same heap and one thread in `read` on a timerfd armed absolute on CLOCK_MONOTONIC, as asio's steady_timer under epoll; \
tokio::time::sleep on a 2-thread runtime.
";

/// How each wake baseline works, printed with the results.
pub(crate) const WAKE_BASELINES: &str = "\
Baselines: condvar(1): one thread in `Condvar::wait` on a mutex-protected queue, notified on every push; crossbeam(1): one thread in crossbeam's `recv`.
";

pub(crate) fn timer_variants() -> Vec<TimerVariant> {
    vec![
        TimerVariant {
            name: "heap timer thread",
            make: || TimerTarget::Heap(HeapTimer::new()),
        },
        TimerVariant {
            name: "timerfd timer thread",
            make: || TimerTarget::Timerfd(TimerfdTimer::new()),
        },
        TimerVariant {
            name: "tokio::time::sleep",
            make: || match pools::tokio2() {
                Target::Tokio(rt) => TimerTarget::Tokio(rt),
                _ => unreachable!("tokio2 builds a tokio runtime"),
            },
        },
        TimerVariant {
            name: "asio_thread(1)",
            make: || TimerTarget::Executor(pools::asio_thread1()),
        },
        TimerVariant {
            name: "asio_strand",
            make: || TimerTarget::Executor(pools::asio_strand()),
        },
        TimerVariant {
            name: "time_wheel dt 100us",
            make: || TimerTarget::Executor(pools::time_wheel_100()),
        },
        TimerVariant {
            name: "time_wheel dt 1000us",
            make: || TimerTarget::Executor(pools::time_wheel_1000()),
        },
    ]
}

/// A small xorshift for the submission phase.
fn next_random(state: &mut u64) -> u64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    *state
}

/// `samples` timers of `delay`, with a random phase in [0, 1 ms) before each; µs of
/// overshoot (negative = fired early), in firing order. Up to `in_flight` timers run at
/// once.
pub(crate) fn overshoot(
    variant: &TimerVariant,
    delay: Duration,
    samples: usize,
    in_flight: usize,
) -> Vec<f64> {
    let target = (variant.make)();
    let (tx, rx) = crossbeam_channel::unbounded::<(Instant, Instant)>();
    let mut seed = 0x9E37_79B9_7F4A_7C15u64 ^ Instant::now().elapsed().as_nanos() as u64;
    let mut out = Vec::with_capacity(samples);
    let mut pending = 0usize;
    let mut sent = 0usize;
    while out.len() < samples {
        while pending < in_flight && sent < samples {
            let phase = next_random(&mut seed) % 1000;
            std::thread::sleep(Duration::from_micros(phase));
            let tx = tx.clone();
            let deadline = Instant::now() + delay;
            target.after(delay, move || {
                let _ = tx.send((deadline, Instant::now()));
            });
            pending += 1;
            sent += 1;
        }
        let (deadline, fired) = rx
            .recv_timeout(delay + Duration::from_secs(10))
            .unwrap_or_else(|_| {
                panic!(
                    "{}: a timer did not fire within 10 s of its deadline",
                    variant.name
                )
            });
        pending -= 1;
        let us = if fired >= deadline {
            fired.duration_since(deadline).as_secs_f64() * 1e6
        } else {
            -(deadline.duration_since(fired).as_secs_f64() * 1e6)
        };
        out.push(us);
    }
    target.stop();
    out
}

/// A timer's lateness while another worker of its pool is busy: on an `asio_thread` with
/// two workers, timed task A (due in 2 ms) runs 20 ms; timed task B is due 3 ms after A.
/// µs of B's lateness. With the lead handed to the idle worker, B runs on time; without,
/// it would wait for A (about 17 ms late).
pub(crate) fn busy_worker_lateness(samples: usize) -> Percentiles {
    let e = pools::executor("asio_thread", "asio2_busy", r#"{"thread_num": 2}"#, vec![]);
    let (tx, rx) = crossbeam_channel::unbounded::<(Instant, Instant)>();
    let mut out = Vec::with_capacity(samples);
    for _ in 0..samples {
        let a_done = crossbeam_channel::bounded::<()>(1);
        let done = a_done.0.clone();
        e.execute_after(Duration::from_millis(2), move || {
            std::thread::sleep(Duration::from_millis(20));
            let _ = done.send(());
        })
        .expect("asio_thread takes timers");
        let tx = tx.clone();
        let deadline = Instant::now() + Duration::from_millis(5);
        e.execute_after(Duration::from_millis(5), move || {
            let _ = tx.send((deadline, Instant::now()));
        })
        .expect("asio_thread takes timers");
        let (deadline, fired) = rx
            .recv_timeout(Duration::from_secs(10))
            .expect("B fired within 10 s");
        out.push(fired.saturating_duration_since(deadline).as_secs_f64() * 1e6);
        let _ = a_done.1.recv_timeout(Duration::from_secs(10));
    }
    e.raw().shutdown();
    percentiles(out)
}
