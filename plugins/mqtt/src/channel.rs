//! The `mqtt` channel backend: a topic and type's messages go to the broker on
//! [`crate::wire::channel_topic`] as AimRT's channel payload; one subscription per such
//! topic serves every module subscription of it. A process's own subscribers hear its
//! messages through the broker, as in AimRT.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, OnceLock, RwLock};

use aimrt_plugin_api::channel::{
    ChannelBackend, Publication, PublisherInfo, Sink, Subscription, TopicRegistry,
    RECEIVERS_UNKNOWN,
};
use aimrt_plugin_api::ffi::{find_table, type_name_of, TypeSupportVtable};
use aimrt_plugin_api::{BackendOptions, Error};
use aimrt_wire::payload::{channel_header_len, put_channel_header, ChannelView};
use rumqttc::QoS;
use serde::Deserialize;

use crate::connection::{lock, qos_of, read, write, Mqtt};
use crate::wire::channel_topic;
use crate::{check_qos, Rules};

/// `pub_topics_options[i]` / `sub_topics_options[i]`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct TopicRule {
    topic_name: String,
    #[serde(default)]
    qos: Option<i64>,
}

#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    pub_topics_options: Vec<TopicRule>,
    #[serde(default)]
    sub_topics_options: Vec<TopicRule>,
}

/// A registered publish type.
struct Pub {
    ts: &'static TypeSupportVtable,
    type_name: &'static str,
    topic: String,
    qos: QoS,
}

type Sinks = Arc<RwLock<Vec<Sink>>>;

/// The backend.
pub(crate) struct MqttChannel {
    mqtt: Arc<Mqtt>,
    pub_rules: OnceLock<Rules<u8>>,
    sub_rules: OnceLock<Rules<u8>>,
    pubs: TopicRegistry<Pub>,
    /// By MQTT topic: the sinks its messages go to.
    subs: Mutex<HashMap<String, Sinks>>,
}

impl MqttChannel {
    pub(crate) fn new(mqtt: Arc<Mqtt>) -> MqttChannel {
        MqttChannel {
            mqtt,
            pub_rules: OnceLock::new(),
            sub_rules: OnceLock::new(),
            pubs: TopicRegistry::default(),
            subs: Mutex::default(),
        }
    }
}

/// Compiles a list of topic rules into `(regex, qos)`.
fn topic_rules(list: Vec<TopicRule>, where_: &str, name: &str) -> Result<Rules<u8>, Error> {
    let mut entries = Vec::new();
    for (i, r) in list.into_iter().enumerate() {
        entries.push((r.topic_name, check_qos(r.qos, where_, name, i)?));
    }
    Rules::compile(entries, where_, name, "topic_name")
}

impl ChannelBackend for MqttChannel {
    fn type_name(&self) -> &str {
        "mqtt"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let o: Options = options.read()?;
        let where_ = options.location();
        let _ = self.pub_rules.set(topic_rules(
            o.pub_topics_options,
            where_,
            "pub_topics_options",
        )?);
        let _ = self.sub_rules.set(topic_rules(
            o.sub_topics_options,
            where_,
            "sub_topics_options",
        )?);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        self.mqtt.wait_subscribed();
        Ok(())
    }

    /// Nothing is delivered after it returns: what the connection (closed by the
    /// plugin's shutdown, later) still brings is counted in the plugin's line.
    fn shutdown(&self) {
        for sinks in lock(&self.subs).values() {
            write(sinks).clear();
        }
    }

    fn register_publish_type(&self, publisher: &PublisherInfo<'_>) -> Result<(), Error> {
        let type_name = type_name_of(publisher.type_support);
        let topic = channel_topic(publisher.topic, type_name);
        let qos = self
            .pub_rules
            .get()
            .and_then(|r| r.first(&[publisher.topic]).copied())
            .unwrap_or(2);
        let added = self.pubs.register(publisher.topic, |of_topic| {
            if !of_topic.iter().any(|p| p.type_name == type_name) {
                tracing::info!(target: "aimrt", "Register publish type to mqtt channel, url: {topic}");
                of_topic.push(Pub {
                    ts: publisher.type_support,
                    type_name,
                    topic: topic.clone(),
                    qos: qos_of(qos),
                });
            }
            Ok(())
        });
        added.unwrap_or_else(|| {
            Err(Error::msg(format!(
                "cannot register '{topic}' after the first publish: register publish types in initialize"
            )))
        })
    }

