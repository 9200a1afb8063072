//! Services and RPC backends across the ABI: a service is one function (bytes in a named
//! format in, bytes out) registered under its full function name; a backend (e.g. HTTP)
//! receives requests from outside and invokes services through the host.
//!
//! Every call ends in exactly one [`Completion`], which may run on any thread.

use std::ffi::c_void;
use std::sync::Arc;

use super::{contain, BytesView, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::rpc::{BackendOptions, HostServices, Responder, RpcBackend, ServiceError, ServiceHost};

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
}

// ---- the completion ----------------------------------------------------------------------

type Done = Box<dyn FnOnce(Result<Vec<u8>, ServiceError>) + Send>;

impl Completion {
    /// A completion that calls `done` with the copied response.
    pub(crate) fn new(done: Done) -> Completion {
        unsafe extern "C" fn complete(ctx: *mut c_void, status: Status, response: BytesView) {
            // SAFETY: `ctx` is the `Box<Done>` of `Completion::new`, completed exactly once
            // (completion contract); the view is valid for this call.
            let (done, bytes) = unsafe {
                (
                    Box::from_raw(ctx.cast::<Done>()),
                    response.as_bytes().to_vec(),
                )
            };
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
            complete,
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
    };

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

    pub(crate) fn invoke(&self, func_name: &str, format: &str, request: &[u8], done: Done) {
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
}

impl<B: RpcBackend> BackendObj<B> {
    const VTABLE: RpcBackendVtable = RpcBackendVtable {
        header: Header::of::<RpcBackendVtable>(),
        type_name: Self::type_name,
        init: Self::init,
        start: Self::start,
        shutdown: Self::shutdown,
        drop: Self::drop,
    };

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
        report(err, contain(|| this.backend.init(&options, host)))
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

    /// Starts serving (host use).
    pub fn start(&self) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; the sink outlives the call.
        let status = unsafe { (self.vt().start)(self.obj, slot.sink()) };
        slot.result(status)
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
