//! Module RPC across the ABI (1.2): a module registers service functions and client
//! functions through its RPC handle, and invokes client functions; every invoke ends in
//! exactly one [`RawRpcReply`].
//!
//! - A **call context** ([`RawRpcCtx`]) is a timeout and borrowed meta pairs.
//! - Requests and responses are message objects of a [`TypeSupportVtable`] (one reference
//!   handed over), as channel messages: the host passes the object itself when caller and
//!   service use the same table, and encodes once and decodes once otherwise.
//! - A **service function** ([`RawServiceFunc`], module → host) is called with a server
//!   context, one request reference of its own request table and a reply.
//! - A **reply** ([`RawRpcReply`], caller → callee) carries an AimRT status code, a response
//!   reference (or null), the meta to merge back into the caller's context and a detail
//!   text (why a call failed; may be empty).

use std::ffi::c_void;
use std::marker::PhantomData;
use std::sync::Arc;

use super::channel::TypeSupportVtable;
use super::context::{current_module_tag, with_module_tag};
use super::executor::RawExecutor;
use super::pubsub::{MetaPair, MetaView};
use super::{contain, ErrorSink, Header, RawMessage, Status, StrView};
use crate::channel::Message;
use crate::rpc::{RpcContext, RpcContextKind, RpcStatus};

/// A call context crossing the ABI, borrowed for the call.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawRpcCtx {
    /// The timeout in nanoseconds; 0: none given.
    pub timeout_ns: u64,
    /// The meta pairs.
    pub meta: MetaView,
}

impl RawRpcCtx {
    /// A view of `meta` with `timeout_ns`.
    pub fn new(timeout_ns: u64, meta: &[MetaPair<'_>]) -> RawRpcCtx {
        RawRpcCtx {
            timeout_ns,
            meta: MetaView::new(meta),
        }
    }

    /// A copy as a context of `kind`.
    ///
    /// # Safety
    /// The views must be readable for the call.
    pub unsafe fn to_context(self, kind: RpcContextKind) -> RpcContext {
        // SAFETY: per the caller's guarantee.
        let pairs = unsafe { self.meta.pairs() };
        let timeout =
            (self.timeout_ns > 0).then(|| std::time::Duration::from_nanos(self.timeout_ns));
        // The host sends distinct keys (a duplicate from a foreign caller would be kept;
        // lookups find the first).
        RpcContext::from_distinct(kind, timeout, pairs)
    }
}

/// `timeout_ns` of a context (0 when it has none).
pub(crate) fn timeout_ns(ctx: &RpcContext) -> u64 {
    ctx.timeout()
        .map_or(0, |t| u64::try_from(t.as_nanos()).unwrap_or(u64::MAX))
}

/// The answer to one call: `complete` is called exactly once, from any thread.
#[repr(C)]
pub struct RawRpcReply {
    /// The caller's state.
    pub ctx: *mut c_void,
    /// `status`: an AimRT code. `rsp`: one reference to an object of `rsp_ts` handed over,
    /// or null (always null unless the status is 0). `meta`: pairs to merge into the
    /// caller's context. `detail`: why the call failed, or empty. All views are borrowed
    /// for the call.
    pub complete: unsafe extern "C" fn(
        ctx: *mut c_void,
        status: u32,
        rsp_ts: *const TypeSupportVtable,
        rsp: *const c_void,
        meta: MetaView,
        detail: StrView,
    ),
}

// SAFETY: the reply contract allows completing from any thread.
unsafe impl Send for RawRpcReply {}

/// What a reply delivers: the status, the response (if any), the meta to merge back and a
/// detail text.
pub struct ReplyParts {
    /// The AimRT status.
    pub status: RpcStatus,
    /// The response object, of whatever table the answerer used.
    pub rsp: Option<RawMessage>,
    /// The meta to merge into the caller's context.
    pub meta: Vec<(String, String)>,
    /// Why the call failed, or empty.
    pub detail: String,
}

struct ReplyObj<F> {
    done: F,
    module_tag: usize,
}

impl RawRpcReply {
    /// A reply that calls `done`, in the logging context of the current module (one
    /// allocation).
    pub fn new<F: FnOnce(ReplyParts) + Send + 'static>(done: F) -> RawRpcReply {
        unsafe extern "C" fn complete<F: FnOnce(ReplyParts) + Send + 'static>(
            ctx: *mut c_void,
            status: u32,
            rsp_ts: *const TypeSupportVtable,
            rsp: *const c_void,
            meta: MetaView,
            detail: StrView,
        ) {
            // SAFETY: `ctx` is the `Box<ReplyObj<F>>` of `new::<F>` (this function is its
            // `complete`), completed exactly once (reply contract); `rsp` is one reference
            // of the static table `rsp_ts` handed over; the views are valid for this call.
            let (obj, rsp, meta, detail) = unsafe {
                let rsp = (!rsp.is_null() && !rsp_ts.is_null())
                    .then(|| RawMessage::from_raw(&*rsp_ts, rsp));
                let meta: Vec<(String, String)> = meta
                    .pairs()
                    .iter()
                    .map(|p| (p.key().to_owned(), p.value().to_owned()))
                    .collect();
                (
                    Box::from_raw(ctx.cast::<ReplyObj<F>>()),
                    rsp,
                    meta,
                    detail.to_string_lossy(),
                )
            };
            let ReplyObj { done, module_tag } = *obj;
            let parts = ReplyParts {
                status: RpcStatus::from_code(status),
                rsp,
                meta,
                detail,
            };
            let _ = with_module_tag(module_tag as *const c_void, || contain(move || done(parts)));
        }
        let obj = ReplyObj {
            done,
            module_tag: current_module_tag() as usize,
        };
        RawRpcReply {
            ctx: Box::into_raw(Box::new(obj)).cast(),
            complete: complete::<F>,
        }
    }

    /// Completes the reply, consuming it.
    pub fn complete(
        self,
        status: RpcStatus,
        rsp: Option<RawMessage>,
        meta: &[MetaPair<'_>],
        detail: &str,
    ) {
        let (ts, ptr) = match rsp {
            Some(m) => {
                let (ts, ptr) = m.into_raw();
                (ts as *const TypeSupportVtable, ptr)
            }
            None => (std::ptr::null(), std::ptr::null()),
        };
        // SAFETY: a reply is completed exactly once: it is consumed here; the response
        // reference passes to the callee; the views outlive the call.
        unsafe {
            (self.complete)(
                self.ctx,
                status.code(),
                ts,
                ptr,
                MetaView::new(meta),
                StrView::new(detail),
            )
        }
    }
}

