//! Services and RPC backends across the ABI: a service is one function (bytes in a named
//! format in, bytes out) registered under its full function name; a backend (e.g. HTTP)
//! receives requests from outside and invokes services through the host.
//!
//! Every call ends in exactly one [`Completion`], which may run on any thread.

use std::ffi::c_void;
use std::sync::Arc;

use super::executor::RawExecutor;
use super::pubsub::{meta_of, MetaView};
use super::{contain, BytesView, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::rpc::{
    BackendAnswer, BackendCall, BackendOptions, BackendReply, CallView, HostServices, Responder,
    RpcBackend, RpcStatus, ServiceError, ServiceHost,
};

/// Completion of a service call: called exactly once, from any thread, with the response.
#[repr(C)]
pub struct Completion {
    /// The caller's context.
    pub ctx: *mut c_void,
    /// `status` OK with the response bytes, or an error status with a message in `response`.
    pub complete: unsafe extern "C" fn(ctx: *mut c_void, status: Status, response: BytesView),
}

/// A service method registered by a plugin.
#[repr(C)]
pub struct RawService {
    /// The operations.
    pub vtable: *const ServiceVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: service objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawService {}
// SAFETY: see `Send`.
unsafe impl Sync for RawService {}

/// Service operations.
#[repr(C)]
pub struct ServiceVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Handles one request in `format` (e.g. `json`); calls `completion` exactly once.
    pub call: unsafe extern "C" fn(
        obj: *const c_void,
        format: StrView,
        request: BytesView,
        completion: Completion,
    ),
    /// Frees the service.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
}

/// The host as seen by a backend: invoke a registered service by function name.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawHost {
    /// The operations.
    pub vtable: *const HostVtable,
    /// The host's object.
    pub obj: *const c_void,
}

// SAFETY: host objects are `Send + Sync` and never freed (exported by `leak`).
unsafe impl Send for RawHost {}
// SAFETY: see `Send`.
unsafe impl Sync for RawHost {}

/// Host operations for backends.
#[repr(C)]
pub struct HostVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Invokes the service registered as `func_name`; `completion` is called exactly once
    /// (also when the status returned is not OK).
    pub invoke: unsafe extern "C" fn(
        obj: *const c_void,
        func_name: StrView,
        format: StrView,
        request: BytesView,
        completion: Completion,
    ) -> Status,
    /// (1.2) Hands a call the backend received to the runtime (a module service or a
    /// plugin service); `reply` is completed exactly once.
    pub call:
        unsafe extern "C" fn(obj: *const c_void, call: RawBackendCall, reply: RawBackendReply),
    /// (1.2) Looks up an executor by name (e.g. a backend's `timeout_executor`);
    /// `NOT_FOUND` if there is none.
    pub executor:
        unsafe extern "C" fn(obj: *const c_void, name: StrView, out: *mut RawExecutor) -> Status,
}

/// One call between the runtime and a backend, borrowed for the call (ABI 1.2).
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawBackendCall {
    /// The full function name.
    pub func: StrView,
    /// The meta pairs (`aimrt-serialization_type` among them).
    pub meta: MetaView,
    /// The time left for the answer in nanoseconds; 0: none given.
    pub timeout_ns: u64,
    /// The request in the serialization type.
    pub body: BytesView,
}

impl RawBackendCall {
    /// A copy as a [`BackendCall`].
    ///
    /// # Safety
    /// The views must be readable for the call.
    pub unsafe fn to_call(self) -> BackendCall {
        // SAFETY: per the caller's guarantee.
        unsafe {
            BackendCall::from_abi(
                self.func.to_string_lossy(),
                self.meta.pairs(),
                self.timeout(),
                self.body.as_bytes().to_vec(),
            )
        }
    }

    /// The time left for the answer; `None` when none was given (0).
    fn timeout(&self) -> Option<std::time::Duration> {
        (self.timeout_ns > 0).then(|| std::time::Duration::from_nanos(self.timeout_ns))
    }

