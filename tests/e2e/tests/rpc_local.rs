//! Module RPC over the `local` backend, in process: every call style, every way a call can
//! end (response, service status, panic, dropped reply, deadline, unknown function, used
//! context, refusing executor, blocking where it could never be answered, before start,
//! shutdown with calls in flight), 1 000 concurrent calls, and the zero-copy same-library
//! path. One test, because runtimes in one process run one after another.

use aimrt_e2e::lib;
use aimrt_e2e::rpc_modules::run_scenario;
use aimrt_plugin_api::RpcStatus;

#[test]
fn local_calls_end_exactly_once_in_every_way() {
    let cfg = format!(
        r#"aimrt:
  plugin:
    plugins:
      - name: std_executors
        path: {}
  executor:
    executors:
      - name: refusing
        type: simple_thread
        options:
          queue_threshold: 0
      - name: serial
        type: simple_thread
  rpc:
    backends:
      - type: local
    clients_options:
      - func_name: "(.*)"
        enable_backends: [local]
    servers_options:
      - func_name: "(.*)"
        enable_backends: [local]
"#,
        lib("libaimrt_std_executors_plugin.so").display()
    );
    let s = run_scenario(&cfg, None);
    let r = &s.results;
    let get = |k: &str| r.get(k).map(String::as_str).unwrap_or("<missing>");
    assert_eq!(get("done"), "true", "{r:#?}");
    assert_eq!(get("before start"), "err: 2011");
    assert!(
        get("register in start").contains("initialize only"),
        "{r:#?}"
    );
    assert_eq!(get("sync"), "ok: echo hi via local from Client");
    assert_eq!(
        get("same object"),
        "true",
        "same library: the request is not copied"
    );
    assert_eq!(get("future"), "ok: echo f via local from Client");
    assert_eq!(get("function name in ctx"), "serde:/test.Svc/Echo");
    assert_eq!(get("used ctx"), "err: 2003");
    assert_eq!(get("callback"), "ok: echo cb via local from Client");
    assert_eq!(get("slow"), "err: 2");
    assert_eq!(get("slow took < 250 ms"), "true");
    assert_eq!(get("slow inline"), "err: 2");
    assert_eq!(get("Panic"), "err: 1008");
    assert_eq!(get("Status"), "err: 1002");
    assert_eq!(get("Drop"), "err: 1008");
    assert_eq!(get("Missing"), "err: 1003");
    assert_eq!(get("Async"), "ok: async Async");
    assert_eq!(get("Refused"), "err: 1009");
    assert_eq!(
        get("blocking on the service's serial executor"),
        "err: 2002"
    );
    assert_eq!(get("refused at once"), "true");
    assert_eq!(get("OnSerial from elsewhere"), "ok: serial y");
    assert_eq!(get("concurrent ok"), "1000");
    assert_eq!(get("filter starts = ends"), "true true");
    assert_eq!(get("chain"), "ok: abc|", "only the passed key goes along");
    // The 100 calls in flight at shutdown were answered "not ready" before run returned.
    assert_eq!(s.in_flight.len(), 100);
    assert!(
        s.in_flight.iter().all(|st| *st == RpcStatus::CLI_NOT_READY),
        "{:?}",
        s.in_flight
    );
}
