//! Channel backends: what carries published messages to subscriptions. The runtime's
//! built-in `local` backend implements this trait exactly like a plugin's backend would.

use std::mem::ManuallyDrop;
use std::sync::Arc;

use super::{DropReason, KEY_SERIALIZATION_TYPE};
use crate::ffi::{formats_of, type_name_of, MetaPair, RawMessage, RawPublication};
use crate::ffi::{RawSink, TypeSupportVtable};
use crate::{BackendOptions, Error};

/// `publish`'s answer when a backend cannot tell how many subscriptions it reached (a
/// network backend).
pub const RECEIVERS_UNKNOWN: u64 = u64::MAX;

/// A channel backend (AimRT's `ChannelBackendBase`). The runtime calls `init` for each
/// backend `aimrt.channel.backends` lists, then — while modules initialize —
/// `register_publish_type` and `subscribe` for each topic whose rule enables the backend,
/// `start` before modules start, `publish` from any thread while running, and `shutdown`
/// after modules shut down.
pub trait ChannelBackend: Send + Sync + 'static {
    /// The type the config names (`backends: [{type: zenoh}]`).
    fn type_name(&self) -> &str;
    /// Reads the backend's options.
    fn init(&self, options: &BackendOptions) -> Result<(), Error>;
    /// Starts delivering.
    fn start(&self) -> Result<(), Error> {
        Ok(())
    }
    /// Stops delivering; returns when no delivery runs any more.
    fn shutdown(&self) {}
    /// A module publishes `type_support` on `topic`.
    fn register_publish_type(&self, publisher: &PublisherInfo<'_>) -> Result<(), Error>;
    /// A module subscribes to `topic`: deliver its messages to `subscription.sink`.
    fn subscribe(&self, subscription: Subscription) -> Result<(), Error>;
    /// Carries one message; returns how many subscriptions it was handed to, or
    /// [`RECEIVERS_UNKNOWN`]. Called on the publisher's thread.
    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error>;
}

/// A publish type a module registered.
#[derive(Debug, Clone, Copy)]
pub struct PublisherInfo<'a> {
    /// The topic.
    pub topic: &'a str,
    /// The message's table in the publisher's library.
    pub type_support: &'static TypeSupportVtable,
    /// The module's pkg path.
    pub pkg: &'a str,
    /// The module.
    pub module: &'a str,
}

/// One subscription handed to a backend.
#[derive(Debug)]
pub struct Subscription {
    /// The topic.
    pub topic: String,
    /// The subscribing module's pkg path.
    pub pkg: String,
    /// The subscribing module.
    pub module: String,
    /// Where its messages go.
    pub sink: Sink,
}

/// Where a backend delivers one subscription's messages. Cloning is cheap (a reference
/// count); the runtime counts every delivery and every reported drop.
#[derive(Debug, Clone)]
pub struct Sink {
    raw: RawSink,
}

impl Sink {
    pub(crate) fn from_raw(raw: RawSink) -> Sink {
        Sink { raw }
    }

    /// The subscriber's message table: deliver objects of this table.
    pub fn type_support(&self) -> &'static TypeSupportVtable {
        self.raw.type_support()
    }

    /// The subscriber's message type name.
    pub fn type_name(&self) -> &'static str {
        type_name_of(self.type_support())
    }

    /// Runs the subscriber on `msg` with the context `ctx` (plus `aimrt-backend`, which
    /// the runtime adds). An `Err` means the subscriber failed; it is already counted and
    /// logged.
    pub fn deliver(&self, ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String> {
        self.raw.deliver(ctx, msg)
    }

    /// Reports a message this backend could not deliver; the runtime counts it and logs
    /// the first of each reason per topic.
    pub fn report_drop(&self, reason: DropReason, details: &str) {
        self.raw.report_drop(reason, details);
    }

    /// Reports `count` messages this backend could not deliver, for one reason, in one
    /// call (ABI 1.12): e.g. a gap in a publisher's sequence. The runtime counts them all
    /// and logs as for [`report_drop`](Sink::report_drop). `0` reports nothing.
    pub fn report_drops(&self, reason: DropReason, count: u64, details: &str) {
        self.raw.report_drops(reason, count, details);
    }
}