    /// Views of `call`, valid while what it borrows is.
    pub fn of(call: &CallView<'_>) -> RawBackendCall {
        RawBackendCall {
            func: StrView::new(call.func),
            meta: MetaView::new(call.meta),
            timeout_ns: call.timeout.map_or(0, |t| {
                u64::try_from(t.as_nanos()).unwrap_or(u64::MAX).max(1)
            }),
            body: StrView {
                ptr: call.body.as_ptr(),
                len: call.body.len(),
            },
        }
    }
}

/// The answer to a [`RawBackendCall`]: `complete` is called exactly once, from any thread
/// (ABI 1.2).
#[repr(C)]
pub struct RawBackendReply {
    /// The caller's state.
    pub ctx: *mut c_void,
    /// `status`: an AimRT code; `body`: the response (empty unless 0); `meta`: pairs for
    /// the caller; `detail`: why it failed, or empty. All borrowed for the call.
    pub complete: unsafe extern "C" fn(
        ctx: *mut c_void,
        status: u32,
        body: BytesView,
        meta: MetaView,
        detail: StrView,
    ),
}

// SAFETY: the reply contract allows completing from any thread.
unsafe impl Send for RawBackendReply {}

impl RawBackendReply {
    /// A reply that calls `done` with a copy of the answer (one allocation).
    pub fn new<F: FnOnce(BackendAnswer) + Send + 'static>(done: F) -> RawBackendReply {
        unsafe extern "C" fn complete<F: FnOnce(BackendAnswer) + Send + 'static>(
            ctx: *mut c_void,
            status: u32,
            body: BytesView,
            meta: MetaView,
            detail: StrView,
        ) {
            // SAFETY: `ctx` is the `Box<F>` of `new::<F>` (this function is its `complete`),
            // completed exactly once (reply contract); the views are valid for this call.
            let (done, answer) = unsafe {
                (
                    Box::from_raw(ctx.cast::<F>()),
                    BackendAnswer {
                        status: RpcStatus::from_code(status),
                        body: body.as_bytes().to_vec(),
                        meta: meta
                            .pairs()
                            .iter()
                            .map(|p| (p.key().to_owned(), p.value().to_owned()))
                            .collect(),
                        detail: detail.to_string_lossy(),
                    },
                )
            };
            let _ = contain(move || done(answer));
        }
        RawBackendReply {
            ctx: Box::into_raw(Box::new(done)).cast(),
            complete: complete::<F>,
        }
    }

    /// Completes the reply with `answer`, consuming it.
    pub fn complete(self, answer: &BackendAnswer) {
        let meta = meta_of(answer.meta.iter().map(|(k, v)| (k.as_str(), v.as_str())));
        // SAFETY: consumed here, so completed once; the views outlive the call.
        unsafe {
            (self.complete)(
                self.ctx,
                answer.status.code(),
                StrView {
                    ptr: answer.body.as_ptr(),
                    len: answer.body.len(),
                },
                MetaView::new(&meta),
                StrView::new(&answer.detail),
            )
        }
    }
}

/// An RPC backend (e.g. HTTP) contributed by a plugin.
#[repr(C)]
pub struct RawRpcBackend {
    /// The operations.
    pub vtable: *const RpcBackendVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: backend objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawRpcBackend {}
// SAFETY: see `Send`.
unsafe impl Sync for RawRpcBackend {}

/// RPC backend operations.
#[repr(C)]
pub struct RpcBackendVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The backend type the config names (`backends: [{type: http}]`).
    pub type_name: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// Reads its options; may keep `host` to invoke services.
    pub init: unsafe extern "C" fn(
        obj: *const c_void,
        options_json: StrView,
        location: StrView,
        host: RawHost,
        err: ErrorSink,
    ) -> Status,
    /// Starts serving.
    pub start: unsafe extern "C" fn(obj: *const c_void, err: ErrorSink) -> Status,
    /// Stops serving.
    pub shutdown: unsafe extern "C" fn(obj: *const c_void),
    /// Frees the backend.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
    /// (1.2) A module serves `func` through this backend (called during module
    /// initialize, for each function its `servers_options` rule routes here).
    pub register_service_func:
        unsafe extern "C" fn(obj: *const c_void, func: StrView, err: ErrorSink) -> Status,
    /// (1.2) A module calls `func` through this backend (as above, `clients_options`).
    pub register_client_func:
        unsafe extern "C" fn(obj: *const c_void, func: StrView, err: ErrorSink) -> Status,
    /// (1.2) Carries a module's client call; `reply` is completed exactly once.
    pub invoke:
        unsafe extern "C" fn(obj: *const c_void, call: RawBackendCall, reply: RawBackendReply),
    /// (1.8) Writes to `out` the options as `init` read them, defaults filled in (JSON),
    /// if the backend reported them (`--dump_cfg_file`).
    pub reported_options: unsafe extern "C" fn(obj: *const c_void, out: ErrorSink),
}

