//! The `events_cbg` executor plugin, exported from `libaimrt_cbg_executor_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: cbg_executor_plugin
//!         path: ./target/debug/libaimrt_cbg_executor_plugin.so
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_cbg_executor::plugin);
