//! RPC filters from plugins (ABI 1.9; AimRT's client and server filters): code a plugin
//! registers by name ([`Registrar::register_rpc_filter`](crate::Registrar::register_rpc_filter))
//! that the runtime runs around each call of the functions whose `clients_options` /
//! `servers_options` rule lists the name in `enable_filters`.

use std::time::Duration;

use super::{RpcContext, RpcContextKind, RpcStatus};
use crate::ffi::{meta_of, MetaPair, RawMessage};
use crate::ffi::{RawReplyObserver, RawRpcFilterCall, RpcFilterNext};

/// Which side of a call a filter runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CallFilterSide {
    /// Around a module's call, on the calling thread: after the runtime completed the
    /// context (`aimrt-request_id`, `aimrt-serialization_type`) and before a backend is
    /// chosen, so a filter's context reaches the backend and the server.
    Client,
    /// Around a service function, on the thread that runs it, with the server's context
    /// (`aimrt-backend` set).
    Server,
}

impl CallFilterSide {
    /// The code that crosses the ABI.
    pub fn code(self) -> u32 {
        match self {
            CallFilterSide::Client => 0,
            CallFilterSide::Server => 1,
        }
    }

    /// The side of a code, if it is one.
    pub fn from_code(code: u32) -> Option<CallFilterSide> {
        match code {
            0 => Some(CallFilterSide::Client),
            1 => Some(CallFilterSide::Server),
            _ => None,
        }
    }

    /// `client` or `server`.
    pub fn name(self) -> &'static str {
        match self {
            CallFilterSide::Client => "client",
            CallFilterSide::Server => "server",
        }
    }

    fn kind(self) -> RpcContextKind {
        match self {
            CallFilterSide::Client => RpcContextKind::Client,
            CallFilterSide::Server => RpcContextKind::Server,
        }
    }
}

/// An RPC filter: sees each call of its functions and passes it on, with its context
/// changed or not, or answers it itself.
///
/// `filter` gets the call (function, context, request, module) and the rest of the chain
/// as `next`, and does at most one of these during its call:
/// - [`CallNext::pass`] / [`CallNext::pass_with`]: the call goes on (the next filter,
///   then the backend on the client side or the service on the server side). With
///   [`CallNext::on_reply`] first, the filter hears the answer, once, on the thread that
///   answers.
/// - [`CallNext::answer`]: the call is answered with that status and goes no further.
///
/// Returning without either, or with `Err` before either, answers the call with the
/// side's unknown error (`CLI_UNKNOWN`, `SVR_UNKNOWN`) and the reason; the runtime logs it
/// and counts it as failed. A closure `Fn(&FilterCall, CallNext) -> Result<(), String>`
/// is a filter.
///
/// ```
/// use std::time::Instant;
/// use aimrt_plugin_api::rpc::{CallFilter, CallNext, FilterCall, RpcStatus};
///
/// /// Refuses calls without a `token`; times the others.
/// struct Guard;
///
/// impl CallFilter for Guard {
///     fn filter(&self, call: &FilterCall<'_>, next: CallNext<'_>) -> Result<(), String> {
///         if call.get("token").is_none() {
///             return next.answer(RpcStatus::SVR_HANDLE_FAILED, "no token");
///         }
///         let began = Instant::now();
///         let func = call.func().to_owned();
///         next.on_reply(move |reply| {
///             tracing::info!("{func}: {} in {:?}", reply.status(), began.elapsed());
///         })
///         .pass()
///     }
/// }
/// ```
pub trait CallFilter: Send + Sync + 'static {
    /// Runs on one call; see the trait's documentation.
    fn filter(&self, call: &FilterCall<'_>, next: CallNext<'_>) -> Result<(), String>;
}

impl<F> CallFilter for F
where
    F: Fn(&FilterCall<'_>, CallNext<'_>) -> Result<(), String> + Send + Sync + 'static,
{
    fn filter(&self, call: &FilterCall<'_>, next: CallNext<'_>) -> Result<(), String> {
        self(call, next)
    }
}

/// One call, borrowed for a filter's call.
pub struct FilterCall<'a> {
    raw: &'a RawRpcFilterCall,
    req: std::mem::ManuallyDrop<RawMessage>,
}

impl std::fmt::Debug for FilterCall<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FilterCall")
            .field("func", &self.func())
            .field("module", &self.module())
            .finish()
    }
}

impl<'a> FilterCall<'a> {
    /// Wraps a raw call (plugin shim).
    ///
    /// # Safety
    /// `raw` must be a valid call: live views, a live request of its table.
    pub(crate) unsafe fn new(raw: &'a RawRpcFilterCall) -> FilterCall<'a> {
        // SAFETY: the request stays alive for the call; `ManuallyDrop` never releases the
        // borrowed reference.
        let req = unsafe { RawMessage::from_raw(&*raw.req_ts, raw.req) };
        FilterCall {
            raw,
            req: std::mem::ManuallyDrop::new(req),
        }
    }

    /// The full function name (`pb:/example.ExampleService/GetFooData`).
    pub fn func(&self) -> &'a str {
        // SAFETY: views of a valid call live for `'a`.
        unsafe { self.raw.func.as_str().unwrap_or("") }
    }

