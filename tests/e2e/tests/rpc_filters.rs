//! RPC filters from a plugin (ABI 1.9): `config/rpc_filter_plugin.yaml` with
//! `libexample_filters_plugin.so` — a client filter that changes the context every call
//! carries and hears each answer, a server filter that answers calls itself, the order of
//! a chain with the built-in `debug_log`, the init report, the errors of names that are
//! not filters of their side, and both sides of a call between two processes over http
//! and zenoh.

use std::time::Duration;

use aimrt_e2e::{assert_failure, repo_config, run_main, run_main_in, Output};

const LIMIT: Duration = Duration::from_secs(60);

/// The example calling 20 times a second, with `edit` applied to it.
fn example(edit: impl Fn(String) -> String) -> String {
    let cfg = repo_config("rpc_filter_plugin");
    assert!(cfg.contains("rpc_frq: 2\n"), "{cfg}");
    edit(cfg.replace("rpc_frq: 2\n", "rpc_frq: 20\n"))
}

/// The text after `marker` on each line that has it.
fn after<'a>(out: &'a Output, marker: &str) -> Vec<&'a str> {
    out.stdout
        .lines()
        .filter_map(|l| l.split_once(marker).map(|(_, rest)| rest))
        .collect()
}

const FUNC: &str = "pb:/aimrt.protocols.example.ExampleService/GetFooData";

#[test]
fn the_example_stamps_each_call_that_the_server_then_lets_through() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_main_in(
        dir.path(),
        Some(&example(|c| c)),
        &[
            "--cfg_file_path=./cfg.yaml",
            "--running_duration=1",
            "--dump_init_report=true",
        ],
        LIMIT,
    );
    out.assert_exit(0, "the rpc filter example");
    let answered = after(
        &out,
        "]Client get rpc ret, status: suc, code 0, msg: OK, rsp: ",
    );
    assert!(answered.len() >= 4, "{}", out.stdout);
    // The server handled every call, each with its own trace id: the client filter's
    // context reached the service through `local`.
    let handled = after(&out, "]Server handle new rpc call. context: ");
    assert_eq!(handled.len(), answered.len(), "{}", out.stdout);
    for (i, line) in handled.iter().enumerate() {
        let stamp = format!("{{\"trace-id\":\"NormalRpcCoClientModule-{}\"}}", i + 1);
        assert!(line.contains(&stamp), "{stamp} not in {line}");
    }
    // `debug_log` is listed first, so it runs last, inside `trace_id`, and logs the stamp.
    let logged = after(&out, "]RPC client start new rpc call. func name: ");
    assert_eq!(logged.len(), answered.len(), "{}", out.stdout);
    assert!(
        logged.iter().all(|l| l.contains("\"trace-id\":")),
        "{logged:?}"
    );
    // The client filter heard each answer once, after `debug_log` (the inner filter) did.
    let heard = after(&out, "]trace_id: call of '");
    assert_eq!(heard.len(), answered.len(), "{}", out.stdout);
    for (i, line) in heard.iter().enumerate() {
        let expected = format!(
            "{FUNC}' with trace-id NormalRpcCoClientModule-{} answered suc, code 0, msg: OK",
            i + 1
        );
        assert_eq!(*line, expected);
    }
    let lines: Vec<&str> = out.stdout.lines().collect();
    let first = |marker: &str| lines.iter().position(|l| l.contains(marker)).unwrap();
    assert!(first("]RPC client get rpc ret.") < first("]trace_id: call of '"));
    assert!(
        out.stdout.contains(&format!(
            "Module RPC: {} calls, 0 answered with an error status",
            answered.len()
        )),
        "{}",
        out.stdout
    );
    let report = std::fs::read_to_string(dir.path().join("init_report.txt")).unwrap();
    for part in [
        "Rpc Client Filter List\n[ debug_log , time_cost , trace_id ]",
        "Rpc Server Filter List\n[ debug_log , time_cost , require_trace_id ]",
        "|  debug_log,trace_id  |",
        "|  require_trace_id  |",
    ] {
        assert!(report.contains(part), "no {part:?} in:\n{report}");
    }
}

