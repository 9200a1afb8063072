//! What the `udp` and `tcp` channel backends share: the topic rules
//! (`pub_topics_options[].{topic_name, server_url_list}`), addresses, turning a publication
//! into AimRT's body, and delivering a received body to the subscribers of its uri.

use std::collections::HashMap;
use std::net::{SocketAddr, ToSocketAddrs};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Duration;

use aimrt_plugin_api::channel::{
    LossReporter, Publication, PublisherInfo, Sink, Subscription, TopicRegistry,
};
use aimrt_plugin_api::ffi::type_name_of;
use aimrt_plugin_api::{BackendOptions, Error, RateLimit};
use regex::Regex;
use serde::Deserialize;

use crate::wire::{body_header, channel_uri, Body};

/// `pub_topics_options[i]` of a backend's options.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct PubTopic {
    topic_name: String,
    #[serde(default)]
    server_url_list: Vec<String>,
}

#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    pub_topics_options: Vec<PubTopic>,
}

/// `addr` without a leading `<scheme>://` and without a path (`http://h:1/x` → `h:1`).
fn normalize<'a>(addr: &'a str, scheme: &str) -> &'a str {
    let addr = addr
        .strip_prefix(scheme)
        .and_then(|a| a.strip_prefix("://"))
        .unwrap_or(addr);
    addr.split('/').next().unwrap_or(addr)
}

/// Resolves `host:port`, `ip:port` or `[ipv6]:port` to the addresses to send to; the
/// error says what is wrong (`is not an address; …`, `has port 0 …`, `names host 'h',
/// which does not resolve …`), after the entry's name.
pub(crate) fn resolve(addr: &str) -> Result<Vec<SocketAddr>, String> {
    let not_an_address = || {
        "is not an address; write ip:port, [ipv6]:port or host:port, e.g. 127.0.0.1:50040"
            .to_owned()
    };
    let (host, port) = addr.rsplit_once(':').ok_or_else(not_an_address)?;
    let port: u16 = port.parse().map_err(|_| not_an_address())?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() || host.contains(char::is_whitespace) {
        return Err(not_an_address());
    }
    if port == 0 {
        return Err(
            "has port 0, where no server listens; give the port of the subscriber's listen_port"
                .into(),
        );
    }
    let found: Vec<SocketAddr> = (host, port)
        .to_socket_addrs()
        .map_err(|e| format!("names host '{host}', which does not resolve ({e}); give its IP address, or add the name to /etc/hosts"))?
        .collect();
    if found.is_empty() {
        return Err(format!("names host '{host}', which resolves to no address"));
    }
    Ok(found)
}

/// The address of one `aimrt-to_addr` entry: an IP address and port, never a host name,
/// whose lookup would block every publish that names it (AimRT takes IPv4 only).
fn to_addr_target(entry: &str, addr: &str, scheme: &str) -> Result<SocketAddr, String> {
    addr.parse().map_err(|_| {
        // Told apart by its form: looking it up here would be the wait this avoids.
        let host_and_port = addr.rsplit_once(':').is_some_and(|(host, port)| {
            port.parse::<u16>().is_ok() && !host.is_empty() && !host.contains(char::is_whitespace)
        });
        if host_and_port {
            format!("aimrt-to_addr entry '{entry}' names a host: a context's addresses are not looked up (a DNS query on every publish could block it); give its IP, {scheme}://ip:port, or put the host in server_url_list, which is looked up once")
        } else {
            format!("aimrt-to_addr entry '{entry}' is not an address ({scheme}://ip:port or {scheme}://[ipv6]:port)")
        }
    })
}

/// Counters of one backend.
#[derive(Debug, Default)]
pub(crate) struct Stats {
    /// Messages sent (one per target).
    pub(crate) sent: AtomicU64,
    /// Messages refused at publish time (too large, a full queue, a bad `to_addr`).
    pub(crate) refused: AtomicU64,
    /// Messages (one per target) `publish` took that were then not sent: a send error, a
    /// peer's error answer or none, or still queued or in flight at shutdown.
    pub(crate) lost: AtomicU64,
    /// Datagrams longer than `max_pkg_size` (udp); frames a connection ended in the middle
    /// of (tcp).
    pub(crate) truncated: AtomicU64,
    /// Received bytes that are not a message (or a frame).
    pub(crate) malformed: AtomicU64,
    /// Received messages for a uri nobody here subscribes to.
    pub(crate) unknown_uri: AtomicU64,
    /// Datagrams the kernel dropped for the receiving socket before they were read (udp).
    pub(crate) kernel_dropped: AtomicU64,
}

