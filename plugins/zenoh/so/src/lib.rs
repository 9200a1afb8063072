//! `zenoh_plugin`, exported from `libaimrt_zenoh_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: zenoh_plugin
//!         path: ./target/debug/libaimrt_zenoh_plugin.so
//!         options:
//!           native_cfg_path: ./config/zenoh_native_pub.json5
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_zenoh::plugin);
