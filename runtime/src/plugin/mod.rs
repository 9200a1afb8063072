//! Plugin loading and the registry of what plugins contribute.

mod core;
mod elf;
pub(crate) mod loader;

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use aimrt_plugin_api::__private::RegistrarHost;
use aimrt_plugin_api::ffi::{
    type_name_of, RawChannelBackend, RawControl, RawCore, RawExecutor, RawExecutorType, RawHost,
    RawLogger, RawPlugin, RawRpcBackend, RawService, RawThreadFactory, TypeSupportVtable,
};
use aimrt_plugin_api::{LogLevel, Plugin};

use crate::channel::ChannelManager;
use crate::config::Config;
use crate::log::{LogHub, Logger};
use crate::rpc::{direct_host, ServiceTable};
use crate::Error;
use loader::Library;

/// An executor type and who registered it.
pub(crate) struct ExecutorType {
    pub(crate) raw: RawExecutorType,
    pub(crate) bind_keys: Vec<String>,
    pub(crate) owner: String,
}

/// A backend (rpc or channel) and the plugin that registered it.
pub(crate) struct BackendType<B> {
    pub(crate) raw: B,
    pub(crate) owner: String,
}

/// A log backend type and the plugin that registered it.
pub(crate) type LogBackendType = BackendType<aimrt_plugin_api::ffi::RawLogBackendType>;

/// Records `backend` under its type name; a type registered twice is refused.
fn register_backend<B>(
    map: &mut BTreeMap<String, BackendType<B>>,
    kind: &str,
    name: String,
    backend: B,
    owner: &str,
) -> Result<(), String> {
    if let Some(existing) = map.get(&name) {
        return Err(format!(
            "{kind} backend '{name}' is already registered by '{}'",
            existing.owner
        ));
    }
    map.insert(
        name,
        BackendType {
            raw: backend,
            owner: owner.to_owned(),
        },
    );
    Ok(())
}

/// What the host hands every plugin's registrar.
#[derive(Clone, Copy)]
pub(crate) struct HostHandles {
    /// The thread factory for executor threads.
    pub(crate) threads: RawThreadFactory,
    /// The runtime's control (ABI 1.13).
    pub(crate) control: RawControl,
}

/// Loaded plugins and the executor types they registered.
#[derive(Default)]
pub(crate) struct PluginManager {
    plugins: Vec<(String, RawPlugin)>,
    /// Name and where it came from (a library path, or `linked into aimrt_main`).
    pub(crate) sources: Vec<(String, String)>,
    pub(crate) executor_types: BTreeMap<String, ExecutorType>,
    /// Services registered by plugins.
    pub(crate) services: Arc<ServiceTable>,
    /// RPC backends registered by plugins, by type.
    pub(crate) rpc_backends: BTreeMap<String, BackendType<RawRpcBackend>>,
    /// Channel backends registered by plugins, by type.
    pub(crate) channel_backends: BTreeMap<String, BackendType<RawChannelBackend>>,
    /// Channel filters registered by plugins.
    pub(crate) channel_filters: crate::channel::RegisteredFilters,
    /// RPC filters registered by plugins.
    pub(crate) rpc_filters: crate::rpc::RegisteredRpcFilters,
    /// Log backend types registered by plugins, by name.
    pub(crate) log_backend_types: BTreeMap<String, LogBackendType>,
    /// The options each plugin reported as it reads them, by plugin name (the dump's).
    pub(crate) normalized_options: BTreeMap<String, serde_json::Value>,
    /// Context meta keys plugins registered to pass from server to client contexts.
    pub(crate) passed_keys: Vec<String>,
    /// Message types of the type support packages plugins loaded: table and library.
    type_supports: BTreeMap<String, (&'static TypeSupportVtable, String)>,
    /// The type support packages loaded, by canonical path: their type names.
    ts_pkgs: BTreeMap<String, Vec<String>>,
    /// The cores plugins asked for, by plugin name.
    cores: Vec<(String, Arc<core::PluginCore>, RawCore)>,
    started: usize,
    shut_down: bool,
}

struct Registering<'a> {
    types: &'a mut BTreeMap<String, ExecutorType>,
    services: &'a Arc<ServiceTable>,
    rpc_backends: &'a mut BTreeMap<String, BackendType<RawRpcBackend>>,
    channel_backends: &'a mut BTreeMap<String, BackendType<RawChannelBackend>>,
    channel_filters: &'a mut crate::channel::RegisteredFilters,
    rpc_filters: &'a mut crate::rpc::RegisteredRpcFilters,
    log_backend_types: &'a mut BTreeMap<String, LogBackendType>,
    normalized_options: &'a mut BTreeMap<String, serde_json::Value>,
    passed_keys: &'a mut Vec<String>,
    type_supports: &'a mut BTreeMap<String, (&'static TypeSupportVtable, String)>,
    ts_pkgs: &'a mut BTreeMap<String, Vec<String>>,
    cores: &'a mut Vec<(String, Arc<core::PluginCore>, RawCore)>,
    owner: &'a str,
    /// The plugin's library (or `linked into aimrt_main`).
    library: &'a str,
    builtin: bool,
    handles: HostHandles,
    core_lvl: LogLevel,
    hub: &'a Arc<LogHub>,
}

