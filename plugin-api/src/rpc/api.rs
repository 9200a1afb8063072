//! The module side of RPC: service functions and client functions.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::future::Future;
use std::marker::PhantomData;
use std::pin::Pin;
use std::sync::{Arc, Condvar, Mutex};
use std::task::{Context, Poll, Waker};

use super::context::meta_keys;
use super::{RpcContext, RpcContextKind, RpcStatus};
use crate::channel::Message;
use crate::ffi::{
    meta_of, type_support, RawCore, RawMessage, RawRpcReply, RawServiceFunc, ReplyParts,
    RpcHandleVtable,
};
use crate::{Error, ExecutorRef};

/// The result of one call: the response, or the status that ended the call.
pub type RpcResult<Rsp> = Result<Arc<Rsp>, RpcStatus>;

/// AimRT's full function name: `<rpc_type>:/<service>/<method>`.
///
/// ```
/// use aimrt_plugin_api::rpc::full_func_name;
/// assert_eq!(
///     full_func_name("pb", "aimrt.protocols.example.ExampleService", "GetFooData"),
///     "pb:/aimrt.protocols.example.ExampleService/GetFooData"
/// );
/// ```
pub fn full_func_name(rpc_type: &str, service: &str, method: &str) -> String {
    format!("{rpc_type}:/{service}/{method}")
}

/// A module's RPC handle (AimRT's `RpcHandleRef`), from [`CoreRef::rpc`](crate::CoreRef::rpc).
/// Copyable; valid for the process's life.
///
/// Functions are registered in `initialize` only; calls work from `start` until the
/// runtime shuts RPC down (module `shutdown` included). Every call ends with exactly one
/// answer: the response, or an [`RpcStatus`] saying why not (a deadline always applies:
/// the context's timeout, else 5 s).
///
/// ```no_run
/// use std::sync::Arc;
/// use aimrt_plugin_api::rpc::{RpcClient, RpcRef};
/// use aimrt_plugin_api::{CoreRef, Error, RpcContext, RpcStatus};
///
/// #[derive(Debug, serde::Serialize, serde::Deserialize)]
/// struct Ask { q: String }
/// #[derive(Debug, serde::Serialize, serde::Deserialize)]
/// struct Answer { a: String }
/// aimrt_plugin_api::serde_message!(Ask, "example.Ask");
/// aimrt_plugin_api::serde_message!(Answer, "example.Answer");
///
/// fn initialize(core: CoreRef) -> Result<RpcClient<Ask, Answer>, Error> {
///     let rpc = core.rpc()?;
///     rpc.serve_sync("serde:/example.Oracle/Ask", |_ctx: &RpcContext, req: &Ask| {
///         Ok(Answer { a: format!("echo {}", req.q) })
///     })?;
///     rpc.client("serde:/example.Oracle/Ask")
/// }
///
/// // In `start` or later, on any thread that is not needed for the answer:
/// fn ask(client: &RpcClient<Ask, Answer>) -> Result<(), RpcStatus> {
///     let mut ctx = client.new_context();
///     let rsp = client.call(&mut ctx, Ask { q: "hi".into() })?;
///     tracing::info!("got {}", rsp.a);
///     Ok(())
/// }
/// ```
#[derive(Clone, Copy)]
pub struct RpcRef {
    core: RawCore,
    vt: &'static RpcHandleVtable,
}

impl std::fmt::Debug for RpcRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RpcRef")
    }
}

impl RpcRef {
    pub(crate) fn new(core: RawCore) -> Result<RpcRef, Error> {
        let vt = core.rpc().ok_or_else(|| {
            Error::Rpc(
                "this runtime has no module RPC (it predates ABI 1.2); run the module with a newer aimrt_main".into(),
            )
        })?;
        Ok(RpcRef { core, vt })
    }

    /// Copies into the client context `client` the non-empty values, in the server context
    /// `server`, of the keys plugins registered to pass along (AimRT's
    /// `MergeServerContextToClientContext`). Nothing happens for other kinds of context.
    pub fn merge_server_context(&self, server: &RpcContext, client: &mut RpcContext) {
        let keys = self.core.passed_keys(self.vt);
        let keys: Vec<&str> = keys.iter().map(String::as_str).collect();
        client.merge_from_server(server, &keys);
    }

