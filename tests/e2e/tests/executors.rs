//! End-to-end: the standard executors under the real `aimrt_main` — AimRT's own executor
//! example configs (modules replaced by the demo module), linked in and loaded from
//! `std_executors_so`; bind keys; thread settings.

use std::time::Duration;

use aimrt_e2e::{assert_failure, corpus, run_main, Output};

const LIMIT: Duration = Duration::from_secs(60);

/// AimRT's config with its module package replaced by the demo module, which uses `work`
/// and the thread-safe executor `safe`. With `from_so`, the standard executors come from
/// their shared library instead of the copy linked into `aimrt_main`.
fn with_demo(text: &str, module: &str, work: &str, safe: &str, from_so: bool) -> String {
    let mut cfg = text
        .replace("./libexecutor_pkg.so", "${AIMRT_LIB_DIR}/libdemo_pkg.so")
        .replace(&format!("[{module}]"), "[DemoModule]")
        .replace(&format!("name: {module}"), "name: DemoModule");
    if from_so {
        cfg = cfg.replacen(
            "aimrt:\n",
            "aimrt:\n  plugin:\n    plugins:\n      - name: std_executors\n        path: ${AIMRT_LIB_DIR}/libaimrt_std_executors_plugin.so\n",
            1,
        );
    }
    cfg.push_str(&format!(
        "\nDemoModule:\n  work_executor: {work}\n  thread_safe_executor: {safe}\n"
    ));
    cfg
}

