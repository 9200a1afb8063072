//! RPC filters a plugin registers by name (ABI 1.9; AimRT's `RegisterClientFilter` /
//! `RegisterServerFilter`): the plugin exports a [`CallFilter`] as a [`RawRpcFilter`];
//! the host runs it around each call of the functions whose `clients_options` /
//! `servers_options` rule names it in `enable_filters`.
//!
//! A filter sees the call ([`RawRpcFilterCall`], borrowed for its own call) and an
//! [`RpcFilterNext`], through which it does at most one of two things during its call:
//! pass the call on (with a context, and a [`RawReplyObserver`] the host calls with the
//! answer), or answer it with a status. The host owns the call's completion, so every
//! call is still answered exactly once whatever the filter does.

use std::ffi::c_void;
use std::mem::ManuallyDrop;

use super::channel::TypeSupportVtable;
use super::pubsub::{MetaPair, MetaView};
use super::rpc_call::RawRpcCtx;
use super::{contain, ErrorSink, ErrorSlot, Header, RawMessage, Status, StrView};
use crate::rpc::{CallFilter, CallNext, FilterCall, ReplyView, RpcStatus};

/// One call as a filter sees it, borrowed for the filter's call.
#[repr(C)]
pub struct RawRpcFilterCall {
    /// Size and minor of this struct.
    pub header: Header,
    /// The full function name (`pb:/example.ExampleService/GetFooData`).
    pub func: StrView,
    /// The call's timeout and context pairs.
    pub ctx: RawRpcCtx,
    /// The request's table.
    pub req_ts: *const TypeSupportVtable,
    /// The request object (borrowed).
    pub req: *const c_void,
    /// The calling module (client side) or the serving module (server side).
    pub module: StrView,
    /// The side: 0 client, 1 server ([`CallFilterSide::code`](crate::rpc::CallFilterSide::code)).
    pub side: u32,
}

/// What a filter wants to hear of the answer of a call it passed on: `reply` or `drop` is
/// called exactly once. A null `obj` is no observer (neither is called).
#[repr(C)]
pub struct RawReplyObserver {
    /// The filter's state, or null.
    pub obj: *mut c_void,
    /// The answer: an AimRT status, the response (borrowed; null unless the status is 0),
    /// the meta the answer carries back, why the call failed (or empty). Views are valid
    /// for the call.
    pub reply: unsafe extern "C" fn(
        obj: *mut c_void,
        status: u32,
        rsp_ts: *const TypeSupportVtable,
        rsp: *const c_void,
        meta: MetaView,
        detail: StrView,
    ),
    /// Frees the state without an answer (the host could not take the observer).
    pub drop: unsafe extern "C" fn(obj: *mut c_void),
}

// SAFETY: observers are `Send` (required by `CallNext::on_reply`); the host calls one once.
unsafe impl Send for RawReplyObserver {}

/// The rest of a filter chain, handed to a filter for one call.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RpcFilterNext {
    /// The host's context.
    pub ctx: *mut c_void,
    /// Passes the call on with `meta` as its context (valid for the call); the host takes
    /// `observer` (also when it refuses). At most once, during the filter's call, and not
    /// after `answer`.
    pub pass: unsafe extern "C" fn(
        ctx: *mut c_void,
        meta: MetaView,
        observer: RawReplyObserver,
        err: ErrorSink,
    ) -> Status,
    /// Answers the call with `status` (an AimRT code other than 0) and `detail`, without
    /// passing it on. At most once, during the filter's call, and not after `pass`.
    pub answer: unsafe extern "C" fn(
        ctx: *mut c_void,
        status: u32,
        detail: StrView,
        err: ErrorSink,
    ) -> Status,
}

/// RPC filter operations.
#[repr(C)]
pub struct RpcFilterVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Runs the filter on `call`. A status other than OK reports the filter's own failure
    /// (`err` says why).
    pub call: unsafe extern "C" fn(
        obj: *const c_void,
        call: *const RawRpcFilterCall,
        next: RpcFilterNext,
        err: ErrorSink,
    ) -> Status,
    /// Frees the filter.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
}

