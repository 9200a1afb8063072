//! `opentelemetry_plugin`, exported from `libaimrt_opentelemetry_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: opentelemetry_plugin
//!         path: ./target/debug/libaimrt_opentelemetry_plugin.so
//!         options:
//!           node_name: example_channel_node
//!           trace_otlp_http_exporter_url: http://localhost:4318/v1/traces
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_opentelemetry::plugin);
