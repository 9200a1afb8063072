//! End-to-end: the pb_rpc examples under the real `aimrt_main`, with real pkgs: AimRT's
//! configs with only the pkg paths changed, client and server in two libraries (each call
//! crosses as protobuf bytes, or JSON when the client asks) or in one (the objects pass).

use aimrt_e2e::{example_config, Output};

/// [`aimrt_e2e::run_for`], with no warning in the output either.
fn run(cfg: &str, secs: u32) -> Output {
    let out = aimrt_e2e::run_for(cfg, secs);
    assert!(!out.stdout.contains("[Warn]"), "{}", out.stdout);
    out
}

const RSP: &str = aimrt_e2e::RPC_EXAMPLE_RSP;

/// The first call was answered as AimRT's example answers it, and the server saw the
/// context AimRT's local backend gives.
fn check(out: &Output, server_meta: &[&str]) {
    assert!(out.stdout.contains(RSP), "{}", out.stdout);
    let server = out
        .stdout
        .lines()
        .find_map(|l| {
            l.split_once("Server handle new rpc call. context: ")
                .map(|(_, r)| r)
        })
        .unwrap_or_else(|| panic!("no server line:\n{}", out.stdout));
    assert!(
        server.starts_with("Server context, timeout: 3000ms, meta: {"),
        "{server}"
    );
    for kv in server_meta {
        assert!(server.contains(kv), "{kv} not in {server}");
    }
    assert!(
        server.ends_with(
            r#"req: {"msg":"hello world foo, count 1"}, return rsp: {"code":"0","msg":"echo hello world foo, count 1"}"#
        ),
        "{server}"
    );
}

const LOCAL_META: &[&str] = &[
    r#"{"aimrt-function_name":"pb:/aimrt.protocols.example.ExampleService/GetFooData"}"#,
    r#"{"aimrt-request_id":"1"}"#,
    r#"{"aimrt-response_id":"1"}"#,
    r#"{"aimrt-backend":"local"}"#,
    r#"{"aimrt-serialization_type":"pb"}"#,
];

