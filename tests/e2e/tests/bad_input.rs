//! Every broken config and command line gets exit code 255, no panic, and one line saying
//! what is wrong and where.

use std::time::Duration;

use aimrt_e2e::{assert_failure, run_main};

const LIMIT: Duration = Duration::from_secs(60);

/// Minimal pieces to build broken configs from.
const DEMO_PKG: &str = "  module:\n    pkgs:\n      - path: ${AIMRT_LIB_DIR}/libdemo_pkg.so\n";

const TM_PLUGIN: &str = "      - name: time_manipulator_plugin\n        path: ${AIMRT_LIB_DIR}/libaimrt_time_manipulator_plugin.so\n";
const NET_PLUGIN: &str =
    "      - name: net_plugin\n        path: ${AIMRT_LIB_DIR}/libaimrt_net_plugin.so\n";

/// A `time_manipulator` named `sim` bound to `pool`, with `options`.
fn time_manipulator(options: &str) -> String {
    format!("aimrt:\n  plugin:\n    plugins:\n{TM_PLUGIN}  executor:\n    executors:\n      - name: pool\n        type: simple_thread\n      - name: sim\n        type: time_manipulator\n        options: {options}\n")
}

/// `net_plugin` with `options`, and an `aimrt.rpc` section.
fn rpc(net_options: &str, rpc: &str) -> String {
    format!("aimrt:\n  plugin:\n    plugins:\n{NET_PLUGIN}        options: {net_options}\n  rpc:\n{rpc}")
}

fn executors(list: &str) -> String {
    format!("aimrt:\n  executor:\n    executors:\n{list}")
}