#[test]
fn a_server_filter_answers_calls_without_a_trace_id_and_each_is_counted() {
    let cfg = example(|c| {
        c.replace(
            "enable_filters: [debug_log, trace_id]",
            "enable_filters: [debug_log]",
        )
    });
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    out.assert_exit(0, "the rpc filter example without trace_id");
    let failed = after(
        &out,
        "]Client get rpc error ret, status: fail, code 1008, msg: Server handle failed",
    );
    assert!(failed.len() >= 4, "{}", out.stdout);
    assert!(
        !out.stdout.contains("]Server handle new rpc call."),
        "the service ran:\n{}",
        out.stdout
    );
    assert!(!out.stdout.contains("]trace_id: call of"), "{}", out.stdout);
    // The reason is logged (rate-limited) and every call is counted as failed.
    assert!(
        out.stdout.contains(&format!("Rpc call failed: call of '{FUNC}' failed on the server: server filter 'require_trace_id' of 'example_filters' answered: the call has no trace-id in its context")),
        "{}",
        out.stdout
    );
    let n = failed.len();
    assert!(
        out.stdout.contains(&format!(
            "Module RPC: {n} calls, {n} answered with an error status"
        )),
        "{}",
        out.stdout
    );
}

#[test]
fn a_filter_of_the_other_side_or_of_no_plugin_is_an_error_naming_the_filters() {
    let cfg = example(|c| {
        c.replace(
            "enable_filters: [require_trace_id]",
            "enable_filters: [trace_id]",
        )
    });
    // The servers' rule names it, at its line.
    let line = 1 + cfg
        .lines()
        .position(|l| l.ends_with("enable_filters: [trace_id]"))
        .unwrap();
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            &format!("cfg.yaml:{line}:"),
            "'trace_id'",
            "debug_log, time_cost, require_trace_id",
        ],
    );

    let cfg = example(|c| {
        c.replace(
            "      - name: example_filters\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_filters_plugin.so\n",
            "",
        )
        .replace("  plugin:\n    plugins:\n", "")
    });
    assert!(!cfg.contains("name: example_filters"), "{cfg}");
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    // The servers' rules are read first.
    assert_failure(
        &out,
        &[
            "'require_trace_id'",
            "the filters are: debug_log, time_cost",
        ],
    );
}

/// `cfg` with `libexample_filters_plugin.so` loaded beside its transport plugin and
/// `filters` on the one rule of `key` (`clients_options` or `servers_options`), whose
/// backend is `backend`.
fn with_filters_on(cfg: &str, backend: &str, key: &str, filters: &str) -> String {
    let plugin = format!(
        "  plugin:\n    plugins:\n      - name: example_filters\n        path: {}\n",
        aimrt_e2e::lib("libexample_filters_plugin.so").display()
    );
    let rule =
        format!("    {key}:\n      - func_name: \"(.*)\"\n        enable_backends: [{backend}]\n");
    let cfg = cfg
        .replacen("  plugin:\n    plugins:\n", &plugin, 1)
        .replacen(
            &rule,
            &format!("{rule}        enable_filters: [{filters}]\n"),
            1,
        );
    assert!(
        cfg.contains(&format!("enable_filters: [{filters}]")),
        "{cfg}"
    );
    cfg
}

/// [`with_filters_on`] a rule of net_plugin's `http`.
fn with_filters(cfg: &str, key: &str, filters: &str) -> String {
    with_filters_on(cfg, "http", key, filters)
}

/// Over net_plugin's `http` between two processes: the key the client filter adds crosses
/// as a header and the server filter reads it, and a client without it gets the server
/// filter's status back.
#[test]
fn filters_on_both_sides_of_an_http_call_between_two_processes() {
    let server_cfg = with_filters(
        &aimrt_e2e::net_example("pb_rpc_http_server", 0),
        "servers_options",
        "require_trace_id",
    );
    let mut server = aimrt_e2e::Running::start(&server_cfg);
    let addr = server.http_address(LIMIT);
    server.wait_for("Module manager start completed.", LIMIT);
    let port = addr.rsplit(':').next().unwrap().parse().unwrap();
    // One call, 2 s after start (`rpc_frq: 0.5`).
    let client_cfg = aimrt_e2e::net_example("pb_rpc_http_client", port);

    let stamped = aimrt_e2e::run_for(&with_filters(&client_cfg, "clients_options", "trace_id"), 3);
    assert!(
        stamped.stdout.contains(&format!("]trace_id: call of '{FUNC}' with trace-id NormalRpcCoClientModule-1 answered suc, code 0, msg: OK")),
        "{}",
        stamped.stdout
    );
    let (_, line) = server.wait_for("Server handle new rpc call. context: ", LIMIT);
    for kv in [
        r#"{"trace-id":"NormalRpcCoClientModule-1"}"#,
        r#"{"aimrt-backend":"http"}"#,
    ] {
        assert!(line.contains(kv), "{kv} not in {line}");
    }

    let plain = aimrt_e2e::run_for(&client_cfg, 3);
    assert!(
        plain.stdout.contains(
            "]Client get rpc error ret, status: fail, code 1008, msg: Server handle failed"
        ),
        "{}",
        plain.stdout
    );
    server.wait_for(
        "server filter 'require_trace_id' of 'example_filters' answered: the call has no trace-id in its context",
        LIMIT,
    );
}