    /// The calling module (client side) or the serving module (server side).
    pub fn module(&self) -> &'a str {
        // SAFETY: as above.
        unsafe { self.raw.module.as_str().unwrap_or("") }
    }

    /// The side the filter runs on.
    pub fn side(&self) -> CallFilterSide {
        CallFilterSide::from_code(self.raw.side).unwrap_or(CallFilterSide::Client)
    }

    /// The context pairs.
    pub fn meta(&self) -> &'a [MetaPair<'a>] {
        // SAFETY: as above.
        unsafe { self.raw.ctx.meta.pairs() }
    }

    /// A context value.
    pub fn get(&self, key: &str) -> Option<&'a str> {
        self.meta()
            .iter()
            .find(|p| p.is_key(key))
            .map(|p| p.value())
    }

    /// The call's timeout (the runtime's 5 s when the caller set none).
    pub fn timeout(&self) -> Option<Duration> {
        (self.raw.ctx.timeout_ns > 0).then(|| Duration::from_nanos(self.raw.ctx.timeout_ns))
    }

    /// The request (borrowed; [`RawMessage::share`] keeps it).
    pub fn request(&self) -> &RawMessage {
        &self.req
    }
}

/// The rest of a filter chain, for one call. Consumed by passing the call on or answering
/// it.
pub struct CallNext<'a> {
    pub(crate) raw: RpcFilterNext,
    meta: &'a [MetaPair<'a>],
    side: CallFilterSide,
    observer: RawReplyObserver,
}

impl std::fmt::Debug for CallNext<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CallNext")
            .field("pairs", &self.meta.len())
            .field("side", &self.side)
            .finish()
    }
}

impl<'a> CallNext<'a> {
    pub(crate) fn new(
        raw: RpcFilterNext,
        meta: &'a [MetaPair<'a>],
        side: CallFilterSide,
    ) -> CallNext<'a> {
        CallNext {
            raw,
            meta,
            side,
            observer: RawReplyObserver::NONE,
        }
    }

    /// A copy of the call's context (of the filter's side), to change and pass on with
    /// [`pass_with`](Self::pass_with).
    pub fn context(&self) -> RpcContext {
        RpcContext::from_distinct(self.side.kind(), None, self.meta)
    }

    /// Hears the call's answer: `f` runs once, with the status, the response (when OK)
    /// and why it failed, on the thread that answers (the service's, a backend's or the
    /// runtime's deadline thread), before the answer goes on towards the caller. Replaces
    /// an earlier `on_reply`.
    pub fn on_reply(mut self, f: impl FnOnce(&ReplyView<'_>) + Send + 'static) -> Self {
        self.observer = RawReplyObserver::new(f);
        self
    }

    /// Passes the call on with its context as it came.
    pub fn pass(self) -> Result<(), String> {
        let meta = self.meta;
        self.pass_pairs(meta)
    }

    /// Passes the call on with `ctx` as its context (e.g. [`context`](Self::context) with
    /// a key added). Its timeout is not read: the call keeps its deadline.
    pub fn pass_with(self, ctx: &RpcContext) -> Result<(), String> {
        let pairs = meta_of(ctx.meta_pairs());
        self.pass_pairs(&pairs)
    }

    fn pass_pairs(self, meta: &[MetaPair<'_>]) -> Result<(), String> {
        self.raw.pass(meta, self.observer)
    }

    /// Answers the call with `status` and `why`, without passing it on (an observer set
    /// with `on_reply` is not called). `RpcStatus::OK` is refused: a filter cannot make a
    /// response.
    pub fn answer(self, status: RpcStatus, why: &str) -> Result<(), String> {
        if status.is_ok() {
            return Err(format!(
                "a filter answered a call with {status}; it may answer only with a failure status"
            ));
        }
        self.raw.answer(status, why)
    }
}

/// A call's answer as a filter hears it.
#[derive(Debug)]
pub struct ReplyView<'a> {
    status: RpcStatus,
    rsp: Option<&'a RawMessage>,
    meta: &'a [MetaPair<'a>],
    detail: &'a str,
}

impl<'a> ReplyView<'a> {
    pub(crate) fn new(
        status: RpcStatus,
        rsp: Option<&'a RawMessage>,
        meta: &'a [MetaPair<'a>],
        detail: &'a str,
    ) -> ReplyView<'a> {
        ReplyView {
            status,
            rsp,
            meta,
            detail,
        }
    }

    /// The status.
    pub fn status(&self) -> RpcStatus {
        self.status
    }

    /// The response (when the status is OK).
    pub fn response(&self) -> Option<&'a RawMessage> {
        self.rsp
    }

    /// Meta the answer carries back to the caller's context.
    pub fn get(&self, key: &str) -> Option<&'a str> {
        self.meta.iter().find(|p| p.is_key(key)).map(|p| p.value())
    }

    /// Why the call failed, or empty.
    pub fn detail(&self) -> &'a str {
        self.detail
    }
}