impl RegistrarHost for Registering<'_> {
    fn register_executor_type(&mut self, ty: RawExecutorType) -> Result<(), String> {
        let name = ty.type_name();
        if let Some(existing) = self.types.get(&name) {
            if self.builtin {
                tracing::info!(
                    target: "aimrt",
                    "built-in executor type '{name}' of '{}' skipped: plugin '{}' already registered it",
                    self.owner,
                    existing.owner
                );
                return Ok(());
            }
            return Err(format!(
                "executor type '{name}' is already registered by '{}'",
                existing.owner
            ));
        }
        let bind_keys = ty.bind_keys();
        self.types.insert(
            name,
            ExecutorType {
                raw: ty,
                bind_keys,
                owner: self.owner.to_owned(),
            },
        );
        Ok(())
    }

    fn control(&self) -> RawControl {
        self.handles.control
    }

    fn thread_factory(&self) -> RawThreadFactory {
        self.handles.threads
    }

    fn register_service(&mut self, func_name: &str, service: RawService) -> Result<(), String> {
        self.services.register(func_name, service, self.owner)?;
        tracing::debug!(target: "aimrt", "plugin '{}' registered service function '{func_name}'", self.owner);
        Ok(())
    }

    fn register_rpc_backend(&mut self, backend: RawRpcBackend) -> Result<(), String> {
        let name = backend.type_name();
        register_backend(self.rpc_backends, "rpc", name, backend, self.owner)
    }

    fn register_channel_backend(&mut self, backend: RawChannelBackend) -> Result<(), String> {
        let name = backend.type_name();
        if name == "local" {
            return Err("channel backend 'local' is built into the runtime; give the backend another type name".into());
        }
        if !backend.is_complete() {
            return Err(format!("channel backend '{name}' was built against ABI 1.0, whose channel backends cannot carry messages; rebuild it against aimrt-plugin-api {}", aimrt_plugin_api::ffi::API_VERSION));
        }
        register_backend(self.channel_backends, "channel", name, backend, self.owner)
    }

    fn host(&self) -> RawHost {
        direct_host(self.services)
    }

    fn register_channel_filter(
        &mut self,
        name: &str,
        side: aimrt_plugin_api::channel::FilterSide,
        filter: aimrt_plugin_api::ffi::RawChannelFilter,
    ) -> Result<(), String> {
        self.channel_filters
            .register(name, side, filter, self.owner)
    }

    fn register_rpc_filter(
        &mut self,
        name: &str,
        side: aimrt_plugin_api::rpc::CallFilterSide,
        filter: aimrt_plugin_api::ffi::RawRpcFilter,
    ) -> Result<(), String> {
        self.rpc_filters.register(name, side, filter, self.owner)
    }

    fn register_log_backend_type(
        &mut self,
        ty: aimrt_plugin_api::ffi::RawLogBackendType,
    ) -> Result<(), String> {
        let name = ty.type_name();
        if name.is_empty() {
            return Err("a log backend type needs a name".into());
        }
        if crate::log::settings::BACKEND_TYPES.contains(&name.as_str()) {
            return Err(format!(
                "log backend type '{name}' is built into the runtime; give the type another name"
            ));
        }
        tracing::debug!(target: "aimrt", "plugin '{}' registers log backend type '{name}'", self.owner);
        register_backend(self.log_backend_types, "log", name, ty, self.owner)
    }

    fn update_options(&mut self, json: &str) -> Result<(), String> {
        let value = serde_json::from_str(json).map_err(|e| {
            format!(
                "plugin '{}' reported options that are not JSON: {e}",
                self.owner
            )
        })?;
        self.normalized_options.insert(self.owner.to_owned(), value);
        Ok(())
    }

    fn add_passed_context_meta_key(&mut self, key: &str) -> Result<(), String> {
        if key.is_empty() {
            return Err("a passed context meta key must not be empty".into());
        }
        if !self.passed_keys.iter().any(|k| k == key) {
            self.passed_keys.push(key.to_owned());
            tracing::debug!(target: "aimrt", "plugin '{}' passes context meta key '{key}' from server to client contexts", self.owner);
        }
        Ok(())
    }

    fn load_type_support_pkg(&mut self, path: &str) -> Result<Vec<String>, String> {
        if let Some(names) = std::fs::canonicalize(path)
            .ok()
            .and_then(|full| self.ts_pkgs.get(&full.display().to_string()))
        {
            return Ok(names.clone());
        }
        let what = format!("type support pkg of plugin '{}'", self.owner);
        let lib = Library::open(&what, path, self.owner, self.core_lvl, self.hub)
            .map_err(|e| e.to_string())?;
        let tables = lib.type_supports();
        let full = lib.path.display().to_string();
        if tables.is_empty() {
            return Err(format!(
                "{full} offers no message types; a type support package calls aimrt_plugin_api::export_type_support! (ABI 1.3)"
            ));
        }
        let mut names = Vec::with_capacity(tables.len());
        for ts in tables {
            let name = type_name_of(ts).to_owned();
            match self.type_supports.get(&name) {
                Some((_, first)) => {
                    tracing::warn!(target: "aimrt", "message type '{name}' of {full} is already loaded from {first}; the first is kept");
                }
                None => {
                    self.type_supports.insert(name.clone(), (ts, full.clone()));
                }
            }
            names.push(name);
        }
        tracing::info!(target: "aimrt", "plugin '{}' loaded type support pkg {full}: {}", self.owner, names.join(", "));
        self.ts_pkgs.insert(full, names.clone());
        Ok(names)
    }

    fn find_type_support(&self, name: &str) -> Option<&'static TypeSupportVtable> {
        self.type_supports.get(name).map(|(ts, _)| *ts)
    }

    fn core(&mut self) -> RawCore {
        if let Some((_, _, raw)) = self.cores.iter().find(|(n, _, _)| n == self.owner) {
            return *raw;
        }
        let logger = RawLogger::leak(Logger::new(self.owner, self.core_lvl, self.hub));
        let core = Arc::new(core::PluginCore::new(self.owner, self.library, logger));
        let raw = RawCore::leak(core.clone());
        self.cores.push((self.owner.to_owned(), core, raw));
        raw
    }
}

