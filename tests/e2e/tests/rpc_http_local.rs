//! The same module RPC scenario as `rpc_local`, with every call carried by net_plugin's
//! `http` backend over loopback (the runtime is client and server of itself): each way a
//! call ends reaches the caller as the same status, the deadline holds across HTTP,
//! 1 000 concurrent calls share a capped connection pool, and the calls in flight at
//! shutdown are answered on both sides.

use aimrt_e2e::lib;
use aimrt_e2e::rpc_modules::{assert_carried_between_processes, run_scenario};

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
    assert_carried_between_processes(&s, "http");
}
