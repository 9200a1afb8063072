//! RPC: services that plugins register under full function names, module service and
//! client functions ([`calls`]), backends (the built-in `local`; `http` from `net_plugin`)
//! that carry calls, and `aimrt.rpc` deciding which backend may reach which function
//! (`servers_options` / `clients_options`: regex full match, first match wins,
//! `enable_backends`).

pub(crate) mod calls;
mod filter;
mod plugin_service;

pub(crate) use self::filter::RegisteredRpcFilters;
mod deadline;

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock, RwLock};

use crate::config::Config;
use crate::plugin::BackendType;
use crate::routing::{listed_backends, Rules};
use crate::Error;
use aimrt_plugin_api::__private::did_you_mean;
use aimrt_plugin_api::ffi::{meta_of, RawExecutor, RawHost, RawRpcBackend, RawService};
use aimrt_plugin_api::rpc::CallFilterSide;
use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall, BackendReply, CallView};
use aimrt_plugin_api::{HostServices, Responder, ServiceError};
use calls::{Routes, RpcRegistry, LOCAL};

struct Registered {
    service: RawService,
    owner: String,
    /// The server filters its `servers_options` rule lists (set when RPC is configured).
    filters: filter::RpcChain,
}

/// What plugins registered for module RPC.
pub(crate) struct FromPlugins {
    /// RPC backends, by type.
    pub(crate) backends: BTreeMap<String, BackendType<RawRpcBackend>>,
    /// Context meta keys passed from server to client contexts.
    pub(crate) passed_keys: Vec<String>,
    /// RPC filters.
    pub(crate) filters: RegisteredRpcFilters,
}

/// Every registered service, and the server rules once the config is read.
#[derive(Default)]
pub(crate) struct ServiceTable {
    funcs: RwLock<BTreeMap<String, Registered>>,
    rules: OnceLock<Rules>,
    /// Calls backends received for plugins' services.
    calls: AtomicU64,
    /// Those answered with a status other than OK.
    failed: AtomicU64,
}

impl ServiceTable {
    /// Records a service; a name registered twice is refused.
    pub(crate) fn register(
        &self,
        func_name: &str,
        service: RawService,
        owner: &str,
    ) -> Result<(), String> {
        if func_name.is_empty() {
            return Err("a service function name must not be empty".into());
        }
        let mut funcs = self.funcs.write().unwrap_or_else(|e| e.into_inner());
        if let Some(existing) = funcs.get(func_name) {
            return Err(format!(
                "service function '{func_name}' is already registered by '{}'",
                existing.owner
            ));
        }
        funcs.insert(
            func_name.to_owned(),
            Registered {
                service,
                owner: owner.to_owned(),
                filters: filter::RpcChain::default(),
            },
        );
        Ok(())
    }

    /// `(function, owner)` of every service, sorted.
    pub(crate) fn list(&self) -> Vec<(String, String)> {
        let funcs = self.funcs.read().unwrap_or_else(|e| e.into_inner());
        funcs
            .iter()
            .map(|(f, r)| (f.clone(), r.owner.clone()))
            .collect()
    }

    /// Logs how many calls backends received for plugins' services and how many failed
    /// (at shutdown; nothing when there were none).
    pub(crate) fn report(&self) {
        let calls = self.calls.load(Ordering::Relaxed);
        if calls > 0 {
            let failed = self.failed.load(Ordering::Relaxed);
            tracing::info!(target: "aimrt", "Plugin services: {calls} calls received through backends, {failed} answered with an error status");
        }
    }

    /// `reply`, counting the call and, when its answer is not OK, its failure.
    fn counted(self: &Arc<Self>, reply: BackendReply) -> BackendReply {
        self.calls.fetch_add(1, Ordering::Relaxed);
        let table = self.clone();
        BackendReply::from_fn(move |answer: BackendAnswer| {
            if !answer.status.is_ok() {
                table.failed.fetch_add(1, Ordering::Relaxed);
            }
            reply.send(answer)
        })
    }

    /// Whether `backend` may reach `func_name`: the first rule whose regex matches the whole
    /// name decides.
    fn enabled(&self, func_name: &str, backend: &str) -> bool {
        self.rules
            .get()
            .is_some_and(|rules| rules.enables(func_name, backend))
    }
}

/// The host handle one caller gets: a backend (checked against `servers_options`) or a
/// plugin calling directly (not checked).
struct Caller {
    table: Arc<ServiceTable>,
    backend: Option<String>,
    /// Module services, for calls a backend received.
    registry: Option<Arc<RpcRegistry>>,
    /// The executors by name, for a backend's options (known before backends initialize).
    executors: HashMap<String, RawExecutor>,
}

