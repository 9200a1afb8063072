//! End-to-end: the real `aimrt_main` on real libraries and configs.

use std::time::Duration;

use aimrt_e2e::{assert_failure, lib, panic_abort_fixture, run_main};

const LIMIT: Duration = Duration::from_secs(60);

fn demo_config() -> String {
    std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/demo.yaml"
    ))
    .expect("config/demo.yaml")
}

/// Runs a config that loads `module` from the pkg at `path` and checks the failure line.
fn assert_pkg_failure(path: std::path::PathBuf, module: &str, expected: &[&str]) {
    let cfg = pkg_config(&path.display().to_string(), module);
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(&out, expected);
}

fn pkg_config(path: &str, module: &str) -> String {
    format!(
        "aimrt:\n  log:\n    backends:\n      - type: console\n  module:\n    pkgs:\n      - path: {path}\n        enable_modules: [{module}]\n"
    )
}

#[test]
fn demo_runs_and_counts_to_ten_thousand() {
    let out = run_main(
        Some(&demo_config()),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    out.assert_exit(0, "the demo");
    assert!(out.stdout.starts_with("AimRT start, version: "));
    assert!(
        out.stdout.contains("final count 10000 (0 refused)"),
        "{}",
        out.stdout
    );
    assert!(out
        .stdout
        .contains("This is a simple task on executor 'work_thread'."));
    // tracing::info! inside the module appears under the module's name.
    assert!(
        out.stdout.contains("[Info]")
            && out
                .stdout
                .contains("][DemoModule][modules/demo/src/lib.rs:"),
        "{}",
        out.stdout
    );
    for hook in ["Init succeeded.", "Start succeeded.", "Shutdown succeeded."] {
        assert!(out.stdout.contains(hook), "missing {hook}");
    }
    assert!(out.stdout.trim_end().ends_with("AimRT exit."));
    // The module config was handed over as AimRT does.
    assert!(out
        .stdout
        .contains("./cfg/tmp/temp_cfg_file_for_DemoModule.yaml"));
}

#[test]
fn demo_runs_with_std_executors_from_their_shared_library() {
    let cfg = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/demo_std_executors_so.yaml"
    ))
    .unwrap();
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    assert!(out.stdout.contains("built-in executor type 'simple_thread' of 'std_executors' skipped: plugin 'std_executors' already registered it"), "{}", out.stdout);
    assert!(
        out.stdout.contains("final count 10000 (0 refused)"),
        "{}",
        out.stdout
    );
}

#[test]
fn no_arguments_prints_usage() {
    let out = run_main(None, &[], LIMIT);
    assert_eq!(out.code, Some(0));
    assert!(out
        .stdout
        .contains("USAGE: aimrt_main --cfg_file_path=<string> [options]"));
}

#[test]
fn unknown_flag_is_explained() {
    let out = run_main(None, &["--cfg_file_pth=x.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            "unknown command line flag '--cfg_file_pth=x.yaml'",
            "did you mean '--cfg_file_path'?",
        ],
    );
}

#[test]
fn missing_config_file() {
    let out = run_main(None, &["--cfg_file_path=./nope.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            "cannot read config file './nope.yaml'",
            "check --cfg_file_path",
        ],
    );
}

#[test]
fn yaml_syntax_error_is_located() {
    let out = run_main(
        Some("aimrt:\n  executor: [\n"),
        &["--cfg_file_path=./cfg.yaml"],
        LIMIT,
    );
    assert_failure(&out, &["./cfg.yaml:2:"]);
    assert!(
        out.stderr.contains("executor: ["),
        "snippet on stderr:\n{}",
        out.stderr
    );
}

#[test]
fn unknown_key_gets_a_suggestion() {
    let cfg = "aimrt:\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n        optons: {}\n";
    let out = run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            "./cfg.yaml:6:9",
            "unknown key 'optons'; did you mean 'options'?",
        ],
    );
}

#[test]
fn unknown_executor_type_gets_a_suggestion() {
    let cfg = "aimrt:\n  executor:\n    executors:\n      - name: w\n        type: simple_thred\n";
    let out = run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            "executor 'w' (./cfg.yaml:4:15)",
            "unknown executor type 'simple_thred'; did you mean 'simple_thread'?",
        ],
    );
}