impl Stats {
    /// The shutdown line of a backend that receives no datagrams.
    pub(crate) fn line(&self) -> String {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        format!(
            "{} messages sent, {} refused, {} lost after publish, {} received truncated, {} malformed, {} for unknown uris",
            g(&self.sent),
            g(&self.refused),
            g(&self.lost),
            g(&self.truncated),
            g(&self.malformed),
            g(&self.unknown_uri)
        )
    }
}

/// Topic rules, and the addresses and uris of each registered topic.
#[derive(Default)]
pub(crate) struct Routes {
    rules: Vec<(Regex, Vec<String>)>,
    /// By topic, one per registered type; sealed by the first publish.
    targets: TopicRegistry<TypeRoute>,
}

/// What registration resolved for one type on a topic.
struct TypeRoute {
    /// The type's table, by address.
    ts: usize,
    uri: Arc<str>,
    /// The topic's configured addresses (the same for every type of the topic).
    addrs: Arc<Vec<SocketAddr>>,
}

/// Where one publication goes, and its uri when its type was registered.
pub(crate) struct Route {
    pub(crate) addrs: Arc<Vec<SocketAddr>>,
    pub(crate) uri: Option<Arc<str>>,
    /// `addrs` are the topic's configured addresses (not a message's `aimrt-to_addr`).
    pub(crate) configured: bool,
}

impl Routes {
    /// Reads `pub_topics_options`; a bad regex or address is an error naming it.
    pub(crate) fn parse(options: &BackendOptions, backend: &str) -> Result<Routes, Error> {
        let o: Options = options.read()?;
        let mut rules = Vec::new();
        for (i, t) in o.pub_topics_options.into_iter().enumerate() {
            let bad = |message: String| Error::Options {
                what: format!(
                    "{backend} channel backend options at {}",
                    options.location()
                ),
                message: format!("pub_topics_options[{i}]: {message}"),
            };
            let re = aimrt_plugin_api::whole_match(&t.topic_name).map_err(|e| {
                bad(format!(
                    "topic_name '{}' is not a valid regular expression: {e}",
                    t.topic_name
                ))
            })?;
            let mut urls = Vec::new();
            for url in &t.server_url_list {
                let addr = normalize(url, backend);
                if let Err(why) = resolve(addr) {
                    return Err(bad(format!("server_url_list entry '{url}' {why}")));
                }
                urls.push(addr.to_owned());
            }
            rules.push((re, urls));
        }
        Ok(Routes {
            rules,
            targets: TopicRegistry::default(),
        })
    }

    /// Resolves the addresses of a publisher's topic (first matching rule).
    pub(crate) fn register(
        &self,
        publisher: &PublisherInfo<'_>,
        backend: &str,
    ) -> Result<(), Error> {
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
            .iter()
            .find(|(re, _)| re.is_match(publisher.topic))
            .map(|(_, urls)| urls.clone())
            .unwrap_or_default();
        let addrs: Vec<SocketAddr> = urls
            .iter()
            .filter_map(|u| resolve(u).ok().and_then(|a| a.into_iter().next()))
            .collect();
        if addrs.is_empty() {
            tracing::warn!(target: "aimrt", "net_plugin {backend}: topic '{}' has no server_url_list; its messages go only where aimrt-to_addr says", publisher.topic);
        }
        let route = TypeRoute {
            ts: publisher.type_support as *const _ as usize,
            uri: uri.into(),
            addrs: Arc::new(addrs),
        };
        self.targets
            .register(publisher.topic, |types| types.push(route))
            .ok_or_else(|| {
                Error::msg(format!(
                    "net_plugin {backend}: topic '{}' is registered after the first publish; register publish types in initialize",
                    publisher.topic
                ))
            })
    }

    /// Where a publication goes: the `<scheme>://` entries of its `aimrt-to_addr`, else
    /// its topic's addresses (shared, not copied). `Err`: a malformed `to_addr` entry.
    pub(crate) fn targets(
        &self,
        publication: &Publication<'_>,
        scheme: &str,
    ) -> Result<Route, String> {
        let mut targets = Vec::new();
        let to_addr = publication.get("aimrt-to_addr").unwrap_or("");
        for entry in to_addr.split(';').map(str::trim).filter(|e| !e.is_empty()) {
            let Some(addr) = entry
                .strip_prefix(scheme)
                .and_then(|a| a.strip_prefix("://"))
            else {
                continue;
            };
            targets.push(to_addr_target(entry, normalize(addr, scheme), scheme)?);
        }
        // Publishing starts once registering has ended: the first publish seals them.
        let types = self.targets.get(publication.topic_bytes());
        let ts = publication.message().type_support() as *const _ as usize;
        let uri = types.iter().find(|r| r.ts == ts).map(|r| r.uri.clone());
        let configured = targets.is_empty();
        let addrs = if configured {
            types.first().map(|r| r.addrs.clone()).unwrap_or_default()
        } else {
            Arc::new(targets)
        };
        Ok(Route {
            addrs,
            uri,
            configured,
        })
    }
}

