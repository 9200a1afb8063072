//! `libpb_rpc_pkg.so`: every module of AimRT's pb_rpc examples in one pkg (calls between
//! them pass the request and response objects themselves).

use aimrt_rpc_examples::{
    client, server, BenchmarkRpcClientModule, ClientModule, ProxyRpcCoModule, ServerModule,
};

aimrt_plugin_api::export_modules!(
    "BenchmarkRpcClientModule" => BenchmarkRpcClientModule::default,
    "NormalRpcSyncClientModule" => || ClientModule::new(client::Style::Sync),
    "NormalRpcAsyncClientModule" => || ClientModule::new(client::Style::Async),
    "NormalRpcFutureClientModule" => || ClientModule::new(client::Style::Future),
    "NormalRpcCoClientModule" => || ClientModule::new(client::Style::Co),
    "NormalRpcSyncServerModule" => || ServerModule::new(server::Style::Sync),
    "NormalRpcAsyncServerModule" => || ServerModule::new(server::Style::Async),
    "NormalRpcCoServerModule" => || ServerModule::new(server::Style::Co),
    "ProxyRpcCoModule" => ProxyRpcCoModule::default,
);
