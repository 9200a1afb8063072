//! Channel filters a plugin registers by name (ABI 1.7; AimRT's `RegisterPublishFilter`
//! / `RegisterSubscribeFilter`): the plugin exports a [`ChannelFilter`] as a
//! [`RawChannelFilter`]; the host runs it around each message of the topics whose rule
//! names it in `enable_filters`, with a [`FilterNext`] that runs the rest of the chain.

use std::ffi::c_void;

use super::pubsub::{MetaPair, MetaView, RawPublication};
use super::{contain, ErrorSink, ErrorSlot, Header, Status};
use crate::channel::{ChannelFilter, Next, Publication};

/// The rest of a filter chain, handed to a filter for one call.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct FilterNext {
    /// The host's context.
    pub ctx: *mut c_void,
    /// Passes the message on with `meta` as its context (valid for the call). Called at
    /// most once, during the filter's call; the status is the rest of the chain's (`err`
    /// says why it failed).
    pub call: unsafe extern "C" fn(ctx: *mut c_void, meta: MetaView, err: ErrorSink) -> Status,
}

/// Channel filter operations.
#[repr(C)]
pub struct ChannelFilterVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Runs the filter on the message `msg` describes (topic, context, message, the
    /// publishing or subscribing module). The filter passes it on by calling `next` at
    /// most once, during this call; not calling it holds the message back. A status other
    /// than OK reports the filter's own failure (`err` says why).
    pub call: unsafe extern "C" fn(
        obj: *const c_void,
        msg: *const RawPublication,
        next: FilterNext,
        err: ErrorSink,
    ) -> Status,
    /// Frees the filter.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
}

/// A channel filter contributed by a plugin.
#[repr(C)]
pub struct RawChannelFilter {
    /// The operations.
    pub vtable: *const ChannelFilterVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: filter objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawChannelFilter {}
// SAFETY: see `Send`.
unsafe impl Sync for RawChannelFilter {}

/// The rest of a chain as the host runs it: the context the filter passes on, in; how the
/// rest ended, out.
pub type RestOfChain<'f> = dyn FnMut(&[MetaPair<'_>]) -> Result<(), String> + 'f;

/// What became of a message a filter was given.
#[derive(Debug, PartialEq, Eq)]
pub enum FilterOutcome {
    /// The filter passed it on; the rest of the chain returned this.
    Passed(Result<(), String>),
    /// The filter returned without passing it on.
    Held,
    /// The filter failed before passing it on.
    Failed(String),
    /// The filter passed it on (the rest of the chain returned the first), then failed.
    FailedAfter(Result<(), String>, String),
}

/// What a filter's call returns across the ABI: OK, `INVALID` for its error, `FAILED` for
/// its panic, with why reported to `err`.
pub(crate) fn filter_status(r: Result<Result<(), String>, String>, err: ErrorSink) -> Status {
    match r {
        Ok(Ok(())) => Status::OK,
        Ok(Err(why)) => {
            err.report(&why);
            Status::INVALID
        }
        Err(panic) => {
            err.report(&format!("the filter panicked: {panic}"));
            Status::FAILED
        }
    }
}

struct FilterObj<F>(F);

impl<F: ChannelFilter> FilterObj<F> {
    const VTABLE: ChannelFilterVtable = ChannelFilterVtable {
        header: Header::of::<ChannelFilterVtable>(),
        call: Self::call,
        drop: Self::drop,
    };

    unsafe extern "C" fn call(
        obj: *const c_void,
        msg: *const RawPublication,
        next: FilterNext,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: a live `Box<FilterObj<F>>` pointer (vtable contract).
        let this = unsafe { &*obj.cast::<FilterObj<F>>() };
        // SAFETY: the host passes a valid publication, its views live for this call.
        let (publication, meta) = unsafe { (Publication::new(&*msg), (*msg).ctx.pairs()) };
        let next = Next::new(next, meta);
        filter_status(contain(|| this.0.filter(&publication, next)), err)
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<FilterObj<F>>()) };
        let _ = contain(move || std::mem::drop(b));
    }
}

