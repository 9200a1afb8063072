//! `mqtt_plugin`, exported from `libaimrt_mqtt_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: mqtt_plugin
//!         path: ./target/debug/libaimrt_mqtt_plugin.so
//!         options:
//!           broker_addr: tcp://127.0.0.1:1883
//!           client_id: example_pb_chn_publisher
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_mqtt::plugin);