#[test]
fn missing_pkg_path() {
    let out = run_main(
        Some(&pkg_config("./libmissing_pkg.so", "X")),
        &["--cfg_file_path=./cfg.yaml"],
        LIMIT,
    );
    assert_failure(
        &out,
        &[
            "pkg at ./cfg.yaml:7:15 (./libmissing_pkg.so)",
            "cannot open the library",
            "check the path",
        ],
    );
}

#[test]
fn missing_plugin_path() {
    let cfg = "aimrt:\n  plugin:\n    plugins:\n      - name: p\n        path: ./libnothing.so\n";
    let out = run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            "plugin 'p' at ./cfg.yaml:5:15 (./libnothing.so)",
            "cannot open the library",
        ],
    );
}

#[test]
fn abi_mismatch_is_refused_before_running_library_code() {
    assert_pkg_failure(
        lib("libfixture_abi_mismatch.so"),
        "X",
        &[
            "libfixture_abi_mismatch.so",
            "was built against ABI 999.3; this aimrt_main needs 1.x",
            "rebuild it against aimrt-plugin-api",
        ],
    );
}

#[test]
fn panic_abort_library_is_refused() {
    assert_pkg_failure(
        panic_abort_fixture(),
        "AbortModule",
        &[
            "libfixture_panic_abort.so",
            "panic = \"abort\"",
            "panic = \"unwind\"",
        ],
    );
}

#[test]
fn library_without_entry_symbol_is_refused() {
    assert_pkg_failure(
        lib("libfixture_no_entry.so"),
        "X",
        &[
            "libfixture_no_entry.so",
            "no aimrt-rs entry symbol 'aimrt_rs_library'",
            "export_modules!",
        ],
    );
}

#[test]
fn module_panicking_in_initialize_fails_cleanly() {
    assert_pkg_failure(
        lib("libfixture_init_panic.so"),
        "PanicModule",
        &[
            "module 'PanicModule'",
            "failed to initialize",
            "panicked in initialize: PanicModule refuses to initialize",
        ],
    );
}

#[test]
fn module_returning_an_error_fails_cleanly() {
    assert_pkg_failure(
        lib("libfixture_init_panic.so"),
        "FailModule",
        &[
            "module 'FailModule'",
            "failed to initialize",
            "required setting 'speed' is missing",
        ],
    );
}

/// With `RUST_BACKTRACE=1`, an error of a library (anyhow's, in zenoh) recorded a backtrace,
/// and one that ran out of memory while recording it hung the process (Rust's
/// out-of-memory hook waits for the lock the recording thread holds). `aimrt_main` turns
/// libraries' backtraces off unless the environment sets `RUST_LIB_BACKTRACE` itself.
#[test]
fn libraries_record_no_backtraces_unless_rust_lib_backtrace_asks() {
    let path = lib("libfixture_init_panic.so");
    let cfg = pkg_config(&path.display().to_string(), "BacktraceStatusModule");
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("cfg.yaml"), cfg).expect("write cfg");
    let status = |lib_backtrace: Option<&str>| {
        let mut cmd = std::process::Command::new(aimrt_e2e::aimrt_main());
        cmd.args(["--cfg_file_path=./cfg.yaml", "--running_duration=1"])
            .env("RUST_BACKTRACE", "1")
            .env_remove("RUST_LIB_BACKTRACE");
        if let Some(v) = lib_backtrace {
            cmd.env("RUST_LIB_BACKTRACE", v);
        }
        let out = aimrt_e2e::run_in(cmd, dir.path(), LIMIT);
        assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
        let line = out
            .stdout
            .lines()
            .find_map(|l| l.split_once("library backtraces: "))
            .map(|(_, status)| status.to_owned());
        line.unwrap_or_else(|| panic!("no status line in:\n{}", out.stdout))
    };
    assert_eq!(status(None), "Disabled");
    assert_eq!(status(Some("1")), "Captured");
    assert_eq!(status(Some("0")), "Disabled");
}

#[test]
fn enable_modules_typo_gets_a_suggestion() {
    assert_pkg_failure(
        lib("libdemo_pkg.so"),
        "DemoModul",
        &[
            "enable_modules names 'DemoModul'",
            "did you mean 'DemoModule'?",
        ],
    );
}

#[test]
fn unset_env_variable_is_named() {
    let cfg = "aimrt:\n  module:\n    pkgs:\n      - path: ${AIMRT_E2E_UNSET_VAR}/x.so\n";
    let out = run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            "./cfg.yaml:4:15",
            "environment variable 'AIMRT_E2E_UNSET_VAR' is not set",
        ],
    );
}