impl HostServices for Caller {
    fn call(&self, call: BackendCall, reply: BackendReply) {
        let meta = meta_of(call.meta_pairs());
        self.call_view(
            CallView::new(&call.func, &meta, call.timeout, &call.body),
            reply,
        );
    }

    fn call_view(&self, call: CallView<'_>, reply: BackendReply) {
        let (Some(registry), Some(backend)) = (&self.registry, &self.backend) else {
            return aimrt_plugin_api::rpc::call_through_invoke(self, call.to_call(), reply);
        };
        let funcs = self.table.funcs.read().unwrap_or_else(|e| e.into_inner());
        match funcs.get(call.func) {
            None => {
                drop(funcs);
                let plugin_services = || {
                    let funcs = self.table.funcs.read().unwrap_or_else(|e| e.into_inner());
                    funcs.keys().cloned().collect()
                };
                registry.serve(backend, call, reply, &plugin_services)
            }
            // A plugin's service whose rule lists server filters: they run around it.
            Some(found) if !found.filters.is_empty() && self.table.enabled(call.func, backend) => {
                let reply = self.table.counted(reply);
                let server = plugin_service::PluginServer {
                    func: call.func,
                    owner: &found.owner,
                    service: &found.service,
                    filters: &found.filters,
                };
                registry.serve_plugin(backend, &server, call, reply);
            }
            // A plugin's service: bytes in, bytes out, its error mapped to a status.
            Some(_) => {
                drop(funcs);
                let reply = self.table.counted(reply);
                aimrt_plugin_api::rpc::call_through_invoke(self, call.to_call(), reply)
            }
        }
    }

    fn executor(&self, name: &str) -> Option<RawExecutor> {
        self.executors.get(name).copied()
    }

    fn invoke(&self, func_name: &str, format: &str, request: &[u8], responder: Responder) {
        let funcs = self.table.funcs.read().unwrap_or_else(|e| e.into_inner());
        let Some(found) = funcs.get(func_name) else {
            let hint = aimrt_plugin_api::__private::did_you_mean(
                func_name,
                funcs.keys().map(String::as_str),
            );
            responder.respond(Err(ServiceError::NotFound(format!(
                "no service function '{func_name}' is registered{hint}"
            ))));
            return;
        };
        if let Some(backend) = &self.backend {
            if !self.table.enabled(func_name, backend) {
                responder.respond(Err(ServiceError::NotFound(format!(
                    "service function '{func_name}' is not enabled for the '{backend}' backend; enable it in aimrt.rpc.servers_options"
                ))));
                return;
            }
        }
        tracing::debug!(target: "aimrt", "rpc call '{func_name}' ({format}, {} bytes) from {}", request.len(), self.backend.as_deref().unwrap_or("a plugin"));
        found.service.call(format, request, responder);
    }
}

/// A host handle for plugins that call services directly (the registrar's `host`).
pub(crate) fn direct_host(table: &Arc<ServiceTable>) -> RawHost {
    RawHost::leak(Arc::new(Caller {
        table: table.clone(),
        backend: None,
        registry: None,
        executors: HashMap::new(),
    }))
}

/// Reads the `local` backend's options: `timeout_executor` (an executor with timers, or
/// empty). AimRT's app-mode examples misspell it `timeout_handle_executor`: warned, not
/// refused, as those configs must run (calls time out anyway: the runtime enforces every
/// deadline itself).
fn local_options(
    config: &Config,
    entry: &crate::config::BackendEntry,
    executors: &HashMap<String, RawExecutor>,
) -> Result<Option<RawExecutor>, Error> {
    let Some(options) = entry.options.as_ref() else {
        return Ok(None);
    };
    let map = match &options.value {
        serde_json::Value::Null => return Ok(None),
        serde_json::Value::Object(m) => m,
        other => {
            return Err(config.error(
                options,
                format!("rpc backend 'local': options must be a map, found {other}"),
            ))
        }
    };
    let mut name = None;
    for (key, value) in map {
        match key.as_str() {
            "timeout_executor" => match value {
                serde_json::Value::String(s) => name = Some(s.clone()),
                other => {
                    return Err(config.error(
                        options,
                        format!("rpc backend 'local': timeout_executor must be an executor name, found {other}"),
                    ))
                }
            },
            "timeout_handle_executor" => {
                tracing::warn!(target: "aimrt", "{}: rpc backend 'local' has no option 'timeout_handle_executor' (a misspelling in AimRT's example configs); did you mean 'timeout_executor'? It is ignored; calls still time out, answered on the runtime's deadline thread", config.at(options));
            }
            other => {
                return Err(config.error(
                    options,
                    format!(
                        "rpc backend 'local' has no option '{other}'{}; it has: timeout_executor",
                        did_you_mean(other, ["timeout_executor"])
                    ),
                ))
            }
        }
    }
    let Some(name) = name.filter(|n| !n.is_empty()) else {
        return Ok(None);
    };
    let Some(raw) = executors.get(&name) else {
        return Err(config.error(
            options,
            format!(
                "rpc backend 'local': timeout_executor '{name}' is not an executor{}; name one from aimrt.executor.executors that supports timers",
                did_you_mean(&name, executors.keys().map(String::as_str))
            ),
        ));
    };
    if !raw.supports_timer_schedule() {
        return Err(config.error(
            options,
            format!(
                "rpc backend 'local': timeout_executor '{name}' is a {} executor, which has no timers; use one that has (e.g. asio_thread or time_wheel)",
                raw.type_name()
            ),
        ));
    }
    Ok(Some(*raw))
}