// ---- the completion ----------------------------------------------------------------------

impl Completion {
    /// A completion that calls `done` with the copied response (one allocation).
    pub(crate) fn new<F>(done: F) -> Completion
    where
        F: FnOnce(Result<Vec<u8>, ServiceError>) + Send + 'static,
    {
        unsafe extern "C" fn complete<F>(ctx: *mut c_void, status: Status, response: BytesView)
        where
            F: FnOnce(Result<Vec<u8>, ServiceError>) + Send + 'static,
        {
            // SAFETY: `ctx` is the `Box<F>` of `Completion::new::<F>` (this function is its
            // `complete`), completed exactly once (completion contract); the view is valid
            // for this call.
            let (done, bytes) =
                unsafe { (Box::from_raw(ctx.cast::<F>()), response.as_bytes().to_vec()) };
            let result = if status.is_ok() {
                Ok(bytes)
            } else {
                Err(ServiceError::from_status(
                    status,
                    String::from_utf8_lossy(&bytes).into_owned(),
                ))
            };
            let _ = contain(move || done(result));
        }
        Completion {
            ctx: Box::into_raw(Box::new(done)).cast(),
            complete: complete::<F>,
        }
    }

    /// Completes with `result`, consuming the completion.
    pub(crate) fn complete(self, result: Result<&[u8], &ServiceError>) {
        let status;
        let text: String;
        let view = match result {
            Ok(bytes) => {
                status = Status::OK;
                StrView {
                    ptr: bytes.as_ptr(),
                    len: bytes.len(),
                }
            }
            Err(e) => {
                status = e.status();
                text = e.message().to_owned();
                StrView::new(&text)
            }
        };
        // SAFETY: a `Completion` is only built by `Completion::new` or handed over by a
        // caller honouring the same contract; it is consumed here, so it runs once.
        unsafe { (self.complete)(self.ctx, status, view) }
    }
}

// ---- services ----------------------------------------------------------------------------

type Handler = dyn Fn(&str, &[u8]) -> Result<Vec<u8>, ServiceError> + Send + Sync;

struct ServiceObj {
    handler: Box<Handler>,
}

impl ServiceObj {
    const VTABLE: ServiceVtable = ServiceVtable {
        header: Header::of::<ServiceVtable>(),
        call: Self::call,
        drop: Self::drop,
    };

    unsafe extern "C" fn call(
        obj: *const c_void,
        format: StrView,
        request: BytesView,
        completion: Completion,
    ) {
        // SAFETY: a live `ServiceObj` (vtable contract).
        let this = unsafe { &*obj.cast::<ServiceObj>() };
        // SAFETY: the views are valid for this call.
        let (format, request) = unsafe { (format.to_string_lossy(), request.as_bytes()) };
        let responder = Responder::new(completion);
        match contain(|| (this.handler)(&format, request)) {
            Ok(result) => responder.respond(result),
            Err(panic) => responder.respond(Err(ServiceError::Failed(format!(
                "the service panicked: {panic}"
            )))),
        }
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<ServiceObj>()) };
        let _ = contain(move || std::mem::drop(b));
    }
}