    /// Registers `func` (a full name, `pb:/pkg.Service/Method`) as a client function of
    /// this module and returns its client (AimRT's `RegisterClientFunc` + proxy). Only in
    /// `initialize`.
    pub fn client<Req: Message, Rsp: Message>(
        &self,
        func: &str,
    ) -> Result<RpcClient<Req, Rsp>, Error> {
        self.core
            .register_client(self.vt, func, type_support::<Req>(), type_support::<Rsp>())
            .map_err(Error::Rpc)?;
        Ok(RpcClient {
            rpc: *self,
            func: func.into(),
            default_ctx: None,
            filters: Arc::new(Vec::new()),
            _types: PhantomData,
        })
    }

    /// Serves `func` with a synchronous handler, run on the thread that delivers the
    /// call. A panic answers [`RpcStatus::SVR_HANDLE_FAILED`]. Only in `initialize`.
    pub fn serve_sync<Req, Rsp, F>(&self, func: &str, handler: F) -> Result<(), Error>
    where
        Req: Message,
        Rsp: Message,
        F: Fn(&RpcContext, &Req) -> Result<Rsp, RpcStatus> + Send + Sync + 'static,
    {
        self.register::<Req, Rsp>(
            func,
            Box::new(move |ctx, req, reply| {
                let reply = Reply::<Rsp>::new(reply);
                let result = handler(&ctx, &req);
                reply.send(result);
            }),
        )
    }

    /// Serves `func` with a handler that answers through a [`Reply`], now or later, from
    /// any thread (AimRT's async service). Only in `initialize`.
    pub fn serve_then<Req, Rsp, F>(&self, func: &str, handler: F) -> Result<(), Error>
    where
        Req: Message,
        Rsp: Message,
        F: Fn(RpcContext, Arc<Req>, Reply<Rsp>) + Send + Sync + 'static,
    {
        self.register::<Req, Rsp>(
            func,
            Box::new(move |ctx, req, reply| handler(ctx, req, Reply::new(reply))),
        )
    }

    /// Serves `func` with an `async` handler (AimRT's co service): the future starts on the
    /// delivering thread and goes on wherever it is woken. Only in `initialize`.
    pub fn serve_async<Req, Rsp, F, Fut>(&self, func: &str, handler: F) -> Result<(), Error>
    where
        Req: Message,
        Rsp: Message,
        F: Fn(RpcContext, Arc<Req>) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Rsp, RpcStatus>> + Send + 'static,
    {
        self.register::<Req, Rsp>(
            func,
            Box::new(move |ctx, req, reply| {
                let reply = Reply::<Rsp>::new(reply);
                let fut = handler(ctx, req);
                spawn_inline(async move { reply.send(fut.await) });
            }),
        )
    }

    /// Serves `func` with an `async` handler run as a task of `executor`. A call the
    /// executor refuses is answered [`RpcStatus::SVR_NOT_READY`]. A blocking call made on a
    /// thread of a thread-safe (serial) `executor` is refused: the service could not run
    /// before it returns. Only in `initialize`.
    pub fn serve_async_on<Req, Rsp, F, Fut>(
        &self,
        executor: &ExecutorRef,
        func: &str,
        handler: F,
    ) -> Result<(), Error>
    where
        Req: Message,
        Rsp: Message,
        F: Fn(RpcContext, Arc<Req>) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Rsp, RpcStatus>> + Send + 'static,
    {
        let exec = *executor;
        self.register_on::<Req, Rsp>(
            func,
            Box::new(move |ctx, req, reply| {
                let mut reply = Reply::<Rsp>::new(reply);
                // Dropped unpolled (refused, or dropped by a stopping executor).
                reply.on_drop = RpcStatus::SVR_NOT_READY;
                let fut = handler(ctx, req);
                drop(crate::co::spawn(exec, async move {
                    reply.on_drop = RpcStatus::SVR_HANDLE_FAILED;
                    reply.send(fut.await)
                }));
            }),
            Some(executor.raw()),
        )
    }

    fn register<Req: Message, Rsp: Message>(
        &self,
        func: &str,
        serve: Box<crate::ffi::rpc_call::ServeFn<Req>>,
    ) -> Result<(), Error> {
        self.register_on::<Req, Rsp>(func, serve, None)
    }

