//! Module RPC: service and client functions of modules, routed by `aimrt.rpc`
//! (`clients_options` / `servers_options`) and carried by the built-in `local` backend.
//!
//! Every call ends in exactly one answer: the response, a status from the service, or a
//! status from the runtime (not registered, no backend, deadline passed, shutting down).
//! The deadline thread enforces the context's timeout (5 s when none is set) on every
//! call; an answer after it is dropped and counted.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock, Weak};
use std::time::{Duration, Instant};

use aimrt_plugin_api::ffi::{
    formats_of, meta_of, type_name_of, MetaPair, RawExecutor, RawMessage, RawRpcReply,
    RawServiceFunc, ReplyParts, TypeSupportVtable,
};
use aimrt_plugin_api::{meta_keys, RateLimit, RpcStatus, Task};

use super::deadline::{on_deadline_thread, Deadlines, Expire};
use crate::routing::Rules;

/// The timeout of a call whose context sets none (AimRT's).
pub(crate) const DEFAULT_TIMEOUT: Duration = Duration::from_secs(5);
/// The built-in backend.
pub(crate) const LOCAL: &str = "local";

const INIT: u8 = 0;
const START: u8 = 1;
const CLOSED: u8 = 2;

fn read<T>(l: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|e| e.into_inner())
}

