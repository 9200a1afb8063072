//! Scenario 1: throughput in three shapes — burst, drain, ~1 µs tasks.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use crate::pools::{self, Target, Variant};

/// Counts completions down and signals the last one.
pub(crate) struct Done {
    left: AtomicUsize,
    tx: crossbeam_channel::Sender<()>,
}

impl Done {
    pub(crate) fn new(n: usize) -> (Arc<Done>, crossbeam_channel::Receiver<()>) {
        let (tx, rx) = crossbeam_channel::bounded(1);
        (
            Arc::new(Done {
                left: AtomicUsize::new(n),
                tx,
            }),
            rx,
        )
    }

    #[inline]
    pub(crate) fn one(&self) {
        if self.left.fetch_sub(1, Ordering::AcqRel) == 1 {
            let _ = self.tx.send(());
        }
    }
}

/// Waits for the last completion; a hang is a failed run, not a frozen harness.
fn wait(rx: &crossbeam_channel::Receiver<()>, what: &str) {
    rx.recv_timeout(Duration::from_secs(120))
        .unwrap_or_else(|_| panic!("{what}: tasks did not complete within 120 s"));
}

/// A loop that takes about 1 µs, calibrated once.
pub(crate) fn spin_iterations_per_us() -> u64 {
    let mut n = 1000u64;
    loop {
        let t = Instant::now();
        spin(n);
        let ns = t.elapsed().as_nanos() as u64;
        if ns > 2_000_000 {
            return (n * 1000 / ns).max(1);
        }
        n *= 2;
    }
}

#[inline(never)]
pub(crate) fn spin(iterations: u64) -> u64 {
    let mut x = 0u64;
    for i in 0..iterations {
        x = std::hint::black_box(x.wrapping_mul(31).wrapping_add(i));
    }
    x
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Shape {
    Burst,
    Drain,
    Work,
}

impl Shape {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Shape::Burst => "burst",
            Shape::Drain => "drain",
            Shape::Work => "work_1us",
        }
    }
}

/// Tasks per second for one fresh target of `variant`.
pub(crate) fn measure(variant: &Variant, shape: Shape, n: usize, spin_per_us: u64) -> f64 {
    let target = (variant.make)();
    // Warm-up.
    burst(&target, 10_000, variant.name);
    let rate = match shape {
        Shape::Burst => burst(&target, n, variant.name),
        Shape::Drain => gated(&target, variant.workers, n, variant.name).drain_rate,
        Shape::Work => work(&target, n, spin_per_us, variant.name),
    };
    target.stop();
    rate
}

/// Tasks per second for a burst of `n` tiny tasks on `t` (also the warm-up of other scenarios).
pub(crate) fn measure_burst_on(t: &Target, n: usize) -> f64 {
    burst(t, n, "warm-up")
}

fn burst(t: &Target, n: usize, what: &str) -> f64 {
    let (done, rx) = Done::new(n);
    let start = Instant::now();
    for _ in 0..n {
        let d = done.clone();
        t.submit(move || d.one());
    }
    wait(&rx, what);
    n as f64 / start.elapsed().as_secs_f64()
}

fn work(t: &Target, n: usize, spin_per_us: u64, what: &str) -> f64 {
    let (done, rx) = Done::new(n);
    let start = Instant::now();
    for _ in 0..n {
        let d = done.clone();
        t.submit(move || {
            std::hint::black_box(spin(spin_per_us));
            d.one();
        });
    }
    wait(&rx, what);
    n as f64 / start.elapsed().as_secs_f64()
}

/// What one gated round measured.
pub(crate) struct Gated {
    /// Nanoseconds per `execute` while every worker is blocked: the caller's cost alone.
    pub(crate) enqueue_ns: f64,
    /// Tasks per second from release until the last one ran.
    pub(crate) drain_rate: f64,
}

/// Queues `n` tasks behind one blocked task per worker, then releases them.
pub(crate) fn gated(t: &Target, workers: usize, n: usize, what: &str) -> Gated {
    let gate = Arc::new((Mutex::new(false), Condvar::new()));
    let (started, started_rx) = Done::new(workers);
    for _ in 0..workers {
        let g = gate.clone();
        let s = started.clone();
        t.submit(move || {
            s.one();
            let (open, cv) = &*g;
            let mut o = open.lock().unwrap_or_else(|e| e.into_inner());
            while !*o {
                o = cv.wait(o).unwrap_or_else(|e| e.into_inner());
            }
        });
    }
    wait(&started_rx, what);
    let (done, rx) = Done::new(n);
    let enqueue = Instant::now();
    for _ in 0..n {
        let d = done.clone();
        t.submit(move || d.one());
    }
    let enqueue_ns = enqueue.elapsed().as_nanos() as f64 / n as f64;
    let start = Instant::now();
    {
        let (open, cv) = &*gate;
        *open.lock().unwrap_or_else(|e| e.into_inner()) = true;
        cv.notify_all();
    }
    wait(&rx, what);
    Gated {
        enqueue_ns,
        drain_rate: n as f64 / start.elapsed().as_secs_f64(),
    }
}

