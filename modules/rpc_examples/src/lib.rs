//! AimRT's `pb_rpc` examples in Rust, with AimRT's module names, config keys and log lines,
//! so that AimRT's `examples_cpp_pb_rpc_*` configs run with only the pkg paths changed:
//!
//! | module | what it does | config keys |
//! |---|---|---|
//! | `NormalRpc{Sync,Async,Future,Co}ClientModule` | calls `GetFooData` `rpc_frq` times a second from a loop on `work_thread_pool`, blocking / with a callback / through a future / with `.await` | `rpc_frq`, `service_name` |
//! | `NormalRpc{Sync,Async,Co}ServerModule` | serves `ExampleService`: `GetFooData` answers `"echo " + msg` | `service_name` |
//! | `ProxyRpcCoModule` | serves `GetFooData` under one name by calling `GetFooData` under another | `service_name_for_server`, `service_name_for_client` |
//! | `BenchmarkRpcClientModule` | runs `bench_plans` on `client_executor_<i>` and logs a report per plan | `max_parallel`, `bench_plans`, `service_name` |
//!
//! The modules live in this rlib; `pb_rpc_pkg`, `pb_rpc_client_pkg` and `pb_rpc_server_pkg`
//! are cdylib shells that export them.
#![deny(unsafe_code)]

mod benchmark;
pub mod client;
mod proxy;
pub mod server;

pub use benchmark::BenchmarkRpcClientModule;
pub use client::ClientModule;
pub use proxy::ProxyRpcCoModule;
pub use server::ServerModule;

use aimrt_plugin_api::Error;

/// A message as one line of JSON (AimRT's `Pb2CompactJson`).
pub fn to_json<M: serde::Serialize>(msg: &M) -> String {
    serde_json::to_string(msg).unwrap_or_else(|e| format!("<not json: {e}>"))
}

/// The optional `service_name` renaming of a module's config, read from `cfg`.
fn service_name(cfg: &serde_json::Value, key: &str) -> Result<Option<String>, Error> {
    match cfg.get(key) {
        None | Some(serde_json::Value::Null) => Ok(None),
        Some(serde_json::Value::String(s)) if !s.is_empty() => Ok(Some(s.clone())),
        Some(other) => Err(Error::msg(format!(
            "{key} is {other}; it must be a non-empty service name"
        ))),
    }
}