impl RawService {
    pub(crate) fn new<F>(handler: F) -> RawService
    where
        F: Fn(&str, &[u8]) -> Result<Vec<u8>, ServiceError> + Send + Sync + 'static,
    {
        RawService {
            vtable: &ServiceObj::VTABLE,
            obj: Box::into_raw(Box::new(ServiceObj {
                handler: Box::new(handler),
            }))
            .cast_const()
            .cast(),
        }
    }

    /// Calls the service (host use); `responder` is completed exactly once.
    pub fn call(&self, format: &str, request: &[u8], responder: Responder) {
        let completion = responder.into_completion();
        // SAFETY: a live service (owned by the host, never freed while callable); the
        // views outlive the call; the completion passes to the callee.
        unsafe {
            ((*self.vtable).call)(
                self.obj,
                StrView::new(format),
                StrView {
                    ptr: request.as_ptr(),
                    len: request.len(),
                },
                completion,
            );
        }
    }
}

impl Drop for RawService {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { ((*self.vtable).drop)(self.obj) }
    }
}

// ---- the host ----------------------------------------------------------------------------

struct ExportHost<T>(T);

impl<T: HostServices> ExportHost<T> {
    const VTABLE: HostVtable = HostVtable {
        header: Header::of::<HostVtable>(),
        invoke: Self::invoke,
        call: Self::call,
        executor: Self::executor,
    };

    unsafe extern "C" fn call(obj: *const c_void, call: RawBackendCall, reply: RawBackendReply) {
        // SAFETY: `obj` is the leaked `Arc<T>` of `RawHost::leak::<T>`; the views are
        // valid for this call.
        let this = unsafe { &*obj.cast::<T>() };
        // SAFETY: as above.
        let func = unsafe { call.func.to_str_lossy() };
        // SAFETY: as above.
        let (meta, body) = unsafe { (call.meta.pairs(), call.body.as_bytes()) };
        let reply = BackendReply::new(reply);
        // A panic drops the reply, which answers it.
        let view = CallView::new(&func, meta, call.timeout(), body);
        let _ = contain(|| this.call_view(view, reply));
    }

    unsafe extern "C" fn executor(
        obj: *const c_void,
        name: StrView,
        out: *mut RawExecutor,
    ) -> Status {
        // SAFETY: as in `call`.
        let (this, name) = unsafe { (&*obj.cast::<T>(), name.to_string_lossy()) };
        match contain(|| this.executor(&name)) {
            Ok(Some(e)) => {
                // SAFETY: `out` is writable (vtable contract).
                unsafe { out.write(e) };
                Status::OK
            }
            Ok(None) => Status::NOT_FOUND,
            Err(_) => Status::FAILED,
        }
    }

    unsafe extern "C" fn invoke(
        obj: *const c_void,
        func_name: StrView,
        format: StrView,
        request: BytesView,
        completion: Completion,
    ) -> Status {
        // SAFETY: `obj` is the leaked `Arc<T>` of `RawHost::leak::<T>`.
        let this = unsafe { &*obj.cast::<T>() };
        // SAFETY: the views are valid for this call.
        let (func, format, request) = unsafe {
            (
                func_name.to_string_lossy(),
                format.to_string_lossy(),
                request.as_bytes(),
            )
        };
        let responder = Responder::new(completion);
        // A panic drops the responder, which completes it with an error.
        match contain(|| this.invoke(&func, &format, request, responder)) {
            Ok(()) => Status::OK,
            Err(_) => Status::FAILED,
        }
    }
}

impl RawHost {
    /// Exports the host's service table; leaked, as backends keep it for the process's life.
    pub fn leak<T: HostServices>(t: Arc<T>) -> RawHost {
        RawHost {
            vtable: &ExportHost::<T>::VTABLE,
            obj: Arc::into_raw(t).cast(),
        }
    }

    fn vt(&self) -> &HostVtable {
        // SAFETY: host tables are static data of the never-unloaded host.
        unsafe { &*self.vtable }
    }

