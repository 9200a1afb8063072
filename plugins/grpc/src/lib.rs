//! `grpc_plugin`: the `grpc` RPC backend, configured like AimRT's grpc_plugin: module
//! services served as unary gRPC methods over HTTP/2 without TLS (h2c), and module calls
//! made as gRPC calls, so an aimrt-rs process, an AimRT process and any gRPC program
//! (`grpcurl -plaintext`, a Python or Go client or server) call each other. This crate is
//! the plugin as an rlib; `plugins/grpc/so` exports it from `libaimrt_grpc_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: grpc_plugin
//!         path: ./target/debug/libaimrt_grpc_plugin.so
//!         options:
//!           thread_num: 4            # the plugin's threads (default 2)
//!           listen_ip: 127.0.0.1     # default 127.0.0.1 (AimRT: 0.0.0.0)
//!           listen_port: 50050       # needed to serve; 0 picks a free port (logged)
//!   rpc:
//!     backends:
//!       - type: grpc
//!         options:
//!           clients_options:
//!             - func_name: "(.*)"
//!               server_url: http://127.0.0.1:50050
//!     clients_options:
//!       - func_name: "(.*)"
//!         enable_backends: [grpc]
//! ```
//!
//! Unary calls only, without compression, as AimRT's. A service function
//! `pb:/<Service>/<Method>` is the gRPC method `/<Service>/<Method>`; a failed call is
//! answered with a gRPC status (and AimRT's code in `aimrt-rs-status`), never left
//! without an answer.
#![deny(unsafe_code)]

mod client;
pub mod server;
pub mod wire;

use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use aimrt_net::close::{Closer, CLOSE_WAIT};
use aimrt_net::receiving::{Receiving, RECEIVING_BYTES};
use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall, BackendReply};
use aimrt_plugin_api::{
    BackendOptions, Error, Plugin, PluginOptions, Registrar, RpcBackend, RpcStatus, ServiceHost,
};
use serde::{Deserialize, Serialize};

/// The plugin's options (AimRT's keys).
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct GrpcOptions {
    #[serde(default = "default_thread_num")]
    thread_num: u32,
    #[serde(default = "loopback")]
    listen_ip: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    listen_port: Option<u16>,
}

fn default_thread_num() -> u32 {
    2
}

fn loopback() -> String {
    "127.0.0.1".into()
}

/// The backend's options: AimRT's `clients_options`, and `servers_options`, which AimRT
/// reads and does not use (which functions the backend serves is `aimrt.rpc`'s choice).
#[derive(Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct BackendConfig {
    #[serde(default)]
    clients_options: Vec<client::ClientOption>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    servers_options: Vec<ServerOption>,
}

#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct ServerOption {
    func_name: String,
}

/// The `grpc` RPC backend.
struct GrpcBackend {
    options: GrpcOptions,
    address: Option<SocketAddr>,
    location: String,
    host: OnceLock<ServiceHost>,
    client: OnceLock<Arc<client::GrpcClient>>,
    routes: server::Routes,
    runtime: Mutex<Option<tokio::runtime::Runtime>>,
    handle: Mutex<Option<tokio::runtime::Handle>>,
    /// Closes the server at shutdown: it stops listening and closes its connections
    /// gracefully.
    closer: Closer,
    /// What the server's connections hold of requests on their way, and the calls it
    /// refused for that.
    receiving: Arc<Receiving>,
}

impl GrpcBackend {
    fn options_error(&self, message: String) -> Error {
        Error::Options {
            what: format!("options of plugin 'grpc_plugin' at {}", self.location),
            message,
        }
    }

    /// Binds the listener and serves on `runtime`.
    fn listen(&self, runtime: &tokio::runtime::Runtime, addr: SocketAddr) -> Result<(), Error> {
        let Some(host) = self.host.get().copied() else {
            return Err(Error::msg("the grpc backend was started before init"));
        };
        let listener = aimrt_net::listen_tcp(addr).map_err(|e| {
            let fix = match e.kind() {
                std::io::ErrorKind::AddrInUse => {
                    "another socket has the port; choose another listen_port (0 picks a free one)"
                }
                std::io::ErrorKind::AddrNotAvailable => {
                    "listen_ip is not an address of this machine; use 127.0.0.1, 0.0.0.0 or one of this machine's addresses"
                }
                std::io::ErrorKind::PermissionDenied => {
                    "ports below 1024 need privileges; choose a listen_port of 1024 or more"
                }
                _ => "check listen_ip and listen_port",
            };
            self.options_error(format!("cannot listen for gRPC on {addr}: {e}; {fix}"))
        })?;
        let bound = listener.local_addr().unwrap_or(addr);
        let listener = {
            let _in_runtime = runtime.enter();
            tokio::net::TcpListener::from_std(listener)
                .map_err(|e| Error::msg(format!("cannot serve gRPC on {bound}: {e}")))?
        };
        runtime.spawn(server::accept(
            self.closer.listener(listener),
            server::Server {
                host,
                routes: self.routes.clone(),
                receiving: self.receiving.clone(),
                closing: self.closer.closing(),
            },
        ));
        tracing::info!(target: "aimrt", "grpc_plugin: gRPC server listening on {bound} (h2c); methods at /<Service>/<Method>");
        Ok(())
    }
}

