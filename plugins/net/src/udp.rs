//! The `udp` channel backend: one datagram per message, in AimRT's layout
//! ([`crate::wire::Body`]), to every address of the topic's `server_url_list` (or the
//! `udp://` entries of the context's `aimrt-to_addr`); a receiver on
//! `udp_options.listen_ip:listen_port` delivers to the subscribers of the datagram's uri.
//!
//! Unlike AimRT, a message that cannot fit a datagram is refused at publish time, and a
//! datagram longer than `max_pkg_size` (read with one spare byte) is counted as truncated
//! instead of decoded.

use std::collections::HashMap;
use std::net::{SocketAddr, ToSocketAddrs, UdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock};
use std::thread::JoinHandle;
use std::time::Duration;

use aimrt_plugin_api::channel::{
    ChannelBackend, DropReason, Publication, PublisherInfo, Sink, Subscription,
    KEY_SERIALIZATION_TYPE,
};
use aimrt_plugin_api::ffi::{formats_of, meta_of, type_name_of, RawMessage};
use aimrt_plugin_api::{BackendOptions, Error, RateLimit};
use regex::Regex;
use serde::Deserialize;

use crate::wire::{channel_uri, Body, MAX_DATAGRAM};

/// `udp_options` of net_plugin.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct UdpOptions {
    #[serde(default = "loopback")]
    listen_ip: String,
    listen_port: u16,
    /// The largest datagram the receiver takes (AimRT's default 1024; at most 65 507).
    #[serde(default = "default_max_pkg_size")]
    max_pkg_size: u32,
}

fn loopback() -> String {
    "127.0.0.1".into()
}

fn default_max_pkg_size() -> u32 {
    1024
}

/// `pub_topics_options[i]` of the backend's options.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PubTopic {
    topic_name: String,
    #[serde(default)]
    server_url_list: Vec<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    pub_topics_options: Vec<PubTopic>,
}

/// Resolves `host:port`, `ip:port` or `[ipv6]:port` (a `<backend>://` prefix is stripped by
/// the caller); `None` when it is not such an address.
pub(crate) fn resolve(addr: &str) -> Option<Vec<SocketAddr>> {
    let (host, port) = addr.rsplit_once(':')?;
    let port: u16 = port.parse().ok()?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() || host.contains(char::is_whitespace) {
        return None;
    }
    let found: Vec<SocketAddr> = (host, port).to_socket_addrs().ok()?.collect();
    (!found.is_empty()).then_some(found)
}

/// Counters of what the backend could not carry.
#[derive(Debug, Default)]
pub(crate) struct UdpStats {
    /// Datagrams sent.
    pub(crate) sent: AtomicU64,
    /// Messages refused at publish time (too large, too many meta pairs, bad `to_addr`).
    pub(crate) refused: AtomicU64,
    /// Datagrams longer than `max_pkg_size`.
    pub(crate) truncated: AtomicU64,
    /// Datagrams that are not a message body.
    pub(crate) malformed: AtomicU64,
    /// Datagrams for a uri nobody here subscribes to.
    pub(crate) unknown_uri: AtomicU64,
}

/// The backend.
pub(crate) struct UdpChannel {
    options: Option<UdpOptions>,
    location: String,
    rules: OnceLock<Vec<(Regex, Vec<String>)>>,
    targets: RwLock<HashMap<String, Arc<Vec<SocketAddr>>>>,
    subs: Arc<RwLock<HashMap<String, Vec<Sink>>>>,
    sender: OnceLock<UdpSocket>,
    receiver: Mutex<Option<(Arc<AtomicBool>, JoinHandle<()>)>>,
    stats: Arc<UdpStats>,
    alarm: Arc<RateLimit>,
}

impl UdpChannel {
    pub(crate) fn new(options: Option<UdpOptions>, location: String) -> UdpChannel {
        UdpChannel {
            options,
            location,
            rules: OnceLock::new(),
            targets: RwLock::default(),
            subs: Arc::default(),
            sender: OnceLock::new(),
            receiver: Mutex::new(None),
            stats: Arc::default(),
            alarm: Arc::new(RateLimit::from_millis(1000)),
        }
    }