impl FilterNext {
    /// Runs the rest of the chain with `meta` (plugin side).
    pub(crate) fn pass(self, meta: &[MetaPair<'_>]) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: the host's entry with its context, during the filter's call; the pairs
        // and the sink outlive the call.
        let status = unsafe { (self.call)(self.ctx, MetaView::new(meta), slot.sink()) };
        slot.result(status)
    }
}

impl RawChannelFilter {
    /// Exports `filter`.
    pub(crate) fn new<F: ChannelFilter>(filter: F) -> RawChannelFilter {
        RawChannelFilter {
            vtable: &FilterObj::<F>::VTABLE,
            obj: Box::into_raw(Box::new(FilterObj(filter)))
                .cast_const()
                .cast(),
        }
    }

    fn vt(&self) -> &ChannelFilterVtable {
        // SAFETY: the vtable is `'static` (its library is never unloaded).
        unsafe { &*self.vtable }
    }

    /// Runs the filter on `msg` (host use): `next` runs the rest of the chain when the
    /// filter passes the message on, with the context the filter gives.
    pub fn run(&self, msg: &RawPublication, next: &mut RestOfChain<'_>) -> FilterOutcome {
        struct Slot<'n, 'f> {
            next: Option<&'n mut RestOfChain<'f>>,
            passed: Option<Result<(), String>>,
        }
        unsafe extern "C" fn call(ctx: *mut c_void, meta: MetaView, err: ErrorSink) -> Status {
            // SAFETY: `ctx` is the `Slot` below, alive for the filter's call.
            let slot = unsafe { &mut *ctx.cast::<Slot<'_, '_>>() };
            let Some(next) = slot.next.take() else {
                err.report("a filter passed the message on twice; the second time is ignored");
                return Status::INVALID;
            };
            // SAFETY: the filter passes pairs valid for this call.
            let pairs = unsafe { meta.pairs() };
            let result = contain(|| next(pairs)).unwrap_or_else(Err);
            let status = match &result {
                Ok(()) => Status::OK,
                Err(why) => {
                    err.report(why);
                    Status::FAILED
                }
            };
            slot.passed = Some(result);
            status
        }
        let mut slot = Slot {
            next: Some(next),
            passed: None,
        };
        let raw_next = FilterNext {
            ctx: (&mut slot as *mut Slot<'_, '_>).cast(),
            call,
        };
        let mut err = ErrorSlot::default();
        // SAFETY: a live filter; `msg`, the slot and the sink outlive the call.
        let status = unsafe { (self.vt().call)(self.obj, msg, raw_next, err.sink()) };
        let own = (!status.is_ok()).then(|| err.take(|| format!("returned {status}")));
        match (slot.passed, own) {
            (Some(result), None) => FilterOutcome::Passed(result),
            (Some(result), Some(why)) => FilterOutcome::FailedAfter(result, why),
            (None, None) => FilterOutcome::Held,
            (None, Some(why)) => FilterOutcome::Failed(why),
        }
    }
}

impl Drop for RawChannelFilter {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { (self.vt().drop)(self.obj) }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::ffi::{RawMessage, StrView};

    #[derive(Debug, serde::Serialize, serde::Deserialize)]
    struct Note {
        n: u32,
    }
    crate::serde_message!(Note, "test.Note");

