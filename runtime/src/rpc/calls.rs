//! Module RPC: service and client functions of modules, routed by `aimrt.rpc`
//! (`clients_options` / `servers_options`) and carried by the built-in `local` backend or
//! by a plugin's backend (`http`), in both directions.
//!
//! Every call ends in exactly one answer: the response, a status from the service, or a
//! status from the runtime (not registered, no backend, deadline passed, shutting down).
//! The deadline thread enforces the context's timeout (5 s when none is set) on every
//! call a module makes, and the caller's deadline on a call a backend brings in where the
//! wire carries one; an answer after it is dropped and counted.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock, Weak};
use std::time::{Duration, Instant};

use aimrt_plugin_api::ffi::{
    formats_of, type_name_of, MetaPair, RawExecutor, RawMessage, RawRpcBackend, RawRpcReply,
    RawServiceFunc, ReplyParts, TypeSupportVtable,
};
use aimrt_plugin_api::rpc::{BackendAnswer, BackendReply, CallFilterSide, CallView};
use aimrt_plugin_api::{meta_keys, RateLimit, RpcStatus, Task};

use super::deadline::{on_deadline_thread, Deadlines, Expire};
use super::filter::{RegisteredRpcFilters, RpcChain, Subject};
use crate::routing::Rules;

/// The timeout of a call whose context sets none (AimRT's).
pub(crate) const DEFAULT_TIMEOUT: Duration = Duration::from_secs(5);
/// How long a call a backend brought in without a deadline (zenoh's layout carries none)
/// may take: unbounded in effect, as in AimRT. The call stays watched, so that shutdown
/// still answers it.
const NO_DEADLINE: Duration = Duration::from_secs(100 * 365 * 24 * 3600);
/// The built-in backend.
pub(crate) const LOCAL: &str = "local";
const INIT: u8 = 0;
const START: u8 = 1;
/// Shutting down: calls to the modules are refused; their own calls go on until
/// [`RpcRegistry::close`].
const STOPPING: u8 = 2;
const CLOSED: u8 = 3;

fn read<T>(l: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|e| e.into_inner())
}

