//! Channels (DESIGN §6): `aimrt.channel`, the channel manager and the built-in `local`
//! backend.
//!
//! The manager owns the phase rules (register and subscribe in `initialize`, publish from
//! `start` until the channel shuts down), the registry (one registration per type, topic
//! and module), the per-topic `aimrt-pub_seq` counter and every topic's counters. Backends
//! — `local` included — are reached only through the channel-backend vtable.

mod filter;
mod local;

pub(crate) use self::filter::{RegisteredFilters, BUILT_IN as BUILT_IN_FILTERS};

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use aimrt_plugin_api::channel::{
    DropReason, FilterSide, PublisherInfo, TopicRegistry, TopicStats, KEY_BACKEND, KEY_PUB_SEQ,
    KEY_PUB_TS, KEY_SERIALIZATION_TYPE, RECEIVERS_UNKNOWN,
};
use aimrt_plugin_api::ffi::{
    find_table, formats_of, type_name_of, Header, MetaPair, MetaPairs, RawChannelBackend,
    RawExecutor, RawMessage, RawPublication, RawSink, RawSubscriber, RawTopicRef, SinkHost,
    StrView, TopicHost, TypeSupportVtable,
};

use crate::config::{Config, ReportedOptions};
use crate::plugin::BackendType;
use crate::routing::{listed_backends, Rules};
use crate::Error;
use aimrt_plugin_api::__private::did_you_mean;

const INIT: u8 = 0;
const STARTED: u8 = 1;
const SHUT_DOWN: u8 = 2;

/// The name of the built-in backend.
const LOCAL: &str = "local";
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// One topic: its backends, its publish counter and its counters.
pub(crate) struct Topic {
    name: String,
    /// Indexes into the manager's backends, from the first matching `pub_topics_options`
    /// rule (`None`: no rule matches).
    pub_backends: Option<Vec<usize>>,
    /// The same for `sub_topics_options`.
    sub_backends: Option<Vec<usize>>,
    /// The filters of the topic's pub (sub) rule, in the order they run.
    pub_filters: filter::Chain,
    sub_filters: filter::Chain,
    seq: AtomicU32,
    published: AtomicU64,
    delivered: AtomicU64,
    dropped: [AtomicU64; DropReason::ALL.len()],
    /// Per reason: when the next report may be logged (ns on [`report_clock`]; 0: none
    /// yet; `u64::MAX`: none again, after a state's one report), and the drop count the
    /// last report covered.
    next_report: [AtomicU64; DropReason::ALL.len()],
    reported_upto: [AtomicU64; DropReason::ALL.len()],
}

/// Nanoseconds since the first call, from 1 up: the clock of drop reports.
fn report_clock() -> u64 {
    static START: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    let start = *START.get_or_init(Instant::now);
    u64::try_from(start.elapsed().as_nanos())
        .unwrap_or(u64::MAX)
        .saturating_add(1)
}

/// Whether a drop for `reason` is a state of the config or the process (no rule, no
/// subscriber, not started, not registered), reported once, rather than an event that
/// may come back (a backend or executor refusing, a decode or a callback failing),
/// reported at most once a second.
fn reported_once(reason: DropReason) -> bool {
    matches!(
        reason,
        DropReason::NoRoute
            | DropReason::NoSubscriber
            | DropReason::WrongPhase
            | DropReason::Unregistered
    )
}

impl Topic {
    /// Counts a drop and logs it: the first of a state-like reason once, an event-like
    /// one at most once a second with how many came since the last report. `details` is
    /// formatted only then (pass `format_args!`): a topic nobody subscribes to drops
    /// every message, and counting one must not allocate.
    fn drop_message(&self, reason: DropReason, details: impl std::fmt::Display) {
        self.drop_messages_as(reason, 1, reported_once(reason), details);
    }

    /// [`drop_message`](Self::drop_message), reported once (`once`) or at most once a
    /// second: a filter holding messages back by design is reported once, one failing
    /// each time it fails.
    fn drop_message_as(&self, reason: DropReason, once: bool, details: impl std::fmt::Display) {
        self.drop_messages_as(reason, 1, once, details);
    }

    /// Counts `n` drops of one reason at once (a backend's report of a gap) and logs them
    /// as [`drop_message_as`](Self::drop_message_as) logs one.
    fn drop_messages_as(
        &self,
        reason: DropReason,
        n: u64,
        once: bool,
        details: impl std::fmt::Display,
    ) {
        let i = reason.code() as usize;
        let count = self.dropped[i].fetch_add(n, Ordering::Relaxed) + n;
        // Read first: once reported, no write to the cache line per message.
        let next = self.next_report[i].load(Ordering::Relaxed);
        if next == u64::MAX {
            return;
        }
        let now = report_clock();
        if now < next {
            return;
        }
        let then = if once { u64::MAX } else { now + 1_000_000_000 };
        if self.next_report[i]
            .compare_exchange(next, then, Ordering::Relaxed, Ordering::Relaxed)
            .is_err()
        {
            return;
        }
        let earlier = self.reported_upto[i].swap(count, Ordering::Relaxed);
        let name = &self.name;
        if once {
            tracing::warn!(target: "aimrt", "Channel topic '{name}': {details} (reported once; every such message is counted in the topic's stats: {reason})");
        } else if earlier == 0 {
            tracing::warn!(target: "aimrt", "Channel topic '{name}': {details} (reported at most once a second; every such message is counted in the topic's stats: {reason})");
        } else {
            let since = count.saturating_sub(earlier);
            tracing::warn!(target: "aimrt", "Channel topic '{name}': {details} ({since} since the last report, {count} so far; every such message is counted in the topic's stats: {reason})");
        }
    }