#[test]
fn a_task_that_never_returns_cannot_hang_shutdown() {
    let path = lib("libfixture_init_panic.so");
    let cfg = format!(
        "aimrt:\n  log:\n    backends:\n      - type: console\n  executor:\n    join_timeout_ms: 300\n    executors:\n      - name: stuck\n        type: simple_thread\n  module:\n    pkgs:\n      - path: {}\n        enable_modules: [HangModule]\nHangModule:\n  executor: stuck\n",
        path.display()
    );
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    assert!(out.stdout.contains("hanging forever"));
    assert!(
        out.stdout
            .contains("executor 'stuck' did not finish within 300 ms"),
        "{}",
        out.stdout
    );
    assert!(out.stdout.trim_end().ends_with("AimRT exit."));
}

#[test]
fn sigterm_shuts_down_gracefully() {
    let (code, lines) =
        aimrt_e2e::run_with_signals(&demo_config(), &[("will wait for shutdown", "TERM")], LIMIT);
    let text = lines.join("\n");
    assert_eq!(code, Some(0), "{text}");
    assert!(text.contains("Received shutdown signal."), "{text}");
    assert!(text.contains("Shutdown succeeded."), "{text}");
    assert!(text.ends_with("AimRT exit."), "{text}");
}

#[test]
fn a_repeat_of_the_first_signal_is_the_same_request_and_a_later_signal_exits_at_once() {
    // The bench module's shutdown waits (up to 30 s) for a very long bench. The first
    // SIGINT starts shutdown; a repeat at once (as timeout(1) sends SIGTERM both to the
    // process and to its group) is the same request, and the shutdown goes on; one
    // 500 ms or more after the first exits at once with 128 + SIGINT.
    let cfg = "aimrt:
  log:
    backends:
      - type: console
        options: {module_filter: core}
  executor:
    executors:
      - name: work_executor
        type: simple_thread
  module:
    pkgs:
      - path: ${AIMRT_LIB_DIR}/liblogger_pkg.so
        enable_modules: [LoggerBenchModule]
LoggerBenchModule:
  log_data_size: [64]
  log_bench_num: 4000000000
";
    let start = std::time::Instant::now();
    let mut run = aimrt_e2e::Running::start(cfg);
    run.wait_for("will wait for shutdown", LIMIT);
    let first = std::time::Instant::now();
    run.signal("INT");
    run.wait_for("AimRT start shutdown.", LIMIT);
    run.signal("INT");
    let apart = first.elapsed();
    std::thread::sleep(Duration::from_millis(700));
    // A machine so busy that the repeat went out late makes it a second request.
    if apart < Duration::from_millis(300) {
        assert_eq!(
            run.exit_code(),
            None,
            "the repeat {apart:?} after the first ended the run:\n{}",
            run.text()
        );
    }
    if run.exit_code().is_none() {
        run.signal("INT");
    }
    let code = run.wait_exit(LIMIT);
    let text = run.text();
    assert_eq!(code, Some(130), "{text}");
    assert!(!text.contains("AimRT exit."), "{text}");
    // Well before the module's 30 s wait would have ended.
    assert!(start.elapsed() < Duration::from_secs(25), "{text}");
}