/// A service function of a module.
#[repr(C)]
pub struct RawServiceFunc {
    /// The operations.
    pub vtable: *const ServiceFuncVtable,
    /// The module's object.
    pub obj: *const c_void,
}

// SAFETY: service objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawServiceFunc {}
// SAFETY: see `Send`.
unsafe impl Sync for RawServiceFunc {}

/// Service function operations.
#[repr(C)]
pub struct ServiceFuncVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Handles one request: `req` is one reference to an object of the request table the
    /// function was registered with, handed over; `reply` is completed exactly once, with
    /// a response of the registered response table.
    pub call: unsafe extern "C" fn(
        obj: *const c_void,
        ctx: RawRpcCtx,
        req: *const c_void,
        reply: RawRpcReply,
    ),
    /// The executor the function runs calls on: `OK` and `out` written, or `NOT_FOUND`
    /// when it runs them on the delivering thread.
    pub executor: unsafe extern "C" fn(obj: *const c_void, out: *mut RawExecutor) -> Status,
    /// Frees the function.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
}

/// What a module's service function does with one call.
pub(crate) type ServeFn<Req> = dyn Fn(RpcContext, Arc<Req>, RawRpcReply) + Send + Sync;

struct ServiceFuncObj<Req> {
    serve: Box<ServeFn<Req>>,
    executor: Option<RawExecutor>,
    module_tag: usize,
}

struct ServiceFuncExport<Req>(PhantomData<Req>);

impl<Req: Message> ServiceFuncExport<Req> {
    const VTABLE: ServiceFuncVtable = ServiceFuncVtable {
        header: Header::of::<ServiceFuncVtable>(),
        call: Self::call,
        executor: Self::executor,
        drop: Self::drop,
    };

    unsafe extern "C" fn executor(obj: *const c_void, out: *mut RawExecutor) -> Status {
        // SAFETY: `obj` is a live `ServiceFuncObj<Req>` (vtable contract).
        let s = unsafe { &*obj.cast::<ServiceFuncObj<Req>>() };
        match s.executor {
            Some(e) => {
                // SAFETY: `out` is writable (vtable contract).
                unsafe { out.write(e) };
                Status::OK
            }
            None => Status::NOT_FOUND,
        }
    }