    fn stats(&self) -> TopicStats {
        TopicStats {
            published: self.published.load(Ordering::Relaxed),
            delivered: self.delivered.load(Ordering::Relaxed),
            dropped: DropReason::ALL
                .iter()
                .zip(&self.dropped)
                .map(|(r, n)| (*r, n.load(Ordering::Relaxed)))
                .filter(|(_, n)| *n > 0)
                .collect(),
        }
    }
}

/// A configured backend.
struct Backend {
    name: String,
    raw: RawChannelBackend,
}

/// The channel manager: one per runtime, shared by every module's core handle.
pub(crate) struct ChannelManager {
    state: AtomicU8,
    backends: Vec<Backend>,
    started: Mutex<usize>,
    pub_rules: Rules,
    sub_rules: Rules,
    topics: Mutex<BTreeMap<String, Arc<Topic>>>,
    /// `(publish?, type, topic, module)` of every registration, for dedupe.
    registered: Mutex<HashSet<(bool, String, String, String)>>,
    /// Topics whose "subscribed but routed nowhere" warning was given.
    unrouted: Mutex<HashSet<String>>,
    /// The channel filters plugins registered.
    filters: RegisteredFilters,
}

impl ChannelManager {
    /// Reads `aimrt.channel`: initialises each listed backend (built-in `local`, or one a
    /// plugin registered) and compiles the topic rules.
    pub(crate) fn configure(
        config: &Config,
        executors: &HashMap<String, RawExecutor>,
        mut registered: BTreeMap<String, BackendType<RawChannelBackend>>,
        filters: RegisteredFilters,
    ) -> Result<ChannelManager, Error> {
        let mut manager = ChannelManager {
            state: AtomicU8::new(INIT),
            backends: Vec::new(),
            started: Mutex::new(0),
            pub_rules: Rules::default(),
            sub_rules: Rules::default(),
            topics: Mutex::new(BTreeMap::new()),
            registered: Mutex::new(HashSet::new()),
            unrouted: Mutex::new(HashSet::new()),
            filters,
        };
        let Some(section) = config.aimrt.channel.as_ref() else {
            for (name, b) in &registered {
                tracing::info!(target: "aimrt", "channel backend '{name}' of '{}' is not started: the config has no aimrt.channel section listing it", b.owner);
            }
            return Ok(manager);
        };
        let listed = listed_backends(config, &section.backends, "aimrt.channel")?;
        for entry in &section.backends {
            let ty = entry.type_name.value.as_str();
            let (options, location) = config.options_of(entry.options.as_ref(), &entry.type_name);
            let (raw, owner) = if ty == LOCAL {
                let drain = config
                    .aimrt
                    .executor
                    .as_ref()
                    .map_or(crate::config::DEFAULT_JOIN_TIMEOUT_MS, |e| {
                        e.join_timeout_ms
                    });
                let local = local::LocalBackend::new(
                    executors.clone(),
                    std::time::Duration::from_millis(drain),
                );
                (RawChannelBackend::new(local), None)
            } else if let Some(b) = registered.remove(ty) {
                (b.raw, Some(b.owner))
            } else {
                let known: Vec<&str> = std::iter::once(LOCAL)
                    .chain(registered.keys().map(String::as_str))
                    .chain(manager.backends.iter().map(|b| b.name.as_str()))
                    .collect();
                return Err(config.error(
                    &entry.type_name,
                    format!(
                        "unknown channel backend type '{ty}'{}; known: {} (plugins add more)",
                        did_you_mean(ty, known.iter().copied()),
                        known.join(", ")
                    ),
                ));
            };
            raw.init(&options, &location)
                .map_err(|message| match &owner {
                    None => config.error(&entry.type_name, message),
                    Some(plugin) => Error::Plugin {
                        plugin: plugin.clone(),
                        action: "initialize its channel backend",
                        message,
                    },
                })?;
            manager.backends.push(Backend {
                name: ty.to_owned(),
                raw,
            });
        }
        for (name, b) in &registered {
            tracing::info!(target: "aimrt", "channel backend '{name}' of '{}' is not started: aimrt.channel.backends does not list it", b.owner);
        }
        manager.pub_rules = Rules::compile(
            config,
            &section.pub_topics_options,
            &listed,
            &manager.filters.names(FilterSide::Publish),
            "aimrt.channel",
        )?;
        manager.sub_rules = Rules::compile(
            config,
            &section.sub_topics_options,
            &listed,
            &manager.filters.names(FilterSide::Subscribe),
            "aimrt.channel",
        )?;
        Ok(manager)
    }

