//! `normal_pb_rpc_server_app <cfg>`: AimRT's app-mode RPC server. The sync server module
//! is registered in code; the config's pkg `libpb_rpc_client_pkg.so` brings the client.

use aimrt_rpc_examples::{server, ServerModule};

fn main() -> std::process::ExitCode {
    app_examples::run_app(vec![Box::new(ServerModule::new(server::Style::Sync))])
}