/// A client filter hears an answer the backend gives on its own thread: an http call to a
/// port nobody listens on fails, and the filter hears the failure once, before the module.
#[test]
fn a_client_filter_hears_the_failure_a_backend_answers() {
    let port = aimrt_e2e::free_port(false);
    let cfg = with_filters(
        &aimrt_e2e::net_example("pb_rpc_http_client", port),
        "clients_options",
        "trace_id",
    );
    let out = aimrt_e2e::run_for(&cfg, 3);
    let heard = after(&out, "]trace_id: call of '");
    let failed = after(&out, "]Client get rpc error ret, status: ");
    assert_eq!((heard.len(), failed.len()), (1, 1), "{}", out.stdout);
    let status = failed[0];
    assert!(status.contains("code 2010"), "{status}");
    assert_eq!(
        heard[0],
        format!("{FUNC}' with trace-id NormalRpcCoClientModule-1 answered {status}")
    );
    let lines: Vec<&str> = out.stdout.lines().collect();
    let first = |marker: &str| lines.iter().position(|l| l.contains(marker)).unwrap();
    assert!(first("]trace_id: call of '") < first("]Client get rpc error ret"));
}

/// Over zenoh between two processes: the key the client filter adds crosses in the
/// payload's meta and the server filter lets the call through.
#[test]
fn filters_on_both_sides_of_a_zenoh_call_between_two_processes() {
    const WAIT: Duration = Duration::from_secs(30);
    let peers = aimrt_e2e::ZenohPeers::new("rpc_filters");
    let start = |cfg: &str, side: &str| {
        let mut p = aimrt_e2e::Running::start_env(cfg, &peers.env(side));
        p.wait_for("Module manager start completed.", WAIT);
        p
    };
    let server_cfg = with_filters_on(
        &aimrt_e2e::zenoh_example("pb_rpc_server"),
        "zenoh",
        "servers_options",
        "require_trace_id",
    );
    let mut server = start(&server_cfg, "b");
    let client_cfg = with_filters_on(
        &aimrt_e2e::zenoh_example("pb_rpc_client").replace("rpc_frq: 0.5", "rpc_frq: 5"),
        "zenoh",
        "clients_options",
        "trace_id",
    );
    let mut client = start(&client_cfg, "a");
    let (_, heard) = client.wait_for("]trace_id: call of '", WAIT);
    assert!(
        heard.ends_with("with trace-id NormalRpcCoClientModule-1 answered suc, code 0, msg: OK"),
        "{heard}"
    );
    let (_, line) = server.wait_for("Server handle new rpc call. context: ", WAIT);
    for kv in [
        r#"{"trace-id":"NormalRpcCoClientModule-1"}"#,
        r#"{"aimrt-backend":"zenoh"}"#,
    ] {
        assert!(line.contains(kv), "{kv} not in {line}");
    }
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
}