    /// Starts the backends in config order; then publishing is allowed.
    pub(crate) fn start(&self) -> Result<(), Error> {
        let mut started = lock(&self.started);
        for b in &self.backends[*started..] {
            b.raw.start().map_err(|message| Error::Channel {
                backend: b.name.clone(),
                message,
            })?;
            *started += 1;
        }
        self.state.store(STARTED, Ordering::SeqCst);
        self.warn_unpublished();
        Ok(())
    }

    /// Warns of each subscription that nothing can feed: no module or plugin of this
    /// process publishes its topic and type, and only `local` carries it (another
    /// backend may bring it from another process).
    fn warn_unpublished(&self) {
        let registered = lock(&self.registered);
        let topics = lock(&self.topics);
        for (publish, ty, topic, module) in registered.iter() {
            if *publish
                || registered
                    .iter()
                    .any(|(p, t, n, _)| *p && t == ty && n == topic)
            {
                continue;
            }
            let local_only = topics
                .get(topic)
                .and_then(|t| t.sub_backends.as_ref())
                .is_some_and(|b| {
                    !b.is_empty() && b.iter().all(|&i| self.backends[i].name == LOCAL)
                });
            if local_only {
                tracing::warn!(target: "aimrt", "Channel topic '{topic}': '{module}' subscribes to type '{ty}', but no module or plugin of this process publishes it and only the local backend carries it, so it will receive nothing; check the topic name and type, or enable a backend that reaches the publishing process");
            }
        }
    }

    /// Refuses further publishing, stops the started backends in reverse order and logs
    /// every topic's counters.
    pub(crate) fn shutdown(&self) {
        self.state.store(SHUT_DOWN, Ordering::SeqCst);
        let started = std::mem::take(&mut *lock(&self.started));
        for b in self.backends[..started].iter().rev() {
            b.raw.shutdown();
        }
        for (name, topic) in lock(&self.topics).iter() {
            tracing::info!(target: "aimrt", "Channel topic '{name}': {}", topic.stats());
        }
    }

    /// The options each backend reported as its `init` read them, by type.
    pub(crate) fn reported_options(&self) -> BTreeMap<String, serde_json::Value> {
        let reported = (self.backends.iter()).map(|b| (b.name.as_str(), b.raw.reported_options()));
        ReportedOptions::by_name("channel backend", reported)
    }

    /// The configured backends, in config order (the init report's "Channel Backend List").
    pub(crate) fn backend_names(&self) -> Vec<&str> {
        self.backends.iter().map(|b| b.name.as_str()).collect()
    }

    /// The names `enable_filters` may list: publish, subscribe (the init report).
    pub(crate) fn filter_names(&self) -> (Vec<&str>, Vec<&str>) {
        (
            self.filters.names(FilterSide::Publish),
            self.filters.names(FilterSide::Subscribe),
        )
    }

    /// `[topic, msg type, modules, backends, filters]` of every publish (or subscribe)
    /// registration, one row per topic and type (the init report's topic info tables).
    pub(crate) fn topic_rows(&self, publish: bool) -> Vec<Vec<String>> {
        let mut rows: BTreeMap<(String, String), Vec<String>> = BTreeMap::new();
        for (p, ty, topic, module) in lock(&self.registered).iter() {
            if *p == publish {
                rows.entry((topic.clone(), ty.clone()))
                    .or_default()
                    .push(module.clone());
            }
        }
        let topics = lock(&self.topics);
        let rules = if publish {
            &self.pub_rules
        } else {
            &self.sub_rules
        };
        rows.into_iter()
            .map(|((topic, ty), mut modules)| {
                modules.sort();
                let backends = topics
                    .get(&topic)
                    .and_then(|t| {
                        if publish {
                            t.pub_backends.clone()
                        } else {
                            t.sub_backends.clone()
                        }
                    })
                    .unwrap_or_default()
                    .iter()
                    .map(|&i| self.backends[i].name.clone())
                    .collect::<Vec<_>>()
                    .join(", ");
                let filters = rules.filters_for(&topic).join(", ");
                vec![topic, ty, modules.join(", "), backends, filters]
            })
            .collect()
    }

    /// The counters of a topic.
    pub(crate) fn stats(&self, topic: &str) -> Option<TopicStats> {
        lock(&self.topics).get(topic).map(|t| t.stats())
    }

    fn phase_error(&self, what: &str) -> Option<String> {
        match self.state.load(Ordering::SeqCst) {
            INIT => None,
            STARTED => Some(format!(
                "{what} only in initialize; the runtime has started"
            )),
            _ => Some(format!(
                "{what} only in initialize; the runtime is shutting down"
            )),
        }
    }