/// (what, config, what the failure line must contain besides the location)
fn broken_configs() -> Vec<(&'static str, String, Vec<&'static str>)> {
    vec![
        ("unclosed flow sequence", "aimrt:\n  log: [\n".into(), vec![]),
        ("tab indentation", "aimrt:\n\tlog: {}\n".into(), vec![]),
        ("aimrt is a list", "aimrt: [1, 2]\n".into(), vec!["expected a map"]),
        ("duplicate key", "aimrt:\n  log: {}\n  log: {}\n".into(), vec!["duplicate key 'log'"]),
        ("unknown section", "aimrt:\n  executr: {}\n".into(), vec!["did you mean 'executor'"]),
        ("unknown log key", "aimrt:\n  log:\n    core_lvel: Info\n".into(), vec!["did you mean 'core_lvl'"]),
        ("unknown core level", "aimrt:\n  log:\n    core_lvl: Loud\n".into(), vec!["Loud"]),
        ("unknown default module level", "aimrt:\n  log:\n    default_module_lvl: verbose\n".into(), vec!["verbose"]),
        (
            "unknown module level",
            format!("aimrt:\n{DEMO_PKG}    modules:\n      - name: DemoModule\n        log_lvl: Chatty\n"),
            vec!["Chatty"],
        ),
        ("unknown log backend type", "aimrt:\n  log:\n    backends:\n      - type: rotate_fle\n".into(), vec!["did you mean 'rotate_file'"]),
        ("two console backends", "aimrt:\n  log:\n    backends:\n      - type: console\n      - type: console\n".into(), vec!["second 'console'"]),
        ("empty log pattern", "aimrt:\n  log:\n    backends:\n      - type: console\n        options: {pattern: ''}\n".into(), vec!["pattern is empty"]),
        ("bad module_filter regex", "aimrt:\n  log:\n    backends:\n      - type: console\n        options: {module_filter: '[a'}\n".into(), vec!["module_filter"]),
        ("rotate_file size 0", "aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {max_file_size_m: 0}\n".into(), vec!["max_file_size_m"]),
        ("rotate_file path is a file", "aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {path: ./cfg.yaml}\n".into(), vec!["rotate_file cannot open"]),
        ("sync without executor", "aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {enable_sync: true}\n".into(), vec!["sync_executor_name is not set"]),
        (
            "sync executor unknown",
            "aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {enable_sync: true, sync_executor_name: timr}\n  executor:\n    executors:\n      - name: timer\n        type: asio_thread\n".into(),
            vec!["'timr' is not an executor; did you mean 'timer'"],
        ),
        (
            "sync executor without timers",
            "aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {enable_sync: true, sync_executor_name: plain}\n  executor:\n    executors:\n      - name: plain\n        type: simple_thread\n".into(),
            vec!["simple_thread executor, which has no timers"],
        ),
        ("unknown executor type", executors("      - name: a\n        type: asio_thred\n"), vec!["did you mean 'asio_thread'"]),
        (
            "duplicate executor name",
            executors("      - name: a\n        type: simple_thread\n      - name: a\n        type: simple_thread\n"),
            vec!["duplicate executor name 'a'"],
        ),
        ("executor named like the main thread", executors("      - name: aimrt_main\n        type: simple_thread\n"), vec!["aimrt_main"]),
        (
            "executor named like the configured guard thread",
            "aimrt:\n  guard_thread:\n    name: guard\n  executor:\n    executors:\n      - name: guard\n        type: simple_thread\n".into(),
            vec!["'guard'"],
        ),
        ("executor without a type", executors("      - name: a\n"), vec!["type"]),
        ("executor without a name", executors("      - type: simple_thread\n"), vec!["name"]),
        ("executor options not a map", executors("      - name: a\n        type: simple_thread\n        options: 5\n"), vec!["expected a map"]),
        ("executor option of the wrong type", executors("      - name: a\n        type: asio_thread\n        options:\n          thread_num: many\n"), vec!["thread_num"]),
        ("negative unsigned executor option", executors("      - name: a\n        type: simple_thread\n        options:\n          queue_threshold: -1\n"), vec!["queue_threshold", "-1"]),
        ("zero threads", executors("      - name: a\n        type: tbb_thread\n        options:\n          thread_num: 0\n"), vec!["thread_num must be at least 1"]),
        ("unknown executor option", executors("      - name: a\n        type: simple_thread\n        options:\n          queue_treshold: 5\n"), vec!["did you mean 'queue_threshold'"]),
        ("executors as a map", "aimrt:\n  executor:\n    executors:\n      a: 1\n".into(), vec!["expected a list"]),
        ("zero tick", executors("      - name: a\n        type: time_wheel\n        options:\n          dt_us: 0\n"), vec!["dt_us"]),
        ("empty wheel", executors("      - name: a\n        type: time_wheel\n        options:\n          wheel_size: []\n"), vec!["wheel_size"]),
        (
            "strand bound to an unknown executor",
            executors("      - name: s\n        type: asio_strand\n        options:\n          bind_asio_thread_executor_name: nope\n"),
            vec!["'nope'"],
        ),
        (
            "wheels bound in a cycle",
            executors("      - name: a\n        type: time_wheel\n        options:\n          bind_executor: b\n      - name: b\n        type: time_wheel\n        options:\n          bind_executor: a\n"),
            vec!["cycle"],
        ),
        ("unset environment variable", "aimrt:\n  log:\n    core_lvl: ${AIMRT_RS_TEST_SURELY_UNSET}\n".into(), vec!["AIMRT_RS_TEST_SURELY_UNSET"]),
        (
            "duplicate pkg path",
            format!("aimrt:\n{DEMO_PKG}      - path: ${{AIMRT_LIB_DIR}}/libdemo_pkg.so\n"),
            vec!["libdemo_pkg.so"],
        ),
        ("pkg without a path", "aimrt:\n  module:\n    pkgs:\n      - enable_modules: [A]\n".into(), vec!["path"]),
        (
            "enable_modules names an unknown module",
            "aimrt:\n  module:\n    pkgs:\n      - path: ${AIMRT_LIB_DIR}/libdemo_pkg.so\n        enable_modules: [DemoModul]\n".into(),
            vec!["did you mean 'DemoModule'"],
        ),
        ("plugin library missing", "aimrt:\n  plugin:\n    plugins:\n      - name: p\n        path: ./no_such_plugin.so\n".into(), vec!["no_such_plugin.so"]),
        (
            "duplicate plugin names",
            "aimrt:\n  plugin:\n    plugins:\n      - name: std_executors\n        path: ${AIMRT_LIB_DIR}/libaimrt_std_executors_plugin.so\n      - name: std_executors\n        path: ${AIMRT_LIB_DIR}/libaimrt_std_executors_plugin.so\n".into(),
            vec!["duplicate plugin name 'std_executors'"],
        ),
        ("negative guard queue threshold", "aimrt:\n  guard_thread:\n    queue_threshold: -5\n".into(), vec!["whole number in 0 ..= 4294967295"]),
        ("negative join timeout", "aimrt:\n  executor:\n    join_timeout_ms: -1\n".into(), vec!["whole number in 0 ..="]),
        ("CPU list as a string", "aimrt:\n  main_thread:\n    thread_bind_cpu: \"0\"\n".into(), vec!["expected a list"]),
        ("plugin options key typo", "aimrt:\n  plugin:\n    plugins:\n      - name: p\n        pth: x.so\n".into(), vec!["did you mean 'path'"]),
        ("time_manipulator without bind_executor", time_manipulator("{dt_us: 1000}"), vec!["bind_executor is required"]),
        ("time_manipulator bound to nothing", time_manipulator("{bind_executor: poll}"), vec!["'poll'", "did you mean 'pool'"]),
        ("time_manipulator NaN ratio", time_manipulator("{bind_executor: pool, init_ratio: .nan}"), vec!["init_ratio", "expected f64"]),
        ("time_manipulator ratio too large", time_manipulator("{bind_executor: pool, init_ratio: 2.0e6}"), vec!["init_ratio", "above the limit"]),
        ("time_manipulator dt_us 0", time_manipulator("{bind_executor: pool, dt_us: 0}"), vec!["dt_us must be greater than 0"]),
        ("time_manipulator option typo", time_manipulator("{bind_executor: pool, init_ration: 2}"), vec!["did you mean 'init_ratio'"]),
        (
            "time_manipulator_plugin option typo",
            format!("aimrt:\n  plugin:\n    plugins:\n{TM_PLUGIN}        options: {{service_nam: x}}\n"),
            vec!["did you mean 'service_name'"],
        ),
        ("rpc backend nobody registered", "aimrt:\n  rpc:\n    backends:\n      - type: http\n".into(), vec!["unknown rpc backend type 'http'", "net_plugin provides http"]),
        ("rpc backend typo", rpc("{http_options: {listen_port: 0}}", "    backends:\n      - type: htp\n"), vec!["did you mean 'http'"]),
        ("rpc backend listed twice", rpc("{http_options: {listen_port: 0}}", "    backends:\n      - type: http\n      - type: http\n"), vec!["listed twice"]),
        (
            "rpc func_name not a regex",
            rpc("{http_options: {listen_port: 0}}", "    backends:\n      - type: http\n    servers_options:\n      - func_name: \"(pb:/x\"\n        enable_backends: [http]\n"),
            vec!["not a valid regular expression"],
        ),
        (
            "rpc enable_backends not listed",
            rpc("{http_options: {listen_port: 0}}", "    backends:\n      - type: http\n    servers_options:\n      - func_name: \".*\"\n        enable_backends: [grpc]\n"),
            vec!["'grpc', which aimrt.rpc.backends does not list"],
        ),
        (
            "rpc servers_options without enable_backends",
            rpc("{http_options: {listen_port: 0}}", "    backends:\n      - type: http\n    servers_options:\n      - func_name: \".*\"\n"),
            vec!["enable_backends"],
        ),
        ("http without http_options", rpc("{thread_num: 2}", "    backends:\n      - type: http\n"), vec!["needs http_options"]),
        ("http listen_ip not an IP", rpc("{http_options: {listen_ip: localhost, listen_port: 0}}", "    backends:\n      - type: http\n"), vec!["'localhost' is not an IP address"]),
        ("net_plugin thread_num 0", rpc("{thread_num: 0, http_options: {listen_port: 0}}", "    backends:\n      - type: http\n"), vec!["thread_num must be at least 1"]),
        ("net_plugin port out of range", rpc("{http_options: {listen_port: 70000}}", "    backends:\n      - type: http\n"), vec!["listen_port"]),
        ("channel backend nobody provides", "aimrt:\n  channel:\n    backends:\n      - type: lcal\n".into(), vec!["unknown channel backend type 'lcal'", "did you mean 'local'"]),
        ("channel backend listed twice", "aimrt:\n  channel:\n    backends:\n      - type: local\n      - type: local\n".into(), vec!["listed twice"]),
        (
            "local backend without its executor",
            "aimrt:\n  channel:\n    backends:\n      - type: local\n        options: {subscriber_use_inline_executor: false}\n".into(),
            vec!["subscriber_executor must name"],
        ),
        (
            "local backend executor unknown",
            format!("{}  channel:\n    backends:\n      - type: local\n        options: {{subscriber_use_inline_executor: false, subscriber_executor: wrk}}\n", executors("      - name: work\n        type: simple_thread\n")),
            vec!["'wrk' is not an executor", "did you mean 'work'"],
        ),
        ("local backend option typo", "aimrt:\n  channel:\n    backends:\n      - type: local\n        options: {subscriber_use_inline_executr: true}\n".into(), vec!["did you mean 'subscriber_use_inline_executor'"]),
        (
            "topic_name not a regex",
            "aimrt:\n  channel:\n    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \"(.*\"\n        enable_backends: [local]\n".into(),
            vec!["topic_name '(.*' is not a valid regular expression"],
        ),
        (
            "topic enable_backends not listed",
            "aimrt:\n  channel:\n    backends:\n      - type: local\n    sub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [zenoh]\n".into(),
            vec!["'zenoh', which aimrt.channel.backends does not list"],
        ),
        (
            "module config of the wrong type",
            format!("aimrt:\n{DEMO_PKG}\nDemoModule:\n  work_executor: [1]\n  thread_safe_executor: x\n"),
            vec!["DemoModule", "work_executor"],
        ),
    ]
}