    unsafe extern "C" fn call(
        obj: *const c_void,
        ctx: RawRpcCtx,
        req: *const c_void,
        reply: RawRpcReply,
    ) {
        // SAFETY: `obj` is a live `ServiceFuncObj<Req>` (vtable contract); `req` is one
        // reference to an `Arc<Req>` of this library's table, handed over; the context's
        // views are valid for this call.
        let (s, req, ctx) = unsafe {
            (
                &*obj.cast::<ServiceFuncObj<Req>>(),
                Arc::from_raw(req.cast::<Req>()),
                ctx.to_context(RpcContextKind::Server),
            )
        };
        with_module_tag(s.module_tag as *const c_void, || {
            // A panic before the handler took the reply is answered by the reply guard
            // of the module side (`serve`); one here would leave it with us: contain it.
            let _ = contain(|| (s.serve)(ctx, req, reply));
        });
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: `obj` came from `Box::into_raw` in `new`; this is its last use.
        let s = unsafe { Box::from_raw(obj.cast::<ServiceFuncObj<Req>>().cast_mut()) };
        let _ = contain(move || drop(s));
    }
}

impl RawServiceFunc {
    /// Exports `serve` for requests of `Req`, attributed to the current module; it runs
    /// calls on `executor`, or on the delivering thread.
    pub(crate) fn new<Req: Message>(
        serve: Box<ServeFn<Req>>,
        executor: Option<RawExecutor>,
    ) -> RawServiceFunc {
        let obj = ServiceFuncObj {
            serve,
            executor,
            module_tag: current_module_tag() as usize,
        };
        RawServiceFunc {
            vtable: &ServiceFuncExport::<Req>::VTABLE,
            obj: Box::into_raw(Box::new(obj)).cast(),
        }
    }

    /// Calls the function (host use): `req` must be an object of the request table it was
    /// registered with.
    pub fn call(&self, ctx: &[MetaPair<'_>], timeout_ns: u64, req: RawMessage, reply: RawRpcReply) {
        let (_, ptr) = req.into_raw();
        // SAFETY: a live function (owned by the host); the views outlive the call; the
        // request reference and the reply pass to the callee.
        unsafe { ((*self.vtable).call)(self.obj, RawRpcCtx::new(timeout_ns, ctx), ptr, reply) }
    }
}

impl RawServiceFunc {
    /// The executor it runs calls on, if not the delivering thread (host use).
    pub fn executor(&self) -> Option<RawExecutor> {
        let mut out = RawExecutor::null();
        // SAFETY: a live function; `out` is writable.
        let status = unsafe { ((*self.vtable).executor)(self.obj, &mut out) };
        (status.is_ok() && !out.is_null()).then_some(out)
    }
}

impl Drop for RawServiceFunc {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { ((*self.vtable).drop)(self.obj) }
    }
}

/// Flag of [`RpcHandleVtable::invoke`]: the caller blocks its thread until the reply.
pub const INVOKE_BLOCKING: u32 = 1;

/// The RPC handle of a module (ABI 1.2). Its object is the module's core object.
#[repr(C)]
pub struct RpcHandleVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Registers a service function under the full name `func` (only in `initialize`);
    /// the host takes ownership of `func_obj`, also on failure.
    pub register_service: unsafe extern "C" fn(
        obj: *const c_void,
        func: StrView,
        req_ts: *const TypeSupportVtable,
        rsp_ts: *const TypeSupportVtable,
        func_obj: RawServiceFunc,
        err: ErrorSink,
    ) -> Status,
    /// Registers a client function under the full name `func` (only in `initialize`).
    pub register_client: unsafe extern "C" fn(
        obj: *const c_void,
        func: StrView,
        req_ts: *const TypeSupportVtable,
        rsp_ts: *const TypeSupportVtable,
        err: ErrorSink,
    ) -> Status,
    /// Invokes the client function `func`: `req` is one reference to an object of
    /// `req_ts`, handed over; the response comes as an object of `rsp_ts`. `reply` is
    /// completed exactly once, also when the call is refused.
    pub invoke: unsafe extern "C" fn(
        obj: *const c_void,
        func: StrView,
        ctx: RawRpcCtx,
        req_ts: *const TypeSupportVtable,
        req: *const c_void,
        rsp_ts: *const TypeSupportVtable,
        flags: u32,
        reply: RawRpcReply,
    ),
    /// The context meta keys plugins registered to pass from server to client contexts:
    /// `each` is called once per key, with `ctx`.
    pub passed_keys: unsafe extern "C" fn(
        obj: *const c_void,
        ctx: *mut c_void,
        each: unsafe extern "C" fn(ctx: *mut c_void, key: StrView),
    ),
}