#[test]
fn dumps_the_normalized_config_which_loads_again_unchanged_and_the_init_report() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("cfg.yaml");
    std::fs::write(&cfg, demo_config()).unwrap();
    let dump = dir.path().join("dump.yaml");
    let report = dir.path().join("report.txt");
    let run = |from: &std::path::Path, to: &std::path::Path| {
        run_main(
            None,
            &[
                &format!("--cfg_file_path={}", from.display()),
                "--running_duration=1",
                "--dump_cfg_file",
                &format!("--dump_cfg_file_path={}", to.display()),
                "--dump_init_report=true",
                &format!("--dump_init_report_path={}", report.display()),
            ],
            LIMIT,
        )
    };
    let out = run(&cfg, &dump);
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    let first = std::fs::read_to_string(&dump).unwrap();
    // ${AIMRT_LIB_DIR:-...} is resolved in the dump.
    assert!(!first.contains("${"), "{first}");
    // The library path as the loader opened it: canonical.
    let pkg = std::fs::canonicalize(lib("libdemo_pkg.so")).unwrap();
    assert!(
        first.contains(&format!("path: {}\n", pkg.display())),
        "{first}"
    );
    // Normalized as AimRT does: what the file leaves out at its default, level names
    // re-capitalized, the module's own node kept.
    for expected in [
        "temp_cfg_path: ./cfg/tmp",
        "queue_threshold: 10000",
        "threshold_alarm_interval_ms: 1000",
        "join_timeout_ms: 5000",
        "core_lvl: Info",
        "color: true",
        "queue_threshold: 20000",
        "work_executor: work_thread",
    ] {
        assert!(first.contains(expected), "{expected} missing:\n{first}");
    }
    // Each executor's options as it read them, defaults filled in (ABI 1.8; AimRT's
    // `options_node = options_`), also where the file gives none.
    for executor in [
        "- name: work_thread\n      type: simple_thread\n      options:\n        queue_threshold: 10000\n        thread_bind_cpu: []\n        thread_policy_strict: false\n        thread_sched_policy: \"\"\n        threshold_alarm_interval_ms: 1000\n",
        "- name: thread_safe_executor\n      type: simple_thread\n      options:\n        queue_threshold: 20000\n        thread_bind_cpu: []\n",
    ] {
        assert!(first.contains(executor), "{executor} missing:\n{first}");
    }
    let again = dir.path().join("again.yaml");
    let out = run(&dump, &again);
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    assert_eq!(std::fs::read_to_string(&again).unwrap(), first);
    let text = std::fs::read_to_string(&report).unwrap();
    for section in [
        "AimRT Initialization Report Begin",
        "]. Base Info",
        "]. Plugin List",
        "]. Executor Type List",
        "]. Executor List",
        "]. Log Backend List",
        "]. Module Info List",
        "DemoModule",
        "\"queue_threshold\":20000",
        // An executor declared without options is listed with those it read.
        "\"queue_threshold\":10000",
    ] {
        assert!(text.contains(section), "{section} missing:\n{text}");
    }
    assert!(
        text.lines().any(|l| l.contains("|  work_thread ")
            && l.contains("|  simple_thread ")
            && l.contains("|  Y ")),
        "{text}"
    );
}

/// Runs `cfg` for a second with `--dump_cfg_file`, then the dump itself the same way: the
/// first dump and the dump of the dump. `what` names the case in a failure.
fn dump_twice(cfg: &str, what: &str) -> (String, String) {
    let dir = tempfile::tempdir().unwrap();
    let run = |from: &std::path::Path, to: &std::path::Path| {
        let out = run_main(
            None,
            &[
                &format!("--cfg_file_path={}", from.display()),
                "--running_duration=1",
                "--dump_cfg_file",
                &format!("--dump_cfg_file_path={}", to.display()),
            ],
            LIMIT,
        );
        assert_eq!(out.code, Some(0), "{what}:\n{}\n{}", out.stdout, out.stderr);
        std::fs::read_to_string(to).unwrap()
    };
    let cfg_path = dir.path().join("cfg.yaml");
    let dump = dir.path().join("dump.yaml");
    std::fs::write(&cfg_path, cfg).unwrap();
    let first = run(&cfg_path, &dump);
    let again = run(&dump, &dir.path().join("again.yaml"));
    (first, again)
}

/// Channel and RPC backends' options as their `init` read them (ABI 1.8): the built-in
/// `local` ones and net_plugin's `udp`, each with its defaults filled in; the dump loads
/// again to itself.
#[test]
fn the_dump_writes_backends_options_as_they_read_them() {
    let cfg = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: net_plugin\n        path: {}\n  executor:\n    executors:\n      - name: timers\n        type: asio_thread\n  channel:\n    backends:\n      - type: local\n      - type: udp\n        options:\n          pub_topics_options:\n            - topic_name: \"/x\"\n  rpc:\n    backends:\n      - type: local\n        options:\n          timeout_executor: timers\n",
        lib("libaimrt_net_plugin.so").display()
    );
    let (dump, again) = dump_twice(&cfg, "backends");
    for expected in [
        "  channel:\n    backends:\n    - type: local\n      options:\n        subscriber_executor: \"\"\n        subscriber_use_inline_executor: true\n",
        "    - type: udp\n      options:\n        pub_topics_options:\n        - server_url_list: []\n          topic_name: /x\n",
        "  rpc:\n    backends:\n    - type: local\n      options:\n        timeout_executor: timers\n",
    ] {
        assert!(dump.contains(expected), "{expected} missing:\n{dump}");
    }
    assert_eq!(again, dump);
}

