//! Services and RPC backends, the subset AimRT uses to serve a plugin's control service
//! over HTTP.
//!
//! A **service** is one function registered under its full function name, AimRT style
//! (`pb:/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService/Pause`): it takes
//! a request in a named format (`json`) and answers bytes in the same format. A **backend**
//! (e.g. `http` from `net_plugin`) carries requests from outside and invokes services
//! through the [`ServiceHost`]; the runtime decides which functions a backend may reach
//! (`aimrt.rpc.servers_options`).
//!
//! ```
//! use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar, ServiceError};
//!
//! struct Echo;
//! impl Plugin for Echo {
//!     fn name(&self) -> &str { "echo_plugin" }
//!     fn initialize(&mut self, registrar: &mut Registrar<'_>, _: &PluginOptions) -> Result<(), Error> {
//!         registrar.register_service("pb:/example.EchoService/Echo", |format, request| {
//!             if format != "json" {
//!                 return Err(ServiceError::UnsupportedFormat(format.to_owned()));
//!             }
//!             Ok(request.to_vec())
//!         })
//!     }
//! }
//! ```

mod api;
mod backend;
mod call_filter;
mod context;
mod status;

pub use api::{
    filter, full_func_name, FilterEnd, MessageView, Reply, RpcClient, RpcFilter, RpcRef, RpcResult,
    ServiceRegistration,
};
pub use backend::{BackendAnswer, BackendCall, BackendReply, CallView};
pub use call_filter::{CallFilter, CallFilterSide, CallNext, FilterCall, ReplyView};
pub use context::{meta_keys, RpcContext, RpcContextKind};
pub use status::RpcStatus;

use crate::ffi::{Completion, RawHost};

/// Why a service call failed. Backends map it to their protocol (HTTP: 400, 404, 415,
/// 500).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ServiceError {
    /// The request is malformed: bad syntax, a missing or mistyped field.
    #[error("bad request: {0}")]
    BadRequest(String),
    /// No such function, or it is not enabled for the calling backend.
    #[error("not found: {0}")]
    NotFound(String),
    /// The service does not speak the request's format.
    #[error("unsupported format: {0}")]
    UnsupportedFormat(String),
    /// The service failed (or panicked) while handling a valid request.
    #[error("failed: {0}")]
    Failed(String),
}

impl ServiceError {
    /// The message without the kind.
    pub fn message(&self) -> &str {
        match self {
            ServiceError::BadRequest(m)
            | ServiceError::NotFound(m)
            | ServiceError::UnsupportedFormat(m)
            | ServiceError::Failed(m) => m,
        }
    }

    pub(crate) fn status(&self) -> crate::ffi::Status {
        use crate::ffi::Status;
        match self {
            ServiceError::BadRequest(_) => Status::INVALID,
            ServiceError::NotFound(_) => Status::NOT_FOUND,
            ServiceError::UnsupportedFormat(_) => Status::UNSUPPORTED,
            ServiceError::Failed(_) => Status::FAILED,
        }
    }

    /// The AimRT status a backend reports for it: `BadRequest` 1007, `NotFound` 1003,
    /// `UnsupportedFormat` 1004, `Failed` 1008.
    pub fn rpc_status(&self) -> RpcStatus {
        match self {
            ServiceError::BadRequest(_) => RpcStatus::SVR_DESERIALIZATION_FAILED,
            ServiceError::NotFound(_) => RpcStatus::SVR_NOT_FOUND,
            ServiceError::UnsupportedFormat(_) => RpcStatus::SVR_INVALID_SERIALIZATION_TYPE,
            ServiceError::Failed(_) => RpcStatus::SVR_HANDLE_FAILED,
        }
    }

    pub(crate) fn from_status(status: crate::ffi::Status, message: String) -> ServiceError {
        use crate::ffi::Status;
        match status {
            Status::INVALID => ServiceError::BadRequest(message),
            Status::NOT_FOUND => ServiceError::NotFound(message),
            Status::UNSUPPORTED => ServiceError::UnsupportedFormat(message),
            _ => ServiceError::Failed(message),
        }
    }
}

/// The options of a plugin whose one option is AimRT's `service_name`, which replaces the
/// service part of its function names when not empty (`time_manipulator_plugin`,
/// `log_control_plugin`, `parameter_plugin`). An unknown key is an error.
///
/// ```
/// use aimrt_plugin_api::rpc::ServiceOptions;
///
/// let o: ServiceOptions = serde_json::from_str(r#"{"service_name": ""}"#).unwrap();
/// assert_eq!(o.service("aimrt.protocols.x.XService"), "aimrt.protocols.x.XService");
/// let o: ServiceOptions = serde_json::from_str(r#"{"service_name": "mine.Svc"}"#).unwrap();
/// assert_eq!(o.service("aimrt.protocols.x.XService"), "mine.Svc");
/// ```
#[derive(Debug, Default, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ServiceOptions {
    /// The service name to register under; empty: the plugin's default (AimRT's).
    #[serde(default)]
    pub service_name: String,
}