    fn warn(&self, what: std::fmt::Arguments<'_>) {
        warn_limited(&self.alarm, what);
    }
}

fn warn_limited(alarm: &RateLimit, what: std::fmt::Arguments<'_>) {
    if let Some(held) = alarm.admit() {
        tracing::warn!(target: "aimrt", "net_plugin udp: {what} ({held} more such lines held back since the last)");
    }
}

impl ChannelBackend for UdpChannel {
    fn type_name(&self) -> &str {
        "udp"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let o: Options = options.get()?;
        let mut rules = Vec::new();
        for (i, t) in o.pub_topics_options.into_iter().enumerate() {
            let bad = |message: String| Error::Options {
                what: format!("udp channel backend options at {}", options.location()),
                message: format!("pub_topics_options[{i}]: {message}"),
            };
            let re = Regex::new(&format!("^(?:{})$", t.topic_name)).map_err(|e| {
                bad(format!(
                    "topic_name '{}' is not a valid regular expression: {e}",
                    t.topic_name
                ))
            })?;
            for url in &t.server_url_list {
                if resolve(url).is_none() {
                    return Err(bad(format!(
                        "server_url_list entry '{url}' is not an address; write ip:port, [ipv6]:port or host:port, e.g. 127.0.0.1:50040"
                    )));
                }
            }
            rules.push((re, t.server_url_list));
        }
        let _ = self.rules.set(rules);
        if let Some(u) = &self.options {
            if u.max_pkg_size == 0 || u.max_pkg_size as usize > MAX_DATAGRAM {
                return Err(Error::Options {
                    what: format!("options of plugin 'net_plugin' at {}", self.location),
                    message: format!(
                        "udp_options.max_pkg_size must be in 1 ..= {MAX_DATAGRAM}, got {}",
                        u.max_pkg_size
                    ),
                });
            }
        }
        let sender = UdpSocket::bind("0.0.0.0:0")
            .map_err(|e| Error::msg(format!("cannot open a UDP socket to publish from: {e}")))?;
        let _ = self.sender.set(sender);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        let Some(u) = &self.options else {
            return Ok(());
        };
        if read(&self.subs).is_empty() {
            return Ok(());
        }
        let addr = format!("{}:{}", u.listen_ip, u.listen_port);
        let socket = bind_receiver(&addr).map_err(|e| {
            Error::msg(format!(
                "cannot listen for UDP on {addr}: {e}; check udp_options.listen_ip and listen_port in the options of net_plugin at {}",
                self.location
            ))
        })?;
        let _ = socket.set_read_timeout(Some(Duration::from_millis(100)));
        let bound = socket.local_addr().map_or(addr, |a| a.to_string());
        tracing::info!(target: "aimrt", "net_plugin: udp channel listening on {bound}");
        let run = Arc::new(AtomicBool::new(true));
        let receive = Receive {
            socket,
            max: u.max_pkg_size as usize,
            subs: self.subs.clone(),
            stats: self.stats.clone(),
            alarm: self.alarm.clone(),
            run: run.clone(),
        };
        let handle = std::thread::Builder::new()
            .name("aimrt_udp_recv".into())
            .spawn(move || receive.run())
            .map_err(|e| Error::msg(format!("cannot start the UDP receiver thread: {e}")))?;
        *self.receiver.lock().unwrap_or_else(|e| e.into_inner()) = Some((run, handle));
        Ok(())
    }

    fn shutdown(&self) {
        let taken = self
            .receiver
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        if let Some((run, handle)) = taken {
            run.store(false, Ordering::SeqCst);
            let _ = handle.join();
        }
        let s = &self.stats;
        tracing::info!(target: "aimrt", "net_plugin udp: {} datagrams sent, {} messages refused, {} received truncated, {} malformed, {} for unknown uris", s.sent.load(Ordering::Relaxed), s.refused.load(Ordering::Relaxed), s.truncated.load(Ordering::Relaxed), s.malformed.load(Ordering::Relaxed), s.unknown_uri.load(Ordering::Relaxed));
    }