    fn resolve(&self, rules: &Rules, topic: &str) -> Option<Vec<usize>> {
        rules.backends_for(topic).map(|names| {
            names
                .iter()
                .filter_map(|n| self.backends.iter().position(|b| &b.name == n))
                .collect()
        })
    }

    fn topic(&self, name: &str) -> Arc<Topic> {
        let chain = |side, rules: &Rules| self.filters.chain(side, rules.filters_for(name));
        lock(&self.topics)
            .entry(name.to_owned())
            .or_insert_with(|| {
                Arc::new(Topic {
                    name: name.to_owned(),
                    pub_backends: self.resolve(&self.pub_rules, name),
                    sub_backends: self.resolve(&self.sub_rules, name),
                    pub_filters: chain(FilterSide::Publish, &self.pub_rules),
                    sub_filters: chain(FilterSide::Subscribe, &self.sub_rules),
                    seq: AtomicU32::new(0),
                    published: AtomicU64::new(0),
                    delivered: AtomicU64::new(0),
                    dropped: Default::default(),
                    next_report: Default::default(),
                    reported_upto: Default::default(),
                })
            })
            .clone()
    }

    fn dedupe(
        &self,
        publish: bool,
        type_name: &str,
        topic: &str,
        module: &str,
    ) -> Result<(), String> {
        let key = (
            publish,
            type_name.to_owned(),
            topic.to_owned(),
            module.to_owned(),
        );
        if lock(&self.registered).insert(key) {
            return Ok(());
        }
        Err(if publish {
            format!("publish type '{type_name}' is registered repeatedly on topic '{topic}' by module '{module}'; register each type once per topic")
        } else {
            format!("type '{type_name}' is subscribed repeatedly on topic '{topic}' by module '{module}'; subscribe each type once per topic")
        })
    }
}

/// A registered publish type of one module.
struct PubEntry {
    ts: &'static TypeSupportVtable,
    topic: Arc<Topic>,
    default_format: String,
}

/// A module's side of the channel: what its core handle serves.
pub(crate) struct ModuleChannel {
    manager: Arc<ChannelManager>,
    module: String,
    /// Set once the module's `start` returned: network backends deliver only from then.
    started: Arc<AtomicBool>,
    pkg: String,
    /// Publish types by topic: registered in `initialize`, sealed by the first publish.
    pubs: TopicRegistry<PubEntry>,
    /// Unregistered `(topic, type)` publishes already reported.
    unregistered: Mutex<HashSet<(String, String)>>,
}

impl ModuleChannel {
    pub(crate) fn new(
        manager: Arc<ChannelManager>,
        module: &str,
        pkg: &str,
        started: Arc<AtomicBool>,
    ) -> ModuleChannel {
        ModuleChannel {
            manager,
            module: module.to_owned(),
            started,
            pkg: pkg.to_owned(),
            pubs: TopicRegistry::default(),
            unregistered: Mutex::new(HashSet::new()),
        }
    }

    pub(crate) fn register_publish_type(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        let type_name = type_name_of(ts);
        let m = &self.manager;
        if let Some(e) = m.phase_error(&format!(
            "publish type '{type_name}' on topic '{topic}' can be registered"
        )) {
            return Err(e);
        }
        check_topic_name(topic)?;
        let formats = formats_of(ts);
        let Some(default_format) = formats.first().cloned() else {
            return Err(format!(
                "message type '{type_name}' declares no format; a message type needs at least one"
            ));
        };
        m.dedupe(true, type_name, topic, &self.module)?;
        let t = m.topic(topic);
        let info = PublisherInfo {
            topic,
            type_support: ts,
            pkg: &self.pkg,
            module: &self.module,
        };
        for &i in t.pub_backends.iter().flatten() {
            let b = &m.backends[i];
            b.raw.register_publish_type(&info).map_err(|e| {
                format!("channel backend '{}' refused publish type '{type_name}' on topic '{topic}': {e}", b.name)
            })?;
        }
        if t.pub_backends.is_none() {
            tracing::warn!(target: "aimrt", "Channel topic '{topic}' matches no aimrt.channel.pub_topics_options rule: what module '{}' publishes on it goes nowhere", self.module);
        }
        let entry = PubEntry {
            ts,
            topic: t,
            default_format,
        };
        self.pubs
            .register(topic, |list| list.push(entry))
            .ok_or_else(|| {
                format!("publish type '{type_name}' on topic '{topic}' can be registered only in initialize; the module's first publish has happened")
            })
    }

