//! Scheduling rules of `events_cbg` pools and `events_cbg_group`s, driven directly (no
//! runtime): exclusion, reentrancy, arrival order, timers and simulated time.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant, SystemTime};

use aimrt_cbg_executor::{create_group, create_pool, CbgExecutor};
use aimrt_plugin_api::{create_timer, Executor, ExecutorArgs, ExecutorRef, ThreadFactory};

const WAIT: Duration = Duration::from_secs(20);

fn args<'a>(name: &'a str, options_json: &'a str) -> ExecutorArgs<'a> {
    ExecutorArgs {
        name,
        options_json,
        location: "test",
        bound: Vec::new(),
        threads: ThreadFactory::plain(),
    }
}

fn pool(threads: u32) -> Arc<CbgExecutor> {
    let options = format!(r#"{{"thread_num": {threads}}}"#);
    let pool = create_pool(args("pool", &options)).unwrap();
    pool.start().unwrap();
    pool
}

fn group(pool: &Arc<CbgExecutor>, name: &str, kind: &str) -> ExecutorRef {
    let options = format!(r#"{{"bind_events_cbg": "pool", "kind": "{kind}"}}"#);
    ExecutorRef::leak(create_group(pool, args(name, &options)).unwrap())
}

/// Polls `done` until it holds or `WAIT` passes.
fn wait_until(what: &str, done: impl Fn() -> bool) {
    let end = Instant::now() + WAIT;
    while !done() {
        assert!(Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// A gate tasks can wait on, with a timeout.
#[derive(Default)]
struct Gate {
    open: Mutex<bool>,
    cv: Condvar,
}

impl Gate {
    fn open(&self) {
        *self.open.lock().unwrap() = true;
        self.cv.notify_all();
    }
    fn wait(&self, timeout: Duration) -> bool {
        let g = self.open.lock().unwrap();
        let (g, _) = self.cv.wait_timeout_while(g, timeout, |o| !*o).unwrap();
        *g
    }
}

#[test]
fn exclusive_groups_never_run_two_callbacks_at_once() {
    let pool = pool(2);
    let groups: Vec<ExecutorRef> = (0..4)
        .map(|i| group(&pool, &format!("g{i}"), "mutually_exclusive"))
        .collect();
    assert!(groups.iter().all(|g| g.thread_safe()));
    let busy: Arc<Vec<AtomicBool>> = Arc::new((0..4).map(|_| AtomicBool::new(false)).collect());
    let overlaps = Arc::new(AtomicUsize::new(0));
    let done = Arc::new(AtomicUsize::new(0));
    let producers: Vec<_> = (0..4)
        .map(|p| {
            let (groups, busy, overlaps, done) =
                (groups.clone(), busy.clone(), overlaps.clone(), done.clone());
            std::thread::spawn(move || {
                for i in 0..2_500 {
                    let g = (p + i) % 4;
                    let (busy, overlaps, done) = (busy.clone(), overlaps.clone(), done.clone());
                    groups[g]
                        .execute(move || {
                            if busy[g].swap(true, Ordering::AcqRel) {
                                overlaps.fetch_add(1, Ordering::Relaxed);
                            }
                            std::hint::black_box((0..200).sum::<u64>());
                            busy[g].store(false, Ordering::Release);
                            done.fetch_add(1, Ordering::Relaxed);
                        })
                        .unwrap();
                }
            })
        })
        .collect();
    for p in producers {
        p.join().unwrap();
    }
    wait_until("10 000 callbacks", || {
        done.load(Ordering::Relaxed) == 10_000
    });
    assert_eq!(
        overlaps.load(Ordering::Relaxed),
        0,
        "an exclusive group ran two callbacks at once"
    );
    // A task is counted as run after its callback returns: the last ones a moment after
    // `done` reached 10 000.
    let run = || groups.iter().map(|g| g.stats().run).sum::<u64>();
    wait_until("10 000 callbacks counted as run", || run() == 10_000);
    assert_eq!(run(), 10_000);
    pool.shutdown();
}

/// Two callbacks of one group try to meet: the most that were ever inside at once.
fn rendezvous(kind: &str, timeout: Duration) -> usize {
    let pool = pool(2);
    let g = group(&pool, "g", kind);
    let inside = Arc::new((Mutex::new((0usize, 0usize)), Condvar::new()));
    let finished = Arc::new(AtomicUsize::new(0));
    for _ in 0..2 {
        let (inside, finished) = (inside.clone(), finished.clone());
        g.execute(move || {
            let (lock, cv) = &*inside;
            let mut st = lock.lock().unwrap();
            st.0 += 1;
            st.1 = st.1.max(st.0);
            cv.notify_all();
            let (mut st, _) = cv.wait_timeout_while(st, timeout, |st| st.1 < 2).unwrap();
            st.0 -= 1;
            finished.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
    }
    wait_until("both callbacks", || finished.load(Ordering::Relaxed) == 2);
    pool.shutdown();
    let most = inside.0.lock().unwrap().1;
    most
}

#[test]
fn reentrant_groups_run_callbacks_in_parallel() {
    // rclcpp bug #3175 treated reentrant groups as exclusive: this rendezvous would time out.
    assert_eq!(rendezvous("reentrant", WAIT), 2);
}

#[test]
fn the_same_rendezvous_cannot_happen_in_an_exclusive_group() {
    assert_eq!(
        rendezvous("mutually_exclusive", Duration::from_millis(200)),
        1
    );
}

#[test]
fn tasks_start_in_arrival_order_across_groups() {
    let pool = pool(1);
    let (a, b, c) = (
        group(&pool, "a", "mutually_exclusive"),
        group(&pool, "b", "mutually_exclusive"),
        group(&pool, "c", "reentrant"),
    );
    let gate = Arc::new(Gate::default());
    let order = Arc::new(Mutex::new(Vec::new()));
    // Hold the only thread while the producer queues everything.
    let held = gate.clone();
    c.execute(move || assert!(held.wait(WAIT))).unwrap();
    let plan = [
        (&a, "a1"),
        (&a, "a2"),
        (&a, "a3"),
        (&b, "b1"),
        (&c, "c1"),
        (&a, "a4"),
        (&b, "b2"),
    ];
    for (g, label) in plan {
        let order = order.clone();
        g.execute(move || order.lock().unwrap().push(label))
            .unwrap();
    }
    gate.open();
    wait_until("all tasks", || order.lock().unwrap().len() == plan.len());
    // Arrival order, not round-robin per group (a1 b1 c1 a2 b2 a3 a4) nor by priority.
    assert_eq!(
        *order.lock().unwrap(),
        ["a1", "a2", "a3", "b1", "c1", "a4", "b2"]
    );
    pool.shutdown();
}

#[test]
fn a_busy_exclusive_group_holds_up_only_its_own_tasks() {
    let pool = pool(2);
    let (a, b) = (
        group(&pool, "a", "mutually_exclusive"),
        group(&pool, "b", "mutually_exclusive"),
    );
    let gate = Arc::new(Gate::default());
    let order = Arc::new(Mutex::new(Vec::new()));
    let (held, o) = (gate.clone(), order.clone());
    a.execute(move || {
        assert!(held.wait(WAIT));
        o.lock().unwrap().push("a1");
    })
    .unwrap();
    let o = order.clone();
    a.execute(move || o.lock().unwrap().push("a2")).unwrap();
    let (o, g) = (order.clone(), gate.clone());
    // b1 arrived after a2, but a2 must wait for a1; b1 runs on the free thread meanwhile.
    b.execute(move || {
        o.lock().unwrap().push("b1");
        g.open();
    })
    .unwrap();
    wait_until("all tasks", || order.lock().unwrap().len() == 3);
    assert_eq!(*order.lock().unwrap(), ["b1", "a1", "a2"]);
    pool.shutdown();
}

#[test]
fn is_in_current_executor_names_the_group_not_the_pool() {
    let pool = pool(2);
    let pool_ref = ExecutorRef::leak(pool.clone());
    let (a, b) = (
        group(&pool, "a", "mutually_exclusive"),
        group(&pool, "b", "reentrant"),
    );
    let seen = Arc::new(Mutex::new(None));
    let s = seen.clone();
    a.execute(move || {
        *s.lock().unwrap() = Some((
            a.is_in_current_executor(),
            b.is_in_current_executor(),
            pool_ref.is_in_current_executor(),
        ));
    })
    .unwrap();
    wait_until("the task", || seen.lock().unwrap().is_some());
    assert_eq!(*seen.lock().unwrap(), Some((true, false, false)));
    assert!(!a.is_in_current_executor());
    pool.shutdown();
}

#[test]
fn a_slow_timer_callback_skips_missed_periods_without_catching_up() {
    let pool = pool(2);
    let g = group(&pool, "g", "mutually_exclusive");
    let starts = Arc::new(Mutex::new(Vec::<Instant>::new()));
    let s = starts.clone();
    let period = Duration::from_millis(100);
    let t0 = Instant::now();
    let timer = create_timer(
        g,
        period,
        move |_| {
            let mut s = s.lock().unwrap();
            s.push(Instant::now());
            if s.len() == 1 {
                drop(s);
                // Runs 3.5 periods: the grid points at 200, 300 and 400 ms are missed.
                std::thread::sleep(Duration::from_millis(350));
            }
        },
        true,
    )
    .unwrap();
    wait_until("three runs", || starts.lock().unwrap().len() >= 3);
    timer.cancel();
    let s: Vec<Duration> = starts.lock().unwrap().iter().map(|i| *i - t0).collect();
    // Catching up would start the second run as soon as the first returns (~450 ms) and
    // the third right after it. Skipping waits for the next grid point: 500 ms, then 600.
    assert!(
        s[1] >= Duration::from_millis(499),
        "second run at {:?}: caught up",
        s[1]
    );
    assert!(
        s[2] >= Duration::from_millis(599),
        "third run at {:?}: caught up",
        s[2]
    );
    pool.shutdown();
}

#[test]
fn group_timers_follow_a_time_manipulator_clock_through_pause_and_resume() {
    let runner =
        aimrt_std_executors::create_executor("simple_thread", args("runner", "null")).unwrap();
    let sim = aimrt_std_executors::create_time_manipulator(ExecutorArgs {
        bound: vec![Some(runner)],
        ..args("sim", r#"{"bind_executor": "runner", "init_ratio": 1.0}"#)
    })
    .unwrap();
    sim.start().unwrap();
    let sim_ref = ExecutorRef::leak(sim.clone());
    let pool = pool(2);
    let g = ExecutorRef::leak(
        create_group(
            &pool,
            ExecutorArgs {
                bound: vec![None, Some(sim_ref)],
                ..args(
                    "g",
                    r#"{"bind_events_cbg": "pool", "time_executor": "sim"}"#,
                )
            },
        )
        .unwrap(),
    );
    let ticks = Arc::new(AtomicUsize::new(0));
    let on_group = Arc::new(AtomicBool::new(true));
    let (t, on) = (ticks.clone(), on_group.clone());
    let timer = create_timer(
        g,
        Duration::from_millis(20),
        move |_| {
            if !g.is_in_current_executor() {
                on.store(false, Ordering::Relaxed);
            }
            t.fetch_add(1, Ordering::Relaxed);
        },
        true,
    )
    .unwrap();
    wait_until("ticks at ratio 1", || ticks.load(Ordering::Relaxed) >= 3);
    // The group's clock is the simulated one.
    let skew = sim_ref
        .now()
        .duration_since(g.now())
        .unwrap_or_else(|e| e.duration());
    assert!(
        skew < Duration::from_millis(50),
        "group clock is {skew:?} off the sim clock"
    );

    sim.pause();
    std::thread::sleep(Duration::from_millis(60)); // a run already due may still land
    let paused_at = ticks.load(Ordering::Relaxed);
    let frozen = g.now();
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(
        ticks.load(Ordering::Relaxed),
        paused_at,
        "timer ran while the clock was paused"
    );
    assert_eq!(g.now(), frozen, "the group clock moved while paused");

    sim.set_time_ratio(1.0).unwrap();
    wait_until("ticks after resume", || {
        ticks.load(Ordering::Relaxed) >= paused_at + 3
    });
    assert!(
        on_group.load(Ordering::Relaxed),
        "a timer run landed outside its group"
    );
    timer.cancel();
    pool.shutdown();
    sim.shutdown();
    runner.raw().shutdown();
}

#[test]
fn shutdown_runs_queued_work_refuses_new_work_and_drops_pending_timers() {
    let pool = pool(2);
    let g = group(&pool, "g", "mutually_exclusive");
    let ran = Arc::new(AtomicUsize::new(0));
    for _ in 0..100 {
        let ran = ran.clone();
        g.execute(move || {
            ran.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
    }
    g.execute_at(SystemTime::now() + Duration::from_secs(3600), || {})
        .unwrap();
    g.raw().shutdown();
    assert_eq!(
        ran.load(Ordering::Relaxed),
        100,
        "queued work runs before the group is down"
    );
    assert!(g.execute(|| {}).is_err());
    let s = g.stats();
    assert_eq!(
        (s.run, s.refused, s.dropped_at_shutdown, s.queue_depth),
        (100, 1, 1, 0)
    );
    // The pool goes on serving its other groups.
    let other = group(&pool, "other", "reentrant");
    let r = ran.clone();
    other
        .execute(move || {
            r.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
    wait_until("the other group", || ran.load(Ordering::Relaxed) == 101);
    pool.shutdown();
    assert!(other.execute(|| {}).is_err());
}

#[test]
fn bad_options_are_clear_errors() {
    let pool = pool(2);
    let err = |o: &str| create_group(&pool, args("g", o)).unwrap_err().to_string();
    let e = err(r#"{"kind": "exclusive"}"#);
    assert!(
        e.contains(
            "key 'kind': unknown value 'exclusive'; expected one of mutually_exclusive, reentrant"
        ),
        "{e}"
    );
    let e = err("{}");
    assert!(e.contains("bind_events_cbg is required"), "{e}");
    let e = err(r#"{"bind_events_cbg": "pool", "kind": "reentrant", "dedicated_thread": {}}"#);
    assert!(e.contains("cannot have a dedicated_thread"), "{e}");
    let e = err(r#"{"bind_events_cbg": "pool", "dedicated_thrad": {}}"#);
    assert!(e.contains("did you mean 'dedicated_thread'"), "{e}");
    let e = create_pool(args("p", r#"{"on_panic": "crash"}"#))
        .unwrap_err()
        .to_string();
    assert!(e.contains("log") && e.contains("abort"), "{e}");
    pool.shutdown();
}

#[test]
fn a_panicking_callback_is_counted_and_the_pool_goes_on_with_on_panic_log() {
    let pool = pool(2);
    let g = group(&pool, "g", "mutually_exclusive");
    g.execute(|| panic!("boom")).unwrap();
    let ok = Arc::new(AtomicBool::new(false));
    let o = ok.clone();
    g.execute(move || o.store(true, Ordering::Relaxed)).unwrap();
    wait_until("the next task", || ok.load(Ordering::Relaxed));
    assert_eq!(g.stats().panicked, 1);
    pool.shutdown();
}

#[test]
fn a_panicking_callback_aborts_the_process_with_on_panic_abort() {
    use std::os::unix::process::ExitStatusExt;
    const CHILD: &str = "AIMRT_CBG_ABORT_CHILD";
    if std::env::var_os(CHILD).is_some() {
        // The child: a panic on the pool must end the process.
        let pool = create_pool(args("pool", r#"{"thread_num": 1, "on_panic": "abort"}"#)).unwrap();
        pool.start().unwrap();
        ExecutorRef::leak(pool).execute(|| panic!("boom")).unwrap();
        std::thread::sleep(WAIT);
        return;
    }
    let mut child = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "a_panicking_callback_aborts_the_process_with_on_panic_abort",
            "--test-threads=1",
        ])
        .env(CHILD, "1")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let end = Instant::now() + WAIT;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > end {
            let _ = child.kill();
            panic!("the child did not abort within {WAIT:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    assert_eq!(status.signal(), Some(6), "expected SIGABRT, got {status:?}");
}