fn write<T>(l: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(|e| e.into_inner())
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A module's service function, with what its `servers_options` rule says (looked up
/// once, at registration).
struct ServerFunc {
    func: Arc<str>,
    module: String,
    pkg: String,
    req_ts: &'static TypeSupportVtable,
    formats: Vec<Arc<str>>,
    backends: Vec<String>,
    filters: RpcChain,
    service: RawServiceFunc,
}

/// A module's client function, with what its `clients_options` rule says.
struct ClientFunc {
    func: Arc<str>,
    module: String,
    req_ts: &'static TypeSupportVtable,
    formats: Vec<Arc<str>>,
    backends: Vec<String>,
    filters: RpcChain,
    request_ids: Arc<AtomicU32>,
}

/// How `aimrt.rpc` routes module functions.
#[derive(Default)]
pub(crate) struct Routes {
    /// `clients_options`.
    pub(crate) clients: Rules,
    /// `servers_options`.
    pub(crate) servers: Rules,
    /// `local`'s `timeout_executor`: where timeout answers of non-blocking calls run.
    pub(crate) timeout_executor: Option<RawExecutor>,
    /// The started plugin backends, by type.
    pub(crate) backends: HashMap<String, &'static RawRpcBackend>,
    /// Context meta keys plugins registered to pass from server to client contexts.
    pub(crate) passed_keys: Vec<String>,
    /// The RPC filters plugins registered.
    pub(crate) filters: RegisteredRpcFilters,
}

/// Counters of module calls.
#[derive(Default)]
pub(crate) struct CallStats {
    /// Calls made by modules and calls received by backends.
    pub(crate) calls: AtomicU64,
    /// Calls answered with a status other than OK (timeouts included).
    pub(crate) failed: AtomicU64,
    /// Calls whose deadline passed.
    pub(crate) timed_out: AtomicU64,
    /// Answers that came after the call had been answered (deadline, shutdown), but for a
    /// backend's `TIMEOUT`: that is the call's own timeout seen again, not an answer.
    pub(crate) late: AtomicU64,
}

/// A map looked up on every call: a fast hash (the keys are function names that modules
/// registered; a lookup never inserts).
type ByName<V> = HashMap<String, V, foldhash::fast::RandomState>;

/// Every module function, the routes and the deadline thread.
pub(crate) struct RpcRegistry {
    phase: AtomicU8,
    servers: RwLock<ByName<Vec<Arc<ServerFunc>>>>,
    /// Client functions by name, one entry per module that registered it.
    clients: RwLock<ByName<Vec<Arc<ClientFunc>>>>,
    request_ids: Mutex<HashMap<String, Arc<AtomicU32>>>,
    routes: OnceLock<Routes>,
    deadlines: OnceLock<Deadlines>,
    pub(crate) stats: CallStats,
    warn: RateLimit,
}

impl Default for RpcRegistry {
    fn default() -> Self {
        RpcRegistry {
            phase: AtomicU8::new(INIT),
            servers: RwLock::default(),
            clients: RwLock::default(),
            request_ids: Mutex::default(),
            routes: OnceLock::new(),
            deadlines: OnceLock::new(),
            stats: CallStats::default(),
            warn: RateLimit::from_millis(1000),
        }
    }
}

impl RpcRegistry {
    /// Sets the routes (once, from `aimrt.rpc`).
    pub(crate) fn set_routes(&self, routes: Routes) {
        let _ = self.routes.set(routes);
    }

    fn routes(&self) -> &Routes {
        static NONE: OnceLock<Routes> = OnceLock::new();
        self.routes
            .get()
            .unwrap_or_else(|| NONE.get_or_init(Routes::default))
    }

    /// The passed context meta keys.
    pub(crate) fn passed_keys(&self) -> Vec<String> {
        self.routes().passed_keys.clone()
    }

    /// An executor by name.
    /// Calls are taken from now on (after plugins and backends started, before modules
    /// start).
    pub(crate) fn start(&self) -> std::io::Result<()> {
        if self.deadlines.get().is_none() {
            let _ = self.deadlines.set(Deadlines::start()?);
        }
        self.phase.store(START, Ordering::SeqCst);
        Ok(())
    }

    /// Shutdown begins: the modules are about to shut down, so calls a backend carries to
    /// them are answered `SVR_NOT_READY` from now on. The modules' own calls go on, through
    /// every backend, until [`close`](Self::close).
    pub(crate) fn stopping(&self) {
        let _ = self
            .phase
            .compare_exchange(START, STOPPING, Ordering::SeqCst, Ordering::SeqCst);
    }

    /// No call is taken from now on; every call still waiting is answered (a module's
    /// `CLI_NOT_READY`, a backend's `SVR_NOT_READY`) before this returns.
    pub(crate) fn close(&self) {
        self.phase.store(CLOSED, Ordering::SeqCst);
        if let Some(d) = self.deadlines.get() {
            d.close();
        }
        let s = &self.stats;
        let calls = s.calls.load(Ordering::Relaxed);
        if calls > 0 {
            tracing::info!(target: "aimrt", "Module RPC: {calls} calls, {} answered with an error status ({} timed out), {} late answers dropped", s.failed.load(Ordering::Relaxed), s.timed_out.load(Ordering::Relaxed), s.late.load(Ordering::Relaxed));
        }
    }

    /// The names `enable_filters` may list for `side` (the init report).
    pub(crate) fn filter_names(&self, side: CallFilterSide) -> Vec<String> {
        let names = self.routes().filters.names(side);
        names.into_iter().map(str::to_owned).collect()
    }

    /// `func | module | backends | filters` rows of server (`true`) or client functions,
    /// with the server functions `more` names (plugins' services, by plugin), sorted
    /// (AimRT's `Rpc Server Info` / `Rpc Client Info`).
    pub(crate) fn rows(&self, servers: bool, more: Vec<(String, String)>) -> Vec<Vec<String>> {
        let routes = self.routes();
        let rules = if servers {
            &routes.servers
        } else {
            &routes.clients
        };
        let mut rows: Vec<(String, String)> = if servers {
            read(&self.servers)
                .iter()
                .flat_map(|(f, list)| list.iter().map(move |s| (f.clone(), s.module.clone())))
                .collect()
        } else {
            read(&self.clients)
                .iter()
                .flat_map(|(f, list)| list.iter().map(move |c| (f.clone(), c.module.clone())))
                .collect()
        };
        rows.extend(more);
        rows.sort();
        rows.into_iter()
            .map(|(func, module)| {
                let backends = rules.backends_for(&func).unwrap_or_default().join(",");
                let filters = rules.filters_for(&func).join(",");
                vec![func, module, backends, filters]
            })
            .collect()
    }

    /// Counts and logs (at most once a second, with how many were held back) a call the
    /// runtime answers with a failure.
    fn note_failure(&self, status: RpcStatus, detail: &str) {
        self.stats.failed.fetch_add(1, Ordering::Relaxed);
        self.log_failure(status, detail);
    }

    /// Logs a failed call, at most once a second with the count of those held back.
    pub(crate) fn log_failure(&self, status: RpcStatus, detail: &str) {
        if let Some(held) = self.warn.admit() {
            let more = if held > 0 {
                format!(" ({held} more since the last report)")
            } else {
                String::new()
            };
            tracing::warn!(target: "aimrt", "Rpc call failed: {detail}: {status}{more}");
        }
    }

    fn refuse(&self, reply: RawRpcReply, status: RpcStatus, detail: String) {
        self.note_failure(status, &detail);
        reply.complete(status, None, &[], &detail);
    }

    /// Expires `call` at its deadline; `false` once RPC shut down.
    fn watch(&self, call: &Arc<Call>) -> bool {
        let weak: Weak<dyn Expire> = Arc::downgrade(call) as Weak<dyn Expire>;
        self.deadlines
            .get()
            .is_some_and(|d| d.add(call.deadline, weak))
    }

    /// A call `backend` received for a module service: decoded in its serialization type,
    /// served, and answered through `reply` in the same type.
    /// `plugin_services` names the plugins' services, for the hint of a call of no function.
    pub(crate) fn serve(
        self: &Arc<Self>,
        backend: &str,
        call: CallView<'_>,
        reply: BackendReply,
        plugin_services: &dyn Fn() -> Vec<String>,
    ) {
        self.stats.calls.fetch_add(1, Ordering::Relaxed);
        let func = call.func;
        let refuse = |reply: BackendReply, status: RpcStatus, detail: String| {
            self.note_failure(status, &detail);
            reply.send(BackendAnswer::fail(status, detail));
        };
        if self.phase.load(Ordering::SeqCst) != START {
            return refuse(
                reply,
                RpcStatus::SVR_NOT_READY,
                format!("'{func}' was called through {backend} while the runtime is not running"),
            );
        }
        let server = {
            let servers = read(&self.servers);
            match servers.get(func).and_then(|l| l.first()) {
                Some(s) if s.backends.iter().any(|b| b == backend) => s.clone(),
                Some(_) => return refuse(reply, RpcStatus::SVR_NOT_FOUND, format!("service function '{func}' is not enabled for the '{backend}' backend; enable it in aimrt.rpc.servers_options")),
                None => {
                    let others = plugin_services();
                    let names = servers.keys().chain(&others).map(String::as_str);
                    let hint = aimrt_plugin_api::__private::did_you_mean(func, names);
                    return refuse(reply, RpcStatus::SVR_NOT_FOUND, format!("no service function '{func}' is registered{hint}"));
                }
            }
        };
        let format: Arc<str> = match call.serialization_type() {
            Some(f) if !f.is_empty() => match server.formats.iter().find(|x| &***x == f) {
                Some(known) => known.clone(),
                None => {
                    return refuse(
                        reply,
                        RpcStatus::SVR_INVALID_SERIALIZATION_TYPE,
                        format!(
                        "'{func}' was called in '{f}', which '{}' does not support; it supports {}",
                        type_name_of(server.req_ts),
                        server.formats.join(", ")
                    ),
                    )
                }
            },
            _ => match server.formats.first() {
                Some(default) => default.clone(),
                None => {
                    return refuse(
                        reply,
                        RpcStatus::SVR_INVALID_SERIALIZATION_TYPE,
                        format!(
                            "'{}' has no serialization type",
                            type_name_of(server.req_ts)
                        ),
                    )
                }
            },
        };
        let req = match RawMessage::decode(server.req_ts, &format, call.body) {
            Ok(m) => m,
            Err(e) => {
                return refuse(
                    reply,
                    RpcStatus::SVR_DESERIALIZATION_FAILED,
                    format!("the request of '{func}' cannot be deserialized ({format}): {e}"),
                )
            }
        };
        // The caller's deadline, where the wire carries it (http's `Timeout`). Without
        // one the service is not cut off here and its context has no timeout (AimRT's 0):
        // the caller's own deadline decides, in the caller's process.
        let deadline = Instant::now() + call.timeout.unwrap_or(NO_DEADLINE);
        let meta = server_meta(call.pairs(), &format, func, backend);
        let record = Call::new(
            self,
            &server.func,
            &format,
            Waiter::Backend(reply),
            deadline,
        );
        self.dispatch(
            &server,
            &record,
            &meta,
            call.timeout.map_or(0, nanos),
            req,
            RpcStatus::SVR_NOT_READY,
        );
    }

    /// Hands `req` to `server`'s function with the server context `meta`, its filters
    /// around it; a call not answered by the time the function returns goes to the
    /// deadline thread (answered `closed` if RPC shut down meanwhile).
    fn dispatch(
        &self,
        server: &ServerFunc,
        call: &Arc<Call>,
        pairs: &[MetaPair<'_>],
        timeout_ns: u64,
        req: RawMessage,
        closed: RpcStatus,
    ) {
        let answer = call.clone();
        let reply = RawRpcReply::new(move |parts| answer.answer_from_service(parts));
        if server.filters.is_empty() {
            server.service.call(pairs, timeout_ns, req, reply);
        } else {
            let subject = Subject {
                side: CallFilterSide::Server,
                func: &server.func,
                module: &server.module,
                timeout_ns,
                req: &req.share(),
                // The service's reply: the call counts and logs a failure with a reason.
                refuse: &|reply: RawRpcReply, status, detail: String| {
                    reply.complete(status, None, &[], &detail)
                },
            };
            let mut req = Some(req);
            server
                .filters
                .run(&subject, pairs, reply, &mut |passed, reply| {
                    if let Some(req) = req.take() {
                        server.service.call(passed, timeout_ns, req, reply);
                    }
                });
        }
        if call.is_pending() && !self.watch(call) {
            call.answer_from_runtime(
                closed,
                format!("call of '{}' was in flight when RPC shut down", call.func),
            );
        }
    }
}

/// A server context's meta: the pairs as they crossed the ABI (checked as UTF-8 once, by
/// the server's context) and the keys the runtime sets. `aimrt-response_id` is the
/// caller's `aimrt-request_id` (empty without one), as AimRT sets it for every backend.
pub(crate) fn server_meta<'a>(
    pairs: &[MetaPair<'a>],
    format: &'a str,
    func: &'a str,
    backend: &'a str,
) -> Vec<MetaPair<'a>> {
    let mut meta: Vec<MetaPair<'a>> = Vec::with_capacity(pairs.len() + 4);
    meta.extend_from_slice(pairs);
    let request_id = pairs
        .iter()
        .find(|p| p.is_key(meta_keys::REQUEST_ID))
        .map_or("", MetaPair::value);
    for (k, v) in [
        (meta_keys::SERIALIZATION_TYPE, format),
        (meta_keys::FUNCTION_NAME, func),
        (meta_keys::BACKEND, backend),
        (meta_keys::RESPONSE_ID, request_id),
    ] {
        set(&mut meta, k, v);
    }
    meta
}

pub(crate) fn nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

/// The RPC side of one module's core handle.
pub(crate) struct ModuleRpc {
    registry: Arc<RpcRegistry>,
    module: String,
    pkg: String,
}

impl ModuleRpc {
    pub(crate) fn new(registry: Arc<RpcRegistry>, module: &str, pkg: &str) -> ModuleRpc {
        ModuleRpc {
            registry,
            module: module.into(),
            pkg: pkg.into(),
        }
    }

    fn check_registration(&self, what: &str, func: &str) -> Result<(), String> {
        if self.registry.phase.load(Ordering::SeqCst) != INIT {
            return Err(format!(
                "{what} function '{func}' of module '{}': functions are registered in initialize only",
                self.module
            ));
        }
        if func.is_empty() || !func.contains(":/") {
            return Err(format!(
                "{what} function name '{func}' of module '{}' is not a full name; write <type>:/<service>/<method>, e.g. pb:/aimrt.protocols.example.ExampleService/GetFooData",
                self.module
            ));
        }
        Ok(())
    }

    /// Tells each plugin backend `rules` route `func` to that it carries it.
    fn register_on_backends(&self, rules: &Rules, func: &str, server: bool) -> Result<(), String> {
        let routes = self.registry.routes();
        for b in rules.backends_for(func).unwrap_or_default() {
            let Some(backend) = routes.backends.get(b) else {
                continue;
            };
            let registered = if server {
                backend.register_service_func(func)
            } else {
                backend.register_client_func(func)
            };
            registered.map_err(|e| {
                format!(
                    "{} function '{func}' of module '{}': rpc backend '{b}' refused it: {e}",
                    if server { "service" } else { "client" },
                    self.module
                )
            })?;
        }
        Ok(())
    }

    pub(crate) fn register_service(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        _rsp_ts: &'static TypeSupportVtable,
        service: RawServiceFunc,
    ) -> Result<(), String> {
        self.check_registration("service", func)?;
        let mut servers = write(&self.registry.servers);
        if servers
            .get(func)
            .is_some_and(|l| l.iter().any(|s| s.module == self.module))
        {
            return Err(format!(
                "service function '{func}' is registered twice by module '{}' (pkg {})",
                self.module, self.pkg
            ));
        }
        let routes = self.registry.routes();
        match routes.servers.backends_for(func) {
            None => {
                tracing::warn!(target: "aimrt", "service function '{func}' of module '{}' matches no aimrt.rpc.servers_options rule: no backend serves it", self.module)
            }
            Some([]) => {
                tracing::warn!(target: "aimrt", "service function '{func}' of module '{}': its aimrt.rpc.servers_options rule enables no backend: no backend serves it", self.module)
            }
            Some(_) => {}
        }
        self.register_on_backends(&routes.servers, func, true)?;
        servers
            .entry(func.to_owned())
            .or_default()
            .push(Arc::new(ServerFunc {
                func: func.into(),
                module: self.module.clone(),
                pkg: self.pkg.clone(),
                req_ts,
                formats: formats_of(req_ts).into_iter().map(Arc::from).collect(),
                backends: routes
                    .servers
                    .backends_for(func)
                    .unwrap_or_default()
                    .to_vec(),
                filters: (routes.filters)
                    .chain(CallFilterSide::Server, routes.servers.filters_for(func)),
                service,
            }));
        Ok(())
    }

    pub(crate) fn passed_keys(&self) -> Vec<String> {
        self.registry.passed_keys()
    }

    pub(crate) fn register_client(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        _rsp_ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        self.check_registration("client", func)?;
        let mut clients = write(&self.registry.clients);
        if clients
            .get(func)
            .is_some_and(|l| l.iter().any(|c| c.module == self.module))
        {
            return Err(format!(
                "client function '{func}' is registered twice by module '{}' (pkg {})",
                self.module, self.pkg
            ));
        }
        let routes = self.registry.routes();
        if routes.clients.backends_for(func).is_none() {
            tracing::warn!(target: "aimrt", "client function '{func}' of module '{}' matches no aimrt.rpc.clients_options rule: its calls will be answered CLI_NO_BACKEND_TO_HANDLE (2009)", self.module);
        }
        self.register_on_backends(&routes.clients, func, false)?;
        let request_ids = lock(&self.registry.request_ids)
            .entry(func.to_owned())
            .or_default()
            .clone();
        clients
            .entry(func.to_owned())
            .or_default()
            .push(Arc::new(ClientFunc {
                func: func.into(),
                module: self.module.clone(),
                req_ts,
                formats: formats_of(req_ts).into_iter().map(Arc::from).collect(),
                backends: routes
                    .clients
                    .backends_for(func)
                    .unwrap_or_default()
                    .to_vec(),
                filters: (routes.filters)
                    .chain(CallFilterSide::Client, routes.clients.filters_for(func)),
                request_ids,
            }));
        Ok(())
    }

    /// Invokes `func` for this module; `reply` is completed exactly once.
    ///
    /// The context is handled as borrowed views until a backend needs it owned; a call a
    /// `local` service answers before returning never reaches the deadline thread (its
    /// deadline is checked when the answer comes).
    #[allow(clippy::too_many_arguments)] // one call, as it crosses the ABI
    pub(crate) fn invoke(
        &self,
        func: &str,
        ctx: &[MetaPair<'_>],
        timeout_ns: u64,
        req: RawMessage,
        rsp_ts: &'static TypeSupportVtable,
        blocking: bool,
        reply: RawRpcReply,
    ) {
        let reg = &self.registry;
        reg.stats.calls.fetch_add(1, Ordering::Relaxed);
        let refuse = |reply, status, detail: String| reg.refuse(reply, status, detail);
        match reg.phase.load(Ordering::SeqCst) {
            START | STOPPING => {}
            INIT => {
                return refuse(reply, RpcStatus::CLI_NOT_READY, format!("module '{}' called '{func}' before start; calls are answered from start on", self.module));
            }
            _ => {
                return refuse(
                    reply,
                    RpcStatus::CLI_NOT_READY,
                    format!(
                        "module '{}' called '{func}' after RPC shut down",
                        self.module
                    ),
                );
            }
        }
        let Some(client) = read(&reg.clients)
            .get(func)
            .and_then(|l| l.iter().find(|c| c.module == self.module))
            .cloned()
        else {
            return refuse(reply, RpcStatus::CLI_FUNC_NOT_REGISTERED, format!("module '{}' called '{func}' without registering it as a client function in initialize", self.module));
        };
        if blocking && on_deadline_thread() {
            return refuse(reply, RpcStatus::CLI_BACKEND_INTERNAL_ERROR, format!("module '{}' made a blocking call of '{func}' on the RPC deadline thread, which answers it; use call_then or call_async there", self.module));
        }
        // The context's pairs as they crossed the ABI: keys compared as bytes, a value
        // checked as UTF-8 only where it is read.
        let mut meta: Vec<MetaPair<'_>> = Vec::with_capacity(ctx.len() + 8);
        meta.extend_from_slice(ctx);
        let mut id = itoa::Buffer::new();
        let id = id.format(
            client
                .request_ids
                .fetch_add(1, Ordering::Relaxed)
                .wrapping_add(1),
        );
        set(&mut meta, meta_keys::REQUEST_ID, id);
        let format: Arc<str> = match get(&meta, meta_keys::SERIALIZATION_TYPE) {
            Some(f) if !f.is_empty() => match client.formats.iter().find(|x| &***x == f) {
                Some(known) => known.clone(),
                None => {
                    return refuse(reply, RpcStatus::CLI_INVALID_SERIALIZATION_TYPE, format!("call of '{func}': aimrt-serialization_type is '{f}', which '{}' does not support; it supports {}", type_name_of(client.req_ts), client.formats.join(", ")));
                }
            },
            _ => match client.formats.first() {
                Some(default) => default.clone(),
                None => {
                    return refuse(
                        reply,
                        RpcStatus::CLI_INVALID_SERIALIZATION_TYPE,
                        format!(
                            "call of '{func}': '{}' has no serialization type",
                            type_name_of(client.req_ts)
                        ),
                    );
                }
            },
        };
        set(&mut meta, meta_keys::SERIALIZATION_TYPE, &format);
        let timeout = if timeout_ns == 0 {
            DEFAULT_TIMEOUT
        } else {
            Duration::from_nanos(timeout_ns)
        };
        let deadline = Instant::now() + timeout;
        let route = Route {
            client: &client,
            func,
            id,
            format: &format,
            timeout,
            deadline,
            rsp_ts,
            blocking,
        };
        if client.filters.is_empty() {
            return self.route(&route, meta, req, reply);
        }
        let subject = Subject {
            side: CallFilterSide::Client,
            func,
            module: &self.module,
            timeout_ns: nanos(timeout),
            req: &req.share(),
            refuse: &|reply, status, detail| {
                reg.refuse(reply, status, format!("call of '{func}': {detail}"))
            },
        };
        let mut req = Some(req);
        client
            .filters
            .run(&subject, &meta, reply, &mut |passed, reply| {
                if let Some(req) = req.take() {
                    self.route(&route, passed.to_vec(), req, reply);
                }
            });
    }

    /// Sends a call on (after its client filters): to the backend its context or its
    /// rule chooses, or to a module's service through `local`.
    fn route<'a>(
        &'a self,
        r: &'a Route<'a>,
        mut meta: Vec<MetaPair<'a>>,
        req: RawMessage,
        reply: RawRpcReply,
    ) {
        let Route {
            client,
            func,
            id,
            format,
            timeout,
            deadline,
            rsp_ts,
            blocking,
        } = *r;
        let reg = &self.registry;
        let refuse = |reply, status, detail: String| reg.refuse(reply, status, detail);
        let listed = client.backends.as_slice();
        let to_addr = get(&meta, meta_keys::TO_ADDR).unwrap_or("");
        let backend: &str = if to_addr.is_empty() {
            match listed.first() {
                Some(b) => {
                    set(&mut meta, meta_keys::BACKEND, b);
                    b
                }
                None => {
                    return refuse(
                        reply,
                        RpcStatus::CLI_NO_BACKEND_TO_HANDLE,
                        format!(
                            "'{func}' matches no aimrt.rpc.clients_options rule with a backend"
                        ),
                    );
                }
            }
        } else {
            match to_addr.split_once("://") {
                Some((scheme, _)) if listed.iter().any(|b| b == scheme) => scheme,
                _ => {
                    return refuse(reply, RpcStatus::CLI_INVALID_ADDR, format!("call of '{func}': aimrt-to_addr '{to_addr}' does not start with <backend>:// naming one of its backends ({})", listed.join(", ")));
                }
            }
        };
        let waiter = Waiter::Module {
            reply,
            rsp_ts,
            blocking,
        };
        if backend != LOCAL {
            let waiter_refuse = |waiter: Waiter, status, detail: String| {
                Call::new(reg, &client.func, format, waiter, deadline)
                    .answer_from_runtime(status, detail)
            };
            let Some(carrier) = reg.routes().backends.get(backend).copied() else {
                return waiter_refuse(
                    waiter,
                    RpcStatus::CLI_BACKEND_INTERNAL_ERROR,
                    format!("call of '{func}': rpc backend '{backend}' is not started"),
                );
            };
            // Encoded once; the backend carries the bytes.
            let body = match req.encode(format) {
                Ok(b) => b,
                Err(e) => {
                    return waiter_refuse(
                        waiter,
                        RpcStatus::CLI_SERIALIZATION_FAILED,
                        format!("call of '{func}': cannot serialize the request as {format}: {e}"),
                    )
                }
            };
            let call = Call::new(reg, &client.func, format, waiter, deadline);
            if !reg.watch(&call) {
                return call.answer_from_runtime(
                    RpcStatus::CLI_NOT_READY,
                    format!("call of '{func}' arrived while RPC shut down"),
                );
            }
            let answer = call.clone();
            carrier.invoke(CallView::new(func, &meta, Some(timeout), &body), move |a| {
                answer.answer_from_backend(a)
            });
            return;
        }
        let call = Call::new(reg, &client.func, format, waiter, deadline);
        let server = match self.pick_server(func, to_addr) {
            Ok(s) => s,
            Err((status, detail)) => return call.answer_from_runtime(status, detail),
        };
        if blocking {
            if let Some(exec) = server.service.executor() {
                if exec.thread_safe() && exec.is_in_current_executor() {
                    return call.answer_from_runtime(RpcStatus::CLI_BACKEND_INTERNAL_ERROR, format!("module '{}' made a blocking call of '{func}' on executor '{}', which runs the service one task at a time and so could never answer it; use call_then or call_async there", self.module, exec.name()));
                }
            }
        }
        // The request as an object of the server's table: shared when the tables are the
        // same (same library), else encoded once and decoded once.
        let req = if std::ptr::eq(req.type_support(), server.req_ts) {
            req
        } else {
            let bytes = match req.encode(format) {
                Ok(b) => b,
                Err(e) => {
                    return call.answer_from_runtime(
                        RpcStatus::CLI_SERIALIZATION_FAILED,
                        format!("call of '{func}': cannot serialize the request as {format}: {e}"),
                    )
                }
            };
            match RawMessage::decode(server.req_ts, format, &bytes) {
                Ok(m) => m,
                Err(e) => return call.answer_from_runtime(RpcStatus::SVR_DESERIALIZATION_FAILED, format!("call of '{func}': module '{}' cannot deserialize the request ({format}): {e}", server.module)),
            }
        };
        for (k, v) in [
            (meta_keys::FUNCTION_NAME, func),
            (meta_keys::BACKEND, LOCAL),
            (meta_keys::FROM_PKG, self.pkg.as_str()),
            (meta_keys::FROM_MODULE, self.module.as_str()),
            (meta_keys::RESPONSE_ID, id),
        ] {
            set(&mut meta, k, v);
        }
        reg.dispatch(
            &server,
            &call,
            &meta,
            nanos(timeout),
            req,
            RpcStatus::CLI_NOT_READY,
        );
    }

    /// The server of `func` for a call with `to_addr` (`local://rpc/…?pkg_path=…&module_name=…`).
    fn pick_server(
        &self,
        func: &str,
        to_addr: &str,
    ) -> Result<Arc<ServerFunc>, (RpcStatus, String)> {
        let servers = read(&self.registry.servers);
        // The servers of one function share its servers_options rule, resolved when they
        // registered (no regex per call).
        let reachable: &[Arc<ServerFunc>] = match servers.get(func) {
            Some(l)
                if l.first()
                    .is_some_and(|s| s.backends.iter().any(|b| b == LOCAL)) =>
            {
                l
            }
            _ => &[],
        };
        if reachable.is_empty() {
            let why = if servers.get(func).is_some_and(|l| !l.is_empty()) {
                "is registered, but its aimrt.rpc.servers_options rule does not enable local"
            } else {
                "is not registered by any module"
            };
            return Err((
                RpcStatus::SVR_NOT_FOUND,
                format!("service function '{func}' {why}"),
            ));
        }
        if to_addr.is_empty() {
            return Ok(reachable[0].clone());
        }
        let query = to_addr.split_once('?').map_or("", |(_, q)| q);
        let mut pkg = None;
        let mut module = None;
        for pair in query.split('&') {
            if let Some((k, v)) = pair.split_once('=') {
                match k.trim() {
                    "pkg_path" => pkg = Some(v),
                    "module_name" => module = Some(v),
                    _ => {}
                }
            }
        }
        let found = reachable
            .iter()
            .find(|s| pkg.is_none_or(|p| p == s.pkg) && module.is_none_or(|m| m == s.module));
        found.cloned().ok_or_else(|| {
            let serving: Vec<String> = reachable
                .iter()
                .map(|s| format!("module '{}' in pkg {}", s.module, s.pkg))
                .collect();
            (
                RpcStatus::CLI_INVALID_ADDR,
                format!(
                    "aimrt-to_addr '{to_addr}' names no server of '{func}'; it is served by {}",
                    serving.join(", ")
                ),
            )
        })
    }
}

/// The value of `key` among `meta`.
fn get<'a>(meta: &[MetaPair<'a>], key: &str) -> Option<&'a str> {
    meta.iter().find(|p| p.is_key(key)).map(|p| p.value())
}