impl ServiceOptions {
    /// `service_name`, or `default` when it is empty.
    pub fn service<'a>(&'a self, default: &'a str) -> &'a str {
        if self.service_name.is_empty() {
            default
        } else {
            &self.service_name
        }
    }
}

/// Serves one call of a plugin's service whose request and response are [`Message`]s
/// (generated from a `.proto` file): decodes the request in the call's `format` (`pb` or
/// `json`), answers it with `f`, and encodes the answer in the same format. A request that
/// does not decode is a bad request (HTTP 400), a format the types lack is unsupported
/// (HTTP 415).
///
/// ```
/// use aimrt_plugin_api::rpc::serve_message;
///
/// #[derive(serde::Serialize, serde::Deserialize)]
/// struct Hello { name: String }
/// aimrt_plugin_api::serde_message!(Hello, "example.Hello");
///
/// let answer = serve_message("json", br#"{"name":"robot"}"#, |req: Hello| Hello {
///     name: format!("hello, {}", req.name),
/// });
/// assert_eq!(answer.unwrap(), br#"{"name":"hello, robot"}"#);
/// assert!(serve_message("json", b"{", |req: Hello| req).is_err());
/// ```
///
/// [`Message`]: crate::channel::Message
pub fn serve_message<Req, Rsp>(
    format: &str,
    request: &[u8],
    f: impl FnOnce(Req) -> Rsp,
) -> Result<Vec<u8>, ServiceError>
where
    Req: crate::channel::Message,
    Rsp: crate::channel::Message,
{
    use crate::channel::MessageError;
    let req = Req::decode(format, request).map_err(|e| match e {
        MessageError::UnsupportedFormat { .. } => ServiceError::UnsupportedFormat(e.to_string()),
        other => ServiceError::BadRequest(other.to_string()),
    })?;
    f(req)
        .encode(format)
        .map_err(|e| ServiceError::Failed(e.to_string()))
}

/// The answer to one service call, owed exactly once. Dropping it unanswered answers
/// `Failed`, so a caller never waits forever.
pub struct Responder {
    completion: Option<Completion>,
}

// SAFETY: the completion contract allows completing from any thread.
unsafe impl Send for Responder {}

impl std::fmt::Debug for Responder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Responder")
    }
}

impl Responder {
    pub(crate) fn new(completion: Completion) -> Responder {
        Responder {
            completion: Some(completion),
        }
    }

    /// A responder that calls `done` (for hosts and tests).
    pub fn from_fn(done: impl FnOnce(Result<Vec<u8>, ServiceError>) + Send + 'static) -> Responder {
        Responder::new(Completion::new(done))
    }

    /// Answers the call.
    pub fn respond(mut self, result: Result<Vec<u8>, ServiceError>) {
        if let Some(c) = self.completion.take() {
            c.complete(result.as_deref());
        }
    }

    pub(crate) fn into_completion(mut self) -> Completion {
        self.completion
            .take()
            .expect("a responder holds its completion until answered")
    }
}

impl Drop for Responder {
    fn drop(&mut self) {
        if let Some(c) = self.completion.take() {
            c.complete(Err(&ServiceError::Failed(
                "the call was dropped without an answer".into(),
            )));
        }
    }
}

/// What the runtime implements behind the host handle it gives backends.
pub trait HostServices: Send + Sync + 'static {
    /// Routes one call to the service registered as `func_name`, if the calling backend
    /// may reach it, and answers through `responder` exactly once.
    fn invoke(&self, func_name: &str, format: &str, request: &[u8], responder: Responder);

    /// Routes one call with its meta and timeout (a module service or a plugin service)
    /// and answers through `reply` exactly once. By default: [`invoke`](Self::invoke) in
    /// the call's serialization type (`json` when unset), its error mapped to a status.
    fn call(&self, call: BackendCall, reply: BackendReply) {
        call_through_invoke(self, call, reply);
    }

    /// [`call`](Self::call) with the call borrowed, as it crossed the ABI: a host that
    /// reads the call in place overrides it and saves the copy. By default: `call` with a
    /// copy.
    fn call_view(&self, call: CallView<'_>, reply: BackendReply) {
        self.call(call.to_call(), reply);
    }

    /// An executor by name, for backends that take one in their options.
    fn executor(&self, name: &str) -> Option<crate::ffi::RawExecutor> {
        let _ = name;
        None
    }
}