    /// Whether the host has the 1.2 entries (`call`, `executor`).
    fn has_calls(&self) -> bool {
        self.vt().header.has(size_of::<HostVtable>())
    }

    pub(crate) fn call_view(
        &self,
        view: CallView<'_>,
        done: impl FnOnce(BackendAnswer) + Send + 'static,
    ) {
        if !self.has_calls() {
            return done(BackendAnswer::fail(
                RpcStatus::SVR_NOT_READY,
                "this aimrt_main predates module RPC (ABI 1.2)",
            ));
        }
        // SAFETY: a live host with the entry; the views outlive the call; the reply passes
        // to the callee, which completes it exactly once.
        unsafe {
            (self.vt().call)(
                self.obj,
                RawBackendCall::of(&view),
                RawBackendReply::new(done),
            )
        }
    }

    pub(crate) fn executor(&self, name: &str) -> Option<RawExecutor> {
        if !self.has_calls() {
            return None;
        }
        let mut out = RawExecutor::null();
        // SAFETY: a live host with the entry; `out` is writable.
        let status = unsafe { (self.vt().executor)(self.obj, StrView::new(name), &mut out) };
        (status.is_ok() && !out.is_null()).then_some(out)
    }

    pub(crate) fn invoke(
        &self,
        func_name: &str,
        format: &str,
        request: &[u8],
        done: impl FnOnce(Result<Vec<u8>, ServiceError>) + Send + 'static,
    ) {
        let completion = Completion::new(done);
        // SAFETY: host handles come from `leak` and live forever; the views outlive the
        // call; the completion passes to the callee, which completes it exactly once.
        unsafe {
            ((*self.vtable).invoke)(
                self.obj,
                StrView::new(func_name),
                StrView::new(format),
                StrView {
                    ptr: request.as_ptr(),
                    len: request.len(),
                },
                completion,
            );
        }
    }
}

// ---- backends ----------------------------------------------------------------------------

struct BackendObj<B> {
    type_name: String,
    backend: B,
    /// The options `init` reported as it read them.
    reported: std::sync::Mutex<Option<String>>,
}

impl<B: RpcBackend> BackendObj<B> {
    const VTABLE: RpcBackendVtable = RpcBackendVtable {
        header: Header::of::<RpcBackendVtable>(),
        type_name: Self::type_name,
        init: Self::init,
        start: Self::start,
        shutdown: Self::shutdown,
        drop: Self::drop,
        register_service_func: Self::register_service_func,
        register_client_func: Self::register_client_func,
        invoke: Self::invoke,
        reported_options: Self::reported_options,
    };

    unsafe extern "C" fn reported_options(obj: *const c_void, out: ErrorSink) {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        super::hand_back(&this.reported, out);
    }

    unsafe extern "C" fn register_service_func(
        obj: *const c_void,
        func: StrView,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object; the view is valid for this call.
        let (this, func) = unsafe { (Self::get(obj), func.to_string_lossy()) };
        report(err, contain(|| this.backend.register_service_func(&func)))
    }

    unsafe extern "C" fn register_client_func(
        obj: *const c_void,
        func: StrView,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object; the view is valid for this call.
        let (this, func) = unsafe { (Self::get(obj), func.to_string_lossy()) };
        report(err, contain(|| this.backend.register_client_func(&func)))
    }

    unsafe extern "C" fn invoke(obj: *const c_void, call: RawBackendCall, reply: RawBackendReply) {
        // SAFETY: live object; the views are valid for this call.
        let (this, call) = unsafe { (Self::get(obj), call.to_call()) };
        let reply = BackendReply::new(reply);
        // A panic drops the reply, which answers it.
        let _ = contain(|| this.backend.invoke(call, reply));
    }

    /// # Safety
    /// `obj` comes from `RawRpcBackend::new::<B>` and was not dropped.
    unsafe fn get<'a>(obj: *const c_void) -> &'a BackendObj<B> {
        // SAFETY: per the contract.
        unsafe { &*obj.cast::<BackendObj<B>>() }
    }

