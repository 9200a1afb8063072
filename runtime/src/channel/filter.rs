//! Channel filter chains: AimRT's built-in `debug_log` and the filters plugins register
//! (ABI 1.7), run around each message of the topics whose rule names them in
//! `enable_filters`. As in AimRT the filter listed last is the outermost: with
//! `[A, B]`, B runs first and passes the message to A, which passes it to the backends (on
//! publish) or the subscriber (on subscribe).

use std::sync::Arc;

use aimrt_plugin_api::channel::{Context, ContextKind, FilterSide};
use aimrt_plugin_api::ffi::{
    type_name_of, FilterOutcome, Header, MetaPair, RawChannelFilter, RawMessage, RawPublication,
    StrView,
};

use crate::filters::{Registered, Side};

/// The built-in filters `…topics_options[i].enable_filters` may name.
pub(crate) const BUILT_IN: &[&str] = <FilterSide as Side>::BUILT_IN;

/// A channel filter a plugin registered.
type PluginFilter = crate::filters::PluginFilter<RawChannelFilter>;

/// The channel filters plugins registered, by side and name.
pub(crate) type RegisteredFilters = Registered<FilterSide, RawChannelFilter>;

impl RegisteredFilters {
    /// The chain of `listed` (names checked against [`names`](Self::names) already), in
    /// the order it runs: the last listed first.
    pub(crate) fn chain(&self, side: FilterSide, listed: &[String]) -> Chain {
        let built_in = |name: &str| (name == "debug_log").then_some(Stage::DebugLog);
        Chain(self.stages(side, listed, built_in, Stage::Plugin))
    }
}

enum Stage {
    DebugLog,
    Plugin(Arc<PluginFilter>),
}

/// A topic's filters of one side, in the order they run.
#[derive(Default)]
pub(crate) struct Chain(Vec<Stage>);

/// The message a chain runs on, and who publishes or subscribes it.
pub(crate) struct Subject<'a> {
    pub(crate) side: FilterSide,
    pub(crate) topic: &'a str,
    pub(crate) msg: &'a RawMessage,
    pub(crate) pkg: &'a str,
    pub(crate) module: &'a str,
}

/// Why a chain did not end with its last step succeeding.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Stopped {
    /// A filter returned without passing the message on.
    Held { filter: String },
    /// A filter failed before passing the message on.
    Failed { filter: String, why: String },
    /// The last step (the backends, the subscriber) failed: it counted that itself.
    Last(String),
}

impl std::fmt::Display for Stopped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Stopped::Held { filter } => write!(f, "filter '{filter}' held the message back"),
            Stopped::Failed { filter, why } => write!(f, "filter '{filter}' failed: {why}"),
            Stopped::Last(why) => f.write_str(why),
        }
    }
}

impl Chain {
    /// No filter: the caller runs its last step directly.
    pub(crate) fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Runs the filters on `s` with context `pairs`, then `last` with the context the
    /// filters passed on.
    pub(crate) fn run(
        &self,
        s: &Subject<'_>,
        pairs: &[MetaPair<'_>],
        last: &mut dyn FnMut(&[MetaPair<'_>]) -> Result<(), String>,
    ) -> Result<(), Stopped> {
        run_from(&self.0, s, pairs, last)
    }
}

fn run_from(
    stages: &[Stage],
    s: &Subject<'_>,
    pairs: &[MetaPair<'_>],
    last: &mut dyn FnMut(&[MetaPair<'_>]) -> Result<(), String>,
) -> Result<(), Stopped> {
    let Some((first, rest)) = stages.split_first() else {
        return last(pairs).map_err(Stopped::Last);
    };
    let filter = match first {
        Stage::DebugLog => {
            debug_log(s, pairs);
            return run_from(rest, s, pairs, last);
        }
        Stage::Plugin(f) => f,
    };
    let publication = RawPublication {
        header: Header::of::<RawPublication>(),
        topic: StrView::new(s.topic),
        ctx: aimrt_plugin_api::ffi::MetaView::new(pairs),
        type_support: s.msg.type_support(),
        msg: s.msg.as_ptr(),
        pkg: StrView::new(s.pkg),
        module: StrView::new(s.module),
        // A filter reports through its own outcome, not as a backend.
        topic_ref: aimrt_plugin_api::ffi::RawTopicRef::NONE,
    };
    // How the rest of the chain ended, kept whole (the filter sees it as text).
    let mut inner = None;
    let outcome = filter.raw.run(&publication, &mut |passed| {
        run_from(rest, s, passed, last).map_err(|stopped| {
            let text = stopped.to_string();
            inner = Some(stopped);
            text
        })
    });
    let mut rest_result =
        |r: Result<(), String>| r.map_err(|text| inner.take().unwrap_or(Stopped::Last(text)));
    match outcome {
        FilterOutcome::Passed(r) => rest_result(r),
        FilterOutcome::Held => Err(Stopped::Held {
            filter: filter.name.clone(),
        }),
        FilterOutcome::Failed(why) => Err(Stopped::Failed {
            filter: filter.name.clone(),
            why,
        }),
        FilterOutcome::FailedAfter(r, why) => {
            // A filter that hands the rest's error back as its own is not a second failure.
            if r.is_ok() {
                if let Some(held) = filter.late.admit() {
                    tracing::warn!(target: "aimrt", "Channel topic '{}': {} filter '{}' of '{}' failed after passing the message on: {why} ({held} more such failures since the last report)", s.topic, s.side.name(), filter.name, filter.owner);
                }
            }
            rest_result(r)
        }
    }
}

/// AimRT's `debug_log` filter: one INFO line a message, its type and topic, its context
/// and the message as JSON (left out for a type without JSON).
fn debug_log(s: &Subject<'_>, pairs: &[MetaPair<'_>]) {
    let (what, kind) = match s.side {
        FilterSide::Publish => ("Channel publish a new msg", ContextKind::Publish),
        FilterSide::Subscribe => (
            "Channel subscriber handle a new msg",
            ContextKind::Subscribe,
        ),
    };
    let mut ctx = Context::new(kind);
    for p in pairs {
        ctx.set(p.key(), p.value());
    }
    let (type_name, topic) = (type_name_of(s.msg.type_support()), s.topic);
    match s.msg.encode("json") {
        Ok(json) => {
            let json = String::from_utf8_lossy(&json);
            tracing::info!(target: "aimrt", "{what}. msg type: {type_name}, topic name: {topic}, context: {ctx}, msg: {json}")
        }
        Err(_) => {
            tracing::info!(target: "aimrt", "{what}. msg type: {type_name}, topic name: {topic}, context: {ctx}")
        }
    }
}