/// An RPC filter contributed by a plugin.
#[repr(C)]
pub struct RawRpcFilter {
    /// The operations.
    pub vtable: *const RpcFilterVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: filter objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawRpcFilter {}
// SAFETY: see `Send`.
unsafe impl Sync for RawRpcFilter {}

/// What became of a call a filter was given.
#[derive(Debug, PartialEq, Eq)]
pub enum RpcFilterOutcome {
    /// The filter passed the call on.
    Passed,
    /// The filter answered the call with this status and detail.
    Answered(RpcStatus, String),
    /// The filter returned without passing the call on or answering it.
    Held,
    /// The filter failed before passing the call on or answering it.
    Failed(String),
    /// The filter passed the call on or answered it, then failed.
    FailedAfter(Box<RpcFilterOutcome>, String),
}

/// The rest of a chain as the host runs it: the context the filter passes on and its
/// observer.
pub type RestOfCall<'f> = dyn FnMut(&[MetaPair<'_>], RawReplyObserver) + 'f;

impl RawReplyObserver {
    /// No observer.
    pub const NONE: RawReplyObserver = RawReplyObserver {
        obj: std::ptr::null_mut(),
        reply: Self::none_reply,
        drop: Self::none_drop,
    };

    unsafe extern "C" fn none_reply(
        _: *mut c_void,
        _: u32,
        _: *const TypeSupportVtable,
        _: *const c_void,
        _: MetaView,
        _: StrView,
    ) {
    }

    unsafe extern "C" fn none_drop(_: *mut c_void) {}

    /// An observer that calls `f` with the answer (one allocation).
    pub(crate) fn new<F: FnOnce(&ReplyView<'_>) + Send + 'static>(f: F) -> RawReplyObserver {
        unsafe extern "C" fn reply<F: FnOnce(&ReplyView<'_>) + Send + 'static>(
            obj: *mut c_void,
            status: u32,
            rsp_ts: *const TypeSupportVtable,
            rsp: *const c_void,
            meta: MetaView,
            detail: StrView,
        ) {
            // SAFETY: `obj` is the `Box<F>` of `new::<F>`, called once (observer
            // contract); `rsp` is a live object of `rsp_ts` borrowed for this call
            // (`ManuallyDrop` never releases it); the views are valid for this call.
            let (f, rsp, pairs, detail) = unsafe {
                let rsp = (!rsp.is_null() && !rsp_ts.is_null())
                    .then(|| ManuallyDrop::new(RawMessage::from_raw(&*rsp_ts, rsp)));
                (
                    Box::from_raw(obj.cast::<F>()),
                    rsp,
                    meta.pairs(),
                    detail.to_string_lossy(),
                )
            };
            let view = ReplyView::new(RpcStatus::from_code(status), rsp.as_deref(), pairs, &detail);
            let _ = contain(move || f(&view));
        }
        unsafe extern "C" fn drop<F>(obj: *mut c_void) {
            // SAFETY: `obj` is the `Box<F>` of `new::<F>`, freed once (observer contract).
            let f = unsafe { Box::from_raw(obj.cast::<F>()) };
            let _ = contain(move || std::mem::drop(f));
        }
        RawReplyObserver {
            obj: Box::into_raw(Box::new(f)).cast(),
            reply: reply::<F>,
            drop: drop::<F>,
        }
    }

    /// Whether this is no observer.
    pub fn is_none(&self) -> bool {
        self.obj.is_null()
    }

    /// Hands the answer to the observer (host use), consuming it.
    pub fn notify(
        self,
        status: RpcStatus,
        rsp: Option<&RawMessage>,
        meta: &[MetaPair<'_>],
        detail: &str,
    ) {
        if self.obj.is_null() {
            return;
        }
        let this = ManuallyDrop::new(self);
        let (ts, ptr) = rsp.map_or((std::ptr::null(), std::ptr::null()), |m| {
            (m.type_support() as *const TypeSupportVtable, m.as_ptr())
        });
        // SAFETY: the observer's entry with its state, once (`self` is consumed, and
        // `ManuallyDrop` keeps `Drop` from freeing it as well); the response is borrowed
        // and the views outlive the call.
        unsafe {
            (this.reply)(
                this.obj,
                status.code(),
                ts,
                ptr,
                MetaView::new(meta),
                StrView::new(detail),
            )
        }
    }
}

impl Drop for RawReplyObserver {
    fn drop(&mut self) {
        if !self.obj.is_null() {
            // SAFETY: an observer not handed an answer is freed once, here.
            unsafe { (self.drop)(self.obj) }
        }
    }
}

struct FilterObj<F>(F);

impl<F: CallFilter> FilterObj<F> {
    const VTABLE: RpcFilterVtable = RpcFilterVtable {
        header: Header::of::<RpcFilterVtable>(),
        call: Self::call,
        drop: Self::drop,
    };

    unsafe extern "C" fn call(
        obj: *const c_void,
        call: *const RawRpcFilterCall,
        next: RpcFilterNext,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: a live `Box<FilterObj<F>>` pointer (vtable contract).
        let this = unsafe { &*obj.cast::<FilterObj<F>>() };
        // SAFETY: the host passes a valid call whose views and request live for this call.
        let (view, meta) = unsafe { (FilterCall::new(&*call), (*call).ctx.meta.pairs()) };
        let next = CallNext::new(next, meta, view.side());
        super::filter::filter_status(contain(|| this.0.filter(&view, next)), err)
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<FilterObj<F>>()) };
        let _ = contain(move || std::mem::drop(b));
    }
}

impl RpcFilterNext {
    /// Passes the call on with `meta` and `observer` (plugin side).
    pub(crate) fn pass(
        self,
        meta: &[MetaPair<'_>],
        observer: RawReplyObserver,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: the host's entry with its context, during the filter's call; ownership
        // of `observer` passes to the host; the pairs and the sink outlive the call.
        let status = unsafe { (self.pass)(self.ctx, MetaView::new(meta), observer, slot.sink()) };
        slot.result(status)
    }

    /// Answers the call (plugin side).
    pub(crate) fn answer(self, status: RpcStatus, detail: &str) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: the host's entry with its context, during the filter's call; the view
        // and the sink outlive the call.
        let status =
            unsafe { (self.answer)(self.ctx, status.code(), StrView::new(detail), slot.sink()) };
        slot.result(status)
    }
}

impl RawRpcFilter {
    /// Exports `filter`.
    pub(crate) fn new<F: CallFilter>(filter: F) -> RawRpcFilter {
        RawRpcFilter {
            vtable: &FilterObj::<F>::VTABLE,
            obj: Box::into_raw(Box::new(FilterObj(filter)))
                .cast_const()
                .cast(),
        }
    }