    pub(crate) fn subscribe(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
        sub: RawSubscriber,
    ) -> Result<(), String> {
        let type_name = type_name_of(ts);
        let m = &self.manager;
        if let Some(e) = m.phase_error(&format!(
            "type '{type_name}' on topic '{topic}' can be subscribed"
        )) {
            return Err(e);
        }
        check_topic_name(topic)?;
        m.dedupe(false, type_name, topic, &self.module)?;
        let t = m.topic(topic);
        let backends = t.sub_backends.clone().unwrap_or_default();
        if backends.is_empty() && lock(&m.unrouted).insert(topic.to_owned()) {
            tracing::warn!(target: "aimrt", "Channel topic '{topic}' matches no aimrt.channel.sub_topics_options rule that enables a backend: module '{}' subscribes to it but will receive nothing", self.module);
        }
        let sub = Arc::new(sub);
        for i in backends {
            let b = &m.backends[i];
            let sink = RawSink::new(Arc::new(HostSink {
                topic: t.clone(),
                pkg: self.pkg.clone(),
                module: self.module.clone(),
                started: self.started.clone(),
                backend: b.name.clone(),
                ts,
                sub: sub.clone(),
            }));
            b.raw
                .subscribe(topic, &self.pkg, &self.module, sink)
                .map_err(|e| {
                    format!("channel backend '{}' refused the subscription to '{type_name}' on topic '{topic}': {e}", b.name)
                })?;
        }
        Ok(())
    }