    fn register_publish_type(&self, publisher: &PublisherInfo<'_>) -> Result<(), Error> {
        let uri = channel_uri(publisher.topic, type_name_of(publisher.type_support));
        if uri.len() > 255 {
            return Err(Error::msg(format!(
                "topic '{}' with type '{}' makes a uri of {} bytes; AimRT's layout allows 255",
                publisher.topic,
                type_name_of(publisher.type_support),
                uri.len()
            )));
        }
        let urls = self
            .rules
            .get()
            .and_then(|rules| rules.iter().find(|(re, _)| re.is_match(publisher.topic)))
            .map(|(_, urls)| urls.clone())
            .unwrap_or_default();
        let mut addrs = Vec::new();
        for url in &urls {
            // Checked in init; resolved again here, as names may move.
            addrs.extend(resolve(url).unwrap_or_default().into_iter().take(1));
        }
        if addrs.is_empty() {
            tracing::warn!(target: "aimrt", "net_plugin udp: topic '{}' has no server_url_list; its messages go only where aimrt-to_addr says", publisher.topic);
        }
        self.targets
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(publisher.topic.to_owned(), Arc::new(addrs));
        Ok(())
    }

    fn subscribe(&self, subscription: Subscription) -> Result<(), Error> {
        if self.options.is_none() {
            return Err(Error::msg(
                "Failed to subscribe: please set udp listen IP and port in the configuration (net_plugin options: udp_options: {listen_ip: 127.0.0.1, listen_port: 50040})",
            ));
        }
        let uri = channel_uri(&subscription.topic, subscription.sink.type_name());
        self.subs
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .entry(uri)
            .or_default()
            .push(subscription.sink);
        Ok(())
    }

    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error> {
        let topic = publication.topic();
        let refuse = |why: String| {
            self.stats.refused.fetch_add(1, Ordering::Relaxed);
            Err(Error::msg(why))
        };
        // Targets: the udp:// entries of aimrt-to_addr, else the topic's list.
        let to_addr = publication.get("aimrt-to_addr").unwrap_or("");
        let mut targets: Vec<SocketAddr> = Vec::new();
        for entry in to_addr.split(';').map(str::trim).filter(|e| !e.is_empty()) {
            let Some(addr) = entry.strip_prefix("udp://") else {
                continue;
            };
            match resolve(addr) {
                Some(a) => targets.extend(a.into_iter().take(1)),
                None => {
                    return refuse(format!(
                        "aimrt-to_addr entry '{entry}' is not an address (udp://ip:port)"
                    ))
                }
            }
        }
        if targets.is_empty() {
            let known = self
                .targets
                .read()
                .unwrap_or_else(|e| e.into_inner())
                .get(topic)
                .cloned();
            targets = known.map(|t| t.as_ref().clone()).unwrap_or_default();
        }
        if targets.is_empty() {
            return Ok(0);
        }
        let msg = publication.message();
        let ts = msg.type_support();
        let format = publication
            .get(KEY_SERIALIZATION_TYPE)
            .map(str::to_owned)
            .or_else(|| formats_of(ts).into_iter().next())
            .unwrap_or_default();
        let payload = match msg.encode(&format) {
            Ok(p) => p,
            Err(e) => return refuse(format!("cannot encode the message as {format}: {e}")),
        };
        let body = Body {
            uri: channel_uri(topic, type_name_of(ts)),
            serialization_type: format,
            meta: publication
                .ctx()
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .collect(),
            payload,
        };
        let bytes = match body.encode() {
            Ok(b) => b,
            Err(e) => return refuse(format!("cannot lay the message out for udp: {e}")),
        };
        if bytes.len() > MAX_DATAGRAM {
            return refuse(format!(
                "the message is {} bytes as a datagram, over the UDP limit of {MAX_DATAGRAM}; send it over tcp or http",
                bytes.len()
            ));
        }
        let Some(socket) = self.sender.get() else {
            return refuse("the udp backend is not initialized".into());
        };
        let mut sent = 0;
        for t in &targets {
            match socket.send_to(&bytes, t) {
                Ok(_) => sent += 1,
                Err(e) => self.warn(format_args!("sending to {t} failed: {e}")),
            }
        }
        self.stats.sent.fetch_add(sent, Ordering::Relaxed);
        Ok(aimrt_plugin_api::channel::RECEIVERS_UNKNOWN)
    }
}