/// One published message, borrowed for the duration of [`ChannelBackend::publish`].
#[derive(Debug)]
pub struct Publication<'a> {
    raw: &'a RawPublication,
    msg: ManuallyDrop<RawMessage>,
}

impl<'a> Publication<'a> {
    /// Wraps a raw publication (host and backend shims).
    ///
    /// # Safety
    /// `raw` must be a valid publication: live views, a live message of its table.
    pub(crate) unsafe fn new(raw: &'a RawPublication) -> Publication<'a> {
        // SAFETY: the message stays alive for the call; `ManuallyDrop` never releases the
        // borrowed reference.
        let msg = unsafe { RawMessage::from_raw(&*raw.type_support, raw.msg) };
        Publication {
            raw,
            msg: ManuallyDrop::new(msg),
        }
    }

    /// The topic.
    pub fn topic(&self) -> &'a str {
        // SAFETY: views of a valid publication live for `'a`.
        unsafe { self.raw.topic.as_str().unwrap_or("") }
    }

    /// The topic's bytes, not checked as UTF-8: for looking up what is registered by
    /// topic once per message, where [`topic`](Self::topic)'s check would cost more than
    /// the lookup.
    #[inline]
    pub fn topic_bytes(&self) -> &'a [u8] {
        // SAFETY: as above.
        unsafe { self.raw.topic.as_bytes() }
    }

    /// The context pairs (with `aimrt-serialization_type`, `aimrt-pub_seq` and
    /// `aimrt-pub_ts` set).
    #[inline]
    pub fn meta(&self) -> &'a [MetaPair<'a>] {
        // SAFETY: as above.
        unsafe { self.raw.ctx.pairs() }
    }

    /// The context as text pairs.
    pub fn ctx(&self) -> impl Iterator<Item = (&'a str, &'a str)> {
        self.meta().iter().map(|p| (p.key(), p.value()))
    }

    /// A context value.
    #[inline]
    pub fn get(&self, key: &str) -> Option<&'a str> {
        // Keys compared as bytes: only the value found is checked as UTF-8.
        self.meta()
            .iter()
            .find(|p| p.is_key(key))
            .map(|p| p.value())
    }

    /// The message (borrowed; [`RawMessage::share`] keeps it).
    pub fn message(&self) -> &RawMessage {
        &self.msg
    }

    /// The publishing module's pkg path.
    pub fn pkg(&self) -> &'a str {
        // SAFETY: as above.
        unsafe { self.raw.pkg.as_str().unwrap_or("") }
    }

    /// The publishing module.
    pub fn module(&self) -> &'a str {
        // SAFETY: as above.
        unsafe { self.raw.module.as_str().unwrap_or("") }
    }

    /// Where to report that this message, taken by `publish`, is lost afterwards: keep it
    /// with the message while it waits (a queue, a task) and call
    /// [`LossReporter::lost`] if it cannot be sent. Counted in the topic's stats
    /// ([`DropReason::Lost`]).
    pub fn loss_reporter(&self) -> LossReporter {
        LossReporter {
            topic: self.raw.topic_handle(),
        }
    }

    /// Reports now that this message is lost (a send that failed within `publish` after
    /// others succeeded); [`LossReporter::lost`] says what `false` means.
    pub fn report_lost(&self, details: &str) -> bool {
        self.loss_reporter().lost(details)
    }
}

/// A publication's topic, kept by a backend to report a message it took and lost
/// afterwards (ABI 1.8). Cloning is cheap (a reference count).
///
/// ```
/// use aimrt_plugin_api::channel::LossReporter;
/// // A reporter of a host older than ABI 1.8 (or of a filter's publication) counts
/// // nothing, and says so: the backend logs the loss itself.
/// let detached = LossReporter::default();
/// assert!(!detached.lost("the peer closed the connection"));
/// ```
#[derive(Debug, Clone, Default)]
pub struct LossReporter {
    topic: Option<crate::ffi::TopicHandle>,
}

