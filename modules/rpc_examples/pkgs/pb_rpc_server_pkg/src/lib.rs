//! `libpb_rpc_server_pkg.so`: the server modules of AimRT's pb_rpc examples.

use aimrt_rpc_examples::{server, ProxyRpcCoModule, ServerModule};

aimrt_plugin_api::export_modules!(
    "NormalRpcSyncServerModule" => || ServerModule::new(server::Style::Sync),
    "NormalRpcAsyncServerModule" => || ServerModule::new(server::Style::Async),
    "NormalRpcCoServerModule" => || ServerModule::new(server::Style::Co),
    "ProxyRpcCoModule" => ProxyRpcCoModule::default,
);
