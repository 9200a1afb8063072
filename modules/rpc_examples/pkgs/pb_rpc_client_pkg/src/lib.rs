//! `libpb_rpc_client_pkg.so`: the client modules of AimRT's pb_rpc examples.

use aimrt_rpc_examples::{client, BenchmarkRpcClientModule, ClientModule};

aimrt_plugin_api::export_modules!(
    "BenchmarkRpcClientModule" => BenchmarkRpcClientModule::default,
    "NormalRpcSyncClientModule" => || ClientModule::new(client::Style::Sync),
    "NormalRpcAsyncClientModule" => || ClientModule::new(client::Style::Async),
    "NormalRpcFutureClientModule" => || ClientModule::new(client::Style::Future),
    "NormalRpcCoClientModule" => || ClientModule::new(client::Style::Co),
);
