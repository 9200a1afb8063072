//! The standard executors, exported from `libaimrt_std_executors_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: std_executors
//!         path: ./target/debug/libaimrt_std_executors_plugin.so
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_std_executors::plugin);
