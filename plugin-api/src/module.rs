//! Modules: the trait authors implement and the core handle they get.

use serde::de::DeserializeOwned;

use crate::channel::{ChannelRef, TopicStats};
use crate::ffi::TypeSupportVtable;
use crate::ffi::{
    MetaPair, RawCore, RawExecutor, RawLogger, RawMessage, RawRpcReply, RawServiceFunc,
    RawSubscriber,
};
use crate::rpc::RpcRef;
use crate::{Error, ExecutorRef, LogLevel};

/// A module's identity, as AimRT's `ModuleInfo`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ModuleInfo {
    /// The name (required; unique in the process; the config's `modules[i].name`).
    pub name: String,
    /// Version, major.
    pub major_version: u32,
    /// Version, minor.
    pub minor_version: u32,
    /// Version, patch.
    pub patch_version: u32,
    /// Version, build.
    pub build_version: u32,
    /// Author.
    pub author: String,
    /// Description.
    pub description: String,
}

impl ModuleInfo {
    /// Info with just a name.
    pub fn new(name: impl Into<String>) -> ModuleInfo {
        ModuleInfo {
            name: name.into(),
            ..ModuleInfo::default()
        }
    }
}

/// A module: AimRT's `ModuleBase` in Rust. The runtime calls `initialize` (registration,
/// executor lookup; executors already run tasks), then `start`, then `shutdown` in reverse
/// module order, all on the main thread. A panic in any hook is contained: in
/// `initialize`/`start` it fails the runtime with the message, in `shutdown` it is logged.
pub trait Module: Send + 'static {
    /// The module's identity (called once, right after construction).
    fn info(&self) -> ModuleInfo;
    /// Reads config, looks up executors, registers what it needs.
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error>;
    /// Starts work.
    fn start(&mut self) -> Result<(), Error> {
        Ok(())
    }
    /// Stops work; waits for what it started.
    fn shutdown(&mut self) {}
}

/// What the runtime implements behind a module's core handle.
pub trait CoreHost: Send + Sync + 'static {
    /// The module's info.
    fn info(&self) -> &ModuleInfo;
    /// AimRT's `GetConfigFilePath()` result.
    fn config_file_path(&self) -> &str;
    /// The module's root config node as JSON (`null` when absent).
    fn config_json(&self) -> &str;
    /// An executor by name.
    fn executor(&self, name: &str) -> Option<RawExecutor>;
    /// The module's logger.
    fn logger(&self) -> RawLogger;
    /// Registers a publish type of the module on `topic`.
    fn register_publish_type(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
    ) -> Result<(), String>;
    /// Subscribes the module to messages of `ts` on `topic`.
    fn subscribe(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
        sub: RawSubscriber,
    ) -> Result<(), String>;
    /// Publishes `msg` on `topic` (its bytes as the module passed them, not checked as
    /// UTF-8) with the context `ctx`.
    fn publish(&self, topic: &[u8], ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String>;
    /// The counters of `topic`.
    fn topic_stats(&self, topic: &str) -> Option<TopicStats>;
    /// Registers a service function of the module under the full name `func`.
    fn register_service(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        rsp_ts: &'static TypeSupportVtable,
        service: RawServiceFunc,
    ) -> Result<(), String> {
        let _ = (req_ts, rsp_ts, service);
        Err(format!(
            "cannot register service function '{func}': this host has no module RPC"
        ))
    }
    /// Registers a client function of the module under the full name `func`.
    fn register_client(
        &self,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        rsp_ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        let _ = (req_ts, rsp_ts);
        Err(format!(
            "cannot register client function '{func}': this host has no module RPC"
        ))
    }
    /// The context meta keys plugins registered to pass from server to client contexts.
    fn passed_keys(&self) -> Vec<String> {
        Vec::new()
    }
    /// The module's parameter `key` (ABI 1.6).
    fn parameter_get(&self, key: &str) -> Option<String>;
    /// Sets the module's parameter `key` to `value`.
    fn parameter_set(&self, key: &str, value: &str);
    /// Removes the module's parameter `key`; whether it was set.
    fn parameter_remove(&self, key: &str) -> bool;
    /// The keys of the module's parameters, in byte order.
    fn parameter_keys(&self) -> Vec<String>;
    /// Invokes the client function `func`; completes `reply` exactly once.
    #[allow(clippy::too_many_arguments)] // one call, spelled out as it crosses the ABI
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
        let _ = (ctx, timeout_ns, req, rsp_ts, blocking);
        reply.complete(
            crate::RpcStatus::CLI_NOT_READY,
            None,
            &[],
            &format!("cannot invoke '{func}': this host has no module RPC"),
        );
    }
}

