//! RPC filter chains: the built-in `debug_log` and `time_cost`, and the filters plugins
//! register (ABI 1.9), run around each call of the module functions whose
//! `clients_options` / `servers_options` rule names them in `enable_filters`. As in
//! AimRT the filter listed last is the outermost: with `[A, B]`, B runs first and passes
//! the call to A, which passes it to the backend (client side) or the service (server
//! side); the answer goes back through A, then B.

use std::sync::Arc;
use std::time::Instant;

use aimrt_plugin_api::ffi::{
    meta_of, Header, MetaPair, RawMessage, RawReplyObserver, RawRpcCtx, RawRpcFilter,
    RawRpcFilterCall, RawRpcReply, ReplyParts, RpcFilterOutcome, StrView,
};
use aimrt_plugin_api::rpc::CallFilterSide;
use aimrt_plugin_api::{RpcContext, RpcContextKind, RpcStatus};

use crate::filters::{PluginFilter, Registered};

/// The RPC filters plugins registered, by side and name.
pub(crate) type RegisteredRpcFilters = Registered<CallFilterSide, RawRpcFilter>;

enum Stage {
    /// AimRT's `debug_log`: the call with its context and request, then its status and
    /// response (WARN for a failure).
    DebugLog,
    /// Ours: how long the call took, in µs.
    TimeCost,
    Plugin(Arc<PluginFilter<RawRpcFilter>>),
}

/// A function's filters of one side, in the order they run.
#[derive(Default)]
pub(crate) struct RpcChain(Vec<Stage>);

impl RegisteredRpcFilters {
    /// The chain of `listed` (names checked against `names` already), in the order it
    /// runs: the last listed first.
    pub(crate) fn chain(&self, side: CallFilterSide, listed: &[String]) -> RpcChain {
        let built_in = |name: &str| match name {
            "debug_log" => Some(Stage::DebugLog),
            "time_cost" => Some(Stage::TimeCost),
            _ => None,
        };
        RpcChain(self.stages(side, listed, built_in, Stage::Plugin))
    }
}

/// The call a chain runs on.
pub(crate) struct Subject<'a> {
    pub(crate) side: CallFilterSide,
    pub(crate) func: &'a str,
    /// The calling module (client side) or the serving module (server side).
    pub(crate) module: &'a str,
    pub(crate) timeout_ns: u64,
    pub(crate) req: &'a RawMessage,
    /// Answers a call a filter stopped, counted and logged (the detail does not name the
    /// function).
    pub(crate) refuse: &'a dyn Fn(RawRpcReply, RpcStatus, String),
}

/// The last step: the call goes on with this context and this reply.
pub(crate) type Last<'l> = dyn FnMut(&[MetaPair<'_>], RawRpcReply) + 'l;