/// What a client call carries from its checks to [`ModuleRpc::route`].
struct Route<'a> {
    client: &'a ClientFunc,
    func: &'a str,
    /// `aimrt-request_id`, which `local` also sets as `aimrt-response_id`.
    id: &'a str,
    format: &'a Arc<str>,
    timeout: Duration,
    deadline: Instant,
    rsp_ts: &'static TypeSupportVtable,
    blocking: bool,
}

/// Sets `key` in `meta` (in place when it is there, else last).
fn set<'a>(meta: &mut Vec<MetaPair<'a>>, key: &'a str, value: &'a str) {
    match meta.iter_mut().find(|p| p.is_key(key)) {
        Some(p) => *p = MetaPair::new(key, value),
        None => meta.push(MetaPair::new(key, value)),
    }
}

/// Who waits for a call's answer.
enum Waiter {
    /// A module's client function: answered with an object of `rsp_ts`.
    Module {
        reply: RawRpcReply,
        rsp_ts: &'static TypeSupportVtable,
        blocking: bool,
    },
    /// A backend that received the call: answered with bytes in the call's format.
    Backend(BackendReply),
}

/// One call in flight: whoever takes the waiter first answers it.
pub(crate) struct Call {
    registry: Weak<RpcRegistry>,
    func: Arc<str>,
    waiter: Mutex<Option<Waiter>>,
    format: Arc<str>,
    deadline: Instant,
}

