//! The `zenoh` channel backend: per topic and type ([`crate::wire::channel_key`]) a zenoh
//! publisher to other processes and one to this process's own subscribers (see
//! `Pub::local`), one subscriber per key shared by the module subscriptions of it, AimRT's
//! payload ([`crate::wire::ChannelPayload`]).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock};

use aimrt_plugin_api::channel::{
    ChannelBackend, DropReason, Publication, PublisherInfo, Sink, Subscription, TopicRegistry,
    RECEIVERS_UNKNOWN,
};
use aimrt_plugin_api::ffi::{find_table, type_name_of, TypeSupportVtable};
use aimrt_plugin_api::{BackendOptions, Error};
use serde::Deserialize;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::sample::{Locality, Sample, SourceInfo};
use zenoh::session::EntityGlobalId;
use zenoh::Wait;

use crate::sequence::Sequences;
use crate::session::{follow_matching, lock, read, said, write, Buffers, Zenoh};
use crate::wire::{begin_channel, channel_key, decode_channel, end_channel, PayloadError};
use crate::{Release, ShmRule, ShmRules, TopicShmRule};

#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    pub_topics_options: Vec<TopicShmRule>,
}

/// A declared publisher of one topic and type.
struct Pub {
    /// The table it was registered with: a message of that table is found by address.
    ts: &'static TypeSupportVtable,
    type_name: &'static str,
    /// The zenoh key, for what is said about the publisher.
    key: String,
    shm: bool,
    /// Heap buffers of large messages, used again.
    buffers: Arc<Buffers>,
    /// Whether zenoh knows a subscriber matching the key, and whether a publish found none
    /// since it last did (said once per such stretch).
    matching: Arc<Matching>,
    /// The remote publisher's id, sent with each message with its sequence number (`None`:
    /// the topic's `send_sequence` is off).
    source: Option<EntityGlobalId>,
    /// Held across the remote put, so that sequence numbers go out in the order of the
    /// puts when threads publish at once. Nothing else runs under it: the remote put calls
    /// no subscriber of this process.
    sending: Mutex<Sending>,
    /// The publisher to this process's own subscribers of the key (`None` once released):
    /// put after `sending` is let go, since zenoh calls them inside the put, and one may
    /// publish on this very topic again.
    local: Mutex<Option<Arc<Publisher<'static>>>>,
    /// Whether this backend subscribes the key too. Set while modules initialize, when the
    /// second of the two registrations finds the first (zenoh's matching listener would
    /// say so a moment later, on another thread: a message published at once would miss
    /// the subscriber).
    here: AtomicBool,
}

/// What a remote put takes: the publisher to other processes (`None` once released) and
/// its next sequence number.
struct Sending {
    publisher: Option<Publisher<'static>>,
    /// The sequence number of the next put zenoh takes.
    next_sn: u32,
}

/// A publisher's matching status, kept by zenoh's matching listener.
#[derive(Default)]
struct Matching {
    /// A subscriber in another process.
    remote: AtomicBool,
    said: AtomicBool,
}

type Sinks = Arc<RwLock<Vec<Sink>>>;

/// The backend.
pub(crate) struct ZenohChannel {
    zenoh: Arc<Zenoh>,
    rules: OnceLock<ShmRules>,
    declared: Arc<Declared>,
    /// By key: the sinks its subscriber delivers to.
    subs: Mutex<HashMap<String, Sinks>>,
}

/// What the backend declared on the session, released at its shutdown or the plugin's.
#[derive(Default)]
pub(crate) struct Declared {
    /// By topic: its publishers, one per type; sealed by the first publish.
    pubs: TopicRegistry<Pub>,
    subscribers: Mutex<Vec<Subscriber<()>>>,
}

impl Release for Declared {
    fn release(&self) {
        crate::session::undeclare_all(&self.subscribers);
        self.pubs.for_each(|p| {
            let taken = lock(&p.sending).publisher.take();
            if let Some(publisher) = taken {
                let _ = publisher.undeclare().wait();
            }
            // A put under way keeps its clone until it returns.
            drop(lock(&p.local).take());
        });
    }
}

impl ZenohChannel {
    pub(crate) fn new(zenoh: Arc<Zenoh>) -> ZenohChannel {
        ZenohChannel {
            zenoh,
            rules: OnceLock::new(),
            declared: Arc::default(),
            subs: Mutex::default(),
        }
    }

    /// What [`Release`] drops: for the plugin, whose shutdown comes also where the
    /// backend's does not (a start-up that failed before the channel started).
    pub(crate) fn declared(&self) -> Arc<Declared> {
        self.declared.clone()
    }
}

