//! The same module RPC scenario as `rpc_local` and `rpc_http_local`, with every call
//! carried by grpc_plugin's `grpc` backend over loopback (the runtime is client and server
//! of itself): each way a call ends reaches the caller as the same status (AimRT's code
//! crosses in `aimrt-rs-status`), the deadline holds across gRPC, 1 000 concurrent calls
//! share one HTTP/2 connection, and the calls in flight at shutdown are answered.

use std::time::Duration;

use aimrt_e2e::lib;
use aimrt_e2e::rpc_modules::run_scenario;
use aimrt_plugin_api::RpcStatus;

#[test]
fn grpc_calls_end_exactly_once_in_every_way() {
    let port = aimrt_e2e::free_port(false);
    let cfg = format!(
        r#"aimrt:
  plugin:
    plugins:
      - name: std_executors
        path: {std}
      - name: grpc_plugin
        path: {grpc}
        options:
          thread_num: 2
          listen_ip: 127.0.0.1
          listen_port: {port}
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
      - type: grpc
        options:
          clients_options:
            - func_name: "(.*)"
              server_url: http://127.0.0.1:{port}
    clients_options:
      - func_name: "(.*)"
        enable_backends: [grpc]
    servers_options:
      - func_name: "(.*)"
        enable_backends: [grpc]
"#,
        std = lib("libaimrt_std_executors_plugin.so").display(),
        grpc = lib("libaimrt_grpc_plugin.so").display(),
    );
    let s = run_scenario(&cfg, Some("json"));
    let r = &s.results;
    let get = |k: &str| r.get(k).map(String::as_str).unwrap_or("<missing>");
    assert_eq!(get("done"), "true", "{r:#?}");
    assert_eq!(get("before start"), "err: 2011");
    assert_eq!(get("sync"), "ok: echo hi via grpc from ");
    assert_eq!(
        get("same object"),
        "false",
        "over gRPC the request is a copy"
    );
    assert_eq!(get("future"), "ok: echo f via grpc from ");
    assert_eq!(get("used ctx"), "err: 2003");
    assert_eq!(get("callback"), "ok: echo cb via grpc from ");
    assert_eq!(get("slow"), "err: 2");
    assert_eq!(get("slow took < 250 ms"), "true");
    assert_eq!(get("slow inline"), "err: 2");
    assert_eq!(
        get("Panic"),
        "err: 1008",
        "the code crosses in aimrt-rs-status"
    );
    assert_eq!(get("Status"), "err: 1002");
    assert_eq!(get("Drop"), "err: 1008");
    assert_eq!(get("Missing"), "err: 1003");
    assert_eq!(get("Async"), "ok: async Async");
    assert_eq!(get("Refused"), "err: 1009");
    assert_eq!(get("blocking on the service's serial executor"), "err: 2");
    assert_eq!(get("OnSerial from elsewhere"), "ok: serial y");
    assert_eq!(get("concurrent ok"), "1000");
    assert_eq!(get("filter starts = ends"), "true true");
    assert_eq!(get("chain"), "ok: abc|", "only the passed key goes along");
    assert_eq!(s.in_flight.len(), 100);
    assert!(
        s.in_flight.iter().all(|st| *st == RpcStatus::CLI_NOT_READY),
        "{:?}",
        s.in_flight
    );
    assert!(
        s.shutdown_took < Duration::from_secs(10),
        "shutdown took {:?}",
        s.shutdown_took
    );
}