impl PluginManager {
    /// Loads and initialises the plugins of `aimrt.plugin.plugins`, then the built-in ones;
    /// once `stop` is set, none after the plugin under way.
    pub(crate) fn load(
        &mut self,
        config: &Config,
        builtins: Vec<Box<dyn Plugin>>,
        handles: HostHandles,
        core_lvl: LogLevel,
        hub: &Arc<LogHub>,
        stop: &AtomicBool,
    ) -> Result<(), Error> {
        let entries = config
            .aimrt
            .plugin
            .as_ref()
            .map(|p| p.plugins.as_slice())
            .unwrap_or_default();
        for entry in entries {
            let name = &entry.name.value;
            if stop.load(Ordering::SeqCst) {
                tracing::info!(target: "aimrt", "Shutdown requested: plugin '{name}' and the plugins after it are not loaded.");
                return Ok(());
            }
            if self.plugins.iter().any(|(n, _)| n == name) {
                return Err(config.error(&entry.name, format!("duplicate plugin name '{name}'; each entry of aimrt.plugin.plugins needs its own name")));
            }
            if entry.path.value.is_empty() {
                return Err(config.error(
                    &entry.path,
                    format!(
                        "plugin '{name}' has an empty path; give the path of its shared library"
                    ),
                ));
            }
            let what = format!("plugin '{name}' at {}", config.at(&entry.path));
            let lib = Library::open(&what, &entry.path.value, name, core_lvl, hub)?;
            if !lib.has_plugin() {
                return Err(Error::Library {
                    what,
                    path: lib.path.display().to_string(),
                    message:
                        "exports no plugin; a plugin library calls aimrt_plugin_api::export_plugin!"
                            .into(),
                });
            }
            let mut plugin = lib.create_plugin().map_err(|m| Error::Library {
                what: what.clone(),
                path: lib.path.display().to_string(),
                message: m,
            })?;
            let real = plugin.name();
            if &real != name {
                return Err(config.error(
                    &entry.name,
                    format!(
                        "the library {} holds plugin '{real}', not '{name}'; set name: {real}",
                        lib.path.display()
                    ),
                ));
            }
            let (options, location) = config.options_of(entry.options.as_ref(), &entry.name);
            let library = lib.path.display().to_string();
            let logs = (core_lvl, hub);
            self.init_one(
                name,
                &library,
                &mut plugin,
                &options,
                &location,
                false,
                handles,
                logs,
            )?;
            tracing::info!(target: "aimrt", "Load plugin '{name}' from {} succeeded.", lib.path.display());
            self.sources
                .push((name.clone(), lib.path.display().to_string()));
            self.plugins.push((name.clone(), plugin));
        }
        if stop.load(Ordering::SeqCst) {
            return Ok(());
        }
        for builtin in builtins {
            let mut plugin = RawPlugin::new(builtin);
            let name = plugin.name();
            let logs = (core_lvl, hub);
            self.init_one(
                &name,
                "linked into aimrt_main",
                &mut plugin,
                "null",
                "built-in",
                true,
                handles,
                logs,
            )?;
            self.sources
                .push((name.clone(), "linked into aimrt_main".to_owned()));
            self.plugins.push((name, plugin));
        }
        Ok(())
    }

