//! End-to-end: AimRT's five executor examples (`libexecutor_pkg.so`) under the real
//! `aimrt_main`, with the configs in `config/` — AimRT's own, with only the pkg path
//! changed — and again with the standard executors loaded from their plugin library, so
//! the module's timers and async tasks drive executors of another library.

use std::time::Duration;

use aimrt_e2e::{example_config as example, run_main, Output};

const LIMIT: Duration = Duration::from_secs(60);

fn with_executors_from_so(cfg: &str) -> String {
    cfg.replacen(
        "aimrt:\n",
        "aimrt:\n  plugin:\n    plugins:\n      - name: std_executors\n        path: ${AIMRT_LIB_DIR}/libaimrt_std_executors_plugin.so\n",
        1,
    )
}

/// Runs `cfg` for `secs` seconds, both ways, and hands each output to `check`.
fn run_both(name: &str, secs: u32, check: impl Fn(&Output)) {
    let cfg = example(name);
    for (how, text) in [
        ("linked", cfg.clone()),
        ("from .so", with_executors_from_so(&cfg)),
    ] {
        let out = run_main(
            Some(&text),
            &[
                "--cfg_file_path=./cfg.yaml",
                &format!("--running_duration={secs}"),
            ],
            LIMIT,
        );
        out.assert_exit(0, &format!("{name} ({how})"));
        assert!(!out.stdout.contains("panicked:"), "{}", out.stdout);
        eprintln!("{name} ({how}) ok");
        check(&out);
    }
}

fn has(out: &Output, text: &str) {
    assert!(out.stdout.contains(text), "no {text:?} in:\n{}", out.stdout);
}

#[test]
fn executor_example() {
    run_both("executor", 2, |out| {
        has(out, "][ExecutorModule][");
        has(out, "]This is a simple task");
        has(out, "]Value of n is 10000");
        has(out, "]Loop count : 0");
        has(out, "]Loop count : 1");
        has(out, "]Shutdown succeeded.");
    });
}

#[test]
fn executor_co_example_hops_between_executors() {
    run_both("executor_co", 2, |out| {
        has(out, "]This is a simple task");
        has(out, "]Now run in work_executor: true");
        has(out, "]Now run in thread_safe_executor: true");
        has(out, "]Now run in time_schedule_executor: true");
        has(out, "]Value of n is 10000");
        has(out, "]Loop count : 1");
        // shutdown waits for the scope: the loop ends before the module does.
        let exit = out.stdout.find("]Exit loop.").expect("Exit loop.");
        let done = out
            .stdout
            .find("]Shutdown succeeded.")
            .expect("Shutdown succeeded.");
        assert!(exit < done);
    });
}

#[test]
fn executor_co_loop_example() {
    run_both("executor_co_loop", 2, |out| {
        has(out, "]Loop count : 1 -------------------------");
        has(out, "]Loop count : 2 -------------------------");
        let exit = out.stdout.find("]Exit loop.").expect("Exit loop.");
        let done = out
            .stdout
            .find("]Shutdown succeeded.")
            .expect("Shutdown succeeded.");
        assert!(exit < done);
    });
}

#[test]
fn timer_example_resets_and_cancels_itself() {
    run_both("executor_timer", 2, |out| {
        let runs: Vec<(u32, u64)> = out
            .stdout
            .lines()
            .filter_map(|l| {
                let rest = l.split("]Executed ").nth(1)?;
                let (n, rest) = rest.split_once(" times, execute timepoint: ")?;
                Some((n.parse().ok()?, rest.strip_suffix(" ms")?.parse().ok()?))
            })
            .collect();
        // 100 ms period from 0; reset at 350 → 450, 550; reset at 600 → 700 … 1100.
        let expected = [100, 200, 300, 450, 550, 700, 800, 900, 1000, 1100];
        assert_eq!(runs.len(), 10, "{}", out.stdout);
        for (i, (n, at)) in runs.iter().enumerate() {
            assert_eq!(*n as usize, i + 1);
            // Never early; late only by scheduling noise on a loaded machine.
            assert!(
                *at >= expected[i] && *at < expected[i] + 250,
                "run {n} at {at} ms, expected {} ms:\n{}",
                expected[i],
                out.stdout
            );
        }
        has(out, "]Timer reset at timepoint: 350 ms");
        has(out, "]Timer reset at timepoint: 600 ms");
        has(out, "]Timer cancelled at timepoint: ");
    });
}