impl LossReporter {
    /// Counts one message as [lost after publish](DropReason::Lost) in the topic's stats;
    /// the runtime logs `details` at most once a second per topic. `false`: nothing
    /// counts it (a host older than ABI 1.8), so the backend should log it itself.
    pub fn lost(&self, details: &str) -> bool {
        match &self.topic {
            Some(t) => {
                t.report_drop(DropReason::Lost, details);
                true
            }
            None => false,
        }
    }

    /// Whether reports reach the topic's stats.
    pub fn is_connected(&self) -> bool {
        self.topic.is_some()
    }
}

/// A message on its way to one subscription: the publisher's object itself (same library
/// and type), or bytes to decode with the subscriber's table.
#[derive(Debug)]
pub enum Payload {
    /// The same object, shared.
    Shared(RawMessage),
    /// Encoded once per format and shared between subscriptions.
    Encoded {
        /// The format.
        format: String,
        /// The bytes.
        bytes: Arc<Vec<u8>>,
    },
}

impl Payload {
    /// An object of `ts`: the shared one, or one decoded from the bytes.
    pub fn into_message(self, ts: &'static TypeSupportVtable) -> Result<RawMessage, String> {
        match self {
            Payload::Shared(m) => Ok(m),
            Payload::Encoded { format, bytes } => RawMessage::decode(ts, &format, &bytes),
        }
    }
}

/// Turns one publication into a [`Payload`] per subscription: the publisher's object when
/// the subscriber uses the same table, else its bytes, encoded at most once per format.
///
/// The format is the context's `aimrt-serialization_type` when the subscriber's type
/// supports it, else the first of the publisher's formats that it supports.
#[derive(Debug)]
pub struct Converter<'a> {
    msg: &'a RawMessage,
    preferred: Option<&'a str>,
    encoded: Vec<(String, Arc<Vec<u8>>)>,
}

impl<'a> Converter<'a> {
    /// A converter for `publication`.
    pub fn new(publication: &'a Publication<'_>) -> Converter<'a> {
        Converter {
            msg: publication.message(),
            preferred: publication.get(KEY_SERIALIZATION_TYPE),
            encoded: Vec::new(),
        }
    }

    /// The payload for a subscriber with table `ts`, or why there is none.
    pub fn payload_for(
        &mut self,
        ts: &'static TypeSupportVtable,
    ) -> Result<Payload, (DropReason, String)> {
        convert(self.msg, self.preferred, &mut self.encoded, ts)
    }
}

/// A publication kept for delivery later, from any thread (a subscriber's executor): the
/// publisher's object (shared) and a copy of its context in one buffer. Converting it for
/// a subscriber of another library (encode, decode) happens then, not inside `publish`;
/// the bytes of each format are made once and shared by all its deliveries.
///
/// Keeping one costs the publisher two allocations (this and the context's bytes),
/// however many pairs the context has; nothing is checked as UTF-8 until a subscriber
/// reads it.
#[derive(Debug)]
pub struct DeferredPublication {
    msg: RawMessage,
    /// Each pair as key length, key, value length, value (lengths `u32` native-endian).
    meta: Vec<u8>,
    encoded: std::sync::Mutex<Vec<(String, Arc<Vec<u8>>)>>,
}

impl DeferredPublication {
    /// Keeps `publication`.
    pub fn new(publication: &Publication<'_>) -> DeferredPublication {
        let pairs = publication.meta();
        let len = pairs
            .iter()
            .map(|p| {
                let (k, v) = p.bytes();
                8 + k.len() + v.len()
            })
            .sum();
        let mut meta = Vec::with_capacity(len);
        for p in pairs {
            let (k, v) = p.bytes();
            for part in [k, v] {
                // Contexts are small; a key or value over 4 GiB is not one.
                meta.extend_from_slice(&(part.len() as u32).to_ne_bytes());
                meta.extend_from_slice(part);
            }
        }
        DeferredPublication {
            msg: publication.message().share(),
            meta,
            encoded: std::sync::Mutex::default(),
        }
    }

