//! `net_plugin`, exported from `libaimrt_net_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: net_plugin
//!         path: ./target/debug/libaimrt_net_plugin.so
//!         options:
//!           http_options: {listen_ip: 127.0.0.1, listen_port: 50080}
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_net::plugin);