impl Call {
    fn new(
        registry: &Arc<RpcRegistry>,
        func: &Arc<str>,
        format: &Arc<str>,
        waiter: Waiter,
        deadline: Instant,
    ) -> Arc<Call> {
        Arc::new(Call {
            registry: Arc::downgrade(registry),
            func: func.clone(),
            waiter: Mutex::new(Some(waiter)),
            format: format.clone(),
            deadline,
        })
    }

    fn take(&self) -> Option<Waiter> {
        lock(&self.waiter).take()
    }

    /// Whether nobody answered yet.
    fn is_pending(&self) -> bool {
        lock(&self.waiter).is_some()
    }

    fn count(&self, f: impl FnOnce(&CallStats)) {
        if let Some(r) = self.registry.upgrade() {
            f(&r.stats);
        }
    }

    /// Answers `status` (with why) to whoever waits, counted and logged.
    fn fail(&self, waiter: Waiter, status: RpcStatus, detail: String) {
        if let Some(r) = self.registry.upgrade() {
            r.note_failure(status, &detail);
        }
        match waiter {
            Waiter::Module { reply, .. } => reply.complete(status, None, &[], &detail),
            Waiter::Backend(reply) => reply.send(BackendAnswer::fail(status, detail)),
        }
    }

    /// The runtime answers (refusal before the service ran, shutdown).
    fn answer_from_runtime(&self, status: RpcStatus, detail: String) {
        if let Some(w) = self.take() {
            self.fail(w, status, detail);
        }
    }

