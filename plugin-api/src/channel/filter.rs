//! Channel filters (ABI 1.7; AimRT's publish and subscribe filters): code a plugin
//! registers by name ([`Registrar::register_channel_filter`](crate::Registrar::register_channel_filter))
//! that the runtime runs around each message of the topics whose
//! `pub_topics_options` / `sub_topics_options` rule lists the name in `enable_filters`.

use super::{Context, ContextKind, Publication};
use crate::ffi::filter::FilterNext;
use crate::ffi::MetaPair;

/// Which side of a topic a filter runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FilterSide {
    /// On publish, after the runtime stamped the context (`aimrt-pub_seq`,
    /// `aimrt-pub_ts`, `aimrt-serialization_type`) and before any backend has the message;
    /// on the publishing thread.
    Publish,
    /// Before a subscriber's callback, with the subscriber's context (`aimrt-backend`
    /// last); on the thread that runs the subscriber.
    Subscribe,
}

impl FilterSide {
    /// The code that crosses the ABI.
    pub fn code(self) -> u32 {
        match self {
            FilterSide::Publish => 0,
            FilterSide::Subscribe => 1,
        }
    }

    /// The side of a code, if it is one.
    pub fn from_code(code: u32) -> Option<FilterSide> {
        match code {
            0 => Some(FilterSide::Publish),
            1 => Some(FilterSide::Subscribe),
            _ => None,
        }
    }

    /// `publish` or `subscribe`.
    pub fn name(self) -> &'static str {
        match self {
            FilterSide::Publish => "publish",
            FilterSide::Subscribe => "subscribe",
        }
    }
}

/// A channel filter: sees each message of its topics and passes it on, changed or not,
/// or holds it back.
///
/// `filter` gets the message (its topic, context and object, and the publishing or
/// subscribing module) and the rest of the chain as `next`. It passes the message on by
/// calling [`Next::pass`] or [`Next::pass_with`] during the call, at most once (the
/// rest of the chain runs inside that call, so the filter may time it); returning without
/// passing it on holds the message back, and the runtime counts it
/// ([`DropReason::Filtered`](super::DropReason::Filtered)). `Err` reports the filter's
/// own failure, counted the same way. A closure `Fn(&Publication, Next) -> Result<(),
/// String>` is a filter.
///
/// ```
/// use aimrt_plugin_api::channel::{ChannelFilter, Next, Publication};
///
/// /// Adds `trace-id` to every message that has none, and passes it on.
/// struct TraceId;
///
/// impl ChannelFilter for TraceId {
///     fn filter(&self, msg: &Publication<'_>, next: Next<'_>) -> Result<(), String> {
///         if msg.get("trace-id").is_some() {
///             return next.pass();
///         }
///         let mut ctx = next.context();
///         ctx.set("trace-id", "42");
///         next.pass_with(&ctx)
///     }
/// }
/// ```
pub trait ChannelFilter: Send + Sync + 'static {
    /// Runs on one message; see the trait's documentation.
    fn filter(&self, msg: &Publication<'_>, next: Next<'_>) -> Result<(), String>;
}

impl<F> ChannelFilter for F
where
    F: Fn(&Publication<'_>, Next<'_>) -> Result<(), String> + Send + Sync + 'static,
{
    fn filter(&self, msg: &Publication<'_>, next: Next<'_>) -> Result<(), String> {
        self(msg, next)
    }
}

/// The rest of a filter chain, for one message: the next filter, then the backends (on
/// publish) or the subscriber (on subscribe). Consumed by passing the message on.
pub struct Next<'a> {
    raw: FilterNext,
    meta: &'a [MetaPair<'a>],
}

impl std::fmt::Debug for Next<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Next")
            .field("pairs", &self.meta.len())
            .finish()
    }
}

impl<'a> Next<'a> {
    pub(crate) fn new(raw: FilterNext, meta: &'a [MetaPair<'a>]) -> Next<'a> {
        Next { raw, meta }
    }

    /// A copy of the message's context, to change and pass on with
    /// [`pass_with`](Self::pass_with). Its kind is `Publish`; the runtime treats the pairs
    /// the same on either side.
    pub fn context(&self) -> Context {
        let mut ctx = Context::new(ContextKind::Publish);
        for p in self.meta {
            ctx.set(p.key(), p.value());
        }
        ctx
    }

    /// Passes the message on with its context as it came; returns what the rest of the
    /// chain returned.
    pub fn pass(self) -> Result<(), String> {
        self.raw.pass(self.meta)
    }

    /// Passes the message on with `ctx` as its context (e.g. [`context`](Self::context)
    /// with a key added); returns what the rest of the chain returned.
    pub fn pass_with(self, ctx: &Context) -> Result<(), String> {
        let pairs = crate::ffi::meta_of(ctx.iter());
        self.raw.pass(&pairs)
    }
}