pub(crate) use aimrt_wire::channel::{encode_into, encoded, format_of};

/// A publication as AimRT's body bytes, written once: the header, then the message
/// encoded in its format behind it. `uri` is the one registration made (else it is made
/// now).
pub(crate) fn body_of(publication: &Publication<'_>, uri: Option<&str>) -> Result<Vec<u8>, String> {
    let made;
    let uri = match uri {
        Some(u) => u,
        None => {
            made = channel_uri(
                publication.topic(),
                type_name_of(publication.message().type_support()),
            );
            &made
        }
    };
    let format = format_of(publication);
    // Room for a small message; a larger one grows the buffer once.
    let pairs = || publication.meta().iter().map(|p| p.bytes());
    let mut out = body_header(uri, &format, pairs, 256)
        .map_err(|e| format!("cannot lay the message out: {e}"))?;
    encode_into(publication, &format, &mut out)?;
    Ok(out)
}

/// How long shutdown waits for messages a backend took and has not sent yet.
pub(crate) const SETTLE: Duration = Duration::from_secs(2);

/// Messages (one per target) a backend took in `publish` and has not sent yet: queued for
/// a connection, or a request in flight.
#[derive(Debug, Default)]
struct Pending {
    count: AtomicU64,
    none: tokio::sync::Notify,
}

impl Pending {
    pub(crate) fn add(&self, n: u64) {
        self.count.fetch_add(n, Ordering::AcqRel);
    }

    /// `n` of them were sent, or lost.
    pub(crate) fn done(&self, n: u64) {
        if n > 0 && self.count.fetch_sub(n, Ordering::AcqRel) == n {
            self.none.notify_waiters();
        }
    }

    pub(crate) fn get(&self) -> u64 {
        self.count.load(Ordering::Acquire)
    }

    /// Waits up to `limit` for none to be pending; how many still are.
    fn settle(&self, handle: &tokio::runtime::Handle, limit: Duration) -> u64 {
        let none = async {
            loop {
                let woken = self.none.notified();
                tokio::pin!(woken);
                woken.as_mut().enable();
                if self.get() == 0 {
                    return;
                }
                woken.await;
            }
        };
        handle.block_on(async {
            let _ = tokio::time::timeout(limit, none).await;
        });
        self.get()
    }
}

/// One message, to one target, that a backend took in `publish` and has not sent yet. It
/// ends [`sent`](Taken::sent) or [`lost`](Taken::lost); one dropped otherwise (a queue or
/// task let go at shutdown) counts as lost too, so none goes uncounted. A loss is counted
/// in the backend's line and, on a host of ABI 1.8, in the topic's stats.
pub(crate) struct Taken {
    inbox: Arc<Inbox>,
    topic: LossReporter,
    open: bool,
}

impl Taken {
    /// Sent.
    pub(crate) fn sent(self) {
        Taken::sent_all(std::iter::once(self));
    }

    /// All of `taken` sent (one count for the lot).
    pub(crate) fn sent_all(taken: impl IntoIterator<Item = Taken>) {
        let mut n = 0;
        let mut inbox = None;
        for mut t in taken {
            t.open = false;
            n += 1;
            inbox.get_or_insert_with(|| t.inbox.clone());
        }
        if let Some(inbox) = inbox {
            inbox.stats.sent.fetch_add(n, Ordering::Relaxed);
            inbox.pending.done(n);
        }
    }

    /// Not taken after all: `publish` refuses it (which counts it).
    pub(crate) fn refused(mut self) {
        self.open = false;
        self.inbox.pending.done(1);
    }

    /// Not sent, for the reason `what` (logged at a limited rate).
    pub(crate) fn lost(mut self, what: std::fmt::Arguments<'_>) {
        self.open = false;
        self.inbox.lose(&self.topic, what);
        self.inbox.pending.done(1);
    }
}