    fn vt(&self) -> &RpcFilterVtable {
        // SAFETY: the vtable is `'static` (its library is never unloaded).
        unsafe { &*self.vtable }
    }

    /// Runs the filter on `call` (host use): `rest` runs the rest of the chain when the
    /// filter passes the call on, with the context and observer the filter gives.
    pub fn run(&self, call: &RawRpcFilterCall, rest: &mut RestOfCall<'_>) -> RpcFilterOutcome {
        struct Slot<'n, 'f> {
            rest: Option<&'n mut RestOfCall<'f>>,
            done: Option<RpcFilterOutcome>,
        }
        unsafe extern "C" fn pass(
            ctx: *mut c_void,
            meta: MetaView,
            observer: RawReplyObserver,
            err: ErrorSink,
        ) -> Status {
            // SAFETY: `ctx` is the `Slot` below, alive for the filter's call.
            let slot = unsafe { &mut *ctx.cast::<Slot<'_, '_>>() };
            let Some(rest) = slot.rest.take() else {
                err.report("a filter passed on a call it had passed on or answered already; the second time is ignored");
                return Status::INVALID;
            };
            slot.done = Some(RpcFilterOutcome::Passed);
            // SAFETY: the filter passes pairs valid for this call.
            let pairs = unsafe { meta.pairs() };
            match contain(|| rest(pairs, observer)) {
                Ok(()) => Status::OK,
                Err(why) => {
                    err.report(&why);
                    Status::FAILED
                }
            }
        }
        unsafe extern "C" fn answer(
            ctx: *mut c_void,
            status: u32,
            detail: StrView,
            err: ErrorSink,
        ) -> Status {
            // SAFETY: `ctx` is the `Slot` below, alive for the filter's call.
            let slot = unsafe { &mut *ctx.cast::<Slot<'_, '_>>() };
            if slot.rest.take().is_none() {
                err.report("a filter answered a call it had passed on or answered already; the second time is ignored");
                return Status::INVALID;
            }
            // SAFETY: the filter passes a view valid for this call.
            let detail = unsafe { detail.to_string_lossy() };
            slot.done = Some(RpcFilterOutcome::Answered(
                RpcStatus::from_code(status),
                detail,
            ));
            Status::OK
        }
        let mut slot = Slot {
            rest: Some(rest),
            done: None,
        };
        let raw_next = RpcFilterNext {
            ctx: (&mut slot as *mut Slot<'_, '_>).cast(),
            pass,
            answer,
        };
        let mut err = ErrorSlot::default();
        // SAFETY: a live filter; `call`, the slot and the sink outlive the call.
        let status = unsafe { (self.vt().call)(self.obj, call, raw_next, err.sink()) };
        let own = (!status.is_ok()).then(|| err.take(|| format!("returned {status}")));
        match (slot.done, own) {
            (Some(done), None) => done,
            (Some(done), Some(why)) => RpcFilterOutcome::FailedAfter(Box::new(done), why),
            (None, None) => RpcFilterOutcome::Held,
            (None, Some(why)) => RpcFilterOutcome::Failed(why),
        }
    }
}

impl Drop for RawRpcFilter {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { (self.vt().drop)(self.obj) }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use super::*;
    use crate::rpc::CallFilterSide;

