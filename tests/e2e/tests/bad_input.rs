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
            &format!("cannot listen on 127.0.0.1:{port}"),
            "cfg.yaml:",
            "listen_port",
        ],
    );
}