    fn register_on<Req: Message, Rsp: Message>(
        &self,
        func: &str,
        serve: Box<crate::ffi::rpc_call::ServeFn<Req>>,
        executor: Option<crate::ffi::RawExecutor>,
    ) -> Result<(), Error> {
        self.core
            .register_service(
                self.vt,
                func,
                type_support::<Req>(),
                type_support::<Rsp>(),
                RawServiceFunc::new(serve, executor),
            )
            .map_err(Error::Rpc)
    }
}

/// Registers the methods of one service (generated code's helper, AimRT's
/// `RegisterService`): every method is tried, the first failure is returned.
pub struct ServiceRegistration<'a> {
    rpc: &'a RpcRef,
    rpc_type: &'a str,
    service: &'a str,
    filters: Arc<Vec<RpcFilter>>,
    first_error: Option<Error>,
}

impl std::fmt::Debug for ServiceRegistration<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServiceRegistration")
            .field("service", &self.service)
            .field("filters", &self.filters.len())
            .finish()
    }
}

impl<'a> ServiceRegistration<'a> {
    /// Registrations of `<rpc_type>:/<service>/<method>`.
    pub fn new(rpc: &'a RpcRef, rpc_type: &'a str, service: &'a str) -> ServiceRegistration<'a> {
        ServiceRegistration {
            rpc,
            rpc_type,
            service,
            filters: Arc::new(Vec::new()),
            first_error: None,
        }
    }

    /// Puts `filters` around every method registered after this (the last one is the
    /// outermost).
    pub fn with_filters(mut self, filters: Vec<RpcFilter>) -> ServiceRegistration<'a> {
        self.filters = Arc::new(filters);
        self
    }

    fn record(&mut self, r: Result<(), Error>) {
        if let Err(e) = r {
            self.first_error.get_or_insert(e);
        }
    }

    /// [`RpcRef::serve_sync`] of `method`.
    pub fn sync<Req, Rsp, F>(&mut self, method: &str, handler: F)
    where
        Req: Message,
        Rsp: Message,
        F: Fn(&RpcContext, &Req) -> Result<Rsp, RpcStatus> + Send + Sync + 'static,
    {
        let func = full_func_name(self.rpc_type, self.service, method);
        let filters = self.filters.clone();
        let r = self
            .rpc
            .serve_sync(&func, move |ctx: &RpcContext, req: &Req| {
                if filters.is_empty() {
                    return handler(ctx, req);
                }
                let ends = filters_start(&filters, ctx, req);
                let result = handler(ctx, req);
                run_ends(ends, ctx, result.as_ref().map_err(|s| *s));
                result
            });
        self.record(r);
    }

    /// [`RpcRef::serve_then`] of `method`.
    pub fn then<Req, Rsp, F>(&mut self, method: &str, handler: F)
    where
        Req: Message,
        Rsp: Message,
        F: Fn(RpcContext, Arc<Req>, Reply<Rsp>) + Send + Sync + 'static,
    {
        let func = full_func_name(self.rpc_type, self.service, method);
        let filters = self.filters.clone();
        let r = self.rpc.serve_then(
            &func,
            move |ctx: RpcContext, req: Arc<Req>, mut reply: Reply<Rsp>| {
                if !filters.is_empty() {
                    reply.ends = filters_start(&filters, &ctx, &*req);
                    reply.ctx = Some(ctx.clone());
                }
                handler(ctx, req, reply)
            },
        );
        self.record(r);
    }

    /// [`RpcRef::serve_async`] of `method`.
    pub fn co<Req, Rsp, F, Fut>(&mut self, method: &str, handler: F)
    where
        Req: Message,
        Rsp: Message,
        F: Fn(RpcContext, Arc<Req>) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Rsp, RpcStatus>> + Send + 'static,
    {
        let func = full_func_name(self.rpc_type, self.service, method);
        let filters = self.filters.clone();
        let r = self
            .rpc
            .serve_async(&func, move |ctx: RpcContext, req: Arc<Req>| {
                let ends = if filters.is_empty() {
                    Vec::new()
                } else {
                    filters_start(&filters, &ctx, &*req)
                };
                let end_ctx = (!ends.is_empty()).then(|| ctx.clone());
                let fut = handler(ctx, req);
                async move {
                    let result = fut.await;
                    if let Some(ctx) = end_ctx {
                        run_ends(ends, &ctx, result.as_ref().map_err(|s| *s));
                    }
                    result
                }
            });
        self.record(r);
    }

    /// The first failure, if any.
    pub fn finish(self) -> Result<(), Error> {
        self.first_error.map_or(Ok(()), Err)
    }
}