/// A plugin's own service (time_manipulator's control service, bytes in and bytes out)
/// gets the server filters its `servers_options` rule lists, as in AimRT: `debug_log`
/// logs the JSON request and response (a `pb` call without them) and `time_cost` the
/// time; a plugin's server filter answers a call without a `trace-id` itself, and lets one
/// with it (an HTTP header) through.
#[test]
fn server_filters_run_around_a_plugins_own_service() {
    let cfg = aimrt_e2e::with_port(&repo_config("time_manipulator"), 0);
    let rule = "        enable_backends: [http]\n";
    assert!(cfg.contains(rule), "{cfg}");
    let cfg = cfg
        .replace(
            rule,
            "        enable_backends: [http]\n        enable_filters: [debug_log, time_cost, require_trace_id]\n",
        )
        .replace(
            "  log:\n",
            "      - name: example_filters\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_filters_plugin.so\n  log:\n",
        );
    let mut app = aimrt_e2e::Running::start_program(
        &aimrt_e2e::aimrt_main(),
        &["--cfg_file_path=./cfg.yaml", "--dump_init_report=true"],
        &cfg,
    );
    let addr = app.http_address(Duration::from_secs(30));
    // The init report lists the plugin's services with their backends and filters.
    let report = std::fs::read_to_string(app.dir().join("init_report.txt")).unwrap();
    let info = report
        .split_once("Rpc Server Info")
        .unwrap_or_else(|| panic!("no Rpc Server Info in:\n{report}"))
        .1;
    let row = info
        .lines()
        .find(|l| l.contains("TimeManipulatorService/GetTimeRatio "))
        .unwrap_or_else(|| panic!("no row of GetTimeRatio in:\n{report}"));
    assert!(
        row.contains("time_manipulator_plugin")
            && row.contains("http")
            && row.contains("debug_log,time_cost,require_trace_id"),
        "{row}"
    );
    let path = "/rpc/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService/GetTimeRatio";
    let body = br#"{"executor_name": "time_schedule_executor"}"#;
    let json = ("content-type", "application/json");

    let (code, text) = aimrt_e2e::http(&addr, "POST", path, &[json], body);
    assert_eq!(
        (code, text.as_str()),
        (
            500,
            r#"{"error":"server filter 'require_trace_id' of 'example_filters' answered: the call has no trace-id in its context"}"#
        )
    );
    app.wait_for(
        "]Rpc call failed: call of 'pb:/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService/GetTimeRatio' failed on the server: server filter 'require_trace_id' of 'example_filters' answered: the call has no trace-id in its context: fail, code 1008, msg: Server handle failed",
        Duration::from_secs(10),
    );

    let (code, text) = aimrt_e2e::http(&addr, "POST", path, &[json, ("trace-id", "t-1")], body);
    assert_eq!(
        (code, text.as_str()),
        (200, r#"{"time_ratio":2,"code":0,"msg":""}"#)
    );
    let func = "pb:/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService/GetTimeRatio";
    let (_, started) = app.wait_for(
        &format!("RPC server start new rpc call. func name: {func}, context: "),
        Duration::from_secs(10),
    );
    assert!(
        started.contains(r#"req: {"executor_name": "time_schedule_executor"}"#),
        "{started}"
    );
    let (_, ret) = app.wait_for(
        &format!("RPC server get rpc ret. func name: {func}, status: suc, code 0, msg: OK, rsp: "),
        Duration::from_secs(10),
    );
    assert!(
        ret.ends_with(r#"rsp: {"time_ratio":2,"code":0,"msg":""}"#),
        "{ret}"
    );
    app.wait_for(
        &format!("RPC server time cost. func name: {func}, "),
        Duration::from_secs(10),
    );
    // In `pb`, which this service does not take: the filters see the request without
    // JSON, and the service's refusal goes back through them as its own status.
    let pb = ("content-type", "application/protobuf");
    let (code, text) = aimrt_e2e::http(&addr, "POST", path, &[pb, ("trace-id", "t-2")], b"\n\x01x");
    assert_eq!(code, 415, "{text}");
    let (_, started) = app.wait_for(
        &format!("RPC server start new rpc call. func name: {func}, context: "),
        Duration::from_secs(10),
    );
    assert!(
        started.contains(r#"{"aimrt-serialization_type":"pb"}"#) && !started.contains("req:"),
        "{started}"
    );
    app.wait_for(
        &format!("RPC server get rpc error ret. func name: {func}, status: fail, code 1004"),
        Duration::from_secs(10),
    );
    assert_eq!(app.interrupt(Duration::from_secs(20)), Some(0));
    // The refused call was logged and never reached the service: `debug_log`, listed
    // first, is innermost, so only the calls let through show.
    let text = app.text();
    assert_eq!(
        text.matches("RPC server start new rpc call. func name: ")
            .count(),
        2,
        "{text}"
    );
    // Three calls reached the plugin's service through http; two failed (the filter's
    // refusal, the format the service does not take).
    assert!(
        text.contains(
            "]Plugin services: 3 calls received through backends, 2 answered with an error status"
        ),
        "{text}"
    );
}