    #[allow(clippy::too_many_arguments)] // one plugin's setup, spelled out
    fn init_one(
        &mut self,
        name: &str,
        library: &str,
        plugin: &mut RawPlugin,
        options: &str,
        location: &str,
        builtin: bool,
        handles: HostHandles,
        (core_lvl, hub): (LogLevel, &Arc<LogHub>),
    ) -> Result<(), Error> {
        let mut reg = Registering {
            types: &mut self.executor_types,
            services: &self.services,
            rpc_backends: &mut self.rpc_backends,
            channel_backends: &mut self.channel_backends,
            channel_filters: &mut self.channel_filters,
            rpc_filters: &mut self.rpc_filters,
            log_backend_types: &mut self.log_backend_types,
            normalized_options: &mut self.normalized_options,
            passed_keys: &mut self.passed_keys,
            type_supports: &mut self.type_supports,
            ts_pkgs: &mut self.ts_pkgs,
            cores: &mut self.cores,
            owner: name,
            library,
            builtin,
            handles,
            core_lvl,
            hub,
        };
        plugin
            .init(&mut reg, options, location)
            .map_err(|message| Error::Plugin {
                plugin: name.to_owned(),
                action: "initialize",
                message,
            })
    }

    /// Gives the plugins' cores the channel, and applies what the plugins registered on
    /// them during `initialize` (before modules initialize).
    pub(crate) fn bind_cores(
        &self,
        channel: &Arc<ChannelManager>,
        executors: &HashMap<String, RawExecutor>,
    ) -> Result<(), Error> {
        for (name, core, _) in &self.cores {
            core.bind(channel, executors)
                .map_err(|message| Error::Plugin {
                    plugin: name.clone(),
                    action: "use channels",
                    message,
                })?;
        }
        Ok(())
    }

    /// Messages from other processes reach the plugins' subscriptions from now on (after
    /// modules started, AimRT's kPostStart).
    pub(crate) fn start_cores(&self) {
        for (_, core, _) in &self.cores {
            core.start();
        }
    }

    /// Calls every started plugin's `post_start` (ABI 1.4; AimRT's kPostStart), in load
    /// order, once modules have started. A plugin of an older minor has none.
    pub(crate) fn post_start(&mut self) {
        for (_, plugin) in self.plugins[..self.started].iter_mut() {
            plugin.post_start();
        }
    }

    /// Starts every plugin, in load order.
    pub(crate) fn start(&mut self) -> Result<(), Error> {
        for (name, plugin) in &mut self.plugins {
            plugin.start().map_err(|message| Error::Plugin {
                plugin: name.clone(),
                action: "start",
                message,
            })?;
            self.started += 1;
        }
        Ok(())
    }

    /// Shuts down every initialized plugin, once, in reverse load order, started or not:
    /// a start-up that failed or was stopped after a plugin initialized still closes what
    /// the plugin opened (a zenoh session and its listen port), as AimRT does. Plugin
    /// objects are kept (their libraries are never unloaded).
    pub(crate) fn shutdown(&mut self) {
        if std::mem::replace(&mut self.shut_down, true) {
            return;
        }
        self.started = 0;
        for (_, plugin) in self.plugins.iter_mut().rev() {
            plugin.shutdown();
        }
    }
}

impl Drop for PluginManager {
    fn drop(&mut self) {
        // Plugin objects and executor types may be referenced by threads that outlive the
        // runtime (abandoned executors): never free them.
        for (_, p) in std::mem::take(&mut self.plugins) {
            std::mem::forget(p);
        }
        for (_, t) in std::mem::take(&mut self.executor_types) {
            std::mem::forget(t);
        }
        for (_, b) in std::mem::take(&mut self.rpc_backends) {
            std::mem::forget(b);
        }
        for (_, b) in std::mem::take(&mut self.channel_backends) {
            std::mem::forget(b);
        }
    }
}