    /// An answer after the deadline, from a service or a backend, is a timeout and a
    /// late answer, whichever thread comes first: the deadline thread may not have got to
    /// the call yet (it is busy, or never watched a call answered on the caller's thread),
    /// and a backend's own timer (http's) fires a moment after the deadline. `false`
    /// before the deadline. `repeat`: the answer is itself that timeout, not counted.
    fn too_late(&self, repeat: bool) -> bool {
        if Instant::now() <= self.deadline {
            return false;
        }
        self.expire();
        self.late(repeat);
        true
    }

    /// Drops an answer to a call answered already; counted unless it is a `repeat` of the
    /// call's timeout (a backend's own timer, or the record of a call a backend forgets).
    fn late(&self, repeat: bool) {
        if repeat {
            tracing::trace!(target: "aimrt", "a backend's timeout of '{}' dropped: the call was answered already", self.func);
            return;
        }
        self.count(|s| {
            s.late.fetch_add(1, Ordering::Relaxed);
        });
        tracing::trace!(target: "aimrt", "late answer of '{}' dropped: the call was answered already", self.func);
    }

    /// The service answered.
    fn answer_from_service(&self, parts: ReplyParts) {
        if self.too_late(false) {
            return;
        }
        let Some(waiter) = self.take() else {
            return self.late(false);
        };
        let ReplyParts {
            status,
            rsp,
            detail,
            ..
        } = parts;
        if !status.is_ok() {
            if detail.is_empty() {
                // The service's own status: counted, not logged.
                self.count(|s| {
                    s.failed.fetch_add(1, Ordering::Relaxed);
                });
                return match waiter {
                    Waiter::Module { reply, .. } => reply.complete(status, None, &[], ""),
                    Waiter::Backend(reply) => reply.send(BackendAnswer::fail(status, "")),
                };
            }
            // The module side says why (a panic, a dropped reply): log it.
            let detail = format!("call of '{}' failed on the server: {detail}", self.func);
            return self.fail(waiter, status, detail);
        }
        let Some(rsp) = rsp else {
            let detail = format!(
                "the service of '{}' answered OK without a response",
                self.func
            );
            return self.fail(waiter, RpcStatus::SVR_HANDLE_FAILED, detail);
        };
        match waiter {
            Waiter::Module { reply, rsp_ts, .. } => {
                // The response as an object of the caller's table: shared when the tables
                // are the same, else encoded once and decoded once.
                if std::ptr::eq(rsp.type_support(), rsp_ts) {
                    return reply.complete(RpcStatus::OK, Some(rsp), &[], "");
                }
                let waiter = Waiter::Module {
                    reply,
                    rsp_ts,
                    blocking: false,
                };
                let bytes = match rsp.encode(&self.format) {
                    Ok(b) => b,
                    Err(e) => {
                        let detail = format!(
                            "the response of '{}' cannot be serialized as {}: {e}",
                            self.func, self.format
                        );
                        return self.fail(waiter, RpcStatus::SVR_SERIALIZATION_FAILED, detail);
                    }
                };
                self.deliver_bytes(waiter, &bytes);
            }
            Waiter::Backend(reply) => match rsp.encode(&self.format) {
                Ok(body) => reply.send(BackendAnswer::ok(body)),
                Err(e) => {
                    let detail = format!(
                        "the response of '{}' cannot be serialized as {}: {e}",
                        self.func, self.format
                    );
                    self.fail(
                        Waiter::Backend(reply),
                        RpcStatus::SVR_SERIALIZATION_FAILED,
                        detail,
                    );
                }
            },
        }
    }

