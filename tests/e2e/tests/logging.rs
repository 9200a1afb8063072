//! End-to-end: logging under the real `aimrt_main` — AimRT's logger example configs with
//! only the pkg path changed, per-module levels across two libraries, `module_filter`,
//! `rotate_file` rotation and cleanup, and the pipeline flushed at shutdown.

use std::path::Path;
use std::time::Duration;

use aimrt_e2e::{corpus, run_main, run_main_in, Output};

const LIMIT: Duration = Duration::from_secs(60);

/// An AimRT logger config with its pkg path pointed at our `liblogger_pkg.so`.
fn logger_corpus(file: &str) -> String {
    corpus(file).replace("./liblogger_pkg.so", "${AIMRT_LIB_DIR}/liblogger_pkg.so")
}

fn ok(out: &Output) {
    out.assert_exit(0, "the logger config");
    assert!(out.stdout.ends_with("AimRT exit.\n"), "{}", out.stdout);
}

fn lines_of<'a>(text: &'a str, logger: &str) -> Vec<&'a str> {
    let tag = format!("][{logger}][");
    text.lines().filter(|l| l.contains(&tag)).collect()
}

#[test]
fn aimrt_logger_example_logs_every_level_and_the_last_lines() {
    let out = run_main(
        Some(&logger_corpus("examples_cpp_logger_cfg.yaml")),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    ok(&out);
    let module = lines_of(&out.stdout, "LoggerModule");
    // log_lvl: TRACE → every level, in AimRT's layout.
    for level in ["Trace", "Debug", "Info", "Warn", "Error"] {
        let tagged = format!("[{level}]");
        assert!(
            module
                .iter()
                .any(|l| l.contains(&tagged) && l.contains("loop count: 1")),
            "no {level} line:\n{}",
            out.stdout
        );
    }
    // The module's shutdown line and the executors' last lines are written before exit:
    // the pipeline is flushed last.
    assert!(module.iter().any(|l| l.ends_with("]Shutdown succeeded.")));
    let core = lines_of(&out.stdout, "core");
    assert!(
        core.last().unwrap().ends_with("Executor manager shutdown."),
        "{}",
        out.stdout
    );
    // core_lvl: INFO → no Debug lines from the framework.
    assert!(core.iter().all(|l| !l.contains("][Debug][")));
}

#[test]
fn aimrt_format_example_uses_its_pattern() {
    let out = run_main(
        Some(&logger_corpus("examples_cpp_logger_format_cfg.yaml")),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    ok(&out);
    // "[%c.%f][%A][%l][%t][%n][%G] %v"
    let weekdays = [
        "Monday",
        "Tuesday",
        "Wednesday",
        "Thursday",
        "Friday",
        "Saturday",
        "Sunday",
    ];
    let line = out
        .stdout
        .lines()
        .find(|l| l.contains("Test info log, loop count: 1"))
        .unwrap_or_else(|| panic!("{}", out.stdout));
    let fields: Vec<&str> = line.split("][").collect();
    assert!(weekdays.contains(&fields[1]), "{line}");
    assert_eq!(fields[2], "Info", "{line}");
    assert!(fields[3].parse::<i32>().is_ok(), "{line}");
    assert_eq!(fields[4], "LoggerModule", "{line}");
    assert_eq!(fields[5], "lib.rs] Test info log, loop count: 1", "{line}");
}

#[test]
fn per_module_levels_hold_across_libraries() {
    // Two pkgs, two libraries, each with its own copy of `tracing` forwarding to the host.
    let cfg = "aimrt:
  log:
    core_lvl: Warn
    default_module_lvl: error
    backends:
      - type: console
  executor:
    executors:
      - name: work_executor
        type: simple_thread
      - name: safe
        type: simple_thread
  module:
    pkgs:
      - path: ${AIMRT_LIB_DIR}/libdemo_pkg.so
      - path: ${AIMRT_LIB_DIR}/liblogger_pkg.so
        enable_modules: [LoggerModule]
    modules:
      - name: LoggerModule
        log_lvl: DEBUG
DemoModule:
  work_executor: work_executor
  thread_safe_executor: safe
LoggerModule:
  interval_ms: 50
";
    let out = run_main(
        Some(cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    ok(&out);
    let logger = lines_of(&out.stdout, "LoggerModule");
    assert!(
        logger.iter().any(|l| l.contains("][Debug][")),
        "{}",
        out.stdout
    );
    assert!(
        logger.iter().all(|l| !l.contains("][Trace][")),
        "{}",
        out.stdout
    );
    // DemoModule has no log_lvl: default_module_lvl (Error) hides its Info lines.
    assert!(
        lines_of(&out.stdout, "DemoModule").is_empty(),
        "{}",
        out.stdout
    );
    // core_lvl Warn hides the framework's Info lines.
    assert!(
        lines_of(&out.stdout, "core")
            .iter()
            .all(|l| !l.contains("][Info][")),
        "{}",
        out.stdout
    );
}

#[test]
fn module_filter_routes_loggers_to_backends() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = "aimrt:
  log:
    backends:
      - type: console
        options: {module_filter: 'Logger.*', pattern: '%n|%v'}
      - type: rotate_file
        options: {path: ./log, filename: core.log, module_filter: core}
  executor:
    executors:
      - name: work_executor
        type: simple_thread
  module:
    pkgs:
      - path: ${AIMRT_LIB_DIR}/liblogger_pkg.so
        enable_modules: [LoggerModule]
LoggerModule:
  interval_ms: 50
";
    let out = run_main_in(
        dir.path(),
        Some(cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    ok(&out);
    let console: Vec<&str> = out.stdout.lines().filter(|l| l.contains('|')).collect();
    assert!(console.len() > 3, "{}", out.stdout);
    assert!(
        console.iter().all(|l| l.starts_with("LoggerModule|")),
        "{}",
        out.stdout
    );
    let file = std::fs::read_to_string(dir.path().join("log/core.log")).unwrap();
    assert!(!file.is_empty());
    assert!(file.lines().all(|l| l.contains("][core][")), "{file}");
    assert!(file
        .lines()
        .last()
        .unwrap()
        .ends_with("Executor manager shutdown."));
}

/// A `module_filter` that matches no logger (written as a prefix) is said once: on
/// stderr when no backend shows the runtime's lines, in the log when one does. One that
/// matches is not mentioned.
#[test]
fn a_module_filter_that_matches_no_logger_is_said() {
    let cfg = |filters: &str| {
        format!(
            "aimrt:
  log:
    backends:
{filters}  executor:
    executors:
      - name: work_executor
        type: simple_thread
  module:
    pkgs:
      - path: ${{AIMRT_LIB_DIR}}/liblogger_pkg.so
        enable_modules: [LoggerModule]
"
        )
    };
    let args = ["--cfg_file_path=./cfg.yaml", "--running_duration=1"];
    let alone = "      - type: console\n        options: {module_filter: Logger}\n";
    let out = run_main(Some(&cfg(alone)), &args, LIMIT);
    ok(&out);
    assert!(
        out.stderr.contains("aimrt log: log backend 'console' at ./cfg.yaml:4:15: module_filter 'Logger' matches none of this process's loggers (LoggerModule, core, logger_pkg), so the backend writes nothing; the filter must match a whole name (e.g. 'Logger.*')"),
        "{}",
        out.stderr
    );
    let beside = "      - type: console\n      - type: rotate_file\n        options: {path: ./log, module_filter: gger}\n";
    let out = run_main(Some(&cfg(beside)), &args, LIMIT);
    ok(&out);
    assert!(
        out.stdout.contains("[Warn]") && out.stdout.contains("log backend 'rotate_file' at ./cfg.yaml:5:15: module_filter 'gger' matches none of this process's loggers (LoggerModule, core, logger_pkg), so the backend writes nothing; the filter must match a whole name (e.g. '.*gger.*')"),
        "{}",
        out.stdout
    );
    let matching = "      - type: console\n        options: {module_filter: 'Logger.*|core'}\n";
    let out = run_main(Some(&cfg(matching)), &args, LIMIT);
    ok(&out);
    assert!(!out.stdout.contains("matches none"), "{}", out.stdout);
    assert!(!out.stderr.contains("matches none"), "{}", out.stderr);
}

/// Rotated files of `name` in `dir`: (index, size).
fn rotated(dir: &Path, name: &str) -> Vec<(u64, u64)> {
    let mut out: Vec<(u64, u64)> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| {
            let e = e.unwrap();
            let file = e.file_name().into_string().unwrap();
            let rest = file.strip_prefix(&format!("{name}_"))?.to_owned();
            let idx = rest.split('_').next()?.parse().ok()?;
            Some((idx, e.metadata().unwrap().len()))
        })
        .collect();
    out.sort();
    out
}

#[test]
fn rotate_file_rotates_and_cleans_up() {
    let dir = tempfile::tempdir().unwrap();
    // AimRT's rotate_file example, made small: 1 MiB files, 2 kept; the bench module logs
    // 1200 lines of 4 KiB (about 5 MiB).
    let cfg = logger_corpus("examples_cpp_logger_rotate_file_cfg.yaml")
        .replace("max_file_size_m: 4", "max_file_size_m: 1")
        .replace("max_file_num: 10", "max_file_num: 2")
        .replace("[LoggerModule]", "[LoggerBenchModule]")
        .replace("name: LoggerModule", "name: LoggerBenchModule")
        .replace("      - type: console\n", "")
        + "LoggerBenchModule:\n  log_data_size: [4096]\n  log_bench_num: 1200\n";
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    ok(&out);
    let log = dir.path().join("log");
    let name = "examples_cpp_logger_rotate_file.log";
    let files = rotated(&log, name);
    // Every file rotated once it passed 1 MiB: 4 rotations, the 2 newest kept.
    assert_eq!(
        files.iter().map(|f| f.0).collect::<Vec<_>>(),
        [3, 4],
        "{files:?}"
    );
    let mib = 1024 * 1024;
    for (idx, size) in &files {
        assert!(
            *size > mib && *size < mib + 8192,
            "file {idx}: {size} bytes"
        );
    }
    let active = std::fs::read_to_string(log.join(name)).unwrap();
    assert!(active.contains("Bench completed."));
    assert!(active
        .lines()
        .last()
        .unwrap()
        .ends_with("Executor manager shutdown."));
    // Rotated names carry the timestamp suffix (suffix_with_timestamp defaults to true).
    let stamped = std::fs::read_dir(&log)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.starts_with(&format!("{name}_4_")))
        .count();
    assert_eq!(stamped, 1);
}

#[test]
fn aimrt_sync_example_runs_and_writes_its_file() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = logger_corpus("examples_cpp_logger_rotate_file_with_sync_cfg.yaml");
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    ok(&out);
    let file = std::fs::read_to_string(dir.path().join("log/examples_cpp_logger_rotate_file.log"))
        .unwrap();
    assert!(file.contains("[LoggerModule]"), "{file}");
    // Nothing left pending on the sync executor: no dropped-timer warning at shutdown.
    assert!(
        !out.stdout.contains("dropped without running"),
        "{}",
        out.stdout
    );
}

#[test]
fn logger_example_config_runs() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/logger.yaml"
    ))
    .expect("config/logger.yaml");
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    ok(&out);
    assert!(out.stdout.contains("][Trace][") && out.stdout.contains("loop count: 1"));
    let file = std::fs::read_to_string(dir.path().join("log/logger_example.log")).unwrap();
    // The file's own pattern: base name and line, then a space.
    assert!(file.contains("][LoggerModule][lib.rs:"), "{file}");
    assert!(file.contains("] Test trace log, loop count: 1"), "{file}");
}

#[test]
fn aimrt_logger_bench_example_logs_every_size_and_completes() {
    let out = aimrt_e2e::run_for(&logger_corpus("examples_cpp_logger_bench_cfg.yaml"), 2);
    ok(&out);
    let module = lines_of(&out.stdout, "LoggerBenchModule");
    for size in [64, 256, 1024, 4096] {
        let head = format!("Bench: 5000 lines of {size} bytes in ");
        assert!(
            module.iter().any(|l| l.contains(&head)),
            "no '{head}' in\n{}",
            out.stdout
        );
    }
    assert!(
        module.iter().any(|l| l.ends_with("Bench completed.")),
        "{}",
        out.stdout
    );
}