    unsafe extern "C" fn type_name(obj: *const c_void) -> StrView {
        // SAFETY: live object (vtable contract).
        StrView::new(&unsafe { Self::get(obj) }.type_name)
    }

    unsafe extern "C" fn init(
        obj: *const c_void,
        options_json: StrView,
        location: StrView,
        host: RawHost,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        // SAFETY: views valid for this call.
        let options = unsafe {
            BackendOptions::new(
                format!("rpc backend '{}'", this.type_name),
                options_json.to_string_lossy(),
                location.to_string_lossy(),
            )
        };
        let host = ServiceHost::from_raw(host);
        let (result, reported) =
            super::init_reporting(|| contain(|| this.backend.init(&options, host)));
        *this.reported.lock().unwrap_or_else(|e| e.into_inner()) = reported;
        report(err, result)
    }

    unsafe extern "C" fn start(obj: *const c_void, err: ErrorSink) -> Status {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        report(err, contain(|| this.backend.start()))
    }

    unsafe extern "C" fn shutdown(obj: *const c_void) {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        if let Err(panic) = contain(|| this.backend.shutdown()) {
            tracing::error!(target: "aimrt", "rpc backend '{}' panicked in shutdown: {panic}", this.type_name);
        }
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<BackendObj<B>>()) };
        let _ = contain(move || std::mem::drop(b));
    }
}

pub(crate) fn report(err: ErrorSink, r: Result<Result<(), crate::Error>, String>) -> Status {
    match r {
        Ok(Ok(())) => Status::OK,
        Ok(Err(e)) => {
            err.report(&e.to_string());
            Status::INVALID
        }
        Err(panic) => {
            err.report(&format!("panicked: {panic}"));
            Status::FAILED
        }
    }
}

impl RawRpcBackend {
    pub(crate) fn new<B: RpcBackend>(backend: B) -> RawRpcBackend {
        let obj = Box::new(BackendObj {
            type_name: backend.type_name().to_owned(),
            backend,
            reported: Default::default(),
        });
        RawRpcBackend {
            vtable: &BackendObj::<B>::VTABLE,
            obj: Box::into_raw(obj).cast_const().cast(),
        }
    }

    fn vt(&self) -> &RpcBackendVtable {
        // SAFETY: the vtable is `'static` (its library is never unloaded).
        unsafe { &*self.vtable }
    }

    /// The backend type (host use).
    pub fn type_name(&self) -> String {
        // SAFETY: live object; view copied at once.
        unsafe { (self.vt().type_name)(self.obj).to_string_lossy() }
    }

