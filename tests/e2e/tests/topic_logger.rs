//! topic_logger_plugin: log lines published as AimRT's `LogData` and read by another
//! process (the example pair over udp, on a free port), the backend's options in one
//! process (module_filter, max_msg_size), and its bad options stopping start-up.

use std::time::Duration;

use aimrt_e2e::{assert_failure, repo_config, run_for, run_main, with_port, Running};

const WAIT: Duration = Duration::from_secs(30);

/// The `"message"` values of `loop count` lines echoed at `level`, as loop counts, in the
/// order they were printed.
fn loop_counts(echoed: &str, level: &str) -> Vec<u64> {
    let mut counts = Vec::new();
    let mut current_level = "";
    for line in echoed.lines().map(str::trim) {
        if let Some(l) = line.strip_prefix("\"level\": \"") {
            current_level = l.trim_end_matches(['"', ',']);
        }
        if let Some(m) = line.strip_prefix("\"message\": \"") {
            // Keys are printed in byte order: `level` comes before `message`.
            if current_level == level {
                if let Some(n) = m.split("loop count: ").nth(1) {
                    counts.push(n.trim_end_matches(['"', ',']).parse().expect("a count"));
                }
            }
        }
    }
    counts
}

#[test]
fn a_modules_log_lines_reach_an_echo_process_in_order_with_their_parts() {
    let port = aimrt_e2e::free_port(true);
    let mut echo = Running::start(&with_port(&repo_config("topic_logger_plugin_echo"), port));
    echo.wait_for("udp channel listening on", WAIT);
    echo.wait_for("Module manager start completed.", WAIT);
    let mut publisher = Running::start(&with_port(&repo_config("topic_logger_plugin"), port));
    publisher.wait_for("Module manager start completed.", WAIT);
    // LoggerModule logs Trace to Error once a second from loop count 1; its level is
    // TRACE, so every level crosses.
    echo.wait_for("\"message\": \"Test error log, loop count: 3\"", WAIT);
    let code = publisher.interrupt(WAIT);
    assert_eq!(code, Some(0), "{}", publisher.text());
    let echoed = echo.text();
    for level in ["TRACE", "DEBUG", "INFO", "WARN", "ERROR"] {
        let counts = loop_counts(&echoed, level);
        assert!(
            counts.len() >= 3 && counts.iter().enumerate().all(|(i, &n)| n == i as u64 + 1),
            "{level} lines arrive once each, in order, from loop count 1: {counts:?}\n{echoed}"
        );
    }
    // A line's parts: the module, its level, its source, the thread and the time.
    let at = echoed
        .find("\"message\": \"Test info log, loop count: 1\"")
        .expect("the Info line of loop 1");
    let entry = &echoed[echoed[..at].rfind('{').expect("the entry's start")..];
    let entry = &entry[..entry.find('}').expect("the entry's end")];
    for part in [
        "\"module_name\": \"LoggerModule\"",
        "\"level\": \"INFO\"",
        "\"file_name\": \"modules/logger/src/lib.rs\"",
    ] {
        assert!(entry.contains(part), "{part} in:\n{entry}");
    }
    let number = |key: &str| -> u64 {
        let v = entry
            .split(&format!("\"{key}\": "))
            .nth(1)
            .and_then(|r| r.split([',', '\n']).next())
            .unwrap_or_else(|| panic!("{key} in:\n{entry}"));
        v.trim_matches('"')
            .parse()
            .unwrap_or_else(|e| panic!("{key} {v}: {e}"))
    };
    assert!(number("line") > 0, "{entry}");
    assert!(number("thread_id") > 0, "{entry}");
    let now_ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64;
    let age = now_ns.saturating_sub(number("time_point"));
    assert!(
        age < 120_000_000_000,
        "time_point is nanoseconds since the epoch: {age} ns old"
    );
    // The publisher says what crossed, and what its shutdown could not publish.
    let summary = publisher.text();
    let line = summary
        .lines()
        .find(|l| l.contains("topic_logger on topic 'log_topic': "))
        .unwrap_or_else(|| panic!("no topic_logger summary in:\n{summary}"));
    assert!(
        line.contains("lines published in") && line.contains("0 lost to failed publishes"),
        "{line}"
    );
}

