//! The runtime as a library, in this process: it does not link std_executors, so
//! `simple_thread` exists only when the plugin is loaded from its shared library.

use std::time::Duration;

use aimrt_e2e::lib;
use aimrt_runtime::{Runtime, RuntimeOptions};

fn run(cfg: &str) -> Result<(), aimrt_runtime::Error> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    std::fs::write(&path, cfg).unwrap();
    Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_millis(200)),
        ..Default::default()
    })
    .run()
}

#[test]
fn std_executors_load_from_their_shared_library() {
    let so = lib("libaimrt_std_executors_plugin.so");
    let with_plugin = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: std_executors\n        path: {}\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n",
        so.display()
    );
    run(&with_plugin).expect("simple_thread from the .so");

    let without =
        "aimrt:\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n";
    let err = run(without).unwrap_err().to_string();
    assert!(
        err.contains("unknown executor type 'simple_thread'"),
        "{err}"
    );
}