#[test]
fn real_time_example_prints_what_the_os_reports() {
    run_both("executor_real_time", 3, |out| {
        for exec in ["sched_fifo_thread", "sched_other_thread", "sched_rr_thread"] {
            let lines: Vec<&str> = out
                .stdout
                .lines()
                .filter(|l| l.contains(&format!("executor name: {exec},")))
                .collect();
            assert!(
                lines.iter().any(|l| l.contains("]Loop count: 3,")),
                "{exec}:\n{}",
                out.stdout
            );
            let policy = |l: &&str| l.split("sched policy: ").nth(1).unwrap_or("").to_owned();
            let refused = out.stdout.lines().any(|l| {
                l.contains(&format!("thread '{exec}'")) && l.contains("thread_sched_policy")
            });
            for l in &lines {
                let p = policy(l);
                match exec {
                    "sched_other_thread" => assert!(p.starts_with("SCHED_OTHER,"), "{l}"),
                    // Granted, or refused by the OS with a warning naming the thread.
                    "sched_fifo_thread" => {
                        assert!(p.starts_with("SCHED_FIFO:80,") || refused, "{l}")
                    }
                    _ => assert!(p.starts_with("SCHED_RR:80,") || refused, "{l}"),
                }
            }
        }
        // CPUs 0 and 1 exist wherever these tests run: the FIFO thread is bound to them.
        if std::thread::available_parallelism().map_or(0, |n| n.get()) >= 2 {
            has(out, "executor name: sched_fifo_thread, sched policy: ");
            assert!(
                out.stdout
                    .lines()
                    .filter(|l| l.contains("executor name: sched_fifo_thread,"))
                    .all(|l| l.ends_with("bind cpu: [0, 1]")),
                "{}",
                out.stdout
            );
        }
    });
}

/// Every config of AimRT's example corpus (`tests/aimrt-configs/`) has a counterpart
/// under `config/` that names it in its header, or is listed here with where it runs or
/// why it does not. A corpus file added without either fails.
#[test]
fn every_aimrt_example_config_runs_here_or_says_why_not() {
    const ELSEWHERE: &[(&str, &str)] = &[
        ("examples_cpp_logger_cfg.yaml", "tests/logging.rs, as is"),
        (
            "examples_cpp_logger_format_cfg.yaml",
            "tests/logging.rs, as is",
        ),
        (
            "examples_cpp_logger_rotate_file_cfg.yaml",
            "tests/logging.rs, as is",
        ),
        (
            "examples_cpp_logger_rotate_file_with_sync_cfg.yaml",
            "tests/logging.rs, as is",
        ),
        (
            "examples_cpp_logger_bench_cfg.yaml",
            "tests/logging.rs, as is",
        ),
    ];
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let headers: String = std::fs::read_dir(root.join("config"))
        .expect("config/")
        .filter_map(|e| {
            let path = e.ok()?.path();
            (path.extension()? == "yaml").then(|| std::fs::read_to_string(path).ok())?
        })
        .collect();
    let mut missing = Vec::new();
    let mut n = 0;
    for entry in std::fs::read_dir(root.join("tests/aimrt-configs")).expect("the corpus") {
        let name = entry
            .expect("entry")
            .file_name()
            .to_string_lossy()
            .into_owned();
        if !name.ends_with("_cfg.yaml") {
            continue;
        }
        n += 1;
        let named = headers.contains(&format!("AimRT's example config {name}"));
        if !named && !ELSEWHERE.iter().any(|(f, _)| *f == name) {
            missing.push(name);
        }
    }
    assert!(n >= 68, "only {n} corpus configs found");
    assert!(
        missing.is_empty(),
        "no counterpart under config/: {missing:?}"
    );
}