    /// A backend answered a module's client call.
    fn answer_from_backend(&self, answer: BackendAnswer) {
        let repeat = answer.status.is_timeout();
        if self.too_late(repeat) {
            return;
        }
        let Some(waiter) = self.take() else {
            return self.late(repeat);
        };
        if !answer.status.is_ok() {
            let detail = if answer.detail.is_empty() {
                format!("call of '{}' answered {}", self.func, answer.status)
            } else {
                format!("call of '{}': {}", self.func, answer.detail)
            };
            return self.fail(waiter, answer.status, detail);
        }
        self.deliver_bytes(waiter, &answer.body);
    }

    /// Decodes a response in the call's format for a module's client function.
    fn deliver_bytes(&self, waiter: Waiter, bytes: &[u8]) {
        match waiter {
            Waiter::Module { reply, rsp_ts, .. } => {
                match RawMessage::decode(rsp_ts, &self.format, bytes) {
                    Ok(m) => reply.complete(RpcStatus::OK, Some(m), &[], ""),
                    Err(e) => {
                        let detail = format!(
                            "the response of '{}' cannot be deserialized ({}): {e}",
                            self.func, self.format
                        );
                        self.fail(
                            Waiter::Module {
                                reply,
                                rsp_ts,
                                blocking: false,
                            },
                            RpcStatus::CLI_DESERIALIZATION_FAILED,
                            detail,
                        );
                    }
                }
            }
            Waiter::Backend(reply) => reply.send(BackendAnswer::ok(bytes.to_vec())),
        }
    }
}