#[test]
fn broken_configs_exit_255_with_the_location() {
    let cases = broken_configs();
    assert!(cases.len() >= 30);
    for (what, cfg, expected) in cases {
        let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        // A module reads its own config from the file the runtime hands over.
        let location = if what.starts_with("module config") {
            "temp_cfg_file_for_DemoModule.yaml"
        } else {
            "cfg.yaml:"
        };
        let mut all = vec![location];
        all.extend(expected);
        eprintln!("case: {what}");
        assert_failure(&out, &all);
    }
}

#[test]
fn an_http_port_in_use_is_a_clear_failure() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let port = taken.local_addr().expect("addr").port();
    let cfg = rpc(
        &format!("{{http_options: {{listen_port: {port}}}}}"),
        "    backends:\n      - type: http\n",
    );
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            &format!("cannot listen on 127.0.0.1:{port}"),
            "cfg.yaml:",
            "listen_port",
        ],
    );
}

#[test]
fn broken_command_lines_exit_255_and_name_the_flag() {
    let cases: &[(&[&str], &[&str])] = &[
        (&["--running_duration=abc"], &["running_duration", "abc"]),
        (
            &["--cfg_file_path"],
            &["cfg_file_path", "missing its value"],
        ),
        (
            &["--cfg_file_pth=a.yaml"],
            &["did you mean '--cfg_file_path'"],
        ),
        (&["--register_signal=maybe"], &["register_signal", "maybe"]),
        (
            &["--dump_init_reprot"],
            &["did you mean '--dump_init_report'"],
        ),
        (
            &["--cfg_file_path=./no_such_config.yaml"],
            &["no_such_config.yaml"],
        ),
    ];
    for (args, expected) in cases {
        let out = run_main(None, args, LIMIT);
        eprintln!("case: {args:?}");
        assert_failure(&out, expected);
    }
}

#[test]
fn an_empty_config_file_is_a_valid_empty_config() {
    for text in ["", "\n", "# only a comment\n", "aimrt:\n", "aimrt: ~\n"] {
        let out = run_main(
            Some(text),
            &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
            LIMIT,
        );
        assert_eq!(
            out.code,
            Some(0),
            "{text:?}\n{}\n{}",
            out.stdout,
            out.stderr
        );
    }
}