/// The configured backends, in config order.
#[derive(Default)]
pub(crate) struct RpcManager {
    active: Vec<(String, &'static RawRpcBackend)>,
    started: usize,
    /// The built-in `local` backend's options as read, where the config lists it.
    local_options: Option<serde_json::Value>,
}

impl RpcManager {
    /// The options each backend reported as its `init` read them, by type.
    pub(crate) fn reported_options(&self) -> BTreeMap<String, serde_json::Value> {
        let reported =
            (self.active.iter()).map(|(name, raw)| (name.as_str(), raw.reported_options()));
        let mut by_name = crate::config::ReportedOptions::by_name("rpc backend", reported);
        by_name.extend(self.local_options.clone().map(|o| (LOCAL.to_owned(), o)));
        by_name
    }

    /// Tells each backend the server rules route a plugin's service to that it serves it,
    /// as a module's (AimRT's plugins register through the same handle): a backend that
    /// listens per function (zenoh) serves it from then on; http also routes it without.
    /// A backend of ABI 1.1, from before module functions, keeps reaching plugins'
    /// services through its host only.
    fn offer_plugin_services(&self, table: &ServiceTable, servers: &Rules) -> Result<(), Error> {
        // A copy of the names: no lock is held while a backend runs.
        for (func, owner) in table.list() {
            for name in servers.backends_for(&func).unwrap_or_default() {
                let Some((_, backend)) = self.active.iter().find(|(n, _)| n == name) else {
                    continue;
                };
                if !backend.carries_module_calls() {
                    continue;
                }
                backend
                    .register_service_func(&func)
                    .map_err(|message| Error::Plugin {
                        plugin: owner.clone(),
                        action: "serve its service",
                        message: format!("rpc backend '{name}' refused '{func}': {message}"),
                    })?;
            }
        }
        Ok(())
    }

