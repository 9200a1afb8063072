//! The plugin's one MQTT 3.1.1 connection (rumqttc): a thread runs its event loop,
//! connects (again, every `reconnect_interval_ms`, after a failure or a lost connection),
//! subscribes every registered filter after each connect (AimRT's clean sessions keep no
//! subscription across connects), and hands each message to the handler of its topic.
//! Publishing queues the packet for that thread without waiting ([`Mqtt::publish`]).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Condvar, Mutex, RwLock};
use std::time::{Duration, Instant};

use aimrt_plugin_api::{Error, RateLimit};
use bytes::Bytes;
use rumqttc::{
    AsyncClient, ClientError, Event, EventLoop, MqttOptions, Packet, PubAck, PubRec, Publish, QoS,
    Request,
};
use serde::Deserialize;

/// What a topic's messages go to.
pub(crate) type Handler = Arc<dyn Fn(&Bytes) + Send + Sync>;

/// The plugin's options (AimRT's keys).
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct MqttPluginOptions {
    /// `tcp://host:port` or `mqtt://host:port` (port 1883 when left out); `ssl://` or
    /// `mqtts://` for TLS (port 8883 when left out).
    pub broker_addr: String,
    /// This process's MQTT client id: unique among the broker's clients. RPC answers to
    /// this process's calls come on topics named by it.
    pub client_id: String,
    /// The largest payload sent, in KiB (AimRT's default 1024).
    #[serde(default = "default_max_pkg_size_k")]
    pub max_pkg_size_k: u32,
    /// How long to wait before connecting again, in ms (AimRT's default 1000).
    #[serde(default = "default_reconnect_interval_ms")]
    pub reconnect_interval_ms: u32,
    /// The executor that runs the services called through the mqtt RPC backend (else a
    /// thread of the plugin's own; never the connection's thread).
    #[serde(default)]
    pub callback_executor_name: String,
    /// TLS: a PEM file of the CA certificates the broker's certificate must be signed by
    /// (required with `ssl://`).
    #[serde(default)]
    pub truststore: String,
    /// TLS: this client's certificate chain (PEM), for brokers that require one; with
    /// `client_key`.
    #[serde(default)]
    pub client_cert: String,
    /// TLS: the private key of `client_cert` (PEM, not encrypted).
    #[serde(default)]
    pub client_key: String,
    /// AimRT's password of an encrypted `client_key`: refused (write the key decrypted).
    #[serde(default)]
    pub client_key_password: String,
}

impl MqttPluginOptions {
    /// The options of a client `client_id` of `broker_addr`, every other key at its
    /// default.
    ///
    /// ```
    /// let o = aimrt_mqtt::MqttPluginOptions::new("tcp://127.0.0.1:1883", "robot_1");
    /// assert_eq!((o.max_pkg_size_k, o.reconnect_interval_ms), (1024, 1000));
    /// ```
    pub fn new(broker_addr: &str, client_id: &str) -> MqttPluginOptions {
        MqttPluginOptions {
            broker_addr: broker_addr.to_owned(),
            client_id: client_id.to_owned(),
            max_pkg_size_k: default_max_pkg_size_k(),
            reconnect_interval_ms: default_reconnect_interval_ms(),
            callback_executor_name: String::new(),
            truststore: String::new(),
            client_cert: String::new(),
            client_key: String::new(),
            client_key_password: String::new(),
        }
    }
}

fn default_max_pkg_size_k() -> u32 {
    1024
}

fn default_reconnect_interval_ms() -> u32 {
    1000
}

/// Packets queued for the connection's thread at most; a publish beyond is refused.
pub const QUEUE_CAPACITY: usize = 10_000;

/// Bytes of payloads waiting for the broker at most: those handed to the connection and
/// not yet written, those written with QoS 1 or 2 and not yet acknowledged (rumqttc keeps
/// them to send again), and those a lost connection left to send again. A publish beyond
/// is refused. Counted in packets alone, the queue and what a lost connection left could hold
/// 20 000 payloads of up to `max_pkg_size_k`: 20 GiB at the default, for a broker that is
/// away.
pub(crate) const QUEUE_BYTES: usize = 256 << 20;

/// The payloads the connection holds for the broker: handed to it and not yet written, in
/// the order it writes them, and written with QoS 1 or 2 and not yet acknowledged.
#[derive(Default)]
struct Waiting {
    /// The sizes of those not yet written: the queue's, and in front, once connected,
    /// those sent again.
    sizes: VecDeque<usize>,
    /// The sizes of those written and not yet acknowledged (`PUBACK` for QoS 1, `PUBREC`
    /// for QoS 2, after which rumqttc lets the payload go), by packet id.
    unacked: HashMap<u16, usize>,
    /// Their bytes, and those of the payloads a lost connection left (`unsent` of the
    /// connection's thread).
    bytes: usize,
}

