//! Failures that need more than a corpus case (`tests/corpus.rs` runs those): a port
//! another process holds.

use std::time::Duration;

use aimrt_e2e::{assert_failure, run_main};

const LIMIT: Duration = Duration::from_secs(60);

const NET_PLUGIN: &str =
    "      - name: net_plugin\n        path: ${AIMRT_LIB_DIR}/libaimrt_net_plugin.so\n";

/// `net_plugin` with `options`, and an `aimrt.rpc` section.
fn rpc(net_options: &str, rpc: &str) -> String {
    format!("aimrt:\n  plugin:\n    plugins:\n{NET_PLUGIN}        options: {net_options}\n  rpc:\n{rpc}")
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
            &format!("cannot listen for HTTP on 127.0.0.1:{port}"),
            "cfg.yaml:",
            "listen_port",
        ],
    );
}

/// The tcp and udp subscribers' ports taken: the same failure, with the fix for the kind.
#[test]
fn a_tcp_or_udp_port_in_use_is_a_clear_failure() {
    let tcp = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let udp = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
    let cases = [
        (
            "pb_chn_tcp_sub",
            "TCP",
            tcp.local_addr().unwrap().port(),
            "tcp_options",
        ),
        (
            "pb_chn_udp_sub",
            "UDP",
            udp.local_addr().unwrap().port(),
            "udp_options",
        ),
    ];
    for (example, what, port, key) in cases {
        let cfg = aimrt_e2e::net_example(example, port);
        let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        assert_failure(
            &out,
            &[
                &format!("cannot listen for {what} on 127.0.0.1:{port}"),
                &format!("another socket has the port; choose another {key}.listen_port (0 picks a free one)"),
                "cfg.yaml:",
            ],
        );
    }
}

/// An OS error that the failure line already carries is not appended a second time (it
/// was: `cannot write '…': File exists (os error 17): File exists (os error 17)`).
#[test]
fn an_os_error_is_said_once() {
    let cases = [
        (
            "aimrt:\n  configurator:\n    temp_cfg_path: ./cfg.yaml\n  executor:\n    executors:\n      - name: work_thread_pool\n        type: asio_thread\n  module:\n    pkgs:\n      - path: ${AIMRT_LIB_DIR}/libdemo_pkg.so\nDemoModule:\n  work_executor: work_thread_pool\n  thread_safe_executor: work_thread_pool\n",
            vec!["--cfg_file_path=./cfg.yaml"],
            "File exists (os error 17)",
        ),
        (
            "aimrt:\n  log:\n    core_lvl: Info\n",
            vec![
                "--cfg_file_path=./cfg.yaml",
                "--dump_cfg_file",
                "--dump_cfg_file_path=./no/such/dir/dump.yaml",
            ],
            "No such file or directory (os error 2)",
        ),
    ];
    for (cfg, args, error) in cases {
        let out = run_main(Some(cfg), &args, LIMIT);
        assert_failure(&out, &[error]);
        let line = out.failure_line().unwrap_or_default();
        assert_eq!(line.matches(error).count(), 1, "{line}");
    }
}
