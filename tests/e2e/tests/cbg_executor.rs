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
