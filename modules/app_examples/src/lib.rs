//! App mode examples: binaries that embed the runtime instead of running `aimrt_main`.
//!
//! Each binary takes the config path as its only argument (as AimRT's `*_app` examples),
//! registers its modules in code, starts the runtime, serves the main thread with
//! [`App::spin`](aimrt_runtime::App::spin) until Ctrl-C, and shuts down:
//!
//! ```text
//! cargo build --workspace
//! ./target/debug/helloworld_app ./config/helloworld_app_mode.yaml
//! ./target/debug/pb_chn_publisher_app ./config/pb_chn_publisher_app.yaml
//! ./target/debug/pb_chn_subscriber_app ./config/pb_chn_subscriber_app.yaml
//! ./target/debug/normal_pb_rpc_client_app ./config/pb_rpc_client_app.yaml
//! ./target/debug/normal_pb_rpc_server_app ./config/pb_rpc_server_app.yaml
//! ```
#![deny(unsafe_code)]

use std::process::ExitCode;

use aimrt_plugin_api::Module;
use aimrt_runtime::{Runtime, RuntimeOptions};

pub use aimrt_helloworld::HelloWorldModule;

/// The body of every example binary: `<binary> <cfg.yaml>` runs `modules` (registered in
/// code, before the config's pkgs) until SIGINT/SIGTERM. Exit code 0, or 255 with one
/// `AimRT run with exception and exit. <reason>` line, as `aimrt_main`.
pub fn run_app(modules: Vec<Box<dyn Module>>) -> ExitCode {
    // Called first from each binary's `main`: no thread has started yet.
    aimrt_runtime::no_library_backtraces();
    match try_run(modules) {
        Ok(()) => ExitCode::SUCCESS,
        Err(reason) => {
            aimrt_runtime::say(format_args!("AimRT run with exception and exit. {reason}"));
            ExitCode::from(255)
        }
    }
}

fn try_run(modules: Vec<Box<dyn Module>>) -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let (Some(cfg), None) = (args.next(), args.next()) else {
        return Err("usage: <binary> <cfg_file_path> (one argument: the YAML config)".into());
    };
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(cfg.into()),
        ..RuntimeOptions::default()
    });
    runtime.builtin_plugin(aimrt_std_executors::plugin());
    for module in modules {
        runtime.register_module(module);
    }
    let app = runtime.start().map_err(|e| e.to_string())?;
    let handle = app.shutdown_handle();
    aimrt_runtime::on_signals(move || handle.request())
        .map_err(|e| format!("cannot install the SIGINT/SIGTERM handlers: {e}"))?;
    // The main thread serves the main-thread executor until Ctrl-C.
    app.spin().map_err(|e| e.to_string())?;
    app.shutdown();
    Ok(())
}