impl Waiting {
    /// The payload with packet id `pkid` (0 for QoS 0) was written: the first of `sizes`.
    /// A QoS 0 payload is let go; one of QoS 1 or 2 counts until acknowledged.
    fn written(&mut self, pkid: u16) {
        let Some(n) = self.sizes.pop_front() else {
            return;
        };
        if pkid == 0 {
            self.bytes = self.bytes.saturating_sub(n);
        } else if let Some(old) = self.unacked.insert(pkid, n) {
            // rumqttc does not reuse an unacknowledged id; should it, the old one is gone.
            self.bytes = self.bytes.saturating_sub(old);
        }
    }

    /// The broker acknowledged packet `pkid`: rumqttc no longer holds its payload.
    fn acknowledged(&mut self, pkid: u16) {
        if let Some(n) = self.unacked.remove(&pkid) {
            self.bytes = self.bytes.saturating_sub(n);
        }
    }
}

/// How long the backends' start waits for the first connection and its subscriptions.
pub const START_WAIT: Duration = Duration::from_secs(3);

/// A `broker_addr` read by [`parse_broker_addr`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BrokerAddr {
    /// The host: a name, an IPv4 address, or an IPv6 address without its brackets.
    pub host: String,
    /// The port.
    pub port: u16,
    /// Whether the connection is TLS (`ssl://`, `mqtts://`).
    pub tls: bool,
}

/// Reads `broker_addr`, or says what is wrong with it.
///
/// ```
/// use aimrt_mqtt::{parse_broker_addr, BrokerAddr};
/// let at = |host: &str, port, tls| Ok(BrokerAddr { host: host.into(), port, tls });
/// assert_eq!(parse_broker_addr("tcp://127.0.0.1:1883"), at("127.0.0.1", 1883, false));
/// assert_eq!(parse_broker_addr("mqtt://broker"), at("broker", 1883, false));
/// assert_eq!(parse_broker_addr("tcp://[::1]:2000"), at("::1", 2000, false));
/// assert_eq!(parse_broker_addr("ssl://broker"), at("broker", 8883, true));
/// assert!(parse_broker_addr("wss://broker").unwrap_err().contains("websocket"));
/// assert!(parse_broker_addr("127.0.0.1:1883").is_err());
/// ```
pub fn parse_broker_addr(addr: &str) -> Result<BrokerAddr, String> {
    let Some((scheme, rest)) = addr.split_once("://") else {
        return Err(format!(
            "broker_addr '{addr}' has no scheme: write tcp://host:port (or mqtt://, or ssl:// for TLS)"
        ));
    };
    let tls = match scheme {
        "tcp" | "mqtt" => false,
        "ssl" | "mqtts" => true,
        "wss" | "ws" => {
            return Err(format!(
                "broker_addr '{addr}': MQTT over websocket ({scheme}://) is not supported by this mqtt_plugin; use tcp://host:port, or ssl://host:port for TLS"
            ))
        }
        other => {
            return Err(format!(
                "broker_addr '{addr}': unknown scheme '{other}'; write tcp://host:port (or mqtt://, or ssl:// for TLS)"
            ))
        }
    };
    let authority = rest.strip_suffix('/').unwrap_or(rest);
    let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
        let Some((host, after)) = v6.split_once(']') else {
            return Err(format!("broker_addr '{addr}': '[' without ']'"));
        };
        (host, after.strip_prefix(':'))
    } else {
        match authority.rsplit_once(':') {
            Some((h, p)) => (h, Some(p)),
            None => (authority, None),
        }
    };
    if host.is_empty() || host.contains('/') {
        return Err(format!(
            "broker_addr '{addr}' names no host: write tcp://host:port"
        ));
    }
    let port = match port {
        None if tls => 8883,
        None => 1883,
        Some(p) => p.parse::<u16>().ok().filter(|p| *p != 0).ok_or_else(|| {
            format!("broker_addr '{addr}': port '{p}' is not a number from 1 to 65535")
        })?,
    };
    Ok(BrokerAddr {
        host: host.to_owned(),
        port,
        tls,
    })
}

/// Counters the plugin logs at shutdown.
#[derive(Debug, Default)]
pub(crate) struct Stats {
    /// Payloads handed to the connection (channel messages, requests, answers).
    pub(crate) sent: AtomicU64,
    /// Payloads not sent: over `max_pkg_size_k`, the queue full, a topic MQTT refuses,
    /// or the plugin shut down.
    pub(crate) refused: AtomicU64,
    /// Payloads received.
    pub(crate) received: AtomicU64,
    /// Received payloads that are not AimRT's layout.
    pub(crate) malformed: AtomicU64,
    /// Channel messages received after the channel backend shut down (the connection
    /// outlives it): not delivered, since their subscribers' modules have shut down.
    pub(crate) after_shutdown: AtomicU64,
    /// Answers for a request id no call here waits for.
    pub(crate) unknown_ids: AtomicU64,
    /// Channel messages a lost connection had not delivered, sent again on the next.
    pub(crate) resent: AtomicU64,
    /// Payloads a lost connection took with it: RPC requests and answers (their calls
    /// end at their deadlines), and channel messages beyond what is kept to send again.
    pub(crate) lost: AtomicU64,
    /// Connections made to the broker.
    pub(crate) connects: AtomicU64,
}

