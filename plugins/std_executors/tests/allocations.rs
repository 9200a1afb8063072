//! Steady-state allocations of the executors (issue 21: a small task costs no allocation).
//! A test binary of its own, because it counts every allocation of the process.

use std::alloc::System;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use aimrt_plugin_api::{ExecutorArgs, ExecutorRef, ThreadFactory};
use stats_alloc::{Region, StatsAlloc, INSTRUMENTED_SYSTEM};

#[global_allocator]
static GLOBAL: &StatsAlloc<System> = &INSTRUMENTED_SYSTEM;

fn make(ty: &str, name: &str, options: &str, bound: Vec<Option<ExecutorRef>>) -> ExecutorRef {
    aimrt_std_executors::create_executor(
        ty,
        ExecutorArgs {
            name,
            options_json: options,
            location: "test",
            bound,
            threads: ThreadFactory::plain(),
        },
    )
    .unwrap()
}

/// Posts `n` closures capturing three words and waits (without allocating) until all ran.
fn burst(e: ExecutorRef, n: u64) {
    let done = Arc::new(AtomicU64::new(0));
    for i in 0..n {
        let (d, a, b) = (done.clone(), i, i ^ 1);
        e.execute(move || {
            std::hint::black_box((a, b));
            d.fetch_add(1, Ordering::Release);
        })
        .unwrap();
    }
    let end = Instant::now() + Duration::from_secs(20);
    while done.load(Ordering::Acquire) < n {
        assert!(Instant::now() < end, "{}: tasks did not finish", e.name());
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[test]
fn a_small_task_allocates_nothing_once_the_queues_have_grown() {
    const N: u64 = 100_000;
    let pool = make("asio_thread", "pool", r#"{"thread_num": 2}"#, vec![]);
    let executors = [
        make(
            "simple_thread",
            "simple",
            r#"{"queue_threshold": 4294967295}"#,
            vec![],
        ),
        make("asio_thread", "asio1", r#"{"thread_num": 1}"#, vec![]),
        make(
            "tbb_thread",
            "tbb2",
            r#"{"thread_num": 2, "queue_threshold": 4294967295}"#,
            vec![],
        ),
        pool,
        make("asio_strand", "strand", "{}", vec![Some(pool)]),
    ];
    for e in executors {
        // Grows the queues' buffers to what a burst of N needs.
        burst(e, N);
        let region = Region::new(GLOBAL);
        burst(e, N);
        let allocations = region.change().allocations as u64;
        eprintln!("{}: {allocations} allocations for {N} tasks", e.name());
        // A channel of 31-slot blocks made about N / 31 (3 200) here; a strand whose drains
        // each grew a fresh swap buffer made 200 to 1 050. Today each makes one or two.
        assert!(
            allocations < 50,
            "{}: {allocations} allocations for {N} tasks",
            e.name()
        );
    }
    for e in executors.iter().rev() {
        e.raw().shutdown();
    }
}