impl RpcChain {
    /// No filter: the caller runs its last step directly.
    pub(crate) fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Runs the filters on `s` with context `pairs`; `last` gets the context the filters
    /// passed on and the reply that takes the answer back through them. A call a filter
    /// stops is answered through `s.refuse` (and `last` is not called).
    pub(crate) fn run(
        &self,
        s: &Subject<'_>,
        pairs: &[MetaPair<'_>],
        reply: RawRpcReply,
        last: &mut Last<'_>,
    ) {
        run_from(&self.0, s, pairs, reply, last);
    }
}

/// The unknown status of a side: a filter's refusal without a status of its own.
fn unknown(side: CallFilterSide) -> RpcStatus {
    match side {
        CallFilterSide::Client => RpcStatus::CLI_UNKNOWN,
        CallFilterSide::Server => RpcStatus::SVR_UNKNOWN,
    }
}

fn run_from(
    stages: &[Stage],
    s: &Subject<'_>,
    pairs: &[MetaPair<'_>],
    reply: RawRpcReply,
    last: &mut Last<'_>,
) {
    let Some((first, rest)) = stages.split_first() else {
        return last(pairs, reply);
    };
    let side = s.side.name();
    let filter = match first {
        Stage::DebugLog => {
            let reply = debug_log(s, pairs, reply);
            return run_from(rest, s, pairs, reply, last);
        }
        Stage::TimeCost => {
            let (begin, func) = (Instant::now(), s.func.to_owned());
            let reply = RawRpcReply::new(move |parts: ReplyParts| {
                tracing::info!(target: "aimrt", "RPC {side} time cost. func name: {func}, {} us", begin.elapsed().as_micros());
                pass_back(reply, parts);
            });
            return run_from(rest, s, pairs, reply, last);
        }
        Stage::Plugin(f) => f,
    };
    let call = RawRpcFilterCall {
        header: Header::of::<RawRpcFilterCall>(),
        func: StrView::new(s.func),
        ctx: RawRpcCtx::new(s.timeout_ns, pairs),
        req_ts: s.req.type_support(),
        req: s.req.as_ptr(),
        module: StrView::new(s.module),
        side: s.side.code(),
    };
    let mut reply = Some(reply);
    let outcome = filter
        .raw
        .run(&call, &mut |passed, observer: RawReplyObserver| {
            // `run` lets a filter pass a call on once; the reply is there that once.
            if let Some(reply) = reply.take() {
                run_from(rest, s, passed, observed(reply, observer), last);
            }
        });
    let stopped = |reply: &mut Option<RawRpcReply>, status, detail| {
        if let Some(reply) = reply.take() {
            (s.refuse)(reply, status, detail);
        }
    };
    let (name, owner, func) = (&filter.name, &filter.owner, s.func);
    let outcome = match outcome {
        RpcFilterOutcome::FailedAfter(done, why) => {
            if let Some(held) = filter.late.admit() {
                tracing::warn!(target: "aimrt", "RPC {side} filter '{name}' of '{owner}' failed after it passed on or answered a call of '{func}': {why} ({held} more such failures since the last report)");
            }
            *done
        }
        other => other,
    };
    match outcome {
        RpcFilterOutcome::Passed | RpcFilterOutcome::FailedAfter(..) => {}
        RpcFilterOutcome::Answered(status, detail) => {
            let status = if status.is_ok() {
                unknown(s.side)
            } else {
                status
            };
            let detail = format!("{side} filter '{name}' of '{owner}' answered: {detail}");
            stopped(&mut reply, status, detail);
        }
        RpcFilterOutcome::Held => {
            let detail = format!(
                "{side} filter '{name}' of '{owner}' neither passed the call on nor answered it"
            );
            stopped(&mut reply, unknown(s.side), detail);
        }
        RpcFilterOutcome::Failed(why) => {
            let detail = format!("{side} filter '{name}' of '{owner}' failed: {why}");
            stopped(&mut reply, unknown(s.side), detail);
        }
    }
}

/// Hands `parts` on to `reply`.
fn pass_back(reply: RawRpcReply, parts: ReplyParts) {
    let meta = meta_of(parts.meta.iter().map(|(k, v)| (k.as_str(), v.as_str())));
    reply.complete(parts.status, parts.rsp, &meta, &parts.detail);
}

/// `reply`, telling `observer` the answer first (no wrapper without an observer).
fn observed(reply: RawRpcReply, observer: RawReplyObserver) -> RawRpcReply {
    if observer.is_none() {
        return reply;
    }
    RawRpcReply::new(move |parts: ReplyParts| {
        let meta = meta_of(parts.meta.iter().map(|(k, v)| (k.as_str(), v.as_str())));
        observer.notify(parts.status, parts.rsp.as_ref(), &meta, &parts.detail);
        reply.complete(parts.status, parts.rsp, &meta, &parts.detail);
    })
}

/// A message as JSON for a log line, if its type has JSON.
fn json_of(msg: &RawMessage) -> Option<String> {
    msg.encode("json")
        .ok()
        .map(|b| String::from_utf8_lossy(&b).into_owned())
}

/// AimRT's `debug_log`: the opening line now, a reply that logs the answer.
fn debug_log(s: &Subject<'_>, pairs: &[MetaPair<'_>], reply: RawRpcReply) -> RawRpcReply {
    let (side, func) = (s.side.name(), s.func.to_owned());
    let kind = match s.side {
        CallFilterSide::Client => RpcContextKind::Client,
        CallFilterSide::Server => RpcContextKind::Server,
    };
    let mut ctx = RpcContext::new(kind);
    ctx.set_timeout(Some(std::time::Duration::from_nanos(s.timeout_ns)));
    for p in pairs {
        ctx.set_meta(p.key(), p.value());
    }
    match json_of(s.req) {
        Some(j) => {
            tracing::info!(target: "aimrt", "RPC {side} start new rpc call. func name: {func}, context: {ctx}, req: {j}")
        }
        None => {
            tracing::info!(target: "aimrt", "RPC {side} start new rpc call. func name: {func}, context: {ctx}")
        }
    }
    RawRpcReply::new(move |parts: ReplyParts| {
        if parts.status.is_ok() {
            match parts.rsp.as_ref().and_then(json_of) {
                Some(j) => {
                    tracing::info!(target: "aimrt", "RPC {side} get rpc ret. func name: {func}, status: {}, rsp: {j}", parts.status)
                }
                None => {
                    tracing::info!(target: "aimrt", "RPC {side} get rpc ret. func name: {func}, status: {}", parts.status)
                }
            }
        } else {
            tracing::warn!(target: "aimrt", "RPC {side} get rpc error ret. func name: {func}, status: {}", parts.status)
        }
        pass_back(reply, parts);
    })
}
