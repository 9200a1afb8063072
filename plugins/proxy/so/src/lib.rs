//! `proxy_plugin`, exported from `libaimrt_proxy_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: proxy_plugin
//!         path: ./target/debug/libaimrt_proxy_plugin.so
//!         options:
//!           type_support_pkgs: [{path: ./target/debug/libexample_pb_ts.so}]
//!           proxy_actions:
//!             - name: my_proxy
//!               options:
//!                 executor: proxy_plugin_executor
//!                 topic_meta_list:
//!                   - {sub_topic_name: test_topic_http, pub_topic_name: [test_topic_zenoh], msg_type: pb:aimrt.protocols.example.ExampleEventMsg}
//! ```
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_proxy::plugin);
