//! Pkg loading, per-module core handles, and the module lifecycle.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use aimrt_plugin_api::channel::TopicStats;
use aimrt_plugin_api::ffi::{
    MetaPair, RawCore, RawExecutor, RawLogger, RawMessage, RawModule, RawRpcReply, RawServiceFunc,
    RawSubscriber, TypeSupportVtable,
};
use aimrt_plugin_api::{CoreHost, LogLevel, Module, ModuleInfo};

use crate::channel::{ChannelManager, ModuleChannel};
use crate::config::{Config, Located, ModuleEntry};
use crate::log::{LogHub, Logger};
use crate::plugin::loader::Library;
use crate::rpc::calls::{ModuleRpc, RpcRegistry};
use crate::Error;
use aimrt_plugin_api::__private::did_you_mean;

/// The pkg column of a module registered in code (`Runtime::register_module`).
const IN_CODE: &str = "registered in code";

/// What a module's core handle serves.
struct ModuleCore {
    info: ModuleInfo,
    cfg_file_path: String,
    config_json: String,
    executors: Arc<HashMap<String, RawExecutor>>,
    logger: RawLogger,
    channel: ModuleChannel,
    rpc: ModuleRpc,
    /// The module's parameters (its own; no other module sees them).
    parameters: crate::parameter::Parameters,
}

