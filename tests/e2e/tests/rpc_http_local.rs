//! The same module RPC scenario as `rpc_local`, with every call carried by net_plugin's
//! `http` backend over loopback (the runtime is client and server of itself): each way a
//! call ends reaches the caller as the same status, the deadline holds across HTTP,
//! 1 000 concurrent calls share a capped connection pool, and the calls in flight at
//! shutdown are answered on both sides.

use std::time::Duration;

use aimrt_e2e::lib;
use aimrt_e2e::rpc_modules::run_scenario;
use aimrt_plugin_api::RpcStatus;

#[test]
fn http_calls_end_exactly_once_in_every_way() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let cfg = format!(
        r#"aimrt:
  plugin:
    plugins:
      - name: std_executors
        path: {std}
      - name: net_plugin
        path: {net}
        options:
          thread_num: 2
          http_options:
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
      - type: http
        options:
          max_connections_per_host: 8
          clients_options:
            - func_name: "(.*)"
              server_url: http://127.0.0.1:{port}
    clients_options:
      - func_name: "(.*)"
        enable_backends: [http]
    servers_options:
      - func_name: "(.*)"
        enable_backends: [http]
"#,
        std = lib("libaimrt_std_executors_plugin.so").display(),
        net = lib("libaimrt_net_plugin.so").display(),
    );
    let s = run_scenario(&cfg, Some("json"));
    let r = &s.results;
    let get = |k: &str| r.get(k).map(String::as_str).unwrap_or("<missing>");
    assert_eq!(get("done"), "true", "{r:#?}");
    assert_eq!(get("before start"), "err: 2011");
    assert_eq!(get("sync"), "ok: echo hi via http from ");
    assert_eq!(
        get("same object"),
        "false",
        "over HTTP the request is a copy"
    );
    assert_eq!(get("future"), "ok: echo f via http from ");
    assert_eq!(get("used ctx"), "err: 2003");
    assert_eq!(get("callback"), "ok: echo cb via http from ");
    assert_eq!(get("slow"), "err: 2");
    assert_eq!(get("slow took < 250 ms"), "true");
    assert_eq!(get("slow inline"), "err: 2");
    assert_eq!(
        get("Panic"),
        "err: 1008",
        "the code crosses HTTP in aimrt-rs-status"
    );
    assert_eq!(get("Status"), "err: 1002");
    assert_eq!(get("Drop"), "err: 1008");
    assert_eq!(get("Missing"), "err: 1003");
    assert_eq!(get("Async"), "ok: async Async");
    assert_eq!(get("Refused"), "err: 1009");
    // The service runs on the serial executor the caller blocks: the deadline ends it.
    assert_eq!(get("blocking on the service's serial executor"), "err: 2");
    assert_eq!(get("OnSerial from elsewhere"), "ok: serial y");
    assert_eq!(get("concurrent ok"), "1000");
    assert_eq!(get("filter starts = ends"), "true true");
    assert_eq!(get("chain"), "ok: abc|", "only the passed key goes along");
    // The 100 calls in flight when the runtime shut down: answered "not ready".
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