/// A module's handle to the runtime (AimRT's `CoreRef`). Copyable; valid for the
/// process's life.
#[derive(Clone, Copy)]
pub struct CoreRef {
    raw: RawCore,
}

impl CoreRef {
    /// Wraps a raw core handle.
    ///
    /// # Safety
    /// `raw` must come from the host (`RawCore::leak`): valid for the process's life.
    pub unsafe fn from_raw(raw: RawCore) -> CoreRef {
        CoreRef { raw }
    }

    /// The module's info as the runtime knows it.
    pub fn info(&self) -> ModuleInfo {
        self.raw.info()
    }

    /// AimRT's `GetConfigFilePath()`: `modules[i].cfg_file_path` if set, else the file the
    /// runtime wrote from the root config node named after the module
    /// (`<temp_cfg_path>/temp_cfg_file_for_<Module>.yaml`), else empty.
    pub fn config_file_path(&self) -> String {
        self.raw.config_file_path()
    }

    /// The root config node named after the module, read into `T` (no YAML parser needed
    /// in the module). An absent node reads as `{}`.
    ///
    /// ```no_run
    /// #[derive(serde::Deserialize)]
    /// struct Cfg { executor: String }
    /// # fn demo(core: aimrt_plugin_api::CoreRef) -> Result<(), aimrt_plugin_api::Error> {
    /// let cfg: Cfg = core.config()?;
    /// # Ok(()) }
    /// ```
    pub fn config<T: DeserializeOwned>(&self) -> Result<T, Error> {
        crate::suggest::read_options(&self.raw.config_json(), || {
            let name = self.info().name;
            format!(
                "config of module '{name}' (root node '{name}' of the config file, handed over as {})",
                self.config_file_path()
            )
        })
    }

    /// The executor manager.
    pub fn executor_manager(&self) -> ExecutorManagerRef {
        ExecutorManagerRef { raw: self.raw }
    }

    /// Shorthand for `executor_manager().executor(name)`.
    pub fn executor(&self, name: &str) -> Result<ExecutorRef, Error> {
        self.executor_manager().executor(name)
    }

    /// The module's channel handle: publishers and subscribers (see
    /// [`ChannelRef`]). An error only with a runtime that predates channels.
    pub fn channel(&self) -> Result<ChannelRef, Error> {
        ChannelRef::new(self.raw)
    }

    /// The module's RPC handle: service and client functions (see [`RpcRef`]). An error
    /// only with a runtime that predates module RPC (ABI 1.2).
    pub fn rpc(&self) -> Result<RpcRef, Error> {
        RpcRef::new(self.raw)
    }

    /// The module's parameters: AimRT's per-module store of text values (see
    /// [`ParameterRef`](crate::ParameterRef)). An error only with a runtime that predates
    /// them (ABI 1.6).
    pub fn parameter(&self) -> Result<crate::ParameterRef, Error> {
        crate::ParameterRef::new(self.raw)
    }

    /// The module's logger.
    pub fn logger(&self) -> Logger {
        Logger {
            raw: self.raw.logger(),
        }
    }

    pub(crate) fn raw_logger(&self) -> RawLogger {
        self.raw.logger()
    }
}

impl std::fmt::Debug for CoreRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CoreRef")
            .field("module", &self.info().name)
            .finish()
    }
}

/// Looks up executors by name (every executor of `aimrt.executor.executors`; the main and
/// guard threads are not reachable).
#[derive(Clone, Copy)]
pub struct ExecutorManagerRef {
    raw: RawCore,
}

impl ExecutorManagerRef {
    /// The named executor, or an error naming it.
    pub fn executor(&self, name: &str) -> Result<ExecutorRef, Error> {
        self.raw
            .executor(name)
            // SAFETY: the host returns only its executors, which it never frees.
            .map(|raw| unsafe { ExecutorRef::from_raw(raw) })
            .ok_or_else(|| Error::ExecutorNotFound(name.to_owned()))
    }
}

impl std::fmt::Debug for ExecutorManagerRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ExecutorManagerRef")
    }
}

/// A module's logger. `tracing` macros inside a module already go here; this handle is for
/// checking the level or logging with an explicit level.
#[derive(Clone, Copy, Debug)]
pub struct Logger {
    raw: RawLogger,
}

impl Logger {
    /// The logger's level.
    pub fn level(&self) -> LogLevel {
        self.raw.level()
    }

    /// Logs `message` at `level` (filtered by the logger's level).
    #[track_caller]
    pub fn log(&self, level: LogLevel, message: &str) {
        if level < self.level() || level == LogLevel::Off {
            return;
        }
        let loc = std::panic::Location::caller();
        self.raw.log(&crate::LogLine {
            level,
            file: loc.file(),
            line: loc.line(),
            target: "",
            message,
        });
    }
}