impl RpcBackend for GrpcBackend {
    fn type_name(&self) -> &str {
        "grpc"
    }

    fn init(&self, options: &BackendOptions, host: ServiceHost) -> Result<(), Error> {
        let config: BackendConfig = options.read()?;
        if !config.servers_options.is_empty() {
            tracing::warn!(target: "aimrt", "grpc backend at {}: servers_options is accepted but unused (as in AimRT): which functions grpc serves is decided by aimrt.rpc.servers_options", options.location());
        }
        let client = client::GrpcClient::new(config.clients_options, options.location())?;
        let _ = self.client.set(Arc::new(client));
        let _ = self.host.set(host);
        Ok(())
    }

    fn register_service_func(&self, func: &str) -> Result<(), Error> {
        if self.address.is_none() {
            return Err(Error::msg(
                "Failed to register service function: please set grpc listen IP and port in the configuration (grpc_plugin options: listen_ip: 127.0.0.1, listen_port: 50050)",
            ));
        }
        let path = aimrt_net::header::name_without_prefix(func).to_owned();
        tracing::info!(target: "aimrt", "Register grpc method '{path}' for '{func}'");
        self.routes
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(path, func.into());
        Ok(())
    }

    fn register_client_func(&self, func: &str) -> Result<(), Error> {
        if let Some(client) = self.client.get() {
            client.register(func);
        }
        Ok(())
    }

    fn invoke(&self, call: BackendCall, reply: BackendReply) {
        let handle = self
            .handle
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let (Some(handle), Some(client)) = (handle, self.client.get().cloned()) else {
            return reply.send(BackendAnswer::fail(
                RpcStatus::CLI_BACKEND_INTERNAL_ERROR,
                "the grpc backend is not running",
            ));
        };
        handle.spawn(async move { reply.send(client.call(call).await) });
    }

    fn start(&self) -> Result<(), Error> {
        let runtime =
            aimrt_net::start_runtime(self.options.thread_num as usize, "aimrt_grpc", "gRPC")?;
        if let Some(addr) = self.address {
            self.listen(&runtime, addr)?;
        }
        *self.handle.lock().unwrap_or_else(|e| e.into_inner()) = Some(runtime.handle().clone());
        *self.runtime.lock().unwrap_or_else(|e| e.into_inner()) = Some(runtime);
        Ok(())
    }

    fn shutdown(&self) {
        self.handle.lock().unwrap_or_else(|e| e.into_inner()).take();
        let runtime = self
            .runtime
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        if let Some(rt) = runtime {
            // The listener stops; each connection sends `GOAWAY` and ends once the calls
            // it took are answered (the runtime answers every call by now), so a client
            // can tell the calls that never ran. What is left after a second is cut off.
            self.closer.close(CLOSE_WAIT);
            rt.shutdown_timeout(Duration::from_secs(2));
            tracing::info!(target: "aimrt", "grpc_plugin: stopped{}", self.receiving.refused_part());
        }
    }
}

struct GrpcPlugin;

impl Plugin for GrpcPlugin {
    fn name(&self) -> &str {
        "grpc_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: GrpcOptions = options.get()?;
        if o.thread_num == 0 || o.thread_num > aimrt_plugin_api::MAX_THREAD_NUM {
            return Err(options.invalid(format!(
                "thread_num must be in 1 ..= {}, got {}",
                aimrt_plugin_api::MAX_THREAD_NUM,
                o.thread_num
            )));
        }
        let ip: IpAddr = o.listen_ip.parse().map_err(|_| {
            options.invalid(format!(
                "listen_ip '{}' is not an IP address; give one such as 127.0.0.1 (loopback) or 0.0.0.0 (every interface)",
                o.listen_ip
            ))
        })?;
        registrar.update_options(&o)?;
        registrar.register_rpc_backend(GrpcBackend {
            address: o.listen_port.map(|port| SocketAddr::new(ip, port)),
            options: o,
            location: options.location().to_owned(),
            host: OnceLock::new(),
            client: OnceLock::new(),
            routes: server::Routes::default(),
            runtime: Mutex::new(None),
            handle: Mutex::new(None),
            closer: Closer::new(server::MAX_CONNECTIONS),
            receiving: Receiving::new(RECEIVING_BYTES, "grpc_plugin"),
        })
    }
}

/// The plugin, as `libaimrt_grpc_plugin.so` exports it (`plugins/grpc/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(GrpcPlugin)
}

/// For the fuzz targets in `fuzz/`; not a stable API.
#[doc(hidden)]
pub mod __fuzz {
    pub use crate::server::serve_bytes;
}