/// The answer a service owes one call, given once with [`send`](Self::send), from any
/// thread. Dropped unanswered (e.g. by a panic), it answers
/// [`RpcStatus::SVR_HANDLE_FAILED`], so no caller waits for it.
pub struct Reply<Rsp: Message> {
    raw: Option<RawRpcReply>,
    meta: Vec<(String, String)>,
    on_drop: RpcStatus,
    /// Service filters' ends, run when the answer is sent, with the server context.
    ends: Vec<FilterEnd>,
    ctx: Option<RpcContext>,
    _rsp: PhantomData<fn(Rsp)>,
}

impl<Rsp: Message> std::fmt::Debug for Reply<Rsp> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Reply")
    }
}

impl<Rsp: Message> Reply<Rsp> {
    fn new(raw: RawRpcReply) -> Reply<Rsp> {
        Reply {
            raw: Some(raw),
            meta: Vec::new(),
            on_drop: RpcStatus::SVR_HANDLE_FAILED,
            ends: Vec::new(),
            ctx: None,
            _rsp: PhantomData,
        }
    }

    /// Sets a meta key of the server context to travel back; the runtime passes on only
    /// the keys it is told to (AimRT's passed-context keys).
    pub fn set_meta(&mut self, key: &str, value: &str) {
        self.meta.push((key.into(), value.into()));
    }

    /// Answers the call with the response or a status.
    pub fn send(mut self, result: Result<Rsp, RpcStatus>) {
        let Some(raw) = self.raw.take() else { return };
        if let Some(ctx) = self.ctx.take() {
            run_ends(
                std::mem::take(&mut self.ends),
                &ctx,
                result.as_ref().map_err(|s| *s),
            );
        }
        let meta = meta_of(self.meta.iter().map(|(k, v)| (k.as_str(), v.as_str())));
        match result {
            Ok(rsp) => raw.complete(
                RpcStatus::OK,
                Some(RawMessage::new(Arc::new(rsp))),
                &meta,
                "",
            ),
            Err(status) if status.is_ok() => raw.complete(
                RpcStatus::SVR_HANDLE_FAILED,
                None,
                &meta,
                "the service answered Err(OK); answer Ok(response) instead",
            ),
            Err(status) => raw.complete(status, None, &meta, ""),
        }
    }
}

impl<Rsp: Message> Drop for Reply<Rsp> {
    fn drop(&mut self) {
        if let Some(raw) = self.raw.take() {
            let why = if std::thread::panicking() {
                "the service panicked"
            } else if self.on_drop == RpcStatus::SVR_NOT_READY {
                "the service's executor did not run the call"
            } else {
                "the service dropped its reply without answering"
            };
            raw.complete(self.on_drop, None, &[], why);
        }
    }
}

/// A client function of a module (AimRT's proxies in one): call it blocking
/// ([`call`](Self::call)), as a future ([`call_async`](Self::call_async)) or with a
/// callback ([`call_then`](Self::call_then)). Cheap to clone; usable from any thread.
pub struct RpcClient<Req, Rsp> {
    rpc: RpcRef,
    func: Arc<str>,
    default_ctx: Option<Arc<RpcContext>>,
    filters: Arc<Vec<RpcFilter>>,
    _types: PhantomData<fn(Req) -> Rsp>,
}

/// A request or response as a filter sees it, whatever its type.
pub trait MessageView: Send + Sync {
    /// The type name (`pb:aimrt.protocols.example.GetFooDataReq`).
    fn type_name(&self) -> &'static str;
    /// The message as JSON, if its type has JSON.
    fn to_json(&self) -> Option<String>;
}

impl<M: Message> MessageView for M {
    fn type_name(&self) -> &'static str {
        M::type_name()
    }
    fn to_json(&self) -> Option<String> {
        self.encode("json")
            .ok()
            .map(|b| String::from_utf8_lossy(&b).into_owned())
    }
}

/// What a filter runs when the call has ended: the context and the response, or the
/// status that ended the call.
pub type FilterEnd = Box<dyn FnOnce(&RpcContext, Result<&dyn MessageView, RpcStatus>) + Send>;