    /// The context's pairs, as views to hand to a sink.
    pub fn meta(&self) -> Vec<MetaPair<'_>> {
        self.pairs().collect()
    }

    /// The context's pairs, read off the buffer in order.
    fn pairs(&self) -> impl Iterator<Item = MetaPair<'_>> {
        let mut rest = self.meta.as_slice();
        let mut next = move || -> Option<&[u8]> {
            let (len, tail) = rest.split_first_chunk::<4>()?;
            let len = u32::from_ne_bytes(*len) as usize;
            let (part, tail) = tail.split_at_checked(len)?;
            rest = tail;
            Some(part)
        };
        std::iter::from_fn(move || Some(MetaPair::from_bytes(next()?, next()?)))
    }

    /// The payload for a subscriber with table `ts`, or why there is none.
    pub fn payload_for(
        &self,
        ts: &'static TypeSupportVtable,
    ) -> Result<Payload, (DropReason, String)> {
        // The common case (same library) needs neither the context nor the lock.
        if std::ptr::eq(ts, self.msg.type_support()) {
            return Ok(Payload::Shared(self.msg.share()));
        }
        let preferred = self
            .pairs()
            .find(|p| p.is_key(KEY_SERIALIZATION_TYPE))
            .map(|p| p.value());
        let mut encoded = self.encoded.lock().unwrap_or_else(|e| e.into_inner());
        convert(&self.msg, preferred, &mut encoded, ts)
    }
}

