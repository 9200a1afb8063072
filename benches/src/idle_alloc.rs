//! Scenario 4: CPU used by an idle executor; scenario 6: allocations per `execute`.

use std::alloc::System;
use std::time::Duration;

use stats_alloc::{Region, StatsAlloc, INSTRUMENTED_SYSTEM};

use crate::pools::{self, Target};
use crate::stats::process_cpu;

#[global_allocator]
static GLOBAL: &StatsAlloc<System> = &INSTRUMENTED_SYSTEM;

/// (name, builder) of every executor measured idle.
/// A named executor builder.
pub(crate) type Named = (&'static str, fn() -> Target);

pub(crate) fn idle_variants() -> Vec<Named> {
    vec![
        ("simple_thread", pools::simple_thread),
        ("tbb_thread(2)", pools::tbb_thread2),
        ("asio_thread(2)", pools::asio_thread2),
        ("asio_strand", pools::asio_strand),
        ("time_wheel dt 100us (empty)", pools::time_wheel_100),
        ("time_wheel dt 1000us (empty)", pools::time_wheel_1000),
    ]
}

/// Percent of one core the process uses over `window` with only `make`'s executor alive,
/// minus the same window with nothing.
pub(crate) fn idle_percent(make: fn() -> Target, window: Duration) -> f64 {
    let base = {
        let c0 = process_cpu();
        std::thread::sleep(window);
        process_cpu() - c0
    };
    let target = make();
    std::thread::sleep(Duration::from_millis(50)); // let threads settle
    let c0 = process_cpu();
    std::thread::sleep(window);
    let used = process_cpu() - c0;
    target.stop();
    ((used - base) / window.as_secs_f64() * 100.0).max(0.0)
}

/// Allocations per `execute` of a closure capturing 3 words, amortised over `n` tasks
/// (queue blocks, wake-ups and worker-side allocations included).
pub(crate) fn allocations_per_execute(make: fn() -> Target, n: usize) -> f64 {
    let target = make();
    let exec = target.executor().expect("an executor");
    let (done, rx) = crate::throughput::Done::new(n);
    // Warm-up: queues reach their working size.
    crate::throughput::measure_burst_on(&target, 10_000);
    let region = Region::new(GLOBAL);
    for i in 0..n {
        let d = done.clone();
        let (a, b) = (i as u64, (i * 7) as u64);
        // Three words: the Arc and two integers.
        if exec
            .execute(move || {
                std::hint::black_box((a, b));
                d.one();
            })
            .is_err()
        {
            crate::pools::REFUSED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }
    let _ = rx.recv_timeout(Duration::from_secs(60));
    let allocs = region.change().allocations as f64;
    target.stop();
    allocs / n as f64
}

/// Allocations made by wrapping and running a 3-word closure as a `Task`.
pub(crate) fn task_allocations() -> (usize, bool) {
    let (a, b, c) = (1u64, 2u64, 3u64);
    let region = Region::new(GLOBAL);
    let task = aimrt_plugin_api::Task::new(move || {
        std::hint::black_box(a + b + c);
    });
    let inline = task.is_inline();
    task.run("bench");
    (region.change().allocations, inline)
}