/// A filter a module puts around calls (AimRT's co filters), on a client
/// ([`RpcClient::add_filter`]) or a service (the generated traits' `filters`): called with
/// the context and the request as a call starts, it returns what runs when it ends. One
/// filter serves every method, whatever its types.
///
/// ```
/// use aimrt_plugin_api::rpc::{filter, RpcFilter};
/// let time_cost: RpcFilter = filter(|_ctx, _req| {
///     let begin = std::time::Instant::now();
///     Box::new(move |_ctx, _result| {
///         tracing::info!("Client rpc time cost {} us", begin.elapsed().as_micros())
///     })
/// });
/// ```
pub type RpcFilter = Arc<dyn Fn(&RpcContext, &dyn MessageView) -> FilterEnd + Send + Sync>;

/// A filter from a closure.
pub fn filter(
    f: impl Fn(&RpcContext, &dyn MessageView) -> FilterEnd + Send + Sync + 'static,
) -> RpcFilter {
    Arc::new(f)
}

/// Runs the filters' starts, the last added (outermost) first; the ends come back
/// innermost first.
fn filters_start(filters: &[RpcFilter], ctx: &RpcContext, req: &dyn MessageView) -> Vec<FilterEnd> {
    let mut ends: Vec<FilterEnd> = filters.iter().rev().map(|f| f(ctx, req)).collect();
    ends.reverse();
    ends
}

/// Runs the ends of the filters, innermost first.
fn run_ends<Rsp: Message>(ends: Vec<FilterEnd>, ctx: &RpcContext, result: Result<&Rsp, RpcStatus>) {
    for end in ends {
        end(ctx, result.map(|r| r as &dyn MessageView));
    }
}

impl<Req, Rsp> Clone for RpcClient<Req, Rsp> {
    fn clone(&self) -> Self {
        RpcClient {
            rpc: self.rpc,
            func: self.func.clone(),
            default_ctx: self.default_ctx.clone(),
            filters: self.filters.clone(),
            _types: PhantomData,
        }
    }
}

impl<Req, Rsp> std::fmt::Debug for RpcClient<Req, Rsp> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RpcClient")
            .field("func", &self.func)
            .finish()
    }
}

impl<Req: Message, Rsp: Message> RpcClient<Req, Rsp> {
    /// The full function name.
    pub fn func_name(&self) -> &str {
        &self.func
    }

    /// Sets the context every [`new_context`](Self::new_context) starts from (AimRT's
    /// `SetDefaultContextSharedPtr`): its timeout and meta.
    pub fn set_default_context(&mut self, ctx: RpcContext) {
        self.default_ctx = Some(Arc::new(ctx));
    }

    /// A fresh client context: a copy of the default context if one was set, else empty.
    pub fn new_context(&self) -> RpcContext {
        match &self.default_ctx {
            Some(ctx) => {
                let mut c = RpcContext::client();
                c.set_timeout(ctx.timeout());
                for (k, v) in ctx.meta_pairs() {
                    c.set_meta(k, v);
                }
                c
            }
            None => RpcContext::client(),
        }
    }

    /// Adds a filter around every call of this client, in every call style (AimRT's
    /// `RegisterFilter` of a co proxy). The filter added **last is the outermost**: its
    /// start runs first and its end last, as AimRT's. Clones made before keep their
    /// filters.
    ///
    /// ```no_run
    /// # use aimrt_plugin_api::rpc::RpcClient;
    /// # #[derive(serde::Serialize, serde::Deserialize)] struct Req;
    /// # #[derive(serde::Serialize, serde::Deserialize)] struct Rsp;
    /// # aimrt_plugin_api::serde_message!(Req, "x.Req");
    /// # aimrt_plugin_api::serde_message!(Rsp, "x.Rsp");
    /// # fn demo(client: &mut RpcClient<Req, Rsp>) {
    /// client.add_filter(aimrt_plugin_api::rpc::filter(|ctx, req| {
    ///     tracing::info!("Client start new rpc call. context: {ctx}, req: {}", req.to_json().unwrap_or_default());
    ///     Box::new(|_ctx, result| {
    ///         if let Err(status) = result {
    ///             tracing::warn!("Client get rpc error ret, status: {status}");
    ///         }
    ///     })
    /// }));
    /// # }
    /// ```
    pub fn add_filter(&mut self, filter: RpcFilter) {
        Arc::make_mut(&mut self.filters).push(filter);
    }

    fn filters_start(&self, ctx: &RpcContext, req: &Req) -> Vec<FilterEnd> {
        if self.filters.is_empty() {
            return Vec::new();
        }
        filters_start(&self.filters, ctx, req)
    }