    /// Runs `filter` on a note on `/t` with context `k: v`; the context the rest of the
    /// chain saw (if it ran) and the outcome. The rest fails when `rest_fails`.
    fn run_on(
        filter: impl ChannelFilter,
        rest_fails: bool,
    ) -> (Option<Vec<(String, String)>>, FilterOutcome) {
        let raw = RawChannelFilter::new(filter);
        let msg = RawMessage::new(Arc::new(Note { n: 7 }));
        let pairs = [MetaPair::new("k", "v")];
        let publication = RawPublication {
            header: Header::of::<RawPublication>(),
            topic: StrView::new("/t"),
            ctx: MetaView::new(&pairs),
            type_support: msg.type_support(),
            msg: msg.as_ptr(),
            pkg: StrView::new("pkg"),
            module: StrView::new("M"),
            topic_ref: crate::ffi::RawTopicRef::NONE,
        };
        let mut seen = None;
        let outcome = raw.run(&publication, &mut |passed| {
            seen = Some(
                passed
                    .iter()
                    .map(|p| (p.key().to_owned(), p.value().to_owned()))
                    .collect(),
            );
            if rest_fails {
                Err("the subscriber failed".into())
            } else {
                Ok(())
            }
        });
        (seen, outcome)
    }

    fn kv(pairs: &[(&str, &str)]) -> Option<Vec<(String, String)>> {
        Some(
            pairs
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
        )
    }

    #[test]
    fn a_filter_sees_the_message_and_passes_it_on_as_it_came_or_changed() {
        let (seen, outcome) = run_on(
            |msg: &Publication<'_>, next: Next<'_>| {
                assert_eq!((msg.topic(), msg.module(), msg.pkg()), ("/t", "M", "pkg"));
                assert_eq!(msg.get("k"), Some("v"));
                assert_eq!(msg.message().encode("json").unwrap(), br#"{"n":7}"#);
                next.pass()
            },
            false,
        );
        assert_eq!(outcome, FilterOutcome::Passed(Ok(())));
        assert_eq!(seen, kv(&[("k", "v")]));

        let (seen, outcome) = run_on(
            |_: &Publication<'_>, next: Next<'_>| {
                let mut ctx = next.context();
                ctx.set("trace-id", "1");
                next.pass_with(&ctx)
            },
            false,
        );
        assert_eq!(outcome, FilterOutcome::Passed(Ok(())));
        assert_eq!(seen, kv(&[("k", "v"), ("trace-id", "1")]));
    }

    #[test]
    fn holding_failing_and_panicking_are_told_apart() {
        let (seen, outcome) = run_on(|_: &Publication<'_>, _: Next<'_>| Ok(()), false);
        assert_eq!((seen, outcome), (None, FilterOutcome::Held));

        let (seen, outcome) = run_on(
            |_: &Publication<'_>, _: Next<'_>| Err("no".to_owned()),
            false,
        );
        assert_eq!((seen, outcome), (None, FilterOutcome::Failed("no".into())));

        let (seen, outcome) = run_on(
            |_: &Publication<'_>, next: Next<'_>| {
                next.pass()?;
                Err("after".to_owned())
            },
            false,
        );
        assert_eq!(seen, kv(&[("k", "v")]));
        assert_eq!(outcome, FilterOutcome::FailedAfter(Ok(()), "after".into()));

        let (seen, outcome) = run_on(
            |_: &Publication<'_>, _: Next<'_>| -> Result<(), String> { panic!("boom") },
            false,
        );
        assert_eq!(seen, None);
        match outcome {
            FilterOutcome::Failed(why) => assert!(why.contains("boom"), "{why}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_rests_failure_reaches_the_filter_and_the_host() {
        let (seen, outcome) = run_on(|_: &Publication<'_>, next: Next<'_>| next.pass(), true);
        assert!(seen.is_some());
        assert_eq!(
            outcome,
            FilterOutcome::FailedAfter(
                Err("the subscriber failed".into()),
                "the subscriber failed".into()
            )
        );
        // A filter that swallows the rest's failure still leaves it to the host.
        let (_, outcome) = run_on(
            |_: &Publication<'_>, next: Next<'_>| {
                let _ = next.pass();
                Ok(())
            },
            true,
        );
        assert_eq!(
            outcome,
            FilterOutcome::Passed(Err("the subscriber failed".into()))
        );
    }
}