impl ChannelBackend for ZenohChannel {
    fn type_name(&self) -> &str {
        "zenoh"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let o: Options = options.read()?;
        let rules = ShmRules::compile(
            o.pub_topics_options
                .into_iter()
                .map(ShmRule::from)
                .collect(),
            options.location(),
            "pub_topics_options",
            "topic_name",
        )?;
        let _ = self.rules.set(rules);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        Ok(())
    }

    fn shutdown(&self) {
        self.declared.release();
    }

    fn register_publish_type(&self, publisher: &PublisherInfo<'_>) -> Result<(), Error> {
        let type_name = type_name_of(publisher.type_support);
        let key = channel_key(publisher.topic, type_name, &self.zenoh.limit_domain);
        let added = self.declared.pubs.register(publisher.topic, |of_topic| {
            if of_topic.iter().any(|p| p.type_name == type_name) {
                return Ok(());
            }
            let flags = self.rules.get().and_then(|r| r.first(&[publisher.topic]));
            let shm = flags.is_some_and(|f| f.shm);
            if shm {
                self.zenoh.ensure_shm()?;
            }
            // Two publishers of the key: one to other processes, one to this one's own
            // subscribers (see `Pub::local`).
            let session = self.zenoh.session()?;
            let declare = |to: Locality| {
                session
                    .declare_publisher(key.clone())
                    .allowed_destination(to)
                    .wait()
                    .map_err(|e| Error::msg(format!("cannot declare a zenoh publisher on '{key}': {}", said(&e))))
            };
            let (remote, local) = (declare(Locality::Remote)?, declare(Locality::SessionLocal)?);
            let matching = Arc::new(Matching::default());
            let status = matching.clone();
            let matched = key.clone();
            follow_matching(&remote, "subscribers", move |now| {
                status.remote.store(now, Ordering::Relaxed);
                // Said when a publish found none: the end of that stretch is said too.
                if now && status.said.swap(false, Ordering::Relaxed) {
                    tracing::info!(target: "aimrt", "zenoh_plugin: a subscriber matches '{matched}': its messages reach it from now on");
                }
            })?;
            let here = lock(&self.subs).contains_key(&key);
            tracing::info!(target: "aimrt", "Register publish type to zenoh channel, url: {key}, shm_enabled: {shm}");
            // Without a rule, as without the key: sent.
            let source = flags.is_none_or(|f| f.send_sequence).then(|| remote.id());
            of_topic.push(Pub {
                ts: publisher.type_support,
                type_name,
                key: key.clone(),
                shm,
                buffers: Arc::default(),
                matching,
                source,
                sending: Mutex::new(Sending {
                    publisher: Some(remote),
                    next_sn: 0,
                }),
                local: Mutex::new(Some(Arc::new(local))),
                here: AtomicBool::new(here),
            });
            Ok(())
        });
        added.unwrap_or_else(|| {
            Err(Error::msg(format!(
                "cannot register '{key}' after the first publish: register publish types in initialize"
            )))
        })
    }