    #[derive(Debug, serde::Serialize, serde::Deserialize)]
    struct Note {
        n: u32,
    }
    crate::serde_message!(Note, "test.Note");

    /// What the rest of the chain was given.
    type Passed = Option<(Vec<(String, String)>, RawReplyObserver)>;

    /// Runs `filter` on a client call of `/f` by module `M` with context `k: v`; what the
    /// rest of the chain got (if it ran) and the outcome.
    fn run_on(filter: impl CallFilter) -> (Passed, RpcFilterOutcome) {
        let raw = RawRpcFilter::new(filter);
        let req = RawMessage::new(Arc::new(Note { n: 7 }));
        let pairs = [MetaPair::new("k", "v")];
        let call = RawRpcFilterCall {
            header: Header::of::<RawRpcFilterCall>(),
            func: StrView::new("/f"),
            ctx: RawRpcCtx::new(2_000_000_000, &pairs),
            req_ts: req.type_support(),
            req: req.as_ptr(),
            module: StrView::new("M"),
            side: CallFilterSide::Client.code(),
        };
        let mut passed = None;
        let outcome = raw.run(&call, &mut |meta, observer| {
            let meta = meta
                .iter()
                .map(|p| (p.key().to_owned(), p.value().to_owned()))
                .collect();
            passed = Some((meta, observer));
        });
        (passed, outcome)
    }

    fn kv(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    }

