//! `normal_pb_rpc_client_app <cfg>`: AimRT's app-mode RPC client. The sync client module
//! is registered in code; the config's pkg `libpb_rpc_server_pkg.so` brings the server
//! (renamed `example_service` by both modules' config).

use aimrt_rpc_examples::{client, ClientModule};

fn main() -> std::process::ExitCode {
    app_examples::run_app(vec![Box::new(ClientModule::new(client::Style::Sync))])
}