impl CoreHost for ModuleCore {
    crate::parameter::serve_parameters!(parameters);
    fn info(&self) -> &ModuleInfo {
        &self.info
    }
    fn config_file_path(&self) -> &str {
        &self.cfg_file_path
    }
    fn config_json(&self) -> &str {
        &self.config_json
    }
    fn executor(&self, name: &str) -> Option<RawExecutor> {
        let found = self.executors.get(name).copied();
        if found.is_none() {
            tracing::warn!(target: "aimrt", "module '{}' asked for executor '{name}', which does not exist", self.info.name);
        }
        found
    }
    fn logger(&self) -> RawLogger {
        self.logger
    }
    fn register_publish_type(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        self.channel.register_publish_type(topic, ts)
    }
    fn subscribe(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
        sub: RawSubscriber,
    ) -> Result<(), String> {
        self.channel.subscribe(topic, ts, sub)
    }
    fn publish(&self, topic: &[u8], ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String> {
        self.channel.publish(topic, ctx, msg)
    }
    fn topic_stats(&self, topic: &str) -> Option<TopicStats> {
        self.channel.stats(topic)
    }
    fn register_service(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        rsp_ts: &'static TypeSupportVtable,
        service: RawServiceFunc,
    ) -> Result<(), String> {
        self.rpc.register_service(func, req_ts, rsp_ts, service)
    }
    fn register_client(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        rsp_ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        self.rpc.register_client(func, req_ts, rsp_ts)
    }
    fn passed_keys(&self) -> Vec<String> {
        self.rpc.passed_keys()
    }
    fn invoke(
        &self,
        func: &str,
        ctx: &[MetaPair<'_>],
        timeout_ns: u64,
        req: RawMessage,
        rsp_ts: &'static TypeSupportVtable,
        blocking: bool,
        reply: RawRpcReply,
    ) {
        self.rpc
            .invoke(func, ctx, timeout_ns, req, rsp_ts, blocking, reply);
    }
}

struct Loaded {
    name: String,
    pkg: PathBuf,
    module: RawModule,
    enabled: bool,
    /// Set when `start` returned (network channel backends deliver from then).
    started: Arc<AtomicBool>,
}

/// What every module's core handle serves from.
pub(crate) struct Services {
    /// Every executor, by name.
    pub(crate) executors: Arc<HashMap<String, RawExecutor>>,
    /// Topics.
    pub(crate) channel: Arc<ChannelManager>,
    /// Module service and client functions.
    pub(crate) calls: Arc<RpcRegistry>,
    /// Where plugins find the modules' parameters.
    pub(crate) control: Arc<crate::control::Control>,
}

/// Modules in initialization order.
#[derive(Default)]
pub(crate) struct ModuleManager {
    modules: Vec<Loaded>,
    initialized: usize,
    started: usize,
}

impl ModuleManager {
    /// Name, pkg path, `major.minor.patch.build` of every enabled module, in order.
    pub(crate) fn report_rows(&self) -> Vec<Vec<String>> {
        self.modules
            .iter()
            .filter(|m| m.enabled)
            .map(|m| {
                let i = m.module.info();
                vec![
                    m.name.clone(),
                    m.pkg.display().to_string(),
                    format!(
                        "{}.{}.{}.{}",
                        i.major_version, i.minor_version, i.patch_version, i.build_version
                    ),
                ]
            })
            .collect()
    }

    /// Takes the modules registered in code, then loads every pkg of `aimrt.module.pkgs`
    /// in order and creates its enabled modules.
    pub(crate) fn load(
        &mut self,
        config: &Config,
        in_code: Vec<Box<dyn Module>>,
        core_lvl: LogLevel,
        hub: &Arc<LogHub>,
    ) -> Result<(), Error> {
        let entries = config
            .aimrt
            .module
            .as_ref()
            .map(|m| m.modules.as_slice())
            .unwrap_or_default();
        for module in in_code {
            let name = module.info().name;
            let err = |message: String| Error::Module {
                module: name.clone(),
                pkg: IN_CODE.to_owned(),
                action: "register",
                message,
            };
            if name.is_empty() {
                return Err(err(
                    "a module needs a non-empty name in its ModuleInfo".into()
                ));
            }
            if self.modules.iter().any(|m| m.name == name) {
                return Err(err(
                    "another module registered in code has this name; module names must be unique"
                        .into(),
                ));
            }
            let module = RawModule::new(module).map_err(err)?;
            let enabled = find(entries, &name).is_none_or(|m| m.enable);
            self.modules.push(Loaded {
                name,
                pkg: PathBuf::from(IN_CODE),
                module,
                enabled,
                started: Arc::default(),
            });
        }
        let Some(section) = config.aimrt.module.as_ref() else {
            self.warn_unused_roots(config);
            return Ok(());
        };
        if let Some(again) = Located::repeated(section.modules.iter().map(|m| &m.name)) {
            return Err(config.error(
                again,
                format!(
                    "module '{}' is listed twice under aimrt.module.modules; list each module once",
                    again.value
                ),
            ));
        }
        let mut seen_paths = HashSet::new();
        for pkg in &section.pkgs {
            let stem = std::path::Path::new(&pkg.path.value)
                .file_stem()
                .map_or_else(
                    || "pkg".to_owned(),
                    |s| s.to_string_lossy().trim_start_matches("lib").to_owned(),
                );
            let what = format!("pkg at {}", config.at(&pkg.path));
            let lib = Library::open(&what, &pkg.path.value, &stem, core_lvl, hub)?;
            if !seen_paths.insert(lib.path.clone()) {
                return Err(config.error(
                    &pkg.path,
                    format!(
                        "pkg {} is listed twice; list each pkg once",
                        lib.path.display()
                    ),
                ));
            }
            let lib_err = |m: String| Error::Library {
                what: what.clone(),
                path: lib.path.display().to_string(),
                message: m,
            };
            let names = lib.module_names();
            if names.is_empty() {
                return Err(lib_err(
                    "exports no modules; a module library calls aimrt_plugin_api::export_modules!"
                        .into(),
                ));
            }
            let mut unique = HashSet::new();
            for n in &names {
                if n.is_empty() || !unique.insert(n.as_str()) {
                    return Err(lib_err(format!(
                        "its module list is invalid (empty or repeated name '{n}')"
                    )));
                }
            }
            for e in &pkg.enable_modules {
                if !unique.contains(e.value.as_str()) {
                    return Err(config.error(
                        e,
                        format!(
                            "enable_modules names '{}', which {} does not export{}; it exports: {}",
                            e.value,
                            lib.path.display(),
                            did_you_mean(&e.value, names.iter().map(String::as_str)),
                            names.join(", ")
                        ),
                    ));
                }
            }
            if !pkg.enable_modules.is_empty() && !pkg.disable_modules.is_empty() {
                tracing::warn!(target: "aimrt", "pkg {}: both enable_modules and disable_modules are given; only enable_modules is used", lib.path.display());
            }
            let selected: Vec<&String> = names
                .iter()
                .filter(|n| {
                    if pkg.enable_modules.is_empty() {
                        !pkg.disable_modules.iter().any(|d| &d.value == *n)
                    } else {
                        pkg.enable_modules.iter().any(|e| &e.value == *n)
                    }
                })
                .collect();
            for name in selected {
                if let Some(other) = self.modules.iter().find(|m| &m.name == name) {
                    return Err(lib_err(format!(
                        "module '{name}' is also {}; module names must be unique",
                        if other.pkg.as_os_str() == IN_CODE {
                            "registered in code".to_owned()
                        } else {
                            format!("exported by {}", other.pkg.display())
                        }
                    )));
                }
                let module = lib
                    .create_module(name)
                    .map_err(|m| lib_err(format!("cannot create module '{name}': {m}")))?;
                let real = module.info().name;
                if &real != name {
                    return Err(lib_err(format!(
                        "module listed as '{name}' reports the name '{real}'; the two must match"
                    )));
                }
                let enabled = find(section.modules.as_slice(), name).is_none_or(|m| m.enable);
                self.modules.push(Loaded {
                    name: name.clone(),
                    pkg: lib.path.clone(),
                    module,
                    enabled,
                    started: Arc::default(),
                });
            }
        }
        for entry in &section.modules {
            if !self.modules.iter().any(|m| m.name == entry.name.value) {
                tracing::warn!(
                    target: "aimrt",
                    "{}: options for module '{}', which no pkg loaded{}",
                    config.at(&entry.name),
                    entry.name.value,
                    did_you_mean(&entry.name.value, self.modules.iter().map(|m| m.name.as_str()))
                );
            }
        }
        self.warn_unused_roots(config);
        Ok(())
    }

    /// Warns about each root node of the config (other than `aimrt`) that names no loaded
    /// module: a misspelt module name would otherwise leave the module on its defaults.
    fn warn_unused_roots(&self, config: &Config) {
        for root in config.roots.keys().filter(|k| k.as_str() != "aimrt") {
            if !self.modules.iter().any(|m| &m.name == root) {
                tracing::warn!(
                    target: "aimrt",
                    "{}: root node '{root}' configures no loaded module, so it is not used{}",
                    config.file,
                    did_you_mean(root, self.modules.iter().map(|m| m.name.as_str()))
                );
            }
        }
    }

    /// Initializes enabled modules in order, each with its own core handle.
    pub(crate) fn initialize(
        &mut self,
        config: &Config,
        services: &Services,
        default_lvl: LogLevel,
        hub: &Arc<LogHub>,
        stop: &AtomicBool,
    ) -> Result<(), Error> {
        let entries = config
            .aimrt
            .module
            .as_ref()
            .map(|m| m.modules.as_slice())
            .unwrap_or_default();
        for m in self.modules.iter_mut().filter(|m| m.enabled) {
            if stop.load(Ordering::SeqCst) {
                tracing::info!(target: "aimrt", "Shutdown requested: module '{}' and the modules after it are not initialized.", m.name);
                break;
            }
            let entry = find(entries, &m.name);
            let level = match entry.and_then(|e| e.log_lvl.as_ref()) {
                Some(l) => l
                    .value
                    .parse::<LogLevel>()
                    .map_err(|e| config.error(l, format!("log_lvl of module '{}': {e}", m.name)))?,
                None => default_lvl,
            };
            let root = config.roots.get(&m.name).filter(|v| !v.is_null());
            let cfg_file_path = match entry
                .map(|e| e.cfg_file_path.as_str())
                .filter(|p| !p.is_empty())
            {
                Some(p) => p.to_owned(),
                None => match root {
                    Some(node) => write_temp_cfg(config, &m.name, node)?,
                    None => String::new(),
                },
            };
            let pkg = m.pkg.display().to_string();
            let core = RawCore::leak(Arc::new(ModuleCore {
                info: m.module.info(),
                cfg_file_path,
                config_json: root.map_or_else(|| "null".to_owned(), |v| v.to_string()),
                executors: services.executors.clone(),
                logger: RawLogger::leak(Logger::new(&m.name, level, hub)),
                channel: ModuleChannel::new(
                    services.channel.clone(),
                    &m.name,
                    &pkg,
                    m.started.clone(),
                ),
                rpc: ModuleRpc::new(services.calls.clone(), &m.name, &pkg),
                parameters: Default::default(),
            }));
            m.module.initialize(core).map_err(|message| Error::Module {
                module: m.name.clone(),
                pkg,
                action: "initialize",
                message,
            })?;
            self.initialized += 1;
            services.control.add_module(&m.name, core);
            tracing::info!(target: "aimrt", "Init module '{}' succeeded.", m.name);
        }
        Ok(())
    }

    /// Starts initialized modules in order; stops early once `stop` is set.
    pub(crate) fn start(&mut self, stop: &AtomicBool) -> Result<(), Error> {
        for m in self
            .modules
            .iter_mut()
            .filter(|m| m.enabled)
            .take(self.initialized)
        {
            if stop.load(Ordering::SeqCst) {
                tracing::info!(target: "aimrt", "Shutdown requested: module '{}' and the modules after it are not started.", m.name);
                break;
            }
            m.module.start().map_err(|message| Error::Module {
                module: m.name.clone(),
                pkg: m.pkg.display().to_string(),
                action: "start",
                message,
            })?;
            m.started.store(true, Ordering::Release);
            self.started += 1;
        }
        Ok(())
    }

    /// Shuts down every initialized module in reverse order (AimRT: modules that
    /// initialized get `shutdown`, also when a later one failed).
    pub(crate) fn shutdown(&mut self) {
        let n = std::mem::take(&mut self.initialized);
        self.started = 0;
        let mut done: Vec<&mut Loaded> = self
            .modules
            .iter_mut()
            .filter(|m| m.enabled)
            .take(n)
            .collect();
        for m in done.iter_mut().rev() {
            m.module.shutdown();
            tracing::info!(target: "aimrt", "Shutdown module '{}'.", m.name);
        }
    }
}

impl Drop for ModuleManager {
    fn drop(&mut self) {
        // Module objects live in libraries that are never unloaded, and tasks they posted
        // may still be queued on abandoned executors: leak them rather than free them.
        for m in std::mem::take(&mut self.modules) {
            std::mem::forget(m.module);
        }
    }
}

fn find<'a>(entries: &'a [ModuleEntry], name: &str) -> Option<&'a ModuleEntry> {
    entries.iter().find(|e| e.name.value == name)
}

/// AimRT's hand-over: `<temp_cfg_path>/temp_cfg_file_for_<Module>.yaml`.
fn write_temp_cfg(
    config: &Config,
    module: &str,
    node: &serde_json::Value,
) -> Result<String, Error> {
    let dir = config.temp_cfg_path();
    let path = dir.join(format!("temp_cfg_file_for_{module}.yaml"));
    let text = serde_saphyr::to_string(node).unwrap_or_else(|_| node.to_string());
    std::fs::create_dir_all(&dir)
        .and_then(|()| std::fs::write(&path, text))
        .map_err(|source| Error::Write {
            path: path.clone(),
            source,
        })?;
    Ok(path.display().to_string())
}