/// The receiving socket, with a receive buffer of 4 MiB (or what the kernel allows) so a
/// burst waits in the kernel while subscribers run.
fn bind_receiver(addr: &str) -> std::io::Result<UdpSocket> {
    let sa: SocketAddr = addr
        .to_socket_addrs()?
        .next()
        .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::InvalidInput, "no address"))?;
    let socket = socket2::Socket::new(
        socket2::Domain::for_address(sa),
        socket2::Type::DGRAM,
        Some(socket2::Protocol::UDP),
    )?;
    let _ = socket.set_recv_buffer_size(4 << 20);
    socket.bind(&sa.into())?;
    Ok(socket.into())
}

fn read<T>(l: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|e| e.into_inner())
}

/// The receiver thread.
struct Receive {
    socket: UdpSocket,
    max: usize,
    subs: Arc<RwLock<HashMap<String, Vec<Sink>>>>,
    stats: Arc<UdpStats>,
    alarm: Arc<RateLimit>,
    run: Arc<AtomicBool>,
}

impl Receive {
    fn run(self) {
        // One spare byte tells a datagram that fits from one the kernel cut.
        let mut buf = vec![0u8; self.max + 1];
        while self.run.load(Ordering::SeqCst) {
            let (n, from) = match self.socket.recv_from(&mut buf) {
                Ok(r) => r,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    continue
                }
                Err(e) => {
                    warn_limited(&self.alarm, format_args!("receiving failed: {e}"));
                    std::thread::sleep(Duration::from_millis(10));
                    continue;
                }
            };
            if n > self.max {
                self.stats.truncated.fetch_add(1, Ordering::Relaxed);
                warn_limited(&self.alarm, format_args!("a datagram from {from} is longer than udp_options.max_pkg_size ({} bytes) and was dropped; raise max_pkg_size (at most {MAX_DATAGRAM})", self.max));
                continue;
            }
            self.dispatch(&buf[..n], from);
        }
    }

    fn dispatch(&self, bytes: &[u8], from: SocketAddr) {
        let body = match Body::decode(bytes) {
            Ok(b) => b,
            Err(e) => {
                self.stats.malformed.fetch_add(1, Ordering::Relaxed);
                warn_limited(
                    &self.alarm,
                    format_args!("a datagram from {from} is not a message: {e}"),
                );
                return;
            }
        };
        let subs = read(&self.subs);
        let Some(sinks) = subs.get(&body.uri) else {
            self.stats.unknown_uri.fetch_add(1, Ordering::Relaxed);
            warn_limited(
                &self.alarm,
                format_args!(
                    "a datagram from {from} is for '{}', which nobody here subscribes to",
                    body.uri
                ),
            );
            return;
        };
        // AimRT's order: the serialization type, then the wire meta (may overwrite); the
        // sink adds aimrt-backend.
        let mut meta: Vec<(&str, &str)> = vec![(KEY_SERIALIZATION_TYPE, &body.serialization_type)];
        for (k, v) in &body.meta {
            match meta.iter_mut().find(|(key, _)| *key == k.as_str()) {
                Some(slot) => slot.1 = v,
                None => meta.push((k, v)),
            }
        }
        let pairs = meta_of(meta.iter().copied());
        for sink in sinks {
            match RawMessage::decode(sink.type_support(), &body.serialization_type, &body.payload) {
                Ok(msg) => {
                    let _ = sink.deliver(&pairs, msg);
                }
                Err(e) => sink.report_drop(
                    DropReason::DecodeFailed,
                    &format!(
                        "a udp datagram from {from} cannot be decoded ({}): {e}",
                        body.serialization_type
                    ),
                ),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_are_ipv4_ipv6_or_names() {
        assert_eq!(resolve("127.0.0.1:50040").unwrap()[0].port(), 50040);
        assert!(resolve("[::1]:50040").unwrap()[0].is_ipv6());
        assert!(resolve("localhost:1").is_some());
        for bad in [
            "127.0.0.1",
            "127.0.0.1:",
            ":80",
            "127.0.0.1:99999",
            "a b:1",
            "x:y",
        ] {
            assert!(resolve(bad).is_none(), "{bad}");
        }
    }
}
