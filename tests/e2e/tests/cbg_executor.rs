//! The `events_cbg` plugin loaded from its `.so` by an unmodified `aimrt_main`
//! (`config/cbg_executor.yaml` with `CbgModule`), and its config errors.

use std::time::Duration;

use aimrt_e2e::{assert_failure, repo_config, run_main};

const WAIT: Duration = Duration::from_secs(60);

#[test]
fn aimrt_main_runs_callback_groups_from_the_plugin_library() {
    let out = run_main(
        Some(&repo_config("cbg_executor")),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=3"],
        WAIT,
    );
    let text = &out.stdout;
    assert_eq!(out.code, Some(0), "{text}\n{}", out.stderr);
    // thread_safe() crosses the ABI: exclusive yes, reentrant no.
    assert!(
        text.contains("Groups: 'control_group' thread safe true, 'worker_group' thread safe false, 'rt_group' thread safe true"),
        "{text}"
    );
    let rounds: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("'control_group' ran "))
        .collect();
    assert!(!rounds.is_empty(), "no round finished:\n{text}");
    for r in &rounds {
        assert!(
            r.contains("ran 1000 callbacks") && r.ends_with(", 0 overlapping"),
            "{r}"
        );
    }

    // The dedicated group's own thread, as the OS reports it.
    let report = text
        .lines()
        .find(|l| l.contains("group 'rt_group' on thread"))
        .unwrap_or_else(|| panic!("no report from the dedicated thread:\n{text}"));
    assert!(report.contains("on thread 'rt_group'"), "{report}");
    assert!(report.contains("bind cpu: [0]"), "{report}");
    // SCHED_FIFO where the OS grants it; otherwise one warning with the OS's reason.
    if !report.contains("sched policy: SCHED_FIFO:10") {
        assert!(report.contains("sched policy: SCHED_OTHER"), "{report}");
        assert!(
            text.contains("thread 'rt_group': ") && text.contains("[Warn]"),
            "a refused policy must be warned about:\n{text}"
        );
    }
    // sim_group's clock is the time_manipulator's, at twice real time: between its first
    // and last loop, its clock advanced about twice as far as the log's wall clock.
    let sim: Vec<(f64, f64)> = text
        .lines()
        .filter(|l| l.contains("group 'sim_group' clock: "))
        .map(|l| {
            let wall = seconds_of_day(&l[1..l.find(']').unwrap_or(1)]);
            (
                wall,
                seconds_of_day(l.rsplit("clock: ").next().unwrap_or_default()),
            )
        })
        .collect();
    assert!(sim.len() >= 3, "too few simulated-time loops:\n{text}");
    let (first, last) = (sim[0], sim[sim.len() - 1]);
    let ratio = (last.1 - first.1) / (last.0 - first.0);
    assert!(
        (1.6..2.6).contains(&ratio),
        "sim clock ran at {ratio:.2}× wall time:\n{text}"
    );
    // The pool's threads are named after it; the runtime counts every group's work.
    assert!(
        text.contains("executor 'control_group' shut down: submitted"),
        "{text}"
    );
    assert!(
        !text.contains("panicked:") && !out.stderr.contains("panicked at"),
        "{text}"
    );
}

/// `2026-11-22 02:08:40.598[123]` → seconds since midnight.
fn seconds_of_day(stamp: &str) -> f64 {
    let time = stamp.trim().rsplit(' ').next().unwrap_or_default();
    let parts: Vec<f64> = time
        .split(':')
        .map(|p| p.parse().unwrap_or(f64::NAN))
        .collect();
    assert_eq!(parts.len(), 3, "not a time: {stamp}");
    parts[0] * 3600.0 + parts[1] * 60.0 + parts[2]
}

fn with_group_options(options: &str) -> String {
    repo_config("cbg_executor").replace(
        "          bind_events_cbg: cbg_pool\n          kind: reentrant\n",
        options,
    )
}

#[test]
fn group_config_errors_name_the_group_and_what_would_be_right() {
    let run = |cfg: &str| {
        run_main(
            Some(cfg),
            &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
            WAIT,
        )
    };
    let out = run(&with_group_options(
        "          bind_events_cbg: control_group\n",
    ));
    assert_failure(
        &out,
        &[
            "worker_group",
            "'control_group' is a events_cbg_group executor",
            "must name an events_cbg pool",
        ],
    );
    let out = run(&with_group_options("          kind: reentrant\n"));
    assert_failure(&out, &["worker_group", "bind_events_cbg is required"]);
    let out = run(&with_group_options(
        "          bind_events_cbg: cbg_pool\n          kind: reentrant\n          time_executor: cbg_pol\n",
    ));
    assert_failure(
        &out,
        &["worker_group", "cbg_pol", "did you mean 'cbg_pool'"],
    );
    let out = run(&with_group_options(
        "          bind_events_cbg: cbg_pool\n          kind: reentrant\n          dedicated_thread: {}\n",
    ));
    assert_failure(
        &out,
        &[
            "worker_group",
            "reentrant group cannot have a dedicated_thread",
        ],
    );
}
