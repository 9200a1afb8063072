//! `echo_plugin`, exported from `libaimrt_echo_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: echo_plugin
//!         path: ./target/debug/libaimrt_echo_plugin.so
//!         options:
//!           type_support_pkgs: [{path: ./target/debug/libexample_pb_ts.so}]
//!           topic_meta_list:
//!             - {topic_name: test_topic, msg_type: pb:aimrt.protocols.example.ExampleEventMsg, echo_type: json}
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_echo::plugin);