/// One process: the module's lines go to `log_topic` on the local backend, cut to
/// `max_msg_size`, and `module_filter` keeps the runtime's and the plugins' lines out.
#[test]
fn module_filter_and_max_msg_size_shape_what_is_published() {
    let config = r#"
aimrt:
  plugin:
    plugins:
      - name: topic_logger_plugin
        path: ${AIMRT_LIB_DIR}/libaimrt_topic_logger_plugin.so
      - name: echo_plugin
        path: ${AIMRT_LIB_DIR}/libaimrt_echo_plugin.so
        options:
          type_support_pkgs:
            - path: ${AIMRT_LIB_DIR}/libaimrt_msgs_pb_ts.so
          topic_meta_list:
            - topic_name: log_topic
              msg_type: pb:aimrt.protocols.topic_logger.LogData
              echo_type: json
  log:
    core_lvl: INFO
    backends:
      - type: console
      - type: topic_logger
        options:
          timer_executor_name: timer_executor
          topic_name: log_topic
          interval_ms: 50
          max_msg_size: 13
          module_filter: "LoggerModule"
  executor:
    executors:
      - name: work_executor
        type: simple_thread
      - name: timer_executor
        type: asio_thread
  channel:
    backends:
      - type: local
    pub_topics_options:
      - topic_name: "(.*)"
        enable_backends: [local]
    sub_topics_options:
      - topic_name: "(.*)"
        enable_backends: [local]
  module:
    pkgs:
      - path: ${AIMRT_LIB_DIR}/liblogger_pkg.so
        enable_modules: [LoggerModule]
    modules:
      - name: LoggerModule
        log_lvl: INFO
LoggerModule:
  interval_ms: 200
"#;
    let out = run_for(config, 2);
    let echoed: Vec<&str> = out
        .stdout
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("\"message\": "))
        .collect();
    // "Test info log, loop count: 3" cut to 13 bytes, once a loop.
    let info = echoed
        .iter()
        .filter(|m| m.trim_end_matches(',') == "\"message\": \"Test info log\"")
        .count();
    assert!(info >= 4, "cut Info lines were published:\n{}", out.stdout);
    for m in &echoed {
        let text = m
            .trim_end_matches(',')
            .trim_start_matches("\"message\": \"");
        assert!(
            text.trim_end_matches('"').len() <= 13,
            "{m}\n{}",
            out.stdout
        );
    }
    assert!(
        !out.stdout.contains("\"module_name\": \"core\""),
        "module_filter keeps the runtime's lines out:\n{}",
        out.stdout
    );
}

#[test]
fn bad_options_stop_start_up_naming_the_entry() {
    let config = |executor_type: &str, options: &str| {
        format!(
            r#"
aimrt:
  plugin:
    plugins:
      - name: topic_logger_plugin
        path: ${{AIMRT_LIB_DIR}}/libaimrt_topic_logger_plugin.so
  log:
    backends:
      - type: topic_logger
        options: {options}
  executor:
    executors:
      - name: timer_executor
        type: {executor_type}
"#
        )
    };
    for (executor_type, options, expected) in [
        (
            "asio_thread",
            "{topic_name: log_topic, timer_executor_name: timer_exec}",
            &["topic_logger", "cfg.yaml:10:", "timer_exec"][..],
        ),
        (
            "simple_thread",
            "{topic_name: log_topic, timer_executor_name: timer_executor}",
            &["topic_logger", "timer_executor", "supports timers"],
        ),
        (
            "asio_thread",
            "{topic_name: log_topic, timer_executor_name: timer_executor, interval_ms: 0}",
            &["topic_logger", "cfg.yaml:10:", "interval_ms is 0"],
        ),
        (
            "asio_thread",
            "{timer_executor_name: timer_executor}",
            &["topic_logger", "topic_name"],
        ),
    ] {
        let out = run_main(
            Some(&config(executor_type, options)),
            &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
            WAIT,
        );
        assert_failure(&out, expected);
    }
}