/// Every executor type of the project reports its options (ABI 1.8): in the dumps of the
/// examples that use them all (the five standard types; `events_cbg`, `events_cbg_group`
/// and `time_manipulator`), each executor's `options` have every key of its type, and
/// each dump loads again to itself, so what the executors report is what they accept.
#[test]
fn every_executor_type_reports_options_that_load_again() {
    for example in ["std_executors", "cbg_executor"] {
        let (first, again) = dump_twice(&aimrt_e2e::repo_config(example), example);
        let executors = first
            .split_once("  executor:\n")
            .and_then(|(_, rest)| rest.split_once("    join_timeout_ms:"))
            .map(|(section, _)| section)
            .unwrap_or_else(|| panic!("{example}: no executor section in:\n{first}"));
        // Each executor's options have every key of its type, whatever the file wrote.
        let blocks: Vec<&str> = executors.split("\n    - name: ").skip(1).collect();
        assert!(blocks.len() >= 5, "{example}:\n{executors}");
        for block in blocks {
            let ty = block
                .lines()
                .find_map(|l| l.strip_prefix("      type: "))
                .unwrap_or_else(|| panic!("{example}: no type in {block}"));
            let keys = block
                .lines()
                .filter_map(|l| l.strip_prefix("        "))
                .filter(|l| l.starts_with(|c: char| c.is_ascii_lowercase()))
                .count();
            let expected = match ty {
                "asio_thread" | "tbb_thread" | "time_wheel" => 7,
                "time_manipulator" => 8,
                "simple_thread" | "events_cbg" => 5,
                "asio_strand" | "events_cbg_group" => 4,
                other => panic!("{example}: executor type {other} not expected"),
            };
            assert_eq!(keys, expected, "{example}: the options of\n{block}");
        }
        assert_eq!(again, first, "{example}");
    }
}

/// A stop requested during a slow `initialize`: that hook finishes, no later module is
/// initialized or started, the initialized one is shut down, and the process exits 0 soon
/// after the hook returns (as after a signal during run).
#[test]
fn a_signal_during_a_slow_initialize_starts_nothing_more() {
    for signal in ["TERM", "INT"] {
        let cfg = format!(
            "aimrt:\n  log:\n    backends:\n      - type: console\n  executor:\n    executors:\n      - name: work_thread_pool\n        type: asio_thread\n  module:\n    pkgs:\n      - path: {}\n        enable_modules: [SlowInitModule]\n      - path: {}\nSlowInitModule:\n  init_ms: 1500\nDemoModule:\n  work_executor: work_thread_pool\n  thread_safe_executor: work_thread_pool\n",
            lib("libfixture_init_panic.so").display(),
            lib("libdemo_pkg.so").display()
        );
        let mut run = aimrt_e2e::Running::start(&cfg);
        let (sent, _) = run.wait_for("SlowInitModule initialize begins", LIMIT);
        run.signal(signal);
        let code = run.wait_exit(LIMIT);
        let exited = std::time::Instant::now();
        let text = run.text();
        // The request is said at once, while the module still initializes.
        let heard = text
            .find("Received shutdown signal during start-up: AimRT shuts down as soon as the step under way ends; a second signal exits at once.")
            .unwrap_or_else(|| panic!("{signal}: the request is not said:\n{text}"));
        assert!(
            text.find("SlowInitModule initialize ends")
                .is_some_and(|ends| heard < ends),
            "{signal}:\n{text}"
        );
        assert_eq!(code, Some(0), "{signal}:\n{text}");
        assert!(
            exited.duration_since(sent) < Duration::from_millis(1500 + 2000),
            "{signal}: exit {:?} after the signal:\n{text}",
            exited.duration_since(sent)
        );
        for present in [
            "SlowInitModule initialize ends",
            "module 'DemoModule' and the modules after it are not initialized",
            "SlowInitModule shutdown",
        ] {
            assert!(text.contains(present), "{signal}: no '{present}':\n{text}");
        }
        for absent in [
            "Init module 'DemoModule'",
            "SlowInitModule start",
            "Start succeeded",
        ] {
            assert!(!text.contains(absent), "{signal}: '{absent}' seen:\n{text}");
        }
    }
}