impl Stats {
    fn line(&self) -> String {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        format!(
            "{} payloads sent, {} refused, {} received, {} malformed received, {} channel messages received after the channel shut down (not delivered), {} answers for unknown request ids, {} channel messages sent again after a lost connection, {} payloads lost with a connection, {} connections made to the broker",
            g(&self.sent),
            g(&self.refused),
            g(&self.received),
            g(&self.malformed),
            g(&self.after_shutdown),
            g(&self.unknown_ids),
            g(&self.resent),
            g(&self.lost),
            g(&self.connects)
        )
    }
}

/// The subscriptions, and where the current connection is with them.
#[derive(Default)]
struct Subs {
    filters: Vec<(String, QoS)>,
    connected: bool,
    /// Filters subscribed on the current connection and not acknowledged yet.
    unacked: usize,
    /// When the current connection was made.
    since: Option<Instant>,
    /// Connections in a row the broker closed within [`SHORT_LIVED`] of their making.
    short_lived: u32,
}

/// A connection closed sooner than this after its making counts as taken over.
const SHORT_LIVED: Duration = Duration::from_secs(2);

/// How many such connections in a row make the plugin say that another client has the
/// same client id.
const TAKEN_OVER: u32 = 3;

/// The connection.
pub(crate) struct Mqtt {
    client: AsyncClient,
    pub(crate) client_id: String,
    pub(crate) broker: String,
    /// Whether the connection is TLS.
    tls: bool,
    /// The largest payload sent.
    pub(crate) max_payload: usize,
    pub(crate) callback_executor_name: String,
    /// Runs the services of requests (when no callback executor is named).
    pub(crate) serve: tokio::runtime::Handle,
    handlers: RwLock<HashMap<String, Handler>>,
    subs: Mutex<Subs>,
    subscribed: Condvar,
    pub(crate) stats: Stats,
    /// Held while a payload is handed to rumqttc, so the sizes keep its order.
    waiting: Mutex<Waiting>,
    alarm: RateLimit,
    stopping: AtomicBool,
    /// Ends the event loop where a graceful disconnect cannot (no connection, or a broker
    /// that does not take the packets).
    stop: tokio::sync::Notify,
    /// Told when the connection's thread has ended.
    ended: Mutex<Option<mpsc::Receiver<()>>>,
}

impl Mqtt {
    /// Reads the options and starts the connection's thread (which connects at once, and
    /// keeps trying). `Err` for options that cannot work.
    pub(crate) fn open(o: MqttPluginOptions, location: &str) -> Result<Arc<Mqtt>, Error> {
        let bad = |message: String| Error::Options {
            what: format!("mqtt_plugin options at {location}"),
            message,
        };
        let broker = parse_broker_addr(&o.broker_addr).map_err(bad)?;
        if o.client_id.is_empty() {
            return Err(bad(
                "client_id is empty: give this process a client id unique among the broker's clients".into(),
            ));
        }
        if o.max_pkg_size_k == 0 || o.max_pkg_size_k > 256 * 1024 {
            return Err(bad(format!(
                "max_pkg_size_k is {}: it must be from 1 to 262144 (MQTT's 256 MiB)",
                o.max_pkg_size_k
            )));
        }
        if o.reconnect_interval_ms == 0 {
            return Err(bad("reconnect_interval_ms must be at least 1".into()));
        }
        let tls = if broker.tls {
            Some(crate::tls::client_config(&o).map_err(bad)?)
        } else {
            for (key, value) in [
                ("truststore", &o.truststore),
                ("client_cert", &o.client_cert),
                ("client_key", &o.client_key),
                ("client_key_password", &o.client_key_password),
            ] {
                if !value.is_empty() {
                    tracing::warn!(target: "aimrt", "mqtt_plugin: broker protocol is not ssl/mqtts, the {key} you set will be ignored.");
                }
            }
            None
        };
        let max_payload = o.max_pkg_size_k as usize * 1024;
        let over_tls = broker.tls;
        let mut mo = MqttOptions::new(o.client_id.clone(), broker.host, broker.port);
        if let Some(config) = tls {
            mo.set_transport(rumqttc::Transport::tls_with_config(
                rumqttc::TlsConfiguration::Rustls(config),
            ));
        }
        mo.set_keep_alive(Duration::from_secs(20))
            .set_clean_session(true)
            // Outgoing: the payload, its topic and the header. Incoming: anything MQTT
            // allows (a larger packet would cost the connection, not one message).
            .set_max_packet_size(268_435_455, max_payload + 65_536 + 16)
            .set_inflight(1000);
        let (client, mut eventloop) = AsyncClient::new(mo, QUEUE_CAPACITY);
        // No Nagle: a small message goes out at once instead of waiting for the ACK of the
        // one before (up to 40 ms with a delayed ACK; rumqttc leaves Nagle on).
        let mut network = eventloop.network_options();
        network.set_tcp_nodelay(true);
        eventloop.set_network_options(network);
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .max_blocking_threads(8)
            .thread_name("aimrt_mqtt_serve")
            .build()
            .map_err(|e| Error::msg(format!("mqtt_plugin cannot start its runtime: {e}")))?;
        let mqtt = Arc::new(Mqtt {
            client,
            client_id: o.client_id,
            broker: o.broker_addr,
            tls: over_tls,
            max_payload,
            callback_executor_name: o.callback_executor_name,
            serve: rt.handle().clone(),
            handlers: RwLock::default(),
            subs: Mutex::default(),
            subscribed: Condvar::new(),
            stats: Stats::default(),
            waiting: Mutex::default(),
            alarm: RateLimit::from_millis(1000),
            stopping: AtomicBool::new(false),
            stop: tokio::sync::Notify::new(),
            ended: Mutex::new(None),
        });
        let (tx, rx) = mpsc::channel();
        *lock(&mqtt.ended) = Some(rx);
        let running = mqtt.clone();
        let interval = Duration::from_millis(o.reconnect_interval_ms.into());
        std::thread::Builder::new()
            .name("aimrt_mqtt".into())
            .spawn(move || {
                rt.block_on(running.run(eventloop, interval));
                // A service still running gets a moment; the runtime is dropped after.
                rt.shutdown_timeout(Duration::from_secs(1));
                let _ = tx.send(());
            })
            .map_err(|e| Error::msg(format!("mqtt_plugin cannot start its thread: {e}")))?;
        Ok(mqtt)
    }

