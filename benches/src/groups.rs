//! Callback groups: 4 mutually exclusive `events_cbg_group`s on a 2-thread `events_cbg`
//! pool against 4 `asio_strand`s on a 2-thread `asio_thread` — the same promise (each
//! group's tasks one at a time, groups in parallel) from two designs.
//!
//! Four producers, one per group, post `n / 4` tasks each; a task optionally spins about
//! 1 µs. The figure is tasks per second from the first post to the last task's end.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use aimrt_plugin_api::{Executor, ExecutorArgs, ExecutorRef, ThreadFactory};

use crate::pools::REFUSED;
use crate::throughput::spin;

/// 4 groups and how to stop them.
pub(crate) struct Groups {
    pub(crate) name: &'static str,
    pub(crate) groups: Vec<ExecutorRef>,
    stop: Vec<ExecutorRef>,
}

impl Groups {
    pub(crate) fn stop(self) {
        for e in self.groups.iter().chain(&self.stop) {
            e.raw().shutdown();
        }
    }
}

fn args<'a>(
    name: &'a str,
    options_json: &'a str,
    bound: Vec<Option<ExecutorRef>>,
) -> ExecutorArgs<'a> {
    ExecutorArgs {
        name,
        options_json,
        location: "aimrt-bench",
        bound,
        threads: ThreadFactory::plain(),
    }
}

/// `events_cbg` (2 threads) with 4 mutually exclusive groups.
pub(crate) fn cbg() -> Groups {
    let pool = aimrt_cbg_executor::create_pool(args("cbg", r#"{"thread_num": 2}"#, Vec::new()))
        .expect("events_cbg");
    let _ = pool.start();
    let groups = (0..4)
        .map(|i| {
            let name = format!("g{i}");
            let g = aimrt_cbg_executor::create_group(
                &pool,
                args(
                    &name,
                    r#"{"bind_events_cbg": "cbg", "kind": "mutually_exclusive"}"#,
                    Vec::new(),
                ),
            )
            .expect("events_cbg_group");
            ExecutorRef::leak(g)
        })
        .collect();
    Groups {
        name: "4 events_cbg_group",
        groups,
        stop: vec![ExecutorRef::leak(pool)],
    }
}

/// `asio_thread` (2 threads) with 4 `asio_strand`s.
pub(crate) fn strands() -> Groups {
    let pool = aimrt_std_executors::create_executor(
        "asio_thread",
        args("asio", r#"{"thread_num": 2}"#, Vec::new()),
    )
    .expect("asio_thread");
    let groups = (0..4)
        .map(|i| {
            let name = format!("s{i}");
            aimrt_std_executors::create_executor(
                "asio_strand",
                args(
                    &name,
                    r#"{"bind_asio_thread_executor_name": "asio"}"#,
                    vec![Some(pool)],
                ),
            )
            .expect("asio_strand")
        })
        .collect();
    Groups {
        name: "4 asio_strand",
        groups,
        stop: vec![pool],
    }
}

/// Tasks per second for `n` tasks from 4 producers, each task spinning `work` iterations.
/// Also checks that no group ever ran two of its tasks at once.
pub(crate) fn measure(g: &Groups, n: usize, work: u64) -> f64 {
    let done = Arc::new(AtomicUsize::new(0));
    let overlaps = Arc::new(AtomicUsize::new(0));
    let busy: Arc<Vec<AtomicBool>> = Arc::new((0..4).map(|_| AtomicBool::new(false)).collect());
    let start = Instant::now();
    std::thread::scope(|s| {
        for (i, exec) in g.groups.iter().enumerate() {
            let (done, overlaps, busy) = (done.clone(), overlaps.clone(), busy.clone());
            s.spawn(move || {
                for _ in 0..n / 4 {
                    let (finished, overlaps, busy) = (done.clone(), overlaps.clone(), busy.clone());
                    let posted = exec.execute(move || {
                        if busy[i].swap(true, Ordering::Acquire) {
                            overlaps.fetch_add(1, Ordering::Relaxed);
                        }
                        if work > 0 {
                            std::hint::black_box(spin(work));
                        }
                        busy[i].store(false, Ordering::Release);
                        finished.fetch_add(1, Ordering::Release);
                    });
                    if posted.is_err() {
                        REFUSED.fetch_add(1, Ordering::Relaxed);
                        done.fetch_add(1, Ordering::Release);
                    }
                }
            });
        }
    });
    let expected = n / 4 * 4;
    let end = Instant::now() + Duration::from_secs(120);
    while done.load(Ordering::Acquire) < expected {
        assert!(
            Instant::now() < end,
            "{}: tasks did not complete within 120 s",
            g.name
        );
        std::thread::yield_now();
    }
    let rate = expected as f64 / start.elapsed().as_secs_f64();
    assert_eq!(
        overlaps.load(Ordering::Relaxed),
        0,
        "{}: a group ran two tasks at once",
        g.name
    );
    rate
}
