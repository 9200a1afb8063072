//! The module side of channels: publishers and subscribers.

use std::future::Future;
use std::marker::PhantomData;
use std::sync::Arc;

use super::{Context, ContextKind, Message, TopicStats, KEY_SERIALIZATION_TYPE};
use crate::ffi::{
    meta_of, type_support, ChannelHandleVtable, MetaPair, MetaPairs, RawCore, RawMessage,
    RawSubscriber, TypeSupportVtable,
};
use crate::{Error, ExecutorRef};

/// A module's channel handle (AimRT's `ChannelHandleRef`), from
/// [`CoreRef::channel`](crate::CoreRef::channel). Copyable; valid for the process's life.
///
/// Publish types are registered and subscriptions made in `initialize` only; publishing
/// works from `start` until the runtime shuts the channel down. A call in the wrong phase
/// returns an error that names the phase.
///
/// ```no_run
/// use std::sync::Arc;
/// use aimrt_plugin_api::channel::{Context, Publisher};
/// use aimrt_plugin_api::{CoreRef, Error};
///
/// #[derive(Debug, serde::Serialize, serde::Deserialize)]
/// struct Ping { n: u64 }
/// aimrt_plugin_api::serde_message!(Ping, "example.Ping");
///
/// fn initialize(core: CoreRef) -> Result<Publisher<Ping>, Error> {
///     let channel = core.channel()?;
///     channel.subscriber("/ping").subscribe(|ctx: &Context, msg: Arc<Ping>| {
///         tracing::info!("got {} (seq {:?})", msg.n, ctx.get("aimrt-pub_seq"));
///     })?;
///     channel.publisher::<Ping>("/ping")
/// }
///
/// // In `start` or later:
/// fn tick(publisher: &Publisher<Ping>) -> Result<(), Error> {
///     publisher.publish(Ping { n: 1 })
/// }
/// ```
#[derive(Clone, Copy)]
pub struct ChannelRef {
    core: RawCore,
    vt: &'static ChannelHandleVtable,
}

impl std::fmt::Debug for ChannelRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ChannelRef")
    }
}

impl ChannelRef {
    pub(crate) fn new(core: RawCore) -> Result<ChannelRef, Error> {
        let vt = core.channel().ok_or_else(|| {
            Error::Channel(
                "this runtime has no channel support (it predates ABI 1.1); run the module with a newer aimrt_main".into(),
            )
        })?;
        Ok(ChannelRef { core, vt })
    }

    /// Registers `M` as a type this module publishes on `topic` and returns its publisher
    /// (AimRT's `GetPublisher` + `RegisterPublishType` + `PublisherProxy`). Only in
    /// `initialize`; registering the same type on the same topic twice is an error.
    pub fn publisher<M: Message>(&self, topic: &str) -> Result<Publisher<M>, Error> {
        self.core
            .register_publish_type(self.vt, topic, type_support::<M>())
            .map_err(Error::Channel)?;
        Ok(Publisher {
            channel: *self,
            topic: topic.into(),
            default_meta: Vec::new(),
            _msg: PhantomData,
        })
    }

    /// The subscriber handle of `topic`; subscribe on it in `initialize`.
    pub fn subscriber(&self, topic: &str) -> Subscriber {
        Subscriber {
            channel: *self,
            topic: topic.into(),
        }
    }

    /// Registers the message type of table `ts` (e.g. from a type support package) as one
    /// this module or plugin publishes on `topic`, for [`publish_raw`](Self::publish_raw).
    pub fn register_publish_raw(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
    ) -> Result<(), Error> {
        self.core
            .register_publish_type(self.vt, topic, ts)
            .map_err(Error::Channel)
    }

    /// Subscribes to messages of the table `ts` on `topic`, handed over as
    /// [`RawMessage`]s: for code that knows a type by its name only (echo, recording).
    /// `callback` returns `Err` to report the message as not handled (counted).
    pub fn subscribe_raw<F>(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
        callback: F,
    ) -> Result<(), Error>
    where
        F: Fn(&Context, RawMessage) -> Result<(), String> + Send + Sync + 'static,
    {
        let sub = RawSubscriber::raw(ts, Box::new(callback));
        self.core
            .subscribe(self.vt, topic, ts, sub)
            .map_err(Error::Channel)
    }

