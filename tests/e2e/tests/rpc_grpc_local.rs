//! The same module RPC scenario as `rpc_local` and `rpc_http_local`, with every call
//! carried by grpc_plugin's `grpc` backend over loopback (the runtime is client and server
//! of itself): each way a call ends reaches the caller as the same status (AimRT's code
//! crosses in `aimrt-rs-status`), the deadline holds across gRPC, 1 000 concurrent calls
//! share one HTTP/2 connection, and the calls in flight at shutdown are answered.

use aimrt_e2e::lib;
use aimrt_e2e::rpc_modules::{assert_carried_between_processes, run_scenario};

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
    assert_carried_between_processes(&s, "grpc");
}