#[test]
fn sync_client_and_server_in_two_pkgs() {
    // 0.5 Hz: the first call comes 2 s after start.
    let out = run(&example_config("pb_rpc_sync"), 3);
    check(&out, LOCAL_META);
    assert!(out
        .stdout
        .contains(r#"Client start new rpc call. req: {"msg":"hello world foo, count 1"}"#));
    assert!(out
        .stdout
        .contains(r#"{"aimrt-from_module":"NormalRpcSyncClientModule"}"#));
    assert!(
        out.stdout
            .contains("Module RPC: 1 calls, 0 answered with an error status"),
        "{}",
        out.stdout
    );
}

#[test]
fn async_future_and_co_clients() {
    for (name, client) in [
        ("pb_rpc_async", "NormalRpcAsyncClientModule"),
        ("pb_rpc_future", "NormalRpcFutureClientModule"),
        ("pb_rpc_co", "NormalRpcCoClientModule"),
    ] {
        let out = run(&example_config(name), 3);
        check(&out, LOCAL_META);
        assert!(
            out.stdout
                .contains(&format!(r#"{{"aimrt-from_module":"{client}"}}"#)),
            "{name}: {}",
            out.stdout
        );
    }
}

#[test]
fn co_client_and_server_in_one_pkg() {
    let out = run(&example_config("pb_rpc_single_pkg"), 3);
    check(&out, LOCAL_META);
    assert!(
        out.stdout.contains("Client rpc time cost"),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout.contains("Svr get new rpc call. context: "),
        "{}",
        out.stdout
    );
}

#[test]
fn proxy_renames_services_and_chains_two_calls() {
    let out = run(&example_config("pb_proxy_rpc_co"), 3);
    assert!(out.stdout.contains(RSP), "{}", out.stdout);
    // The client called ExampleService_1 (the proxy), which called ExampleService_2.
    assert!(
        out.stdout
            .contains(r#"{"aimrt-function_name":"pb:/ExampleService_1/GetFooData"}"#),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout
            .contains(r#"{"aimrt-function_name":"pb:/ExampleService_2/GetFooData"}"#),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout
            .contains("] Server handle new rpc call. context: "),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout
            .contains("Module RPC: 2 calls, 0 answered with an error status"),
        "{}",
        out.stdout
    );
}

#[test]
fn json_crosses_libraries_as_aimrt_prints_it() {
    let cfg = example_config("pb_rpc_sync").replace(
        "NormalRpcSyncClientModule:\n  rpc_frq: 0.5",
        "NormalRpcSyncClientModule:\n  rpc_frq: 0.5\n  serialization_type: json",
    );
    let out = run(&cfg, 3);
    let mut meta = LOCAL_META.to_vec();
    meta.retain(|m| !m.contains("serialization_type"));
    meta.push(r#"{"aimrt-serialization_type":"json"}"#);
    check(&out, &meta);
}

#[test]
fn debug_log_and_time_cost_filters_wrap_both_sides() {
    let cfg = example_config("pb_rpc_sync")
        .replace(
            "    clients_options:\n      - func_name: \"(.*)\"\n        enable_backends: [local]",
            "    clients_options:\n      - func_name: \"(.*)\"\n        enable_backends: [local]\n        enable_filters: [time_cost, debug_log]",
        )
        .replace(
            "    servers_options:\n      - func_name: \"(.*)\"\n        enable_backends: [local]",
            "    servers_options:\n      - func_name: \"(.*)\"\n        enable_backends: [local]\n        enable_filters: [debug_log]",
        );
    assert!(cfg.contains("enable_filters: [time_cost, debug_log]"));
    let out = run(&cfg, 3);
    let lines: Vec<&str> = out
        .stdout
        .lines()
        .filter(|l| l.contains("]RPC "))
        .map(|l| l.split_once("]RPC ").unwrap().1)
        .collect();
    const F: &str = "func name: pb:/aimrt.protocols.example.ExampleService/GetFooData";
    // The filter listed last is the outermost: debug_log opens first and closes last.
    assert_eq!(lines.len(), 5, "{lines:#?}");
    assert!(
        lines[0].starts_with(&format!(
            "client start new rpc call. {F}, context: Client context, timeout: 3000ms, meta: {{"
        )),
        "{}",
        lines[0]
    );
    assert!(
        lines[0].ends_with(r#", req: {"msg":"hello world foo, count 1"}"#),
        "{}",
        lines[0]
    );
    assert!(
        lines[1].starts_with(&format!(
            "server start new rpc call. {F}, context: Server context, timeout: 3000ms"
        )),
        "{}",
        lines[1]
    );
    assert_eq!(
        lines[2],
        format!(
            r#"server get rpc ret. {F}, status: suc, code 0, msg: OK, rsp: {{"code":"0","msg":"echo hello world foo, count 1"}}"#
        )
    );
    assert!(
        lines[3].starts_with(&format!("client time cost. {F}, ")) && lines[3].ends_with(" us"),
        "{}",
        lines[3]
    );
    assert_eq!(
        lines[4],
        format!(
            r#"client get rpc ret. {F}, status: suc, code 0, msg: OK, rsp: {{"code":"0","msg":"echo hello world foo, count 1"}}"#
        )
    );
}

#[test]
fn benchmark_client_reports_every_plan_without_errors() {
    for name in ["pb_rpc_benchmark", "pb_rpc_benchmark_single_pkg"] {
        let out = run(&example_config(name), 10);
        let reports: Vec<&str> = out.stdout.split("Benchmark plan ").skip(1).collect();
        assert_eq!(reports.len(), 2, "{name}:\n{}", out.stdout);
        for (i, r) in reports.iter().enumerate() {
            assert!(r.starts_with(&format!("{i} completed, report:")), "{r}");
            assert!(r.contains("\nerror rate: 0 %\n"), "{r}");
        }
        assert!(reports[0].contains("mode: bench\nmsg size: 256\nparallel: 4\nmsg count per co: 10000\ntotal count: 40000\n"), "{}", reports[0]);
        assert!(
            reports[0].contains("\ncorrect count: 40000\n"),
            "{}",
            reports[0]
        );
        assert!(reports[1].contains("mode: fixed-freq\nfreq: 1000\nmsg size: 1024\nparallel: 2\nmsg count per co: 1000\ntotal count: 2000\n"), "{}", reports[1]);
        assert!(out.stdout.contains("Bench completed."), "{}", out.stdout);
    }
}