    /// Reads `aimrt.rpc`, compiles the rules, initialises each listed backend and hands
    /// the module routes to `registry`.
    pub(crate) fn configure(
        &mut self,
        config: &Config,
        table: &Arc<ServiceTable>,
        plugins: FromPlugins,
        registry: &Arc<RpcRegistry>,
        executors: &HashMap<String, RawExecutor>,
    ) -> Result<(), Error> {
        let FromPlugins {
            backends: mut registered,
            passed_keys,
            filters,
        } = plugins;
        let Some(section) = config.aimrt.rpc.as_ref() else {
            let _ = table.rules.set(Rules::default());
            registry.set_routes(Routes {
                passed_keys,
                filters,
                ..Routes::default()
            });
            for (name, b) in &registered {
                tracing::info!(target: "aimrt", "rpc backend '{name}' of '{}' is not started: the config has no aimrt.rpc section listing it", b.owner);
            }
            return Ok(());
        };
        let listed = listed_backends(config, &section.backends, "aimrt.rpc")?;
        let mut timeout_executor = None;
        for entry in &section.backends {
            let ty = entry.type_name.value.as_str();
            if ty == LOCAL && !registered.contains_key(LOCAL) {
                timeout_executor = local_options(config, entry, executors)?;
                let name = timeout_executor
                    .map(|e| e.name().to_owned())
                    .unwrap_or_default();
                self.local_options = Some(serde_json::json!({ "timeout_executor": name }));
                continue;
            }
            let Some(backend) = registered.remove(ty) else {
                let known: Vec<String> = self
                    .active
                    .iter()
                    .map(|(n, _)| n.clone())
                    .chain(registered.keys().cloned())
                    .chain([LOCAL.to_owned()])
                    .collect();
                return Err(config.error(
                    &entry.type_name,
                    format!(
                        "unknown rpc backend type '{ty}'{}; known: {} (a plugin provides each backend, e.g. net_plugin provides http)",
                        did_you_mean(ty, known.iter().map(String::as_str)),
                        known.join(", ")
                    ),
                ));
            };
            let (options, location) = config.options_of(entry.options.as_ref(), &entry.type_name);
            let host = RawHost::leak(Arc::new(Caller {
                table: table.clone(),
                backend: Some(ty.to_owned()),
                registry: Some(registry.clone()),
                executors: executors.clone(),
            }));
            backend
                .raw
                .init(&options, &location, host)
                .map_err(|message| Error::Plugin {
                    plugin: backend.owner.clone(),
                    action: "initialize its rpc backend",
                    message,
                })?;
            // Backends live in libraries that are never unloaded and may keep threads:
            // never dropped.
            self.active
                .push((ty.to_owned(), Box::leak(Box::new(backend.raw))));
        }
        for (name, b) in &registered {
            tracing::info!(target: "aimrt", "rpc backend '{name}' of '{}' is not started: aimrt.rpc.backends does not list it", b.owner);
        }
        let servers = Rules::compile(
            config,
            &section.servers_options,
            &listed,
            &filters.names(CallFilterSide::Server),
            "aimrt.rpc",
        )?;
        // Plugins' services (registered in their initialize, before this) get their rule's
        // server filters, as module services do.
        for (func, registered) in table
            .funcs
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .iter_mut()
        {
            registered.filters = filters.chain(CallFilterSide::Server, servers.filters_for(func));
        }
        let _ = table.rules.set(servers.clone());
        self.offer_plugin_services(table, &servers)?;
        registry.set_routes(Routes {
            clients: Rules::compile(
                config,
                &section.clients_options,
                &listed,
                &filters.names(CallFilterSide::Client),
                "aimrt.rpc",
            )?,
            servers,
            timeout_executor,
            backends: self.active.iter().map(|(n, b)| (n.clone(), *b)).collect(),
            passed_keys,
            filters,
        });
        Ok(())
    }

    /// Starts every configured backend, in config order.
    pub(crate) fn start(&mut self) -> Result<(), Error> {
        for (name, backend) in &self.active {
            backend.start().map_err(|message| Error::Rpc {
                backend: name.clone(),
                message,
            })?;
            self.started += 1;
        }
        Ok(())
    }

    /// Stops the started backends in reverse order: no call arrives after this.
    pub(crate) fn shutdown(&mut self) {
        let started = std::mem::take(&mut self.started);
        for (_, backend) in self.active[..started].iter().rev() {
            backend.shutdown();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calls_reach_only_registered_and_enabled_functions() {
        let table = Arc::new(ServiceTable::default());
        let _ = table.rules.set(Rules::test(&[("pb:/svc/Echo", &["http"])]));
        let echo = aimrt_plugin_api::__private::service(|_, req: &[u8]| Ok(req.to_vec()));
        table.register("pb:/svc/Echo", echo, "test").unwrap();
        let again = aimrt_plugin_api::__private::service(|_, _: &[u8]| Ok(Vec::new()));
        assert!(table
            .register("pb:/svc/Echo", again, "other")
            .unwrap_err()
            .contains("already registered by 'test'"));
        let call = |backend: Option<&str>, func: &str| {
            let caller = Caller {
                table: table.clone(),
                backend: backend.map(str::to_owned),
                registry: None,
                executors: HashMap::new(),
            };
            let (tx, rx) = std::sync::mpsc::channel();
            caller.invoke(
                func,
                "json",
                b"{}",
                Responder::from_fn(move |r| tx.send(r).unwrap()),
            );
            rx.recv_timeout(std::time::Duration::from_secs(5)).unwrap()
        };
        assert_eq!(call(Some("http"), "pb:/svc/Echo"), Ok(b"{}".to_vec()));
        assert!(
            matches!(call(Some("local"), "pb:/svc/Echo"), Err(ServiceError::NotFound(m)) if m.contains("not enabled for the 'local' backend"))
        );
        assert!(
            matches!(call(Some("http"), "pb:/svc/Nope"), Err(ServiceError::NotFound(m)) if m.contains("no service function"))
        );
        // A plugin calling directly is not subject to servers_options.
        assert_eq!(call(None, "pb:/svc/Echo"), Ok(b"{}".to_vec()));
    }
}
