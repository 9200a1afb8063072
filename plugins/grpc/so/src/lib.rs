//! `grpc_plugin`, exported from `libaimrt_grpc_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: grpc_plugin
//!         path: ./target/debug/libaimrt_grpc_plugin.so
//!         options:
//!           listen_ip: 127.0.0.1
//!           listen_port: 50050
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_grpc::plugin);