    /// Publishes `msg` on `topic` (its bytes as the module passed them: looked up without
    /// checking them as UTF-8; text only for what is reported).
    pub(crate) fn publish(
        &self,
        topic: &[u8],
        ctx: &[MetaPair<'_>],
        msg: RawMessage,
    ) -> Result<(), String> {
        let m = &self.manager;
        let ts = msg.type_support();
        let state = m.state.load(Ordering::SeqCst);
        if state != STARTED {
            let text = String::from_utf8_lossy(topic);
            let why = if state == INIT {
                format!("publish on topic '{text}' during initialize: messages can be published from start() on")
            } else {
                format!("publish on topic '{text}' after the channel shut down")
            };
            // Read without sealing: registering may still go on during initialize.
            self.pubs.peek(topic, |list| {
                if let Some(entry) = find_table(list, ts, |e| e.ts) {
                    entry.topic.drop_message(DropReason::WrongPhase, &why);
                }
            });
            return Err(why);
        }
        // Registering ended before the channel started: the first publish seals the
        // registry, and from then on this lookup takes no lock and no reference count (a
        // subscriber that publishes inline runs inside `send`).
        let list = self.pubs.get(topic);
        // The entry of the message's type: by its table, else by its name.
        let Some(entry) = find_table(list, ts, |e| e.ts) else {
            let topic = String::from_utf8_lossy(topic);
            let type_name = type_name_of(ts);
            let why = format!("module '{}' publishes '{type_name}' on topic '{topic}' without registering it; call channel.publisher::<T>(\"{topic}\") in initialize", self.module);
            if lock(&self.unregistered).insert((topic.to_string(), type_name.to_owned())) {
                tracing::warn!(target: "aimrt", "{why} (reported once; every such publish returns this error)");
            }
            if let Some(t) = lock(&m.topics).get(topic.as_ref()) {
                t.dropped[DropReason::Unregistered.code() as usize].fetch_add(1, Ordering::Relaxed);
            }
            return Err(why);
        };
        self.send(entry, ctx, &msg)
    }

    /// The publish pipeline of a registered type: stamp the context, hand the message to
    /// each backend of the topic in rule order, count.
    fn send(&self, entry: &PubEntry, ctx: &[MetaPair<'_>], msg: &RawMessage) -> Result<(), String> {
        let t = &entry.topic;
        // Formatted on the stack: no allocation per message.
        let (mut seq_text, mut now_text) = (itoa::Buffer::new(), itoa::Buffer::new());
        let seq = seq_text.format(t.seq.fetch_add(1, Ordering::Relaxed).wrapping_add(1));
        let now = now_text.format(unix_ns());
        let mut pairs = MetaPairs::default();
        let mut has_format = false;
        for p in ctx {
            // Keys compared as bytes: nothing here needs them checked as UTF-8.
            if p.is_key(KEY_PUB_SEQ) || p.is_key(KEY_PUB_TS) {
                continue;
            }
            has_format |= p.is_key(KEY_SERIALIZATION_TYPE);
            pairs.push(*p);
        }
        if !has_format {
            pairs.push(MetaPair::new(KEY_SERIALIZATION_TYPE, &entry.default_format));
        }
        pairs.push(MetaPair::new(KEY_PUB_SEQ, seq));
        pairs.push(MetaPair::new(KEY_PUB_TS, now));
        t.published.fetch_add(1, Ordering::Relaxed);
        if t.pub_filters.is_empty() {
            return self.to_backends(t, &pairs, msg);
        }
        let subject = filter::Subject {
            side: FilterSide::Publish,
            topic: &t.name,
            msg,
            pkg: &self.pkg,
            module: &self.module,
        };
        match t.pub_filters.run(&subject, &pairs, &mut |passed| {
            self.to_backends(t, passed, msg)
        }) {
            Ok(()) | Err(filter::Stopped::Last(_)) => Ok(()),
            Err(held @ filter::Stopped::Held { .. }) => {
                t.drop_message_as(DropReason::Filtered, true, format_args!("publish {held}"));
                Ok(())
            }
            Err(failed) => {
                let why = format!("publish {failed}");
                t.drop_message(DropReason::Filtered, &why);
                Err(why)
            }
        }
    }

    /// The end of the publish pipeline: hands the message with its context `pairs` to
    /// each backend of the topic in rule order, and counts.
    fn to_backends(
        &self,
        t: &Arc<Topic>,
        pairs: &[MetaPair<'_>],
        msg: &RawMessage,
    ) -> Result<(), String> {
        let Some(backends) = t.pub_backends.as_deref().filter(|b| !b.is_empty()) else {
            t.drop_message(
                DropReason::NoRoute,
                "no aimrt.channel.pub_topics_options rule enables a backend for it, so nothing carries its messages",
            );
            return Ok(());
        };
        let (ts, ptr) = (msg.type_support(), msg.as_ptr());
        let publication = RawPublication {
            header: Header::of::<RawPublication>(),
            topic: StrView::new(&t.name),
            ctx: aimrt_plugin_api::ffi::MetaView::new(pairs),
            type_support: ts,
            msg: ptr,
            pkg: StrView::new(&self.pkg),
            module: StrView::new(&self.module),
            topic_ref: RawTopicRef::borrow(t),
        };
        let mut receivers = 0u64;
        let mut failed = false;
        for &i in backends {
            let b = &self.manager.backends[i];
            match b.raw.publish(&publication) {
                Ok(RECEIVERS_UNKNOWN) => receivers = RECEIVERS_UNKNOWN,
                Ok(n) => receivers = receivers.saturating_add(n),
                Err(e) => {
                    failed = true;
                    t.drop_message(
                        DropReason::Other,
                        format_args!("channel backend '{}' failed to publish: {e}", b.name),
                    )
                }
            }
        }
        // A message a backend refused is counted once, for that reason.
        if receivers == 0 && !failed {
            t.drop_message(
                DropReason::NoSubscriber,
                format_args!(
                    "no module subscribes to '{}' on it, so its messages are dropped",
                    type_name_of(ts)
                ),
            );
        }
        Ok(())
    }

    pub(crate) fn stats(&self, topic: &str) -> Option<TopicStats> {
        self.manager.stats(topic)
    }
}

/// The system clock in nanoseconds since the Unix epoch, for `aimrt-pub_ts` (0 before it,
/// `u64::MAX` after the year 2554). Read straight from the clock: `SystemTime`'s
/// `duration_since` and its `u128` nanoseconds cost more than the reading, per message.
fn unix_ns() -> u64 {
    use nix::time::{clock_gettime, ClockId};
    let Ok(now) = clock_gettime(ClockId::CLOCK_REALTIME) else {
        return 0;
    };
    match (u64::try_from(now.tv_sec()), u64::try_from(now.tv_nsec())) {
        (Ok(s), Ok(ns)) => s.saturating_mul(1_000_000_000).saturating_add(ns),
        _ => 0,
    }
}

fn check_topic_name(topic: &str) -> Result<(), String> {
    if topic.is_empty() {
        return Err("a topic name must not be empty".into());
    }
    Ok(())
}

/// One subscription as a backend delivers to it: counts and reports, then runs the
/// module's callback.
struct HostSink {
    topic: Arc<Topic>,
    pkg: String,
    module: String,
    started: Arc<AtomicBool>,
    backend: String,
    ts: &'static TypeSupportVtable,
    sub: Arc<RawSubscriber>,
}

impl HostSink {
    /// Runs the module's callback and counts.
    fn call(&self, pairs: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String> {
        match self.sub.call(pairs, msg) {
            Ok(()) => {
                self.topic.delivered.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
            Err((reason, e)) => {
                let why = format!("the subscriber of module '{}' failed: {e}", self.module);
                self.topic.drop_message(reason, &why);
                Err(why)
            }
        }
    }
}

/// A backend reports here a message it took in `publish` and lost afterwards.
impl TopicHost for Topic {
    fn report_drop(&self, reason: DropReason, details: &str) {
        self.drop_message(reason, details);
    }
}

impl SinkHost for HostSink {
    fn type_support(&self) -> &'static TypeSupportVtable {
        self.ts
    }

    fn deliver(&self, ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String> {
        // Another process may send before this module started: nothing reaches it until
        // then. (`local` keeps AimRT's behaviour: a module's `start` may publish to the
        // modules after it.)
        // The flag first: once started, the backend's name is never compared.
        if !self.started.load(Ordering::Acquire) && self.backend != LOCAL {
            let why = format!(
                "a message from backend '{}' arrived before module '{}' started",
                self.backend, self.module
            );
            self.topic.drop_message(DropReason::WrongPhase, &why);
            return Err(why);
        }
        // Built in place (not collected and moved): it is per message.
        let mut pairs = MetaPairs::default();
        pairs.extend(ctx.iter().copied().filter(|p| !p.is_key(KEY_BACKEND)));
        pairs.push(MetaPair::new(KEY_BACKEND, &self.backend));
        if self.topic.sub_filters.is_empty() {
            return self.call(&pairs, msg);
        }
        let subject = filter::Subject {
            side: FilterSide::Subscribe,
            topic: &self.topic.name,
            msg: &msg,
            pkg: &self.pkg,
            module: &self.module,
        };
        let mut once = Some(msg.share());
        let ran = self.topic.sub_filters.run(&subject, &pairs, &mut |passed| {
            let msg = once.take().ok_or("the message was passed on twice")?;
            self.call(passed, msg)
        });
        match ran {
            Ok(()) => Ok(()),
            Err(filter::Stopped::Last(why)) => Err(why),
            Err(held @ filter::Stopped::Held { .. }) => {
                self.topic.drop_message_as(
                    DropReason::Filtered,
                    true,
                    format_args!("subscribe {held} for module '{}'", self.module),
                );
                Ok(())
            }
            Err(failed) => {
                let why = format!("subscribe {failed} for module '{}'", self.module);
                self.topic.drop_message(DropReason::Filtered, &why);
                Err(why)
            }
        }
    }

    fn report_drop(&self, reason: DropReason, details: &str) {
        self.topic.drop_message(
            reason,
            format_args!(
                "a message for module '{}' was dropped by backend '{}': {details}",
                self.module, self.backend
            ),
        );
    }

    fn report_drops(&self, reason: DropReason, count: u64, details: &str) {
        if count == 0 {
            return;
        }
        self.topic.drop_messages_as(
            reason,
            count,
            reported_once(reason),
            format_args!(
                "{count} messages for module '{}' were dropped by backend '{}': {details}",
                self.module, self.backend
            ),
        );
    }
}

impl Drop for ChannelManager {
    fn drop(&mut self) {
        // Backends live in libraries that are never unloaded and may have threads left.
        for b in std::mem::take(&mut self.backends) {
            std::mem::forget(b.raw);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use aimrt_plugin_api::__private::with_copied_table;
    use aimrt_plugin_api::ffi::type_support;

    #[derive(Debug, serde::Serialize, serde::Deserialize)]
    struct A {
        n: u32,
    }
    aimrt_plugin_api::serde_message!(A, "test.A");

    #[derive(Debug, serde::Serialize, serde::Deserialize)]
    struct B {
        n: u32,
    }
    aimrt_plugin_api::serde_message!(B, "test.B");

    /// The `local` backend, with every topic published to it.
    const EVERY_TOPIC_TO_LOCAL: &str = "    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [local]\n";

    fn manager(channel: &str) -> Arc<ChannelManager> {
        manager_of(&format!("aimrt:\n  channel:\n{channel}"))
    }

    /// The channel manager of config `text`, with no executors, plugin backends or filters.
    fn manager_of(text: &str) -> Arc<ChannelManager> {
        let config = Config::parse("cfg.yaml", text, |_| None).unwrap();
        Arc::new(
            ChannelManager::configure(
                &config,
                &HashMap::new(),
                BTreeMap::new(),
                Default::default(),
            )
            .unwrap(),
        )
    }

    /// Module `Mod` with `A` registered on `/t`, every topic going to `local`; the channel
    /// not started yet.
    fn module_publishing_a() -> (Arc<ChannelManager>, ModuleChannel) {
        let m = manager(EVERY_TOPIC_TO_LOCAL);
        let module = ModuleChannel::new(m.clone(), "Mod", "pkg.so", Arc::default());
        module
            .register_publish_type("/t", type_support::<A>())
            .unwrap();
        (m, module)
    }

    #[test]
    fn a_message_whose_table_is_another_copy_of_the_registered_one_is_published() {
        let (m, module) = module_publishing_a();
        m.start().unwrap();
        // What the compiler may make of a constant table in another code unit.
        let msg = with_copied_table(RawMessage::new(Arc::new(A { n: 1 })));
        assert!(!std::ptr::eq(msg.type_support(), type_support::<A>()));
        module.publish(b"/t", &[], msg).unwrap();
        let s = m.stats("/t").unwrap();
        assert_eq!(s.published, 1, "{s:?}");
        assert_eq!(s.dropped_for(DropReason::Unregistered), 0);
    }

    #[test]
    fn a_state_is_reported_once_and_an_event_at_most_once_a_second_with_the_count_since() {
        let m = manager(EVERY_TOPIC_TO_LOCAL);
        let t = m.topic("/t");
        let ((), logs) = aimrt_plugin_api::__private::capture_logs(|| {
            for _ in 0..3 {
                t.drop_message(DropReason::NoSubscriber, "nobody");
                t.drop_message(DropReason::Other, "queue full");
            }
        });
        assert_eq!(logs.len(), 2, "{logs:?}");
        assert!(logs[0].ends_with("nobody (reported once; every such message is counted in the topic's stats: no subscriber)"), "{logs:?}");
        assert!(logs[1].ends_with("queue full (reported at most once a second; every such message is counted in the topic's stats: other)"), "{logs:?}");
        std::thread::sleep(std::time::Duration::from_millis(1100));
        let ((), logs) = aimrt_plugin_api::__private::capture_logs(|| {
            t.drop_message(DropReason::NoSubscriber, "nobody");
            t.drop_message(DropReason::Other, "queue full again");
            t.drop_message(DropReason::Other, "queue full again");
        });
        assert_eq!(
            logs,
            ["Channel topic '/t': queue full again (3 since the last report, 4 so far; every such message is counted in the topic's stats: other)"]
        );
        let s = m.stats("/t").unwrap();
        assert_eq!(s.dropped_for(DropReason::NoSubscriber), 4);
        assert_eq!(s.dropped_for(DropReason::Other), 5);
    }

    #[test]
    fn a_gap_counts_every_message_of_it_in_one_report() {
        let m = manager(EVERY_TOPIC_TO_LOCAL);
        let t = m.topic("/t");
        let ((), logs) = aimrt_plugin_api::__private::capture_logs(|| {
            t.drop_messages_as(DropReason::Lost, 3942, false, "a gap");
            t.drop_messages_as(DropReason::Lost, 5, false, "another gap");
        });
        assert_eq!(
            logs,
            ["Channel topic '/t': a gap (reported at most once a second; every such message is counted in the topic's stats: lost after publish)"]
        );
        std::thread::sleep(std::time::Duration::from_millis(1100));
        let ((), logs) = aimrt_plugin_api::__private::capture_logs(|| {
            t.drop_messages_as(DropReason::Lost, 10, false, "a third gap");
        });
        assert_eq!(
            logs,
            ["Channel topic '/t': a third gap (15 since the last report, 3957 so far; every such message is counted in the topic's stats: lost after publish)"]
        );
        assert_eq!(m.stats("/t").unwrap().dropped_for(DropReason::Lost), 3957);
    }

    #[test]
    fn an_unregistered_type_is_refused_every_time_reported_once_and_counted() {
        let (m, module) = module_publishing_a();
        m.start().unwrap();
        for _ in 0..2 {
            let e = module
                .publish(b"/t", &[], RawMessage::new(Arc::new(B { n: 1 })))
                .unwrap_err();
            assert!(
                e.contains(
                    "module 'Mod' publishes 'serde:test.B' on topic '/t' without registering it"
                ),
                "{e}"
            );
        }
        assert_eq!(lock(&module.unregistered).len(), 1, "logged once");
        let s = m.stats("/t").unwrap();
        assert_eq!(s.dropped_for(DropReason::Unregistered), 2);
        assert_eq!(s.published, 0);
        // The registered type goes through (nobody subscribes: counted, not refused).
        module
            .publish(b"/t", &[], RawMessage::new(Arc::new(A { n: 1 })))
            .unwrap();
        let s = m.stats("/t").unwrap();
        assert_eq!(
            (s.published, s.dropped_for(DropReason::NoSubscriber)),
            (1, 1)
        );
        // Once shut down, publishing is refused and counted as the wrong phase.
        m.shutdown();
        let e = module
            .publish(b"/t", &[], RawMessage::new(Arc::new(A { n: 2 })))
            .unwrap_err();
        assert!(e.contains("after the channel shut down"), "{e}");
        assert_eq!(
            m.stats("/t").unwrap().dropped_for(DropReason::WrongPhase),
            1
        );
    }

    #[test]
    fn a_publish_during_initialize_is_counted_and_leaves_registering_open() {
        let (m, module) = module_publishing_a();
        let e = module
            .publish(b"/t", &[], RawMessage::new(Arc::new(A { n: 1 })))
            .unwrap_err();
        assert!(e.contains("during initialize"), "{e}");
        assert_eq!(
            m.stats("/t").unwrap().dropped_for(DropReason::WrongPhase),
            1
        );
        // The refused publish did not seal the registry: registering goes on.
        module
            .register_publish_type("/u", type_support::<A>())
            .unwrap();
        m.start().unwrap();
        module
            .publish(b"/u", &[], RawMessage::new(Arc::new(A { n: 2 })))
            .unwrap();
        assert_eq!(m.stats("/u").unwrap().published, 1);
        // A topic that is not UTF-8 is not registered; the error shows it readably.
        let e = module
            .publish(b"/\xff", &[], RawMessage::new(Arc::new(A { n: 3 })))
            .unwrap_err();
        assert!(
            e.contains("on topic '/\u{fffd}' without registering it"),
            "{e}"
        );
    }

    #[test]
    fn without_a_channel_section_topics_route_nowhere_but_are_counted() {
        let m = manager_of("aimrt: {}\n");
        let module = ModuleChannel::new(m.clone(), "Mod", "pkg.so", Arc::default());
        module
            .register_publish_type("/t", type_support::<A>())
            .unwrap();
        m.start().unwrap();
        module
            .publish(b"/t", &[], RawMessage::new(Arc::new(A { n: 1 })))
            .unwrap();
        assert_eq!(m.stats("/t").unwrap().dropped_for(DropReason::NoRoute), 1);
    }
}