    /// Hands the backend its options and the host (host use).
    pub fn init(&self, options_json: &str, location: &str, host: RawHost) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; views and the sink outlive the call.
        let status = unsafe {
            (self.vt().init)(
                self.obj,
                StrView::new(options_json),
                StrView::new(location),
                host,
                slot.sink(),
            )
        };
        slot.result(status)
    }

    /// The options as the backend's `init` read them (JSON), if it reported them (host use;
    /// a table older than 1.8 has no entry for it).
    pub fn reported_options(&self) -> Option<String> {
        if !self.vt().header.has(size_of::<RpcBackendVtable>()) {
            return None;
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; the sink outlives the call.
        unsafe { (self.vt().reported_options)(self.obj, slot.sink()) };
        slot.taken()
    }

    /// Starts serving (host use).
    pub fn start(&self) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; the sink outlives the call.
        let status = unsafe { (self.vt().start)(self.obj, slot.sink()) };
        slot.result(status)
    }

    /// Whether its table has the 1.2 entries (module functions and client calls).
    pub fn carries_module_calls(&self) -> bool {
        // `invoke`, the last 1.2 entry, ends where 1.8's first begins.
        self.vt()
            .header
            .has(std::mem::offset_of!(RpcBackendVtable, reported_options))
    }

    /// Tells the backend a module serves `func` through it (host use).
    pub fn register_service_func(&self, func: &str) -> Result<(), String> {
        if !self.carries_module_calls() {
            return Err(format!(
                "rpc backend '{}' predates module RPC (ABI 1.2); rebuild its plugin",
                self.type_name()
            ));
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: live object with the entry; the view and the sink outlive the call.
        let status =
            unsafe { (self.vt().register_service_func)(self.obj, StrView::new(func), slot.sink()) };
        slot.result(status)
    }

    /// Tells the backend a module calls `func` through it (host use).
    pub fn register_client_func(&self, func: &str) -> Result<(), String> {
        if !self.carries_module_calls() {
            return Err(format!(
                "rpc backend '{}' predates module RPC (ABI 1.2); rebuild its plugin",
                self.type_name()
            ));
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: live object with the entry; the view and the sink outlive the call.
        let status =
            unsafe { (self.vt().register_client_func)(self.obj, StrView::new(func), slot.sink()) };
        slot.result(status)
    }

    /// Hands the backend a client call; `done` runs exactly once (host use).
    pub fn invoke(&self, call: CallView<'_>, done: impl FnOnce(BackendAnswer) + Send + 'static) {
        if !self.carries_module_calls() {
            return done(BackendAnswer::fail(
                RpcStatus::CLI_BACKEND_INTERNAL_ERROR,
                format!(
                    "rpc backend '{}' predates module RPC (ABI 1.2)",
                    self.type_name()
                ),
            ));
        }
        // SAFETY: live object with the entry; the views outlive the call; the reply
        // passes to the backend, which completes it exactly once.
        unsafe {
            (self.vt().invoke)(
                self.obj,
                RawBackendCall::of(&call),
                RawBackendReply::new(done),
            )
        }
    }

    /// Stops serving (host use).
    pub fn shutdown(&self) {
        // SAFETY: live object.
        unsafe { (self.vt().shutdown)(self.obj) }
    }
}

impl Drop for RawRpcBackend {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { (self.vt().drop)(self.obj) }
    }
}

#[cfg(test)]
mod reported_options_tests {
    use super::*;
    use crate::rpc::RpcBackend;

    #[derive(serde::Deserialize, serde::Serialize)]
    #[serde(deny_unknown_fields)]
    struct Opts {
        #[serde(default)]
        timeout_executor: String,
    }

    struct Reads;

    impl RpcBackend for Reads {
        fn type_name(&self) -> &str {
            "reads"
        }
        fn init(&self, options: &BackendOptions, _: ServiceHost) -> Result<(), crate::Error> {
            options.read::<Opts>().map(drop)
        }
        fn start(&self) -> Result<(), crate::Error> {
            Ok(())
        }
        fn shutdown(&self) {}
    }

    /// Answers nothing: the backend never calls it.
    struct NoServices;

    impl HostServices for NoServices {
        fn invoke(&self, _: &str, _: &str, _: &[u8], _: crate::Responder) {}
    }

    #[test]
    fn an_rpc_backend_reports_its_options_as_read_and_a_table_of_1_7_still_carries_calls() {
        let raw = RawRpcBackend::new(Reads);
        let host = RawHost::leak(Arc::new(NoServices));
        raw.init(r#"{"timeout_executor": "t"}"#, "cfg.yaml:5:9", host)
            .unwrap();
        assert!(raw.carries_module_calls());
        assert_eq!(
            raw.reported_options().as_deref(),
            Some(r#"{"timeout_executor":"t"}"#)
        );
        static TABLE_1_7: RpcBackendVtable = RpcBackendVtable {
            header: Header {
                size: std::mem::offset_of!(RpcBackendVtable, reported_options) as u32,
                abi_minor: 7,
            },
            ..BackendObj::<Reads>::VTABLE
        };
        let old = RawRpcBackend {
            vtable: &TABLE_1_7,
            obj: raw.obj,
        };
        assert!(old.carries_module_calls());
        assert_eq!(old.reported_options(), None);
        std::mem::forget(old);
    }
}