    /// Publishes a message of a registered table ([`register_publish_raw`](Self::register_publish_raw))
    /// with the context `ctx` (e.g. one decoded from bytes with [`RawMessage::decode`]).
    pub fn publish_raw(&self, topic: &str, ctx: &Context, msg: RawMessage) -> Result<(), Error> {
        let meta = meta_of(ctx.iter());
        self.core
            .publish(self.vt, topic, &meta, msg)
            .map_err(Error::Channel)
    }

    /// The counters of `topic` (summed over its types and modules), if any module
    /// registered or subscribed it.
    pub fn stats(&self, topic: &str) -> Option<TopicStats> {
        self.core.topic_stats(self.vt, topic)
    }
}

/// Publishes messages of `M` on one topic (AimRT's `PublisherProxy<M>`). Cheap to clone;
/// usable from any thread.
pub struct Publisher<M> {
    channel: ChannelRef,
    topic: Arc<str>,
    default_meta: Vec<(String, String)>,
    _msg: PhantomData<fn(M)>,
}

impl<M> Clone for Publisher<M> {
    fn clone(&self) -> Self {
        Publisher {
            channel: self.channel,
            topic: self.topic.clone(),
            default_meta: self.default_meta.clone(),
            _msg: PhantomData,
        }
    }
}

impl<M> std::fmt::Debug for Publisher<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Publisher")
            .field("topic", &self.topic)
            .finish()
    }
}

impl<M: Message> Publisher<M> {
    /// The topic.
    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// The counters of the topic (as [`ChannelRef::stats`]): what was published on it and
    /// what the channel dropped after `publish` returned, such as a backend's refusal.
    pub fn stats(&self) -> Option<TopicStats> {
        self.channel.stats(&self.topic)
    }

    /// Sets a key every context of [`new_context`](Self::new_context) and
    /// [`publish`](Self::publish) starts with (AimRT's `SetDefaultContextMeta`).
    pub fn set_default_meta(&mut self, key: &str, value: &str) {
        match self.default_meta.iter_mut().find(|(k, _)| k == key) {
            Some((_, v)) => value.clone_into(v),
            None => self.default_meta.push((key.into(), value.into())),
        }
    }

    /// A fresh publish context: the default meta, then — for a subscriber that publishes
    /// what it received — the user keys of `from` (never its `aimrt-*` keys: this topic
    /// sets its own `aimrt-pub_seq` and `aimrt-pub_ts`).
    pub fn new_context(&self, from: Option<&Context>) -> Context {
        let mut ctx = Context::new(ContextKind::Publish);
        for (k, v) in &self.default_meta {
            ctx.set(k, v);
        }
        if let Some(received) = from {
            ctx.merge_from(received);
        }
        ctx
    }

    /// Publishes `msg` with a fresh context (the default meta). Only from `start` on.
    pub fn publish(&self, msg: impl Into<Arc<M>>) -> Result<(), Error> {
        if self.default_meta.is_empty() {
            // That fresh context would have no pair: none to make, check or copy.
            return self.forward(&[], msg.into());
        }
        self.send(&self.new_context(None), msg.into())
    }

    /// Publishes `msg` with `ctx`, which must be an unused publish context; it is marked
    /// used (reuse it after [`Context::reset`]). Only from `start` on.
    ///
    /// Set `aimrt-serialization_type` in `ctx` to choose the format in which the message
    /// crosses to subscribers in other libraries (one of `M::formats()`; default: the
    /// first).
    pub fn publish_with(&self, ctx: &mut Context, msg: impl Into<Arc<M>>) -> Result<(), Error> {
        if ctx.kind() != ContextKind::Publish {
            return Err(Error::Channel(format!(
                "publish on topic '{}' was given a subscribe context; make one with new_context(Some(&received))",
                self.topic
            )));
        }
        if ctx.is_used() {
            return Err(Error::Channel(format!(
                "publish on topic '{}' was given a context that was published already; call reset() or make a new one",
                self.topic
            )));
        }
        ctx.mark_used();
        self.send(ctx, msg.into())
    }