    fn subscribe(&self, subscription: Subscription) -> Result<(), Error> {
        let topic = channel_topic(&subscription.topic, subscription.sink.type_name());
        let mut subs = lock(&self.subs);
        if let Some(sinks) = subs.get(&topic) {
            write(sinks).push(subscription.sink);
            return Ok(());
        }
        let qos = self
            .sub_rules
            .get()
            .and_then(|r| r.first(&[&subscription.topic]).copied())
            .unwrap_or(2);
        let sinks: Sinks = Arc::new(RwLock::new(vec![subscription.sink]));
        subs.insert(topic.clone(), sinks.clone());
        let mqtt = self.mqtt.clone();
        let key = topic.clone();
        self.mqtt.listen(
            topic.clone(),
            topic.clone(),
            qos_of(qos),
            Arc::new(move |bytes| receive(&mqtt, &sinks, bytes, &key)),
        );
        tracing::info!(target: "aimrt", "Register mqtt handle for channel, uri '{topic}'");
        Ok(())
    }

    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error> {
        let ts = publication.message().type_support();
        let of_topic = self.pubs.get(publication.topic_bytes());
        let Some(p) = find_table(of_topic, ts, |p| p.ts) else {
            self.mqtt.stats.refused.fetch_add(1, Ordering::Relaxed);
            return Err(Error::msg(format!(
                "Url: {} is not registered!",
                channel_topic(publication.topic(), type_name_of(ts))
            )));
        };
        let refused = |why: String| {
            self.mqtt.stats.refused.fetch_add(1, Ordering::Relaxed);
            Error::msg(why)
        };
        let format = aimrt_wire::channel::format_of(publication);
        let meta = publication.meta().iter().map(|p| p.bytes());
        let mut payload = Vec::with_capacity(channel_header_len(&format, meta.clone()) + 256);
        put_channel_header(&mut payload, &format, meta)
            .map_err(|e| refused(format!("cannot lay the message out: {e}")))?;
        aimrt_wire::channel::encode_into(publication, &format, &mut payload).map_err(refused)?;
        self.mqtt
            .publish(&p.topic, p.qos, payload)
            .map_err(Error::msg)?;
        Ok(RECEIVERS_UNKNOWN)
    }
}

/// One received payload: decoded and delivered, or counted as malformed, or as received
/// after the channel shut down (`shutdown` emptied `sinks`; a subscription has one at least).
fn receive(mqtt: &Mqtt, sinks: &Sinks, bytes: &[u8], topic: &str) {
    match ChannelView::read(bytes) {
        Ok(p) => {
            let sinks = read(sinks);
            if sinks.is_empty() {
                mqtt.stats.after_shutdown.fetch_add(1, Ordering::Relaxed);
                return;
            }
            aimrt_wire::channel::deliver(
                &sinks,
                p.serialization_type,
                p.meta,
                p.message,
                &format_args!("'{topic}'"),
            );
        }
        Err(e) => {
            mqtt.stats.malformed.fetch_add(1, Ordering::Relaxed);
            mqtt.warn(format_args!(
                "Handle mqtt channel msg failed: a {}-byte payload on '{topic}' is malformed: {e}",
                bytes.len()
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::connection::tests::open;
    use crate::test_broker::Broker;

    #[test]
    fn a_message_after_the_channel_shut_down_is_counted_not_lost_without_a_word() {
        let broker = Broker::start("127.0.0.1:0").unwrap();
        let mqtt = open(&broker, "sub", 1024);
        // What `shutdown` leaves of a subscription: no sink.
        let sinks: Sinks = Arc::default();
        let mut payload = Vec::new();
        put_channel_header(&mut payload, "pb", [("aimrt-pub_seq", "7")]).unwrap();
        payload.extend_from_slice(b"\x0a\x02hi");
        receive(&mqtt, &sinks, &payload, "/channel/t/pb%3Ax");
        receive(&mqtt, &sinks, b"\xff", "/channel/t/pb%3Ax");
        assert_eq!(mqtt.stats.after_shutdown.load(Ordering::Relaxed), 1);
        assert_eq!(mqtt.stats.malformed.load(Ordering::Relaxed), 1);
        mqtt.close();
    }
}