fn run(cfg: &str) -> Output {
    run_main(
        Some(cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    )
}

fn assert_demo_ran(out: &Output, what: &str) {
    out.assert_exit(0, what);
    assert!(
        out.stdout.contains("final count 10000 (0 refused)"),
        "{what}:\n{}",
        out.stdout
    );
}

#[test]
fn aimrt_executor_examples_run_linked_and_from_the_shared_library() {
    let cases = [
        (
            "examples_cpp_executor_cfg.yaml",
            "ExecutorModule",
            "work_executor",
            "thread_safe_executor",
        ),
        (
            "examples_cpp_executor_co_cfg.yaml",
            "ExecutorCoModule",
            "work_executor",
            "thread_safe_executor",
        ),
        (
            "examples_cpp_executor_co_loop_cfg.yaml",
            "ExecutorCoLoopModule",
            "time_schedule_executor",
            "time_schedule_executor",
        ),
        (
            "examples_cpp_executor_timer_cfg.yaml",
            "TimerModule",
            "timer_executor",
            "timer_executor",
        ),
        (
            "examples_cpp_executor_real_time_cfg.yaml",
            "RealTimeModule",
            "sched_other_thread",
            "sched_fifo_thread",
        ),
    ];
    for (file, module, work, safe) in cases {
        for from_so in [false, true] {
            let out = run(&with_demo(&corpus(file), module, work, safe, from_so));
            assert_demo_ran(&out, &format!("{file} (from .so: {from_so})"));
            if from_so {
                assert!(
                    out.stdout.contains(
                        "built-in executor type 'asio_thread' of 'std_executors' skipped"
                    ),
                    "{file}: the .so's types are used:\n{}",
                    out.stdout
                );
            }
        }
    }
}

#[test]
fn real_time_example_binds_cpus_it_may_use_and_warns_about_the_rest() {
    let cfg = with_demo(
        &corpus("examples_cpp_executor_real_time_cfg.yaml"),
        "RealTimeModule",
        "sched_other_thread",
        "sched_fifo_thread",
        false,
    );
    let out = run(&cfg);
    assert_demo_ran(&out, "real_time");
    // CPUs 4-6 do not exist on the 2-CPU CI machine; on a bigger one nothing is refused.
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    if cpus < 5 {
        assert!(
            out.stdout.contains("thread 'sched_rr_thread'") && out.stdout.contains("not available"),
            "{}",
            out.stdout
        );
    }
}

fn executors_config(executors: &str) -> String {
    format!(
        "aimrt:\n  log:\n    backends:\n      - type: console\n  executor:\n    executors:\n{executors}  module:\n    pkgs:\n      - path: ${{AIMRT_LIB_DIR}}/libdemo_pkg.so\n\nDemoModule:\n  work_executor: work\n  thread_safe_executor: safe\n"
    )
}

#[test]
fn bind_keys_work_in_any_yaml_order() {
    let cfg = executors_config(
        "      - name: safe\n        type: asio_strand\n        options:\n          bind_asio_thread_executor_name: work\n      - name: wheel\n        type: time_wheel\n        options:\n          bind_executor: safe\n          dt_us: 1000\n      - name: work\n        type: asio_thread\n        options:\n          thread_num: 2\n",
    );
    let out = run(&cfg);
    assert_demo_ran(&out, "strand before its pool");
}

#[test]
fn bad_bind_references_are_refused_with_their_location() {
    let unknown = executors_config(
        "      - name: work\n        type: asio_thread\n      - name: safe\n        type: asio_strand\n        options:\n          bind_asio_thread_executor_name: wrok\n",
    );
    let out = run(&unknown);
    assert_failure(&out, &["cfg.yaml:9:", "'wrok'", "did you mean 'work'"]);

    let wrong_type = executors_config(
        "      - name: work\n        type: tbb_thread\n      - name: safe\n        type: asio_strand\n        options:\n          bind_asio_thread_executor_name: work\n",
    );
    let out = run(&wrong_type);
    assert_failure(&out, &["cfg.yaml:", "needs an asio_thread", "tbb_thread"]);

    let cycle = executors_config(
        "      - name: work\n        type: time_wheel\n        options:\n          bind_executor: safe\n      - name: safe\n        type: time_wheel\n        options:\n          bind_executor: work\n",
    );
    let out = run(&cycle);
    assert_failure(&out, &["cfg.yaml:", "cycle", "work", "safe"]);
}

#[test]
fn a_refused_cpu_is_a_warning_and_an_error_when_strict() {
    let executors = |strict: bool| {
        executors_config(&format!(
            "      - name: work\n        type: simple_thread\n        options:\n          thread_bind_cpu: [1000]\n          thread_policy_strict: {strict}\n      - name: safe\n        type: simple_thread\n"
        ))
    };
    let out = run(&executors(false));
    assert_demo_ran(&out, "CPU 1000 refused");
    assert!(
        out.stdout
            .contains("thread 'work': thread_bind_cpu [1000] not available"),
        "{}",
        out.stdout
    );
    let out = run(&executors(true));
    assert_failure(&out, &["thread 'work'", "[1000]", "thread_policy_strict"]);
}

#[test]
fn invalid_executor_options_name_the_key_and_the_place() {
    let cfg = executors_config(
        "      - name: work\n        type: asio_thread\n        options:\n          thread_nmu: 2\n      - name: safe\n        type: simple_thread\n",
    );
    let out = run(&cfg);
    assert_failure(
        &out,
        &["cfg.yaml:", "thread_nmu", "did you mean 'thread_num'"],
    );
    let cfg = executors_config(
        "      - name: work\n        type: time_wheel\n        options:\n          dt_us: 0\n      - name: safe\n        type: simple_thread\n",
    );
    assert_failure(&run(&cfg), &["cfg.yaml:", "dt_us must be greater than 0"]);
}

#[test]
fn executor_stats_are_logged_at_shutdown() {
    let cfg = executors_config(
        "      - name: work\n        type: tbb_thread\n        options:\n          thread_num: 2\n      - name: safe\n        type: asio_strand\n        options:\n          bind_asio_thread_executor_name: pool\n      - name: pool\n        type: asio_thread\n",
    );
    let out = run(&cfg);
    assert_demo_ran(&out, "stats");
    assert!(
        out.stdout
            .contains("executor 'safe' shut down: submitted 10000, run 10000, refused 0"),
        "{}",
        out.stdout
    );
}

#[test]
fn the_std_executors_example_config_runs() {
    let cfg = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/std_executors.yaml"
    ))
    .unwrap();
    let out = run(&cfg);
    assert_demo_ran(&out, "config/std_executors.yaml");
    for name in ["work_pool", "ordered", "bounded_pool", "single", "ticker"] {
        assert!(
            out.stdout.contains(&format!("executor '{name}' shut down")),
            "{name}:\n{}",
            out.stdout
        );
    }
}