    fn send(&self, ctx: &Context, msg: Arc<M>) -> Result<(), Error> {
        if let Some(format) = ctx.serialization_type() {
            if !M::formats().contains(&format) {
                return Err(Error::Channel(format!(
                    "publish on topic '{}': {KEY_SERIALIZATION_TYPE} is '{format}', which '{}' does not support; it supports {}",
                    self.topic,
                    M::type_name(),
                    M::formats().join(", ")
                )));
            }
        }
        // Built in place: it is per message.
        let mut meta = MetaPairs::default();
        meta.extend(ctx.iter().map(|(k, v)| MetaPair::new(k, v)));
        self.forward(&meta, msg)
    }

    /// Hands `msg` with the context's pairs `meta` to the runtime.
    fn forward(&self, meta: &[MetaPair<'_>], msg: Arc<M>) -> Result<(), Error> {
        self.channel
            .core
            .publish(self.channel.vt, &self.topic, meta, RawMessage::new(msg))
            .map_err(Error::Channel)
    }
}

/// Subscribes to one topic (AimRT's `SubscriberRef` with `Subscribe`/`SubscribeCo`).
/// Only in `initialize`; subscribing the same type on the same topic twice is an error.
///
/// Callbacks run where the topic's backend delivers: with the `local` backend, on the
/// publisher's thread (`subscriber_use_inline_executor: true`, the default) or as tasks of
/// its `subscriber_executor`. A panic in a callback is caught, logged and counted.
#[derive(Debug, Clone)]
pub struct Subscriber {
    channel: ChannelRef,
    topic: String,
}

impl Subscriber {
    /// The topic.
    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// Calls `callback` with the context and each message of `M`. The context reads the
    /// delivered pairs in place for the call; `ctx.clone()` makes a copy to keep.
    pub fn subscribe<M, F>(&self, callback: F) -> Result<(), Error>
    where
        M: Message,
        F: Fn(&Context, Arc<M>) + Send + Sync + 'static,
    {
        self.register::<M>(
            Box::new(move |ctx, msg| {
                callback(ctx, msg);
                Ok(())
            }),
            true,
        )
    }

    /// Calls `callback` with each message of `M` (no context: none is built).
    pub fn subscribe_msg<M, F>(&self, callback: F) -> Result<(), Error>
    where
        M: Message,
        F: Fn(Arc<M>) + Send + Sync + 'static,
    {
        self.register::<M>(
            Box::new(move |_, msg| {
                callback(msg);
                Ok(())
            }),
            false,
        )
    }

    /// Runs the future `callback` returns for each message as an async task on `executor`
    /// (AimRT's `SubscribeCo`): the delivery returns once the task is posted. The task
    /// owns a copy of the context. A task the executor refuses is counted as dropped; a
    /// panic in the future is logged.
    pub fn subscribe_async<M, F, Fut>(
        &self,
        executor: &ExecutorRef,
        callback: F,
    ) -> Result<(), Error>
    where
        M: Message,
        F: Fn(Context, Arc<M>) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = ()> + Send + 'static,
    {
        let executor = *executor;
        self.register::<M>(
            Box::new(move |ctx, msg| {
                // The task keeps the context: a copy that owns its pairs.
                let handle = crate::co::spawn(executor, callback(ctx.clone(), msg));
                if handle.is_finished() {
                    // Ended at once: refused by the executor, or already done.
                    if let Err(e) = handle.join() {
                        let reason = match e {
                            crate::co::JoinError::Panicked(_) => {
                                super::DropReason::SubscriberFailed
                            }
                            _ => super::DropReason::Refused,
                        };
                        return Err((reason, e.to_string()));
                    }
                }
                Ok(())
            }),
            true,
        )
    }

    /// Subscribes `callback`; `context`: whether it reads the context (when not, it gets
    /// an empty one and none is built per message).
    fn register<M: Message>(
        &self,
        callback: Box<super::Callback<M>>,
        context: bool,
    ) -> Result<(), Error> {
        self.channel
            .core
            .subscribe(
                self.channel.vt,
                &self.topic,
                type_support::<M>(),
                RawSubscriber::new(callback, context),
            )
            .map_err(Error::Channel)
    }
}