    /// The event loop, until the plugin shuts down.
    async fn run(&self, mut eventloop: EventLoop, interval: Duration) {
        let failures = RateLimit::from_millis(10_000);
        let taken_over = RateLimit::from_millis(10_000);
        let mut unsent: VecDeque<Publish> = VecDeque::new();
        loop {
            let event = tokio::select! {
                e = eventloop.poll() => e,
                () = self.stop.notified() => break,
            };
            match event {
                Ok(Event::Incoming(Packet::Publish(p))) => self.dispatch(&p.topic, &p.payload),
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    // Ahead of what was published since: rumqttc sends `pending` first.
                    self.stats
                        .resent
                        .fetch_add(unsent.len() as u64, Ordering::Relaxed);
                    {
                        let mut w = lock(&self.waiting);
                        for p in unsent.iter().rev() {
                            w.sizes.push_front(p.payload.len());
                        }
                    }
                    eventloop
                        .pending
                        .extend(unsent.drain(..).map(Request::Publish));
                    self.connected();
                }
                Ok(Event::Outgoing(rumqttc::Outgoing::Publish(pkid))) => {
                    lock(&self.waiting).written(pkid);
                }
                Ok(Event::Incoming(Packet::PubAck(PubAck { pkid, .. })))
                | Ok(Event::Incoming(Packet::PubRec(PubRec { pkid, .. }))) => {
                    lock(&self.waiting).acknowledged(pkid);
                }
                Ok(Event::Incoming(Packet::SubAck(ack))) => self.acked(&ack),
                Ok(Event::Outgoing(rumqttc::Outgoing::Disconnect)) => break,
                Ok(_) => {}
                Err(e) => {
                    if self.stopping.load(Ordering::SeqCst) {
                        break;
                    }
                    let (kept, dropped) = self.keep_unsent(&mut eventloop, &mut unsent);
                    let (was, short_lived) = {
                        let mut subs = lock(&self.subs);
                        let was = std::mem::take(&mut subs.connected);
                        if was {
                            let brief = subs.since.is_some_and(|t| t.elapsed() < SHORT_LIVED);
                            subs.short_lived = if brief { subs.short_lived + 1 } else { 0 };
                        }
                        (was, subs.short_lived)
                    };
                    if was && short_lived >= TAKEN_OVER {
                        if let Some(held) = taken_over.admit() {
                            tracing::warn!(target: "aimrt", "mqtt_plugin: the mqtt broker {} closed this process's connection {short_lived} times in a row within {} s of its making: another client with client_id '{}' is probably connected, and each connection takes the id from the other (MQTT allows one connection per client id); give every process its own client_id ({held} more such lines held back since the last)", self.broker, SHORT_LIVED.as_secs(), self.client_id);
                        }
                    } else if was {
                        tracing::warn!(target: "aimrt", "mqtt_plugin: lost the connection to the mqtt broker {}: {e}; connecting again every {} ms; {kept} channel messages it had not delivered go out again once connected, {dropped} payloads are lost with it (RPC requests and answers, whose calls end at their deadlines)", self.broker, interval.as_millis());
                    } else if let Some(held) = failures.admit() {
                        let hint = if self.tls { tls_hint(&e) } else { "" };
                        tracing::warn!(target: "aimrt", "mqtt_plugin: failed to connect to the mqtt broker {}: {e}{hint}; trying again every {} ms ({held} more failures since the last such line)", self.broker, interval.as_millis());
                    }
                    tokio::select! {
                        () = tokio::time::sleep(interval) => {}
                        () = self.stop.notified() => break,
                    }
                }
            }
            if self.stopping.load(Ordering::SeqCst) && !lock(&self.subs).connected {
                break;
            }
        }
        if !lock(&self.subs).connected {
            // What waits for a connection that never came back is lost with the process.
            eventloop.clean();
            let (kept, dropped) = self.keep_unsent(&mut eventloop, &mut unsent);
            let lost = kept as u64 + dropped;
            if lost > 0 {
                // `keep_unsent` counted the dropped ones; the kept ones go nowhere now.
                self.stats.lost.fetch_add(kept as u64, Ordering::Relaxed);
                tracing::warn!(target: "aimrt", "mqtt_plugin: {lost} payloads waiting for the mqtt broker {} are lost: it was not connected at shutdown", self.broker);
            }
        }
    }

    /// Takes out of rumqttc's `pending` what a lost connection had not had acknowledged and
    /// what was queued behind it: rumqttc clears it at the next connect (a clean session,
    /// as AimRT's), which lost those messages without a word. Channel messages are kept in
    /// `unsent`, to go out again first on the next connection (at least once: one the
    /// broker took before its acknowledgement was lost arrives twice); at most
    /// [`QUEUE_CAPACITY`], the oldest counted lost beyond. RPC requests and answers are
    /// counted lost: their calls end at their deadlines. Returns (kept, lost).
    ///
    /// After a connection broke, rumqttc has moved what waited in its queue to `pending`
    /// too; what was published since is moved now, with the publishers held off, so that
    /// the sizes of what waits ([`Waiting`]) start again from what is kept.
    fn keep_unsent(
        &self,
        eventloop: &mut EventLoop,
        unsent: &mut VecDeque<Publish>,
    ) -> (usize, u64) {
        let mut waiting = lock(&self.waiting);
        let connected = lock(&self.subs).connected;
        if connected {
            eventloop.clean();
        }
        let mut lost = 0;
        for request in eventloop.pending.drain(..) {
            // Acknowledgements, releases and subscriptions belong to the old session
            // (`connected` subscribes every filter again).
            if let Request::Publish(mut p) = request {
                if p.topic.starts_with("/channel/") {
                    p.pkid = 0;
                    p.dup = false;
                    unsent.push_back(p);
                } else {
                    lost += 1;
                }
            }
        }
        let over = unsent.len().saturating_sub(QUEUE_CAPACITY);
        unsent.drain(..over);
        lost += over as u64;
        self.stats.lost.fetch_add(lost, Ordering::Relaxed);
        if connected {
            // Everything handed to rumqttc is in `unsent` now, or lost.
            waiting.sizes.clear();
            waiting.unacked.clear();
            waiting.bytes = unsent.iter().map(|p| p.payload.len()).sum();
        }
        (unsent.len(), lost)
    }

    /// A connection was made: every filter is subscribed on it.
    fn connected(&self) {
        self.stats.connects.fetch_add(1, Ordering::Relaxed);
        let mut subs = lock(&self.subs);
        subs.connected = true;
        subs.unacked = 0;
        subs.since = Some(Instant::now());
        tracing::info!(target: "aimrt", "mqtt_plugin: connected to the mqtt broker {}.", self.broker);
        let filters = subs.filters.clone();
        for (filter, qos) in filters {
            self.subscribe_now(&mut subs, filter, qos);
        }
        self.subscribed.notify_all();
    }

    fn subscribe_now(&self, subs: &mut Subs, filter: String, qos: QoS) {
        match self.client.try_subscribe(filter.clone(), qos) {
            Ok(()) => subs.unacked += 1,
            Err(e) => {
                tracing::error!(target: "aimrt", "mqtt_plugin: failed to subscribe '{filter}': {}", said(&e))
            }
        }
    }

    fn acked(&self, ack: &rumqttc::SubAck) {
        for code in &ack.return_codes {
            if matches!(code, rumqttc::SubscribeReasonCode::Failure) {
                tracing::error!(target: "aimrt", "mqtt_plugin: the broker {} refused a subscription (packet id {}): its messages will not arrive", self.broker, ack.pkid);
            }
        }
        let mut subs = lock(&self.subs);
        subs.unacked = subs.unacked.saturating_sub(1);
        self.subscribed.notify_all();
    }

    /// Hears `filter` from now on (and after every connect), handing the messages of
    /// `topic` to `handler` (`filter` is `topic`, or a shared subscription of it).
    pub(crate) fn listen(&self, filter: String, topic: String, qos: QoS, handler: Handler) {
        write(&self.handlers).insert(topic, handler);
        let mut subs = lock(&self.subs);
        if subs.filters.iter().any(|(f, _)| *f == filter) {
            return;
        }
        subs.filters.push((filter.clone(), qos));
        if subs.connected {
            self.subscribe_now(&mut subs, filter, qos);
        }
    }

    /// Waits (at most [`START_WAIT`]) for a connection whose subscriptions the broker has
    /// acknowledged; says so when there is none by then (messages are queued meanwhile).
    pub(crate) fn wait_subscribed(&self) {
        let deadline = Instant::now() + START_WAIT;
        let mut subs = lock(&self.subs);
        while !(subs.connected && subs.unacked == 0) {
            let now = Instant::now();
            if now >= deadline {
                tracing::warn!(target: "aimrt", "mqtt_plugin: not connected to the mqtt broker {} after {} s: starting anyway; until it connects, what is published is queued (at most {QUEUE_CAPACITY} packets, then refused) and calls end at their deadline", self.broker, START_WAIT.as_secs());
                return;
            }
            subs = self
                .subscribed
                .wait_timeout(subs, deadline - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    fn dispatch(&self, topic: &str, payload: &Bytes) {
        self.stats.received.fetch_add(1, Ordering::Relaxed);
        let handler = read(&self.handlers).get(topic).cloned();
        match handler {
            Some(h) => h(payload),
            None => self.warn(format_args!(
                "a {}-byte message on '{topic}', which nothing here listens to, is dropped",
                payload.len()
            )),
        }
    }

    /// Queues `payload` for `topic`; `Err` says why it is not sent (counted).
    pub(crate) fn publish(&self, topic: &str, qos: QoS, payload: Vec<u8>) -> Result<(), String> {
        if self.stopping.load(Ordering::SeqCst) {
            self.stats.refused.fetch_add(1, Ordering::Relaxed);
            return Err(format!(
                "the mqtt_plugin has shut down: nothing is sent to '{topic}' any more"
            ));
        }
        if payload.len() > self.max_payload {
            self.stats.refused.fetch_add(1, Ordering::Relaxed);
            return Err(format!(
                "Mqtt publish failed, pkg is too large, limit {} bytes, actual {} bytes (max_pkg_size_k)",
                self.max_payload,
                payload.len()
            ));
        }
        let len = payload.len();
        let mut waiting = lock(&self.waiting);
        if waiting.bytes > 0 && waiting.bytes + len > QUEUE_BYTES {
            let held = waiting.bytes;
            drop(waiting);
            self.stats.refused.fetch_add(1, Ordering::Relaxed);
            return Err(format!(
                "the mqtt connection's queue is full ({held} bytes wait for the broker {}, at most {QUEUE_BYTES}): nothing is sent to '{topic}'",
                self.broker
            ));
        }
        match self.client.try_publish(topic, qos, false, payload) {
            Ok(()) => {
                waiting.sizes.push_back(len);
                waiting.bytes += len;
                drop(waiting);
                self.stats.sent.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
            Err(e) => {
                self.stats.refused.fetch_add(1, Ordering::Relaxed);
                Err(match e {
                    ClientError::TryRequest(_) if !rumqttc::valid_topic(topic) => {
                        format!("'{topic}' is not a topic MQTT can publish to")
                    }
                    _ => format!(
                        "the mqtt connection's queue is full ({QUEUE_CAPACITY} packets waiting for the broker {}): nothing is sent to '{topic}'",
                        self.broker
                    ),
                })
            }
        }
    }

    /// Logs at most once a second, with how many lines were held back.
    pub(crate) fn warn(&self, what: std::fmt::Arguments<'_>) {
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(target: "aimrt", "mqtt_plugin: {what} ({held} more such lines held back since the last)");
        }
    }

    /// Unsubscribes, sends what is queued and disconnects (when connected), then ends the
    /// thread, waiting at most 4 s for it. Nothing is sent after.
    pub(crate) fn close(&self) {
        if self.stopping.swap(true, Ordering::SeqCst) {
            return;
        }
        let filters: Vec<String> = lock(&self.subs)
            .filters
            .iter()
            .map(|(f, _)| f.clone())
            .collect();
        for f in filters {
            let _ = self.client.try_unsubscribe(f);
        }
        let connected = lock(&self.subs).connected;
        let ended = lock(&self.ended).take();
        if let Some(rx) = ended {
            // Connected: what is queued goes out before the DISCONNECT (given 2 s).
            let graceful = connected
                && self.client.try_disconnect().is_ok()
                && rx.recv_timeout(Duration::from_secs(2)).is_ok();
            if !graceful {
                self.stop.notify_one();
                if rx.recv_timeout(Duration::from_secs(2)).is_err() {
                    tracing::warn!(target: "aimrt", "mqtt_plugin: the connection's thread did not end; left behind");
                }
            }
        }
        write(&self.handlers).clear();
        tracing::info!(target: "aimrt", "mqtt_plugin: {}", self.stats.line());
    }
}

/// An error's text with its causes.
pub(crate) fn said(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cause = c.source();
    }
    s
}

/// The MQTT QoS of AimRT's `qos` option (0, 1 or 2; AimRT's default 2).
pub(crate) fn qos_of(qos: u8) -> QoS {
    match qos {
        0 => QoS::AtMostOnce,
        1 => QoS::AtLeastOnce,
        _ => QoS::ExactlyOnce,
    }
}

/// What to check after a failed TLS connect: the broker's certificate that the client
/// does not trust, or the client's certificate that the broker does not take.
fn tls_hint(e: &rumqttc::ConnectionError) -> &'static str {
    let text = e.to_string();
    if text.contains("invalid peer certificate") {
        " (the broker's certificate must be signed by a CA of truststore and name the host of broker_addr)"
    } else if [
        "CertificateRequired",
        "BadCertificate",
        "UnknownCA",
        "CertificateUnknown",
    ]
    .iter()
    .any(|alert| text.contains(alert))
    {
        " (the broker wants a client certificate it trusts: set client_cert and client_key)"
    } else {
        ""
    }
}

