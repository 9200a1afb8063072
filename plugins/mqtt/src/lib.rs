//! `mqtt_plugin`: the `mqtt` channel backend and the `mqtt` RPC backend over an MQTT
//! 3.1.1 broker, configured like AimRT's mqtt_plugin, on its topics ([`wire`]) and its
//! payload layout ([`aimrt_wire::payload`]), so an aimrt-rs process and an AimRT process
//! on the same broker exchange messages and calls. This crate is the plugin as an rlib;
//! `plugins/mqtt/so` exports it from `libaimrt_mqtt_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: mqtt_plugin
//!         path: ./target/debug/libaimrt_mqtt_plugin.so
//!         options:
//!           broker_addr: tcp://127.0.0.1:1883
//!           client_id: example_pb_chn_publisher   # unique among the broker's clients
//!           max_pkg_size_k: 1024
//!   channel:
//!     backends:
//!       - type: mqtt
//!         options:
//!           pub_topics_options: [{topic_name: "(.*)", qos: 2}]
//!           sub_topics_options: [{topic_name: "(.*)", qos: 2}]
//!   rpc:
//!     backends:
//!       - type: mqtt
//!         options:
//!           timeout_executor: timeout_handle
//!           clients_options: [{func_name: "(.*)", server_mqtt_id: "", qos: 2}]
//!           servers_options: [{func_name: "(.*)", allow_share: true, qos: 2}]
//! ```
//!
//! `broker_addr: ssl://host:port` connects over TLS with `truststore` (and `client_cert`,
//! `client_key` for brokers that require a client certificate): [`tls`].
//!
//! Unlike AimRT, bad options (a `broker_addr` that is not `tcp://host:port` or
//! `ssl://host:port`, a `qos` other than 0, 1 or 2, a bad regular expression, a TLS file
//! that cannot be read) stop start-up with a message naming them. A broker that cannot be reached does not: the plugin keeps connecting, as AimRT.
#![deny(unsafe_code)]

mod channel;
mod connection;
mod rpc;
pub mod tls;
pub mod wire;

#[doc(hidden)]
pub mod test_broker;

use std::sync::{Arc, Mutex};

use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar};

use crate::connection::{lock, Mqtt};
pub use crate::connection::{
    parse_broker_addr, BrokerAddr, MqttPluginOptions, QUEUE_CAPACITY, START_WAIT,
};

struct MqttPlugin {
    mqtt: Mutex<Option<Arc<Mqtt>>>,
    rpc: Mutex<Option<Arc<rpc::Shared>>>,
}

impl Plugin for MqttPlugin {
    fn name(&self) -> &str {
        "mqtt_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: MqttPluginOptions = registrar.read_options(options)?;
        let mqtt = Mqtt::open(o, options.location())?;
        let rpc = rpc::MqttRpc::new(mqtt.clone());
        *lock(&self.rpc) = Some(rpc.shared());
        *lock(&self.mqtt) = Some(mqtt.clone());
        let registered = registrar
            .register_channel_backend(channel::MqttChannel::new(mqtt))
            .and_then(|()| registrar.register_rpc_backend(rpc));
        // A plugin that fails to initialize gets no shutdown: the connection closes here.
        if registered.is_err() {
            self.shutdown();
        }
        registered
    }

    fn shutdown(&mut self) {
        if let Some(rpc) = lock(&self.rpc).take() {
            rpc.stop();
        }
        if let Some(mqtt) = lock(&self.mqtt).take() {
            mqtt.close();
        }
    }
}

/// The plugin, as `libaimrt_mqtt_plugin.so` exports it (`plugins/mqtt/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(MqttPlugin {
        mqtt: Mutex::new(None),
        rpc: Mutex::new(None),
    })
}

/// Rules of a backend's option list: the first whose regular expression fully matches a
/// name decides its settings.
#[derive(Debug)]
struct Rules<T>(Vec<(regex::Regex, T)>);

impl<T> Default for Rules<T> {
    fn default() -> Self {
        Rules(Vec::new())
    }
}

impl<T> Rules<T> {
    /// Compiles `(pattern, settings)` pairs; `list` and `key` name the option in errors.
    fn compile(
        entries: impl IntoIterator<Item = (String, T)>,
        where_: &str,
        list: &str,
        key: &str,
    ) -> Result<Rules<T>, Error> {
        let mut out = Vec::new();
        for (i, (pattern, value)) in entries.into_iter().enumerate() {
            let re = aimrt_plugin_api::whole_match(&pattern).map_err(|e| Error::Options {
                what: format!("mqtt backend options at {where_}"),
                message: format!(
                    "{list}[{i}].{key} '{pattern}' is not a valid regular expression: {e}"
                ),
            })?;
            out.push((re, value));
        }
        Ok(Rules(out))
    }

    /// The settings of the first rule matching any of `names`.
    fn first(&self, names: &[&str]) -> Option<&T> {
        self.0
            .iter()
            .find(|(re, _)| names.iter().any(|n| re.is_match(n)))
            .map(|(_, v)| v)
    }
}

/// AimRT's `qos` (0, 1 or 2; 2 when left out), checked.
fn check_qos(qos: Option<i64>, where_: &str, list: &str, i: usize) -> Result<u8, Error> {
    match qos {
        None => Ok(2),
        Some(q @ 0..=2) => Ok(q as u8),
        Some(q) => Err(Error::Options {
            what: format!("mqtt backend options at {where_}"),
            message: format!("{list}[{i}].qos is {q}: MQTT's QoS is 0, 1 or 2"),
        }),
    }
}