/// The payload of `msg` for a subscriber with table `ts`: the object itself, or its bytes
/// in the chosen format, from `encoded` or encoded now and kept there.
fn convert(
    msg: &RawMessage,
    preferred: Option<&str>,
    encoded: &mut Vec<(String, Arc<Vec<u8>>)>,
    ts: &'static TypeSupportVtable,
) -> Result<Payload, (DropReason, String)> {
    if std::ptr::eq(ts, msg.type_support()) {
        return Ok(Payload::Shared(msg.share()));
    }
    let theirs = formats_of(ts);
    let format = match preferred.filter(|p| theirs.iter().any(|f| f == p)) {
        Some(p) => p.to_owned(),
        None => formats_of(msg.type_support())
            .into_iter()
            .find(|f| theirs.contains(f))
            .ok_or_else(|| {
                (
                    DropReason::Format,
                    format!(
                        "'{}' and the subscriber's '{}' share no format",
                        type_name_of(msg.type_support()),
                        type_name_of(ts)
                    ),
                )
            })?,
    };
    if let Some((_, bytes)) = encoded.iter().find(|(f, _)| *f == format) {
        return Ok(Payload::Encoded {
            format,
            bytes: bytes.clone(),
        });
    }
    let bytes = Arc::new(msg.encode(&format).map_err(|e| (DropReason::Format, e))?);
    encoded.push((format.clone(), bytes.clone()));
    Ok(Payload::Encoded { format, bytes })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ffi::{type_support, Header, MetaView, StrView};

    #[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Mine {
        n: u32,
    }
    crate::serde_message!(Mine, "test.Kept");

    /// The same type as another library declares it (its own table).
    #[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Theirs {
        n: u32,
    }
    crate::serde_message!(Theirs, "test.Kept");

    /// A topic that keeps what backends report.
    #[derive(Default)]
    struct Reported(std::sync::Mutex<Vec<(DropReason, String)>>);

    impl crate::ffi::TopicHost for Reported {
        fn report_drop(&self, reason: DropReason, details: &str) {
            self.0.lock().unwrap().push((reason, details.to_owned()));
        }
    }

    #[test]
    fn a_loss_after_publish_reaches_the_topic_and_a_publication_of_1_7_reaches_none() {
        let topic = Arc::new(Reported::default());
        let msg = RawMessage::new(Arc::new(Mine { n: 7 }));
        let mut raw = RawPublication {
            header: Header::of::<RawPublication>(),
            topic: StrView::new("t"),
            ctx: MetaView::new(&[]),
            type_support: msg.type_support(),
            msg: msg.as_ptr(),
            pkg: StrView::new("p"),
            module: StrView::new("m"),
            topic_ref: crate::ffi::RawTopicRef::borrow(&topic),
        };
        // SAFETY: live views and a live message of its table, for the call.
        let kept = unsafe { Publication::new(&raw) }.loss_reporter();
        assert!(kept.is_connected());
        // The reporter holds the topic past `publish`; each clone holds it once more.
        assert_eq!(Arc::strong_count(&topic), 2);
        let again = kept.clone();
        assert_eq!(Arc::strong_count(&topic), 3);
        assert!(again.lost("the peer closed the connection"));
        drop((kept, again));
        assert_eq!(Arc::strong_count(&topic), 1);
        assert_eq!(
            *topic.0.lock().unwrap(),
            [(
                DropReason::Lost,
                "the peer closed the connection".to_owned()
            )]
        );

        // A host of ABI 1.7 hands a publication that ends before `topic_ref`.
        raw.header.size = std::mem::offset_of!(RawPublication, topic_ref) as u32;
        // SAFETY: as above.
        let old = unsafe { Publication::new(&raw) };
        assert!(!old.loss_reporter().is_connected());
        assert!(!old.report_lost("not counted: the backend logs it itself"));
        // And a filter's publication names no topic.
        raw.header = Header::of::<RawPublication>();
        raw.topic_ref = crate::ffi::RawTopicRef::NONE;
        // SAFETY: as above.
        assert!(!unsafe { Publication::new(&raw) }.report_lost("nowhere"));
        assert_eq!(topic.0.lock().unwrap().len(), 1);
        assert_eq!(Arc::strong_count(&topic), 1);
    }

    #[test]
    fn a_kept_publication_outlives_publish_and_converts_once_per_format() {
        let msg = RawMessage::new(Arc::new(Mine { n: 7 }));
        let pairs = [
            MetaPair::new(KEY_SERIALIZATION_TYPE, "json"),
            MetaPair::from_bytes(b"bad", b"\xff"),
            MetaPair::new("empty", ""),
        ];
        let raw = RawPublication {
            header: Header::of::<RawPublication>(),
            topic: StrView::new("t"),
            ctx: MetaView::new(&pairs),
            type_support: msg.type_support(),
            msg: msg.as_ptr(),
            pkg: StrView::new("p"),
            module: StrView::new("m"),
            topic_ref: crate::ffi::RawTopicRef::NONE,
        };
        // SAFETY: live views and a live message of its table, for the call.
        let kept = DeferredPublication::new(&unsafe { Publication::new(&raw) });
        drop(msg);
        let read: Vec<_> = kept.meta().iter().map(|p| (p.key(), p.value())).collect();
        assert_eq!(
            read,
            [(KEY_SERIALIZATION_TYPE, "json"), ("bad", ""), ("empty", "")]
        );
        let same = kept.payload_for(type_support::<Mine>()).unwrap();
        assert!(matches!(same, Payload::Shared(_)));
        let theirs = type_support::<Theirs>();
        let (a, b) = (kept.payload_for(theirs), kept.payload_for(theirs));
        let (Ok(Payload::Encoded { format, bytes: a }), Ok(Payload::Encoded { bytes: b, .. })) =
            (a, b)
        else {
            panic!("a subscriber of another table gets bytes");
        };
        // The context's format, encoded once for both deliveries.
        assert_eq!(format, "json");
        assert!(Arc::ptr_eq(&a, &b));
        let got = Payload::Encoded { format, bytes: a }
            .into_message(theirs)
            .unwrap()
            .downcast::<Theirs>()
            .unwrap();
        assert_eq!(*got, Theirs { n: 7 });
    }
}