impl Expire for Call {
    fn expire(&self) {
        let Some(waiter) = self.take() else { return };
        self.count(|s| {
            s.timed_out.fetch_add(1, Ordering::Relaxed);
            s.failed.fetch_add(1, Ordering::Relaxed);
        });
        let detail = format!("call of '{}' timed out", self.func);
        let executor = self
            .registry
            .upgrade()
            .and_then(|r| r.routes().timeout_executor);
        match (waiter, executor) {
            // A blocking caller only needs waking; a callback runs on the timeout executor
            // (AimRT's `timeout_executor`), or here if it refuses.
            (
                Waiter::Module {
                    reply,
                    blocking: false,
                    ..
                },
                Some(exec),
            ) => {
                let slot = Arc::new(Mutex::new(Some(reply)));
                let task_slot = slot.clone();
                let task_detail = detail.clone();
                let status = exec.execute(Task::new(move || {
                    if let Some(reply) = lock(&task_slot).take() {
                        reply.complete(RpcStatus::TIMEOUT, None, &[], &task_detail);
                    }
                }));
                if !status.is_ok() {
                    if let Some(reply) = lock(&slot).take() {
                        reply.complete(RpcStatus::TIMEOUT, None, &[], &detail);
                    }
                }
            }
            (Waiter::Module { reply, .. }, _) => {
                reply.complete(RpcStatus::TIMEOUT, None, &[], &detail)
            }
            (Waiter::Backend(reply), _) => {
                reply.send(BackendAnswer::fail(RpcStatus::TIMEOUT, detail))
            }
        }
    }

    fn abandon(&self) {
        let Some(waiter) = self.take() else { return };
        let status = match waiter {
            Waiter::Module { .. } => RpcStatus::CLI_NOT_READY,
            Waiter::Backend(_) => RpcStatus::SVR_NOT_READY,
        };
        self.fail(
            waiter,
            status,
            format!("call of '{}' was in flight when RPC shut down", self.func),
        );
    }
}