/// Serves `call` through `host.invoke`: the body in the call's serialization type (`json`
/// when unset), the service's error mapped to a status ([`ServiceError::rpc_status`]).
pub fn call_through_invoke<H: HostServices + ?Sized>(
    host: &H,
    call: BackendCall,
    reply: BackendReply,
) {
    let format = call.serialization_type().unwrap_or("json").to_owned();
    host.invoke(
        &call.func,
        &format,
        &call.body,
        Responder::from_fn(move |r| {
            reply.send(match r {
                Ok(body) => BackendAnswer::ok(body),
                Err(e) => BackendAnswer::fail(e.rpc_status(), e.message()),
            })
        }),
    );
}

/// A backend's handle to the runtime's services. Copyable; valid for the process's life.
#[derive(Clone, Copy)]
pub struct ServiceHost {
    raw: RawHost,
}

impl std::fmt::Debug for ServiceHost {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ServiceHost")
    }
}

impl ServiceHost {
    pub(crate) fn from_raw(raw: RawHost) -> ServiceHost {
        ServiceHost { raw }
    }

    /// A host over `services` (for a backend's own tests and fuzzing; the runtime hands
    /// backends theirs in `init`). The services live for the rest of the process.
    pub fn new<T: HostServices>(services: std::sync::Arc<T>) -> ServiceHost {
        ServiceHost::from_raw(RawHost::leak(services))
    }

    /// Invokes `func_name` with `request` in `format`; `done` runs exactly once, on this
    /// thread or another, with the response or why there is none.
    pub fn invoke(
        &self,
        func_name: &str,
        format: &str,
        request: &[u8],
        done: impl FnOnce(Result<Vec<u8>, ServiceError>) + Send + 'static,
    ) {
        self.raw.invoke(func_name, format, request, done);
    }

    /// Hands the runtime a call this backend received (for a module service or a plugin
    /// service); `done` runs exactly once, on this thread or another.
    pub fn call(&self, call: &BackendCall, done: impl FnOnce(BackendAnswer) + Send + 'static) {
        let meta = crate::ffi::meta_of(call.meta_pairs());
        let view = CallView::new(&call.func, &meta, call.timeout, &call.body);
        self.raw.call_view(view, done);
    }

    /// [`call`](Self::call) for a call the backend holds as views (its request's headers
    /// and body, say): nothing is copied into a [`BackendCall`] first. The keys of
    /// `call`'s meta must be distinct.
    pub fn call_view(&self, call: CallView<'_>, done: impl FnOnce(BackendAnswer) + Send + 'static) {
        self.raw.call_view(call, done);
    }

    /// An executor by name (e.g. a backend's `timeout_executor`).
    pub fn executor(&self, name: &str) -> Option<crate::ExecutorRef> {
        // SAFETY: the host hands out only live executors, valid for the process's life.
        self.raw
            .executor(name)
            .map(|raw| unsafe { crate::ExecutorRef::from_raw(raw) })
    }
}

/// A backend's `aimrt.rpc.backends[i].options` node: read it with `get::<T>()`.
pub type BackendOptions = crate::PluginOptions;

/// An RPC backend: carries requests from outside the process to services. The runtime
/// calls `init` for each backend the config lists under `aimrt.rpc.backends`, `start`
/// after plugins started, and `shutdown` first thing at shutdown; a registered backend
/// the config does not list is never started.
pub trait RpcBackend: Send + Sync + 'static {
    /// The type the config names (`backends: [{type: http}]`).
    fn type_name(&self) -> &str;
    /// Reads the backend's options and keeps `host` to invoke services.
    fn init(&self, options: &BackendOptions, host: ServiceHost) -> Result<(), crate::Error>;
    /// Starts serving.
    fn start(&self) -> Result<(), crate::Error>;
    /// Stops serving; returns when no request is being handled any more.
    fn shutdown(&self);

    /// A module serves `func` through this backend (during module initialize). An error
    /// fails the registration.
    fn register_service_func(&self, func: &str) -> Result<(), crate::Error> {
        let _ = func;
        Ok(())
    }

    /// A module calls `func` through this backend (during module initialize).
    fn register_client_func(&self, func: &str) -> Result<(), crate::Error> {
        let _ = func;
        Ok(())
    }

    /// Carries one client call of a module and answers it through `reply` exactly once.
    /// By default the backend carries none: `CLI_BACKEND_INTERNAL_ERROR`.
    fn invoke(&self, call: BackendCall, reply: BackendReply) {
        drop(call);
        reply.send(BackendAnswer::fail(
            RpcStatus::CLI_BACKEND_INTERNAL_ERROR,
            format!(
                "rpc backend '{}' does not carry client calls",
                self.type_name()
            ),
        ));
    }
}