pub(crate) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

pub(crate) fn read<T>(l: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|e| e.into_inner())
}

pub(crate) fn write<T>(l: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(|e| e.into_inner())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::test_broker::Broker;

    /// A connection to `broker` as `client_id`, sending at most `max_pkg_size_k` KiB.
    pub(crate) fn open(broker: &Broker, client_id: &str, max_pkg_size_k: u32) -> Arc<Mqtt> {
        open_at(
            &format!("tcp://{}", broker.addr()),
            client_id,
            max_pkg_size_k,
            100,
        )
    }

    fn open_at(
        broker_addr: &str,
        client_id: &str,
        max_pkg_size_k: u32,
        reconnect_ms: u32,
    ) -> Arc<Mqtt> {
        let mut o = MqttPluginOptions::new(broker_addr, client_id);
        o.max_pkg_size_k = max_pkg_size_k;
        o.reconnect_interval_ms = reconnect_ms;
        Mqtt::open(o, "test").unwrap()
    }

    #[test]
    fn a_publish_is_refused_with_why_when_too_large_an_invalid_topic_or_after_close() {
        let broker = Broker::start("127.0.0.1:0").unwrap();
        let mqtt = open(&broker, "p", 1);
        mqtt.wait_subscribed();
        let too_large = mqtt
            .publish("t", QoS::AtMostOnce, vec![0; 1025])
            .unwrap_err();
        assert!(
            too_large.contains("limit 1024 bytes, actual 1025 bytes"),
            "{too_large}"
        );
        let wildcard = mqtt
            .publish("a/#", QoS::AtMostOnce, vec![0; 8])
            .unwrap_err();
        assert!(
            wildcard.contains("not a topic MQTT can publish to"),
            "{wildcard}"
        );
        assert!(mqtt.publish("t", QoS::AtMostOnce, vec![0; 1024]).is_ok());
        mqtt.close();
        let closed = mqtt.publish("t", QoS::AtMostOnce, vec![0; 8]).unwrap_err();
        assert!(closed.contains("shut down"), "{closed}");
        assert_eq!(mqtt.stats.refused.load(Ordering::Relaxed), 3);
        assert_eq!(mqtt.stats.sent.load(Ordering::Relaxed), 1);
    }

    /// Payloads for a broker that is away are bounded in bytes, not only in packets: 16
    /// payloads of 16 MiB fill [`QUEUE_BYTES`] and the 17th is refused with why (the
    /// 10 000 packets would have been 160 GiB).
    #[test]
    fn payloads_waiting_for_an_absent_broker_are_bounded_in_bytes() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let mqtt = open_at(
            &format!("tcp://127.0.0.1:{port}"),
            "away",
            16 * 1024,
            60_000,
        );
        let payload = 16 << 20;
        for _ in 0..QUEUE_BYTES / payload {
            mqtt.publish("t", QoS::AtMostOnce, vec![0; payload])
                .unwrap();
        }
        let full = mqtt
            .publish("t", QoS::AtMostOnce, vec![0; payload])
            .unwrap_err();
        assert!(
            full.contains("queue is full (268435456 bytes wait for the broker tcp://127.0.0.1:")
                && full.contains("at most 268435456): nothing is sent to 't'"),
            "{full}"
        );
        assert_eq!(lock(&mqtt.waiting).bytes, QUEUE_BYTES);
        assert_eq!(mqtt.stats.refused.load(Ordering::Relaxed), 1);
        mqtt.close();
    }

    /// What waits is counted down as it is written (QoS 0) or acknowledged (QoS 1 and 2),
    /// and counted again when a broken connection leaves it to be sent again: payloads the
    /// broker never acknowledged stay counted until the connection drops and they are sent
    /// again, and after that nothing is left counted (a count that crept up would refuse
    /// every publish once it reached the limit; one that let unacknowledged payloads go
    /// would not bound what rumqttc holds for a broker that is slow to acknowledge).
    #[test]
    fn what_waits_is_counted_down_as_it_goes_also_across_a_broken_connection() {
        let broker = Broker::start("127.0.0.1:0").unwrap();
        // A second between attempts: time to see what a broken connection left counted.
        let mqtt = open_at(&format!("tcp://{}", broker.addr()), "counted", 64, 1000);
        mqtt.wait_subscribed();
        // Waits (20 s at most) until `done`; `what` says what did not happen.
        let until = |done: &dyn Fn() -> bool, what: &dyn Fn() -> String| {
            let deadline = Instant::now() + Duration::from_secs(20);
            while !done() {
                assert!(Instant::now() < deadline, "{}", what());
                std::thread::sleep(Duration::from_millis(2));
            }
        };
        // (bytes, payloads not written, payloads not acknowledged) counted.
        let counted = || {
            let w = lock(&mqtt.waiting);
            (w.bytes, w.sizes.len(), w.unacked.len())
        };
        let reaches = |stage: &str, want: (usize, usize, usize)| {
            until(&|| counted() == want, &|| {
                format!("{stage}: counted {:?}, expected {want:?}", counted())
            });
        };
        let drained = |stage: &str| reaches(stage, (0, 0, 0));
        // `n` payloads of 1 000 bytes on a channel topic.
        let publish = |n: usize, qos: QoS| {
            for _ in 0..n {
                mqtt.publish("/channel/t", qos, vec![0; 1000]).unwrap();
            }
        };
        publish(2000, QoS::AtMostOnce);
        drained("QoS 0");
        publish(300, QoS::AtLeastOnce);
        drained("QoS 1, acknowledged");
        publish(300, QoS::ExactlyOnce);
        drained("QoS 2, received");
        // Written and never acknowledged: kept by rumqttc until the connection breaks, and
        // counted as long.
        broker.swallow_publishes(true);
        publish(100, QoS::AtLeastOnce);
        reaches("written, not acknowledged", (100 * 1000, 0, 100));
        // Before the drop: what is sent again on the next connection is acknowledged.
        broker.swallow_publishes(false);
        broker.drop_connections();
        until(&|| !lock(&mqtt.subs).connected, &|| {
            "the broken connection went unnoticed".into()
        });
        // The 100 kept to be sent again count until they are.
        assert_eq!(lock(&mqtt.waiting).bytes, 100 * 1000);
        until(
            &|| mqtt.stats.resent.load(Ordering::Relaxed) >= 100,
            &|| "nothing was sent again".into(),
        );
        publish(100, QoS::AtLeastOnce);
        drained("sent again");
        mqtt.close();
    }

    #[test]
    fn closing_without_a_broker_returns_and_ends_the_thread() {
        // A port nothing listens on: the connection keeps failing.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        // A minute between attempts: close must not wait for the next one.
        let mqtt = open_at(&format!("tcp://127.0.0.1:{port}"), "lonely", 1024, 60_000);
        std::thread::sleep(Duration::from_millis(300));
        let started = Instant::now();
        mqtt.close();
        // Ended by the stop notice during the wait, not left behind after 2 s.
        assert!(
            started.elapsed() < Duration::from_secs(2),
            "{:?}",
            started.elapsed()
        );
        assert_eq!(mqtt.stats.connects.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn broker_addresses_are_read_or_refused_with_why() {
        let at = |port, tls| {
            Ok(BrokerAddr {
                host: "h".to_owned(),
                port,
                tls,
            })
        };
        for (addr, expected) in [
            ("tcp://h:1", at(1, false)),
            ("mqtt://h/", at(1883, false)),
            ("ssl://h", at(8883, true)),
            ("mqtts://h:9000", at(9000, true)),
            ("tcp://h:0", Err("port '0'")),
            ("tcp://h:x", Err("port 'x'")),
            ("tcp://:1883", Err("names no host")),
            ("tcp://[::1", Err("'[' without ']'")),
            ("wss://h:1", Err("websocket (wss://) is not supported")),
            ("udp://h:1", Err("unknown scheme 'udp'")),
        ] {
            match (parse_broker_addr(addr), expected) {
                (Ok(got), Ok(want)) => assert_eq!(got, want, "{addr}"),
                (Err(got), Err(want)) => assert!(got.contains(want), "{addr}: {got}"),
                (got, want) => panic!("{addr}: {got:?}, expected {want:?}"),
            }
        }
    }
}