    fn subscribe(&self, subscription: Subscription) -> Result<(), Error> {
        let key = channel_key(
            &subscription.topic,
            subscription.sink.type_name(),
            &self.zenoh.limit_domain,
        );
        let mut subs = lock(&self.subs);
        if let Some(sinks) = subs.get(&key) {
            write(sinks).push(subscription.sink);
            return Ok(());
        }
        let sinks: Sinks = Arc::new(RwLock::new(vec![subscription.sink]));
        let zenoh = self.zenoh.clone();
        let to = sinks.clone();
        let sequences = Mutex::new(Sequences::default());
        let subscriber = self
            .zenoh
            .session()?
            .declare_subscriber(key.clone())
            .callback(move |sample| {
                count_missed(&zenoh, &to, &sequences, &sample);
                let bytes = sample.payload().to_bytes();
                receive(&zenoh, &to, &bytes, sample.key_expr().as_str());
            })
            .wait()
            .map_err(|e| {
                Error::msg(format!(
                    "cannot declare a zenoh subscriber on '{key}': {}",
                    said(&e)
                ))
            })?;
        tracing::info!(target: "aimrt", "Register subscribe type to zenoh channel, url: {key}");
        lock(&self.declared.subscribers).push(subscriber);
        subs.insert(key.clone(), sinks);
        drop(subs);
        // The publishers of the key registered before: theirs go to this process too.
        self.declared.pubs.for_each(|p| {
            if p.key == key {
                p.here.store(true, Ordering::Relaxed);
            }
        });
        Ok(())
    }

    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error> {
        let ts = publication.message().type_support();
        // By the table's address, else by type name (another copy of the table, or the
        // same type from another library).
        // Publishing starts once registering has ended: the first publish seals the
        // registry, and the lookup takes no lock (a local subscriber may publish in `send`).
        let of_topic = self.declared.pubs.get(publication.topic_bytes());
        let Some(p) = find_table(of_topic, ts, |p| p.ts) else {
            return Err(self.zenoh.refuse(format!(
                "Url: {} is not registered!",
                channel_key(
                    publication.topic(),
                    type_name_of(ts),
                    &self.zenoh.limit_domain
                )
            )));
        };
        // The header, then the message encoded straight behind it where the payload goes
        // (no copy for `pb`, whose length is known first): a shared-memory buffer, the
        // header's own buffer when the message fits its capacity, or a buffer of the
        // publisher's kept ones.
        let format = aimrt_wire::channel::format_of(publication);
        let meta = publication.meta().iter().map(|p| p.bytes());
        let laid_out = |e: PayloadError| format!("cannot lay the message out: {e}");
        let mut header =
            begin_channel(&format, meta, 256).map_err(|e| self.zenoh.refuse(laid_out(e)))?;
        let payload = aimrt_wire::channel::encode_to(publication, &format, |len| {
            end_channel(&mut header, len).map_err(laid_out)?;
            Ok(self
                .zenoh
                .room(std::mem::take(&mut header), len, p.shm, &p.buffers))
        })
        .map_err(|why| self.zenoh.refuse(why))?;
        let bytes = self.zenoh.bytes(payload);
        let here = p.here.load(Ordering::Relaxed);
        let local = if here {
            lock(&p.local).clone().map(|l| (l, bytes.clone()))
        } else {
            None
        };
        {
            // The number is held across the remote put.
            let mut sending = lock(&p.sending);
            let Sending { publisher, next_sn } = &mut *sending;
            let Some(publisher) = publisher else {
                return Err(self.zenoh.refuse(format!(
                    "the zenoh session is closed: nothing is put on '{}' any more",
                    p.key
                )));
            };
            let source = p.source.map(|id| SourceInfo::new(id, *next_sn));
            self.zenoh
                .put_bytes(publisher, bytes, source)
                .map_err(|why| self.zenoh.refuse(why))?;
            // A put zenoh refused sent nothing: its number goes to the next.
            *next_sn = next_sn.wrapping_add(1);
        }
        // This process's own subscribers, called inside the put, with no lock held. Their
        // messages cannot be lost on the way: no number.
        if let Some((publisher, bytes)) = local {
            if let Err(e) = publisher.put(bytes).wait() {
                self.zenoh.stats.put_failed.fetch_add(1, Ordering::Relaxed);
                self.zenoh.warn(format_args!(
                    "zenoh refused the put to this process's subscribers on '{}': {}",
                    p.key,
                    said(&e)
                ));
            }
        }
        if !here && !p.matching.remote.load(Ordering::Relaxed) {
            self.unmatched(p);
        }
        Ok(RECEIVERS_UNKNOWN)
    }
}

impl ZenohChannel {
    /// Counts a message put while no subscriber matched, and says so once until one does.
    fn unmatched(&self, p: &Pub) {
        self.zenoh.stats.unmatched.fetch_add(1, Ordering::Relaxed);
        if !p.matching.said.swap(true, Ordering::Relaxed) {
            tracing::warn!(
                target: "aimrt",
                "zenoh_plugin: no subscriber matches '{}': its messages reach no one until one does (counted in the shutdown line)",
                p.key
            );
        }
    }
}

/// Counts the messages of `sample`'s publisher that should have come before it and did
/// not, as lost for every subscription of the key (a sample without source info: none).
fn count_missed(zenoh: &Zenoh, sinks: &Sinks, sequences: &Mutex<Sequences>, sample: &Sample) {
    let Some(info) = sample.source_info() else {
        return;
    };
    let id = info.source_id();
    let source = (id.zid(), id.eid());
    let missed = lock(sequences).missed(source, info.source_sn());
    if missed == 0 {
        return;
    }
    zenoh
        .stats
        .lost
        .fetch_add(u64::from(missed), Ordering::Relaxed);
    let details = format!(
        "zenoh dropped them on the way from publisher {}:{} on '{}' (a gap in its sequence: a congested link, a message over max_message_size, or a link that was down)",
        source.0,
        source.1,
        sample.key_expr()
    );
    for sink in read(sinks).iter() {
        sink.report_drops(DropReason::Lost, u64::from(missed), &details);
    }
}

/// One received payload: decoded and delivered, or counted as malformed.
fn receive(zenoh: &Zenoh, sinks: &Sinks, bytes: &[u8], key: &str) {
    match decode_channel(bytes) {
        Ok(p) => {
            let sinks = read(sinks);
            aimrt_wire::channel::deliver(
                &sinks,
                p.serialization_type,
                p.meta,
                p.message,
                &format_args!("'{key}'"),
            );
        }
        Err(e) => {
            zenoh.stats.malformed.fetch_add(1, Ordering::Relaxed);
            zenoh.warn(format_args!(
                "Handle Zenoh channel msg failed: a {}-byte payload on '{key}' is malformed: {e}",
                bytes.len()
            ));
        }
    }
}