/// Every variant of the throughput scenario, in interleaving order.
pub(crate) fn variants() -> Vec<Variant> {
    vec![
        Variant {
            name: "crossbeam(1)",
            workers: 1,
            make: pools::crossbeam1,
        },
        Variant {
            name: "ring(1)",
            workers: 1,
            make: pools::ring1,
        },
        Variant {
            name: SWAP1,
            workers: 1,
            make: pools::swap_queue1,
        },
        Variant {
            name: "simple_thread",
            workers: 1,
            make: pools::simple_thread,
        },
        Variant {
            name: "asio_thread(1)",
            workers: 1,
            make: pools::asio_thread1,
        },
        Variant {
            name: "crossbeam(2)",
            workers: 2,
            make: pools::crossbeam2,
        },
        Variant {
            name: "ring(2)",
            workers: 2,
            make: pools::ring2,
        },
        Variant {
            name: SWAP2,
            workers: 2,
            make: pools::swap_queue2,
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
            name: "tokio(2)",
            workers: 2,
            make: pools::tokio2,
        },
        Variant {
            name: "rayon(2)",
            workers: 2,
            make: pools::rayon2,
        },
        Variant {
            name: "naive strand",
            workers: 1,
            make: pools::naive_strand,
        },
        Variant {
            name: "asio_strand",
            workers: 1,
            make: pools::asio_strand,
        },
    ]
}

/// How each throughput baseline works, printed with the results.
pub(crate) const BASELINES: &str = "\
Baselines (boxed closures, as each design would run them):
- crossbeam(n): one unbounded crossbeam channel, n threads blocking in `recv`.
- ring(n): a lock-free `SegQueue` (one CAS per push and pop), n threads popping one job at a time; an idle thread spins and yields (crossbeam `Backoff`), then sleeps on a condvar; a producer locks and notifies only while one sleeps.
- swap queue(n) [AimRT model]: AimRT's simple_thread: mutex + VecDeque + condvar, notify_one on every push; the worker swaps the whole queue out (with 2 workers each takes len/2) and runs it outside the lock.
- tokio(2), rayon(2): `spawn` on a 2-thread runtime / pool.
- naive strand: a mutex-protected queue drained one job per lock by a task on crossbeam(2).
Best raw queue(n): per round, the faster of crossbeam(n) and ring(n).
";

/// AimRT's `simple_thread` design (a swap queue) with one and two workers: the AimRT
/// model each of our executors is held to.
pub(crate) const SWAP1: &str = "swap queue(1) [AimRT simple_thread model]";
pub(crate) const SWAP2: &str = "swap queue(2) [AimRT simple_thread model]";

/// The raw queues of each thread count; per round, the faster one is "the best raw queue".
pub(crate) fn raw_queues(threads: usize) -> [&'static str; 2] {
    if threads == 1 {
        ["crossbeam(1)", "ring(1)"]
    } else {
        ["crossbeam(2)", "ring(2)"]
    }
}

/// Issue 21's throughput targets, in burst and drain: each executor, its AimRT-model
/// baseline (at least [`MODEL_TARGET`]×), and its thread count (at least
/// [`RAW_TARGET`]× the best raw queue with as many threads). The strand serialises, so
/// it is held to one thread.
pub(crate) const KINDS: &[(&str, &str, usize)] = &[
    ("simple_thread", SWAP1, 1),
    ("asio_thread(1)", SWAP1, 1),
    ("asio_thread(2)", SWAP2, 2),
    ("tbb_thread(2)", SWAP2, 2),
    ("asio_strand", "naive strand", 1),
];
pub(crate) const MODEL_TARGET: f64 = 1.2;
pub(crate) const RAW_TARGET: f64 = 0.9;
/// work_1us: each executor against crossbeam with its thread count (kept from issue 5).
pub(crate) const WORK_TARGET: f64 = 0.9;

/// Ratios printed for reference beside the targets.
pub(crate) const PAIRS: &[(&str, &str)] = &[
    ("simple_thread", "crossbeam(1)"),
    ("asio_thread(1)", "crossbeam(1)"),
    ("asio_thread(2)", "crossbeam(2)"),
    ("tbb_thread(2)", "crossbeam(2)"),
    ("ring(1)", "crossbeam(1)"),
    ("ring(2)", "crossbeam(2)"),
    ("asio_thread(2)", "tokio(2)"),
    ("tbb_thread(2)", "tokio(2)"),
    ("asio_thread(2)", "rayon(2)"),
    ("tokio(2)", "crossbeam(2)"),
    ("rayon(2)", "crossbeam(2)"),
    ("asio_strand", "naive strand"),
];