    /// A fresh client context for a call made while serving one (AimRT's
    /// `NewContextSharedPtr(parent)`): [`new_context`](Self::new_context) plus the
    /// non-empty values, in `parent`, of the keys plugins registered to pass along a chain
    /// of calls (`Registrar::add_passed_context_meta_keys`, e.g. a trace id).
    pub fn new_context_from(&self, parent: &RpcContext) -> RpcContext {
        let mut ctx = self.new_context();
        self.rpc.merge_server_context(parent, &mut ctx);
        ctx
    }

    /// Calls and blocks this thread until the answer (AimRT's sync proxy). Refused with
    /// [`RpcStatus::CLI_BACKEND_INTERNAL_ERROR`] on a thread the answer needs (the
    /// runtime's deadline thread, a backend's I/O threads).
    pub fn call(&self, ctx: &mut RpcContext, req: impl Into<Arc<Req>>) -> RpcResult<Rsp> {
        let req = req.into();
        ctx.set_meta(meta_keys::FUNCTION_NAME, &self.func);
        let ends = self.filters_start(ctx, &req);
        let slot = Arc::new(BlockSlot::default());
        let filled = slot.clone();
        self.start(ctx, req, true, move |parts| filled.fill(parts));
        let parts = slot.wait();
        let result = finish(ctx, parts);
        filters_end(ends, ctx, result)
    }

    /// Calls and returns a future of the answer (AimRT's future and co proxies). The call
    /// starts at the first poll; dropping the future early drops the answer, not the call.
    pub fn call_async<'a>(
        &'a self,
        ctx: &'a mut RpcContext,
        req: impl Into<Arc<Req>>,
    ) -> impl Future<Output = RpcResult<Rsp>> + Send + 'a {
        let req = req.into();
        async move {
            ctx.set_meta(meta_keys::FUNCTION_NAME, &self.func);
            let ends = self.filters_start(ctx, &req);
            let slot = Arc::new(Mutex::new(AsyncSlot::default()));
            let filled = slot.clone();
            self.start(ctx, req, false, move |parts| {
                let waker = {
                    let mut s = lock(&filled);
                    s.parts = Some(parts);
                    s.waker.take()
                };
                if let Some(w) = waker {
                    w.wake();
                }
            });
            let parts = WaitSlot { slot }.await;
            let result = finish(ctx, parts);
            filters_end(ends, ctx, result)
        }
    }

    /// Calls and runs `done` with the context and the answer, on whichever thread the
    /// answer arrives (AimRT's async proxy).
    pub fn call_then(
        &self,
        mut ctx: RpcContext,
        req: impl Into<Arc<Req>>,
        done: impl FnOnce(RpcContext, RpcResult<Rsp>) + Send + 'static,
    ) {
        let req = req.into();
        ctx.set_meta(meta_keys::FUNCTION_NAME, &self.func);
        let ends = self.filters_start(&ctx, &req);
        let started = self.check(&mut ctx);
        let func = self.func.clone();
        let invoke_ctx = ctx.clone();
        let finish_then = move |parts: ReplyParts| {
            let result = finish(&mut ctx, parts);
            let result = filters_end(ends, &ctx, result);
            done(ctx, result)
        };
        match started {
            Ok(()) => self.invoke(&func, &invoke_ctx, req, false, finish_then),
            Err(status) => finish_then(refused(status)),
        }
    }

    /// Checks and marks the context (every call style has written the function name
    /// into it already); the status is the refusal.
    fn check(&self, ctx: &mut RpcContext) -> Result<(), RpcStatus> {
        if ctx.kind() != RpcContextKind::Client || ctx.is_used() {
            return Err(RpcStatus::CLI_INVALID_CONTEXT);
        }
        ctx.set_used();
        Ok(())
    }

    fn start(
        &self,
        ctx: &mut RpcContext,
        req: Arc<Req>,
        blocking: bool,
        done: impl FnOnce(ReplyParts) + Send + 'static,
    ) {
        match self.check(ctx) {
            Ok(()) => self.invoke(&self.func, ctx, req, blocking, done),
            Err(status) => done(refused(status)),
        }
    }

    fn invoke(
        &self,
        func: &str,
        ctx: &RpcContext,
        req: Arc<Req>,
        blocking: bool,
        done: impl FnOnce(ReplyParts) + Send + 'static,
    ) {
        let meta = meta_of(ctx.meta_pairs());
        self.rpc.core.invoke(
            self.rpc.vt,
            func,
            &meta,
            crate::ffi::rpc_call::timeout_ns(ctx),
            RawMessage::new(req),
            type_support::<Rsp>(),
            blocking,
            RawRpcReply::new(done),
        );
    }
}