impl Drop for Taken {
    fn drop(&mut self) {
        if self.open {
            // The backend's shutdown warns once with the number; the topic is told each.
            self.inbox.stats.lost.fetch_add(1, Ordering::Relaxed);
            self.topic.lost(&format!(
                "net_plugin {}: a message publish took was still queued or in flight when the backend stopped, and is lost",
                self.inbox.backend
            ));
            self.inbox.pending.done(1);
        }
    }
}

/// The subscribers of a backend, by uri, and what it received.
pub(crate) struct Inbox {
    backend: &'static str,
    subs: RwLock<HashMap<String, Vec<Sink>>>,
    pub(crate) stats: Stats,
    /// Messages taken by `publish` and not yet sent or lost.
    pending: Pending,
    alarm: RateLimit,
}

impl Inbox {
    pub(crate) fn new(backend: &'static str) -> Inbox {
        Inbox {
            backend,
            subs: RwLock::default(),
            stats: Stats::default(),
            pending: Pending::default(),
            alarm: RateLimit::from_millis(1000),
        }
    }

    /// Logs at most once a second, with how many lines were held back.
    pub(crate) fn warn(&self, what: std::fmt::Arguments<'_>) {
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(target: "aimrt", "net_plugin {}: {what} ({held} more such lines held back since the last)", self.backend);
        }
    }

    /// A message to one target that `publish` took is not sent after all: counted here
    /// and in the topic's stats (which logs it at a limited rate), or logged here at a
    /// limited rate where the host is older than ABI 1.8.
    pub(crate) fn lose(&self, topic: &LossReporter, what: std::fmt::Arguments<'_>) {
        self.stats.lost.fetch_add(1, Ordering::Relaxed);
        if !topic.lost(&format!("net_plugin {}: {what}", self.backend)) {
            self.warn(what);
        }
    }

    /// `publish` takes a message to one target: it is pending until sent or lost.
    pub(crate) fn take(self: &Arc<Inbox>, topic: &LossReporter) -> Taken {
        self.pending.add(1);
        Taken {
            inbox: self.clone(),
            topic: topic.clone(),
            open: true,
        }
    }

    /// At shutdown: waits up to [`SETTLE`] for the messages taken to be sent, and warns
    /// once about those still waiting. They are counted as lost as their queues and tasks
    /// are let go ([`Taken`]'s drop).
    pub(crate) fn settle(&self, handle: &tokio::runtime::Handle) {
        let left = self.pending.settle(handle, SETTLE);
        if left > 0 {
            tracing::warn!(target: "aimrt", "net_plugin {}: {left} messages were still queued or in flight at shutdown, {} s after it began, and are lost", self.backend, SETTLE.as_secs());
        }
    }

    /// Refuses a message at publish time: counted, and the reason for the topic's stats.
    pub(crate) fn refuse(&self, why: String) -> Result<u64, Error> {
        self.stats.refused.fetch_add(1, Ordering::Relaxed);
        Err(Error::msg(why))
    }

    pub(crate) fn subscribe(&self, subscription: Subscription) {
        let uri = channel_uri(&subscription.topic, subscription.sink.type_name());
        self.subs
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .entry(uri)
            .or_default()
            .push(subscription.sink);
    }

    /// What to tell a sender whose `uri` nobody here subscribes to: the subscribed uri it
    /// most likely meant, or nothing. A uri of the same topic and type written without
    /// AimRT's URL-encoding (`pb:` for `pb%3A`) is named whatever the distance.
    pub(crate) fn hint(&self, uri: &str) -> String {
        let subs = self.subs.read().unwrap_or_else(|e| e.into_inner());
        let rest = uri.strip_prefix("/channel/").unwrap_or("");
        // The topic may hold '/' too: every split between topic and type is tried.
        let unencoded = rest
            .match_indices('/')
            .map(|(at, _)| channel_uri(&rest[..at], &rest[at + 1..]))
            .find(|encoded| encoded != uri && subs.contains_key(encoded));
        match unencoded {
            Some(encoded) => format!(
                "; the topic and the type in the uri are URL-encoded, as AimRT sends them: did you mean '{encoded}'?"
            ),
            None => aimrt_plugin_api::__private::did_you_mean(uri, subs.keys().map(String::as_str)),
        }
    }

    /// The shutdown line: [`Stats::line`], and for udp the datagrams the kernel dropped.
    pub(crate) fn line(&self) -> String {
        let line = self.stats.line();
        if self.backend != "udp" {
            return line;
        }
        let dropped = self.stats.kernel_dropped.load(Ordering::Relaxed);
        format!("{line}, {dropped} dropped by the kernel before they were read")
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.subs
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .is_empty()
    }

    /// Delivers one received body to the subscribers of its uri, counting what cannot be.
    pub(crate) fn dispatch(&self, bytes: &[u8], from: SocketAddr) {
        match Body::decode(bytes) {
            Ok(body) => {
                self.deliver(body, &from);
            }
            Err(e) => {
                self.stats.malformed.fetch_add(1, Ordering::Relaxed);
                self.warn(format_args!("a message from {from} is malformed: {e}"));
            }
        }
    }

    /// Delivers a message to the subscribers of its uri; `false` when nobody here
    /// subscribes to it (counted).
    pub(crate) fn deliver(&self, body: Body, from: &dyn std::fmt::Display) -> bool {
        let subs = self.subs.read().unwrap_or_else(|e| e.into_inner());
        let Some(sinks) = subs.get(body.uri) else {
            self.stats.unknown_uri.fetch_add(1, Ordering::Relaxed);
            self.warn(format_args!(
                "a message from {from} is for '{}', which nobody here subscribes to",
                body.uri
            ));
            return false;
        };
        aimrt_wire::channel::deliver(
            sinks,
            body.serialization_type,
            body.meta.iter().copied(),
            body.payload,
            from,
        );
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pages that show a channel backend's shutdown line show it as written, numbers
    /// aside (`net_plugin tcp: 120 messages sent, …`).
    #[test]
    fn the_docs_show_the_shutdown_line_as_written() {
        use aimrt_plugin_api::__private::numbers_as_hash;
        let mut shown = 0;
        for page in ["net-plugin.md", "channels.md"] {
            let path = format!("{}/../../docs/{page}", env!("CARGO_MANIFEST_DIR"));
            let docs = std::fs::read_to_string(&path).expect("a page");
            for line in docs.lines().filter(|l| l.contains(" messages sent, ")) {
                let Some(at) = line.find("net_plugin ") else {
                    continue;
                };
                let (backend, numbers) = line[at..].split_once(": ").expect("'<backend>: '");
                assert!(
                    [
                        "net_plugin tcp",
                        "net_plugin udp",
                        "net_plugin http channel"
                    ]
                    .contains(&backend),
                    "{page}: {backend}"
                );
                let written = match backend {
                    "net_plugin udp" => Inbox::new("udp").line(),
                    _ => Stats::default().line(),
                };
                assert_eq!(
                    numbers_as_hash(numbers.trim_end_matches(['`', '.'])),
                    numbers_as_hash(&written),
                    "{page}"
                );
                shown += 1;
            }
        }
        assert!(shown >= 3, "{shown} shutdown lines shown");
    }

    #[test]
    fn a_contexts_addresses_are_ip_addresses_never_looked_up() {
        assert_eq!(
            to_addr_target("tcp://10.0.0.4:50060", "10.0.0.4:50060", "tcp"),
            Ok("10.0.0.4:50060".parse().unwrap())
        );
        assert!(to_addr_target("udp://[::1]:1", "[::1]:1", "udp")
            .unwrap()
            .is_ipv6());
        let named = to_addr_target("tcp://localhost:1", "localhost:1", "tcp").unwrap_err();
        assert!(
            named.contains("names a host") && named.contains("server_url_list"),
            "{named}"
        );
        let bad = to_addr_target("tcp://10.0.0.4", "10.0.0.4", "tcp").unwrap_err();
        assert!(bad.contains("is not an address"), "{bad}");
    }

    #[test]
    fn addresses_are_ipv4_ipv6_or_names() {
        assert_eq!(resolve("127.0.0.1:50040").unwrap()[0].port(), 50040);
        assert!(resolve("[::1]:50040").unwrap()[0].is_ipv6());
        assert!(resolve("localhost:1").is_ok());
        for bad in [
            "127.0.0.1",
            "127.0.0.1:",
            ":80",
            "127.0.0.1:99999",
            "a b:1",
            "x:y",
        ] {
            let why = resolve(bad).unwrap_err();
            assert!(
                why.starts_with("is not an address; write ip:port"),
                "{bad}: {why}"
            );
        }
        let why = resolve("127.0.0.1:0").unwrap_err();
        assert!(
            why.starts_with("has port 0, where no server listens"),
            "{why}"
        );
        let why = resolve("robot-pc.invalid:50060").unwrap_err();
        assert!(
            why.starts_with("names host 'robot-pc.invalid', which does not resolve (")
                && why.ends_with("); give its IP address, or add the name to /etc/hosts"),
            "{why}"
        );
    }
}