fn write<T>(l: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(|e| e.into_inner())
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A module's service function.
struct ServerFunc {
    module: String,
    pkg: String,
    req_ts: &'static TypeSupportVtable,
    rsp_ts: &'static TypeSupportVtable,
    service: RawServiceFunc,
}

/// A module's client function.
struct ClientFunc {
    req_ts: &'static TypeSupportVtable,
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
}

/// Counters of module calls.
#[derive(Default)]
pub(crate) struct CallStats {
    /// Calls made.
    pub(crate) calls: AtomicU64,
    /// Calls answered with a status other than OK (timeouts included).
    pub(crate) failed: AtomicU64,
    /// Calls whose deadline passed.
    pub(crate) timed_out: AtomicU64,
    /// Service answers that came after the call had been answered (deadline, shutdown).
    pub(crate) late: AtomicU64,
}

/// Every module function, the routes and the deadline thread.
pub(crate) struct RpcRegistry {
    phase: AtomicU8,
    servers: RwLock<HashMap<String, Vec<Arc<ServerFunc>>>>,
    clients: RwLock<HashMap<(String, String), Arc<ClientFunc>>>,
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

    /// Calls are taken from now on (after plugins and backends started, before modules
    /// start).
    pub(crate) fn start(&self) -> std::io::Result<()> {
        if self.deadlines.get().is_none() {
            let _ = self.deadlines.set(Deadlines::start()?);
        }
        self.phase.store(START, Ordering::SeqCst);
        Ok(())
    }

    /// No call is taken from now on; every call still waiting is answered
    /// `CLI_NOT_READY` before this returns.
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

    /// `func | module | backends` rows of server (`true`) or client functions, sorted.
    pub(crate) fn rows(&self, servers: bool) -> Vec<Vec<String>> {
        let routes = self.routes();
        let mut rows: Vec<(String, String)> = if servers {
            read(&self.servers)
                .iter()
                .flat_map(|(f, list)| list.iter().map(move |s| (f.clone(), s.module.clone())))
                .collect()
        } else {
            read(&self.clients).keys().cloned().collect()
        };
        rows.sort();
        rows.into_iter()
            .map(|(func, module)| {
                let rules = if servers {
                    &routes.servers
                } else {
                    &routes.clients
                };
                let backends = rules.backends_for(&func).unwrap_or_default().join(",");
                vec![func, module, backends]
            })
            .collect()
    }

    fn refuse(&self, reply: RawRpcReply, status: RpcStatus, detail: String) {
        self.stats.failed.fetch_add(1, Ordering::Relaxed);
        if let Some(held) = self.warn.admit() {
            let more = if held > 0 {
                format!(" ({held} more refusals since the last report)")
            } else {
                String::new()
            };
            tracing::warn!(target: "aimrt", "Rpc call refused: {detail}: {status}{more}");
        }
        reply.complete(status, None, &[], &detail);
    }
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

    pub(crate) fn register_service(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        rsp_ts: &'static TypeSupportVtable,
        service: RawServiceFunc,
    ) -> Result<(), String> {
        self.check_registration("service", func)?;
        let mut servers = write(&self.registry.servers);
        let list = servers.entry(func.to_owned()).or_default();
        if list.iter().any(|s| s.module == self.module) {
            return Err(format!(
                "service function '{func}' is registered twice by module '{}' (pkg {})",
                self.module, self.pkg
            ));
        }
        let routes = self.registry.routes();
        match routes.servers.backends_for(func) {
            None => tracing::warn!(target: "aimrt", "service function '{func}' of module '{}' matches no aimrt.rpc.servers_options rule: no backend serves it", self.module),
            Some([]) => tracing::warn!(target: "aimrt", "service function '{func}' of module '{}': its aimrt.rpc.servers_options rule enables no backend: no backend serves it", self.module),
            Some(_) => {}
        }
        list.push(Arc::new(ServerFunc {
            module: self.module.clone(),
            pkg: self.pkg.clone(),
            req_ts,
            rsp_ts,
            service,
        }));
        Ok(())
    }

    pub(crate) fn register_client(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        _rsp_ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        self.check_registration("client", func)?;
        let key = (func.to_owned(), self.module.clone());
        let mut clients = write(&self.registry.clients);
        if clients.contains_key(&key) {
            return Err(format!(
                "client function '{func}' is registered twice by module '{}' (pkg {})",
                self.module, self.pkg
            ));
        }
        if self.registry.routes().clients.backends_for(func).is_none() {
            tracing::warn!(target: "aimrt", "client function '{func}' of module '{}' matches no aimrt.rpc.clients_options rule: its calls will be answered CLI_NO_BACKEND_TO_HANDLE (2009)", self.module);
        }
        let request_ids = lock(&self.registry.request_ids)
            .entry(func.to_owned())
            .or_default()
            .clone();
        clients.insert(
            key,
            Arc::new(ClientFunc {
                req_ts,
                request_ids,
            }),
        );
        Ok(())
    }

    /// Invokes `func` for this module; `reply` is completed exactly once.
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
            START => {}
            INIT => {
                return refuse(reply, RpcStatus::CLI_NOT_READY, format!("module '{}' called '{func}' before start; calls are answered from start on", self.module));
            }
            _ => {
                return refuse(reply, RpcStatus::CLI_NOT_READY, format!("module '{}' called '{func}' after RPC shut down", self.module));
            }
        }
        let Some(client) = read(&reg.clients)
            .get(&(func.to_owned(), self.module.clone()))
            .cloned()
        else {
            return refuse(reply, RpcStatus::CLI_FUNC_NOT_REGISTERED, format!("module '{}' called '{func}' without registering it as a client function in initialize", self.module));
        };
        if blocking && on_deadline_thread() {
            return refuse(reply, RpcStatus::CLI_BACKEND_INTERNAL_ERROR, format!("module '{}' made a blocking call of '{func}' on the RPC deadline thread, which answers it; use call_then or call_async there", self.module));
        }
        let mut meta: Vec<(String, String)> = ctx
            .iter()
            .map(|p| (p.key().to_owned(), p.value().to_owned()))
            .collect();
        let id = client
            .request_ids
            .fetch_add(1, Ordering::Relaxed)
            .wrapping_add(1);
        set(&mut meta, meta_keys::REQUEST_ID, &id.to_string());
        let format = match get(&meta, meta_keys::SERIALIZATION_TYPE) {
            Some(f) if !f.is_empty() => f.to_owned(),
            _ => {
                let default = formats_of(client.req_ts).into_iter().next().unwrap_or_default();
                set(&mut meta, meta_keys::SERIALIZATION_TYPE, &default);
                default
            }
        };
        let formats = formats_of(client.req_ts);
        if !formats.iter().any(|f| *f == format) {
            return refuse(reply, RpcStatus::CLI_INVALID_SERIALIZATION_TYPE, format!("call of '{func}': aimrt-serialization_type is '{format}', which '{}' does not support; it supports {}", type_name_of(client.req_ts), formats.join(", ")));
        }
        let timeout = if timeout_ns == 0 {
            DEFAULT_TIMEOUT
        } else {
            Duration::from_nanos(timeout_ns)
        };
        let routes = reg.routes();
        let listed = routes.clients.backends_for(func).unwrap_or_default();
        let to_addr = get(&meta, meta_keys::TO_ADDR).unwrap_or("").to_owned();
        let backend = if to_addr.is_empty() {
            match listed.first() {
                Some(b) => {
                    let b = b.clone();
                    set(&mut meta, meta_keys::BACKEND, &b);
                    b
                }
                None => {
                    return refuse(reply, RpcStatus::CLI_NO_BACKEND_TO_HANDLE, format!("'{func}' matches no aimrt.rpc.clients_options rule with a backend"));
                }
            }
        } else {
            match to_addr.split_once("://") {
                Some((scheme, _)) if listed.iter().any(|b| b == scheme) => scheme.to_owned(),
                _ => {
                    return refuse(reply, RpcStatus::CLI_INVALID_ADDR, format!("call of '{func}': aimrt-to_addr '{to_addr}' does not start with <backend>:// naming one of its backends ({})", listed.join(", ")));
                }
            }
        };
        if backend != LOCAL {
            return refuse(reply, RpcStatus::CLI_BACKEND_INTERNAL_ERROR, format!("call of '{func}': rpc backend '{backend}' does not carry module client calls yet; list local first in its clients_options rule"));
        }
        let server = match self.pick_server(func, &to_addr) {
            Ok(s) => s,
            Err((status, detail)) => return refuse(reply, status, detail),
        };
        if blocking {
            if let Some(exec) = server.service.executor() {
                if exec.thread_safe() && exec.is_in_current_executor() {
                    return refuse(reply, RpcStatus::CLI_BACKEND_INTERNAL_ERROR, format!("module '{}' made a blocking call of '{func}' on executor '{}', which runs the service one task at a time and so could never answer it; use call_then or call_async there", self.module, exec.name()));
                }
            }
        }
        let call = Arc::new(Call {
            registry: Arc::downgrade(&self.registry),
            func: func.to_owned(),
            reply: Mutex::new(Some(reply)),
            rsp_ts,
            server_rsp_ts: server.rsp_ts,
            format: format.clone(),
            blocking,
        });
        let deadlines = reg.deadlines.get();
        let weak: Weak<dyn Expire> = Arc::downgrade(&call) as Weak<dyn Expire>;
        if !deadlines.is_some_and(|d| d.add(Instant::now() + timeout, weak)) {
            return call.answer_from_runtime(RpcStatus::CLI_NOT_READY, format!("call of '{func}' arrived while RPC shut down"));
        }
        // The request as an object of the server's table: shared when the tables are the
        // same (same library), else encoded once and decoded once.
        let req = if std::ptr::eq(req.type_support(), server.req_ts) {
            req
        } else {
            let bytes = match req.encode(&format) {
                Ok(b) => b,
                Err(e) => return call.answer_from_runtime(RpcStatus::CLI_SERIALIZATION_FAILED, format!("call of '{func}': cannot serialize the request as {format}: {e}")),
            };
            match RawMessage::decode(server.req_ts, &format, &bytes) {
                Ok(m) => m,
                Err(e) => return call.answer_from_runtime(RpcStatus::SVR_DESERIALIZATION_FAILED, format!("call of '{func}': module '{}' cannot deserialize the request ({format}): {e}", server.module)),
            }
        };
        for (k, v) in [
            (meta_keys::FUNCTION_NAME, func),
            (meta_keys::BACKEND, LOCAL),
            (meta_keys::FROM_PKG, self.pkg.as_str()),
            (meta_keys::FROM_MODULE, self.module.as_str()),
            (meta_keys::RESPONSE_ID, &id.to_string()),
        ] {
            set(&mut meta, k, v);
        }
        let pairs = meta_of(meta.iter().map(|(k, v)| (k.as_str(), v.as_str())));
        let answer = call.clone();
        let timeout_ns = u64::try_from(timeout.as_nanos()).unwrap_or(u64::MAX);
        server.service.call(
            &pairs,
            timeout_ns,
            req,
            RawRpcReply::new(move |parts| answer.answer_from_service(parts)),
        );
    }

    /// The server of `func` for a call with `to_addr` (`local://rpc/…?pkg_path=…&module_name=…`).
    fn pick_server(&self, func: &str, to_addr: &str) -> Result<Arc<ServerFunc>, (RpcStatus, String)> {
        let servers = read(&self.registry.servers);
        let routes = self.registry.routes();
        let reachable: Vec<&Arc<ServerFunc>> = if routes.servers.enables(func, LOCAL) {
            servers.get(func).map(|l| l.iter().collect()).unwrap_or_default()
        } else {
            Vec::new()
        };
        if reachable.is_empty() {
            let why = if servers.get(func).is_some_and(|l| !l.is_empty()) {
                "is registered, but its aimrt.rpc.servers_options rule does not enable local"
            } else {
                "is not registered by any module"
            };
            return Err((RpcStatus::SVR_NOT_FOUND, format!("service function '{func}' {why}")));
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
        let found = reachable.iter().find(|s| {
            pkg.is_none_or(|p| p == s.pkg) && module.is_none_or(|m| m == s.module)
        });
        found.map(|s| (*s).clone()).ok_or_else(|| {
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

fn get<'a>(meta: &'a [(String, String)], key: &str) -> Option<&'a str> {
    meta.iter()
        .find(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
}

fn set(meta: &mut Vec<(String, String)>, key: &str, value: &str) {
    match meta.iter_mut().find(|(k, _)| k == key) {
        Some((_, v)) => value.clone_into(v),
        None => meta.push((key.to_owned(), value.to_owned())),
    }
}

/// One call in flight: whoever takes the reply first answers it.
struct Call {
    registry: Weak<RpcRegistry>,
    func: String,
    reply: Mutex<Option<RawRpcReply>>,
    /// The caller's response table.
    rsp_ts: &'static TypeSupportVtable,
    /// The service's response table.
    server_rsp_ts: &'static TypeSupportVtable,
    format: String,
    blocking: bool,
}

impl Call {
    fn take(&self) -> Option<RawRpcReply> {
        lock(&self.reply).take()
    }

    fn count(&self, f: impl FnOnce(&CallStats)) {
        if let Some(r) = self.registry.upgrade() {
            f(&r.stats);
        }
    }

    /// The runtime answers (refusal before the service ran, deadline, shutdown).
    fn answer_from_runtime(&self, status: RpcStatus, detail: String) {
        if let Some(reply) = self.take() {
            match self.registry.upgrade() {
                Some(r) => r.refuse(reply, status, detail),
                None => reply.complete(status, None, &[], &detail),
            }
        }
    }

    /// The service answered.
    fn answer_from_service(&self, parts: ReplyParts) {
        let Some(reply) = self.take() else {
            self.count(|s| {
                s.late.fetch_add(1, Ordering::Relaxed);
            });
            tracing::trace!(target: "aimrt", "late answer of '{}' dropped: the call was answered already", self.func);
            return;
        };
        let ReplyParts {
            status, rsp, detail, ..
        } = parts;
        if !status.is_ok() {
            if detail.is_empty() {
                self.count(|s| {
                    s.failed.fetch_add(1, Ordering::Relaxed);
                });
                return reply.complete(status, None, &[], &detail);
            }
            // The module side says why (a panic, a dropped reply): log it.
            return self.fail(reply, status, format!("the service of '{}' failed: {detail}", self.func));
        }
        let rsp = match rsp {
            Some(m) if std::ptr::eq(m.type_support(), self.rsp_ts) => m,
            Some(m) if std::ptr::eq(m.type_support(), self.server_rsp_ts) => {
                let bytes = match m.encode(&self.format) {
                    Ok(b) => b,
                    Err(e) => {
                        return self.fail(reply, RpcStatus::SVR_SERIALIZATION_FAILED, format!("the response of '{}' cannot be serialized as {}: {e}", self.func, self.format));
                    }
                };
                match RawMessage::decode(self.rsp_ts, &self.format, &bytes) {
                    Ok(m) => m,
                    Err(e) => {
                        return self.fail(reply, RpcStatus::CLI_DESERIALIZATION_FAILED, format!("the response of '{}' cannot be deserialized ({}): {e}", self.func, self.format));
                    }
                }
            }
            _ => {
                return self.fail(reply, RpcStatus::SVR_HANDLE_FAILED, format!("the service of '{}' answered OK without a response of its registered type", self.func));
            }
        };
        reply.complete(RpcStatus::OK, Some(rsp), &[], "");
    }

    fn fail(&self, reply: RawRpcReply, status: RpcStatus, detail: String) {
        match self.registry.upgrade() {
            Some(r) => r.refuse(reply, status, detail),
            None => reply.complete(status, None, &[], &detail),
        }
    }
}

impl Expire for Call {
    fn expire(&self) {
        let Some(reply) = self.take() else { return };
        self.count(|s| {
            s.timed_out.fetch_add(1, Ordering::Relaxed);
            s.failed.fetch_add(1, Ordering::Relaxed);
        });
        let detail = format!("call of '{}' timed out", self.func);
        let executor = self
            .registry
            .upgrade()
            .and_then(|r| r.routes().timeout_executor);
        match executor {
            // A blocking caller only needs waking; a callback runs on the timeout executor
            // (AimRT's `timeout_executor`), or here if it refuses.
            Some(exec) if !self.blocking => {
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
            _ => reply.complete(RpcStatus::TIMEOUT, None, &[], &detail),
        }
    }

    fn abandon(&self) {
        self.answer_from_runtime(
            RpcStatus::CLI_NOT_READY,
            format!("call of '{}' was in flight when RPC shut down", self.func),
        );
    }
}