/// Runs the ends of the filters, innermost first, and passes the result on.
fn filters_end<Rsp: Message>(
    ends: Vec<FilterEnd>,
    ctx: &RpcContext,
    result: RpcResult<Rsp>,
) -> RpcResult<Rsp> {
    if !ends.is_empty() {
        run_ends(ends, ctx, result.as_deref().map_err(|s| *s));
    }
    result
}

fn refused(status: RpcStatus) -> ReplyParts {
    ReplyParts {
        status,
        rsp: None,
        meta: Vec::new(),
        detail: String::new(),
    }
}

/// Merges the reply's meta into the context and turns the response into `Rsp`.
fn finish<Rsp: Message>(ctx: &mut RpcContext, parts: ReplyParts) -> RpcResult<Rsp> {
    for (k, v) in &parts.meta {
        ctx.set_meta(k, v);
    }
    if !parts.status.is_ok() {
        return Err(parts.status);
    }
    match parts.rsp.map(RawMessage::downcast::<Rsp>) {
        Some(Ok(rsp)) => Ok(rsp),
        // The host converts to the caller's table; anything else is its defect.
        Some(Err(_)) | None => Err(RpcStatus::CLI_BACKEND_INTERNAL_ERROR),
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

#[derive(Default)]
struct BlockSlot {
    parts: Mutex<Option<ReplyParts>>,
    ready: Condvar,
}

impl BlockSlot {
    fn fill(&self, parts: ReplyParts) {
        *lock(&self.parts) = Some(parts);
        self.ready.notify_one();
    }

    fn wait(&self) -> ReplyParts {
        let mut guard = lock(&self.parts);
        loop {
            if let Some(parts) = guard.take() {
                return parts;
            }
            guard = self.ready.wait(guard).unwrap_or_else(|e| e.into_inner());
        }
    }
}

#[derive(Default)]
struct AsyncSlot {
    parts: Option<ReplyParts>,
    waker: Option<Waker>,
}

struct WaitSlot {
    slot: Arc<Mutex<AsyncSlot>>,
}

impl Future for WaitSlot {
    type Output = ReplyParts;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<ReplyParts> {
        let mut s = lock(&self.slot);
        match s.parts.take() {
            Some(parts) => Poll::Ready(parts),
            None => {
                s.waker = Some(cx.waker().clone());
                Poll::Pending
            }
        }
    }
}

thread_local! {
    /// Inline tasks woken on this thread while one of them runs: run after it, not inside
    /// it, so a future that wakes itself does not grow the stack.
    static INLINE_QUEUE: RefCell<Option<VecDeque<async_task::Runnable>>> = const { RefCell::new(None) };
}

/// Runs `future` on the calling thread until it first waits, then on whichever thread
/// wakes it (AimRT's inline scheduler for co services). A panic is contained and logged.
pub(crate) fn spawn_inline(future: impl Future<Output = ()> + Send + 'static) {
    let future = async move {
        let mut future = std::pin::pin!(future);
        std::future::poll_fn(
            |cx| match crate::panic::contain(|| future.as_mut().poll(cx)) {
                Ok(p) => p,
                Err(message) => {
                    crate::panic::log_panic("rpc service", "", &message);
                    Poll::Ready(())
                }
            },
        )
        .await
    };
    let (runnable, task) = async_task::spawn(future, run_inline);
    task.detach();
    run_inline(runnable);
}

fn run_inline(runnable: async_task::Runnable) {
    let mut runnable = Some(runnable);
    INLINE_QUEUE.with(|q| {
        let mut q = q.borrow_mut();
        match q.as_mut() {
            Some(queue) => queue.extend(runnable.take()),
            None => *q = Some(VecDeque::new()),
        }
    });
    if runnable.is_none() {
        // Queued: the outer call on this thread runs it.
        return;
    }
    let mut next = runnable;
    while let Some(r) = next {
        r.run();
        next = INLINE_QUEUE.with(|q| q.borrow_mut().as_mut().and_then(VecDeque::pop_front));
    }
    INLINE_QUEUE.with(|q| *q.borrow_mut() = None);
}