    #[test]
    fn a_filter_sees_the_call_and_passes_it_on_with_its_context() {
        let (passed, outcome) = run_on(|call: &FilterCall<'_>, next: CallNext<'_>| {
            assert_eq!((call.func(), call.module()), ("/f", "M"));
            assert_eq!(call.side(), CallFilterSide::Client);
            assert_eq!(call.get("k"), Some("v"));
            assert_eq!(call.timeout(), Some(std::time::Duration::from_secs(2)));
            assert_eq!(call.request().encode("json").unwrap(), br#"{"n":7}"#);
            let mut ctx = next.context();
            ctx.set_meta("trace-id", "1");
            next.pass_with(&ctx)
        });
        assert_eq!(outcome, RpcFilterOutcome::Passed);
        let (meta, observer) = passed.unwrap();
        assert_eq!(meta, kv(&[("k", "v"), ("trace-id", "1")]));
        assert!(observer.is_none());
    }

    #[test]
    fn an_observer_hears_the_answer_once_and_is_freed_when_it_hears_none() {
        let heard = Arc::new(Mutex::new(Vec::new()));
        let h = heard.clone();
        let (passed, outcome) = run_on(move |_: &FilterCall<'_>, next: CallNext<'_>| {
            let h = h.clone();
            next.on_reply(move |reply| {
                let rsp = reply.response().map(|m| m.encode("json").unwrap());
                let rsp = rsp.map(|b| String::from_utf8(b).unwrap());
                h.lock().unwrap().push((
                    reply.status(),
                    rsp,
                    reply.get("back").map(str::to_owned),
                    reply.detail().to_owned(),
                ));
            })
            .pass()
        });
        assert_eq!(outcome, RpcFilterOutcome::Passed);
        let (meta, observer) = passed.unwrap();
        assert_eq!(meta, kv(&[("k", "v")]));
        assert!(!observer.is_none());
        let rsp = RawMessage::new(Arc::new(Note { n: 8 }));
        observer.notify(RpcStatus::OK, Some(&rsp), &[MetaPair::new("back", "1")], "");
        assert_eq!(
            *heard.lock().unwrap(),
            [(
                RpcStatus::OK,
                Some(r#"{"n":8}"#.to_owned()),
                Some("1".to_owned()),
                String::new()
            )]
        );

        // An observer the host drops unheard frees what it holds, without a call.
        let token = Arc::new(());
        let t = token.clone();
        let (passed, _) = run_on(move |_: &FilterCall<'_>, next: CallNext<'_>| {
            let t = t.clone();
            next.on_reply(move |_| drop(t)).pass()
        });
        // `run_on` dropped the filter: the test's and the observer's.
        assert_eq!(Arc::strong_count(&token), 2);
        drop(passed);
        assert_eq!(Arc::strong_count(&token), 1);
    }

    #[test]
    fn answering_holding_failing_and_panicking_are_told_apart() {
        let (passed, outcome) = run_on(|_: &FilterCall<'_>, next: CallNext<'_>| {
            next.answer(RpcStatus::SVR_HANDLE_FAILED, "no token")
        });
        assert!(passed.is_none());
        assert_eq!(
            outcome,
            RpcFilterOutcome::Answered(RpcStatus::SVR_HANDLE_FAILED, "no token".into())
        );

        let (passed, outcome) = run_on(|_: &FilterCall<'_>, _: CallNext<'_>| Ok(()));
        assert!(passed.is_none());
        assert_eq!(outcome, RpcFilterOutcome::Held);

        let (_, outcome) = run_on(|_: &FilterCall<'_>, _: CallNext<'_>| Err("broken".to_owned()));
        assert_eq!(outcome, RpcFilterOutcome::Failed("broken".into()));

        // OK is not an answer a filter may give: refused on the plugin side, so the call
        // is neither passed on nor answered.
        let (_, outcome) =
            run_on(|_: &FilterCall<'_>, next: CallNext<'_>| next.answer(RpcStatus::OK, ""));
        match outcome {
            RpcFilterOutcome::Failed(why) => assert!(why.contains("failure status"), "{why}"),
            other => panic!("{other:?}"),
        }

        let (passed, outcome) = run_on(|_: &FilterCall<'_>, next: CallNext<'_>| {
            next.pass()?;
            Err("after".to_owned())
        });
        assert!(passed.is_some());
        assert_eq!(
            outcome,
            RpcFilterOutcome::FailedAfter(Box::new(RpcFilterOutcome::Passed), "after".into())
        );

        let (passed, outcome) =
            run_on(|_: &FilterCall<'_>, _: CallNext<'_>| -> Result<(), String> { panic!("boom") });
        assert!(passed.is_none());
        match outcome {
            RpcFilterOutcome::Failed(why) => assert!(why.contains("boom"), "{why}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_host_takes_one_step_per_call() {
        // A foreign filter may call the entries twice: the second is refused.
        let raw = RawRpcFilter::new(|_: &FilterCall<'_>, next: CallNext<'_>| {
            let raw = next.raw;
            next.pass()?;
            let again = raw.answer(RpcStatus::SVR_UNKNOWN, "again").unwrap_err();
            assert!(again.contains("passed on or answered already"), "{again}");
            let again = raw.pass(&[], RawReplyObserver::NONE).unwrap_err();
            assert!(again.contains("passed on or answered already"), "{again}");
            Ok(())
        });
        let req = RawMessage::new(Arc::new(Note { n: 1 }));
        let call = RawRpcFilterCall {
            header: Header::of::<RawRpcFilterCall>(),
            func: StrView::new("/f"),
            ctx: RawRpcCtx::new(0, &[]),
            req_ts: req.type_support(),
            req: req.as_ptr(),
            module: StrView::new("M"),
            side: CallFilterSide::Server.code(),
        };
        let mut runs = 0;
        let outcome = raw.run(&call, &mut |_, _| runs += 1);
        assert_eq!((outcome, runs), (RpcFilterOutcome::Passed, 1));
    }
}