/// What runs write (per-module temp configs under `cfg/tmp/`, logs under `log/`) is
/// ignored by git wherever a run's working directory is, and none of it is tracked.
#[test]
fn run_outputs_are_ignored_by_git() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    if !root.join(".git").exists() {
        eprintln!("not a git checkout: nothing to check");
        return;
    }
    let git = |args: &[&str]| {
        std::process::Command::new("git")
            .args(args)
            .current_dir(&root)
            .output()
            .expect("run git")
    };
    for path in [
        "cfg/tmp/temp_cfg_file_for_DemoModule.yaml",
        "tests/e2e/cfg/tmp/temp_cfg_file_for_NormalSubscriberModule.yaml",
        "log/aimrt.log",
        "tests/e2e/log/aimrt.log",
    ] {
        assert!(
            git(&["check-ignore", "-q", "--no-index", path])
                .status
                .success(),
            "{path} is not ignored"
        );
    }
    let tracked = git(&["ls-files", "--", "*cfg/tmp/*", "*log/*.log"]);
    assert!(
        tracked.stdout.is_empty(),
        "run outputs are tracked: {}",
        String::from_utf8_lossy(&tracked.stdout)
    );
}

/// Runs `lib` (a fixture of an older ABI minor) for a second with `section` routing its
/// channel or RPC to `local`; its output.
fn run_fixture(lib_file: &str, section: &str) -> String {
    let cfg = format!(
        "aimrt:\n  log:\n    backends:\n      - type: console\n{section}  module:\n    pkgs:\n      - path: {}\n",
        lib(lib_file).display()
    );
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    out.stdout
}

#[test]
fn a_library_of_abi_1_1_loads_and_runs_on_this_host() {
    let out = run_fixture(
        "libfixture_abi_1_1.so",
        "  channel:\n    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \"(.*)\"\n        enable_backends: [local]\n    sub_topics_options:\n      - topic_name: \"(.*)\"\n        enable_backends: [local]\n",
    );
    assert!(out.contains("ABI 1.1 module initialized"), "{out}");
    assert!(
        out.contains("ABI 1.1 module received: hello from 1.1"),
        "{out}"
    );
}

#[test]
fn a_library_of_abi_1_2_in_its_shorter_descriptor_serves_and_calls_on_this_host() {
    let out = run_fixture(
        "libfixture_abi_1_2.so",
        "  rpc:\n    backends:\n      - type: local\n    servers_options:\n      - func_name: \"(.*)\"\n        enable_backends: [local]\n    clients_options:\n      - func_name: \"(.*)\"\n        enable_backends: [local]\n",
    );
    assert!(out.contains("ABI 1.2 module got: echo hi"), "{out}");
}

#[test]
fn a_plugin_of_abi_1_3_in_its_shorter_table_starts_and_is_not_called_past_it() {
    let cfg = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: abi_1_3_plugin\n        path: {}\n  log:\n    backends:\n      - type: console\n",
        lib("libfixture_abi_1_3.so").display()
    );
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    for line in [
        "ABI 1.3 plugin initialized",
        "ABI 1.3 plugin started",
        "ABI 1.3 plugin shut down",
    ] {
        assert!(out.stdout.contains(line), "{line}: {}", out.stdout);
    }
    assert!(
        !out.stdout.contains("post_start reached"),
        "the host read past the 1.3 table: {}",
        out.stdout
    );
}

/// `aimrt_main … | head -3`: stdout is a pipe nobody reads any more. The run goes on and
/// ends as usual (exit 0, no panic); the console backend's failed writes are said once on
/// stderr and counted.
#[test]
fn a_closed_stdout_pipe_is_no_panic() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("cfg.yaml"), demo_config()).unwrap();
    // The reader of the pipe (`true`) exits at once; the exit status goes to stderr.
    let mut child = std::process::Command::new("sh")
        .arg("-c")
        .arg("( \"$0\" --cfg_file_path=./cfg.yaml --running_duration=1; echo \"exit status $?\" >&2 ) | true")
        .arg(aimrt_e2e::aimrt_main())
        .current_dir(dir.path())
        .env("AIMRT_LIB_DIR", aimrt_e2e::profile_dir())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + LIMIT;
    while child.try_wait().unwrap().is_none() {
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            panic!("aimrt_main did not end within {LIMIT:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("exit status 0"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(stderr.contains("failed to write: Broken pipe"), "{stderr}");
}
