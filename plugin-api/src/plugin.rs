//! Plugins: the trait plugin authors implement and the registrar they get.

use std::sync::Arc;

use serde::de::DeserializeOwned;

use crate::channel::ChannelBackend;
use crate::executor::ExecutorArgs;
use crate::ffi::{RawChannelBackend, RawExecutorType, RawRegistrar, RawRpcBackend, RawService};
use crate::rpc::{RpcBackend, ServiceError};
use crate::{Error, Executor, ThreadFactory};

/// A plugin: a library that contributes executor types (and later services and backends).
///
/// `initialize` runs when the runtime loads the plugin (before executors are built),
/// `start` after modules initialized, `shutdown` after modules shut down. `shutdown` comes
/// to every plugin whose `initialize` succeeded, also when start-up failed or was stopped
/// before `start`.
pub trait Plugin: Send + 'static {
    /// The plugin's name; must equal `aimrt.plugin.plugins[i].name`.
    fn name(&self) -> &str;
    /// Reads options and registers contributions.
    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error>;
    /// Starts serving.
    fn start(&mut self) -> Result<(), Error> {
        Ok(())
    }
    /// Called once everything has started, modules included (AimRT's kPostStart; ABI
    /// 1.4): the place to begin work that publishes, such as a playback. Channels refuse a
    /// plugin's publications until then.
    fn post_start(&mut self) {}
    /// Stops.
    fn shutdown(&mut self) {}
}

/// An `options` node of a plugin (or of an RPC backend: [`BackendOptions`](crate::BackendOptions)).
#[derive(Debug, Clone)]
pub struct PluginOptions {
    /// Whose options, for messages: `plugin 'x'`, `rpc backend 'http'`.
    owner: String,
    json: String,
    location: String,
}

impl PluginOptions {
    pub(crate) fn new(owner: String, json: String, location: String) -> PluginOptions {
        PluginOptions {
            owner,
            json,
            location,
        }
    }

    /// Options given in code (a linked-in plugin, a test): `json` as the config would
    /// hand it over, `location` naming where it came from in messages.
    ///
    /// ```
    /// let o = aimrt_plugin_api::PluginOptions::from_json("plugin 'net_plugin'", r#"{"thread_num": 2}"#, "bench");
    /// assert_eq!(o.json(), r#"{"thread_num": 2}"#);
    /// ```
    pub fn from_json(owner: &str, json: &str, location: &str) -> PluginOptions {
        PluginOptions::new(owner.to_owned(), json.to_owned(), location.to_owned())
    }

    /// The options as JSON text (`null` when absent).
    pub fn json(&self) -> &str {
        &self.json
    }

    /// Where the options are in the config, `file:line:col`.
    pub fn location(&self) -> &str {
        &self.location
    }

    /// An error about these options that names whose they are and where
    /// (`options of plugin 'x' at cfg.yaml:12:9: <message>`).
    ///
    /// ```
    /// let o = aimrt_plugin_api::PluginOptions::from_json("plugin 'x'", "{}", "cfg.yaml:3:9");
    /// assert_eq!(o.invalid("n must be positive").to_string(), "options of plugin 'x' at cfg.yaml:3:9: n must be positive");
    /// ```
    pub fn invalid(&self, message: impl Into<String>) -> Error {
        Error::Options {
            what: format!("options of {} at {}", self.owner, self.location),
            message: message.into(),
        }
    }

    /// Reads the options into `T` (absent options read as `{}`).
    pub fn get<T: DeserializeOwned>(&self) -> Result<T, Error> {
        crate::suggest::read_options(&self.json, || {
            format!("options of {} at {}", self.owner, self.location)
        })
    }
    /// Reads the options into `T` ([`get`](Self::get)) and, called from a channel or RPC
    /// backend's `init` (ABI 1.8) or a log backend type's factory (1.11), hands them back
    /// to the runtime as read, defaults filled in (AimRT's `options_node = options_`):
    /// `--dump_cfg_file` writes them in place of
    /// what the config wrote. A plugin reports its own with
    /// [`Registrar::read_options`] instead; elsewhere, or on an older `aimrt_main`, this
    /// only reads.
    ///
    /// ```
    /// #[derive(serde::Deserialize, serde::Serialize)]
    /// struct Opts { #[serde(default)] shm_enabled: bool }
    /// let o = aimrt_plugin_api::BackendOptions::from_json("channel backend 'x'", "null", "cfg.yaml:9:9");
    /// assert!(!o.read::<Opts>().unwrap().shm_enabled);
    /// ```
    pub fn read<T: DeserializeOwned + serde::Serialize>(&self) -> Result<T, Error> {
        let options: T = self.get()?;
        crate::ffi::report_options(&options);
        Ok(options)
    }
}

/// Where a plugin registers its contributions; valid during `initialize` only.
#[derive(Debug)]
pub struct Registrar<'a> {
    raw: RawRegistrar,
    _marker: std::marker::PhantomData<&'a mut ()>,
}

impl std::fmt::Debug for RawRegistrar {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RawRegistrar")
    }
}

impl Registrar<'_> {
    pub(crate) fn from_raw(raw: RawRegistrar) -> Registrar<'static> {
        Registrar {
            raw,
            _marker: std::marker::PhantomData,
        }
    }

    /// Registers executor type `type_name`. `bind_keys` are the option keys whose values
    /// name other executors (e.g. `bind_executor`): the runtime builds those first and
    /// hands them to `factory` in `args.bound`, in the same order.
    ///
    /// A type name that is already registered is refused (the first registration wins).
    pub fn register_executor_type<E, F>(
        &mut self,
        type_name: &str,
        bind_keys: &[&str],
        factory: F,
    ) -> Result<(), Error>
    where
        E: Executor,
        F: Fn(ExecutorArgs<'_>) -> Result<Arc<E>, Error> + Send + Sync + 'static,
    {
        let ty = RawExecutorType::new(type_name, bind_keys, factory);
        self.raw
            .register_executor_type(ty)
            .map_err(Error::Registration)
    }

    /// The runtime's thread factory.
    pub fn thread_factory(&self) -> ThreadFactory {
        ThreadFactory::from_raw(self.raw.thread_factory())
    }

    /// Registers a service function under its full name (e.g.
    /// `pb:/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService/Pause`).
    /// `handler` gets the request's format (`json`) and bytes and answers bytes in the
    /// same format; it runs on the calling backend's thread, so it should not block long.
    /// A panic in it answers [`ServiceError::Failed`]. A name already registered is
    /// refused.
    pub fn register_service<F>(&mut self, func_name: &str, handler: F) -> Result<(), Error>
    where
        F: Fn(&str, &[u8]) -> Result<Vec<u8>, ServiceError> + Send + Sync + 'static,
    {
        self.raw
            .register_service(func_name, RawService::new(handler))
            .map_err(Error::Registration)
    }

    /// Registers an RPC backend; the config enables it with `aimrt.rpc.backends`. A type
    /// already registered is refused.
    pub fn register_rpc_backend<B: RpcBackend>(&mut self, backend: B) -> Result<(), Error> {
        self.raw
            .register_rpc_backend(RawRpcBackend::new(backend))
            .map_err(Error::Registration)
    }

    /// Adds context meta keys that pass from a service's context to the client contexts a
    /// module makes from it ([`RpcClient::new_context_from`](crate::rpc::RpcClient::new_context_from);
    /// AimRT's `AddPassedContextMetaKeys`), e.g. a trace id.
    pub fn add_passed_context_meta_keys(&mut self, keys: &[&str]) -> Result<(), Error> {
        for key in keys {
            self.raw
                .add_passed_context_meta_key(key)
                .map_err(Error::Registration)?;
        }
        Ok(())
    }

    /// Loads a type support package (a library made with
    /// [`export_type_support!`](crate::export_type_support), e.g. AimRT's
    /// `type_support_pkgs[i].path`) and returns the names of the message types it offers.
    /// Its types are then found by name with [`type_support`](Self::type_support), by this
    /// plugin and every other. A path that is not such a library is an error saying why.
    pub fn load_type_support_pkg(&mut self, path: &str) -> Result<Vec<String>, Error> {
        self.raw
            .load_type_support_pkg(path)
            .map_err(Error::Registration)
    }

    /// Loads AimRT's `type_support_pkgs` (in order) and returns their types, to find by
    /// name. `Err` names the entry (`type_support_pkgs[1].path '…': …`).
    pub fn load_type_support_pkgs(
        &mut self,
        pkgs: &[TypeSupportPkg],
    ) -> Result<TypeSupports, String> {
        let mut tables = Vec::new();
        for (i, TypeSupportPkg { path }) in pkgs.iter().enumerate() {
            let names = self
                .load_type_support_pkg(path)
                .map_err(|e| format!("type_support_pkgs[{i}].path '{path}': {e}"))?;
            tables.extend(
                names
                    .into_iter()
                    .filter_map(|n| self.type_support(&n).map(|ts| (n, ts))),
            );
        }
        Ok(TypeSupports { tables })
    }

    /// The table of a message type (`pb:aimrt.protocols.example.ExampleEventMsg`) from a
    /// loaded type support package, to subscribe and publish by name
    /// ([`ChannelRef::subscribe_raw`](crate::channel::ChannelRef::subscribe_raw)).
    pub fn type_support(&self, name: &str) -> Option<&'static crate::ffi::TypeSupportVtable> {
        self.raw.find_type_support(name)
    }

    /// The plugin's own core, named after the plugin, for channels (AimRT's plugins use
    /// channels as module `core`): subscriptions and publish types made during
    /// `initialize` take effect when the channel is configured, before modules
    /// initialize; publishing works from `start` on.
    pub fn core(&mut self) -> Result<crate::CoreRef, Error> {
        let raw = self.raw.core().map_err(Error::Registration)?;
        // SAFETY: the host hands out cores valid for the process's life.
        Ok(unsafe { crate::CoreRef::from_raw(raw) })
    }

    /// The runtime's control handle: the loggers' levels and the modules' parameters,
    /// while the process runs (ABI 1.13; AimRT's `log_control_plugin` and
    /// `parameter_plugin` use the same). Keep it: it is valid for the process's life.
    pub fn control(&self) -> Result<crate::RuntimeControl, Error> {
        let raw = self.raw.control().map_err(Error::Registration)?;
        Ok(crate::RuntimeControl::new(raw))
    }

    /// Registers a channel backend; the config enables it with `aimrt.channel.backends`
    /// and routes topics to it with `pub_topics_options`/`sub_topics_options`. A type
    /// already registered (or `local`) is refused.
    pub fn register_channel_backend<B: ChannelBackend>(&mut self, backend: B) -> Result<(), Error> {
        self.raw
            .register_channel_backend(RawChannelBackend::new(backend))
            .map_err(Error::Registration)
    }

    /// Puts `options` — the plugin's options as it reads them, defaults filled in — in
    /// place of what the config wrote, in the normalized config `--dump_cfg_file` writes
    /// (ABI 1.7; AimRT's `UpdatePluginOptionsNode`). Without this call, or on an
    /// `aimrt_main` older than 1.7, the dump keeps the options as written.
    ///
    /// ```no_run
    /// #[derive(serde::Deserialize, serde::Serialize)]
    /// struct Options {
    ///     #[serde(default = "four")]
    ///     thread_num: u32,
    /// }
    /// fn four() -> u32 { 4 }
    /// # fn init(registrar: &mut aimrt_plugin_api::Registrar<'_>, options: &aimrt_plugin_api::PluginOptions) -> Result<(), aimrt_plugin_api::Error> {
    /// let o: Options = options.get()?;
    /// registrar.update_options(&o)?; // the dump shows `thread_num: 4` when it was left out
    /// # Ok(()) }
    /// ```
    pub fn update_options<T: serde::Serialize>(&mut self, options: &T) -> Result<(), Error> {
        let json = serde_json::to_string(options).map_err(|e| {
            Error::Registration(format!("the options cannot be written as JSON: {e}"))
        })?;
        self.raw
            .update_options(&json)
            .map(drop)
            .map_err(Error::Registration)
    }

    /// Reads `options` as `T` ([`PluginOptions::get`]) and reports them back as read
    /// ([`update_options`](Self::update_options)): the one call most plugins need.
    pub fn read_options<T: DeserializeOwned + serde::Serialize>(
        &mut self,
        options: &PluginOptions,
    ) -> Result<T, Error> {
        let o: T = options.get()?;
        self.update_options(&o)?;
        Ok(o)
    }

    /// Registers a channel filter for `side` under `name` (ABI 1.7; AimRT's
    /// `RegisterPublishFilter` / `RegisterSubscribeFilter`). A topic runs it when its
    /// `pub_topics_options` (publish) or `sub_topics_options` (subscribe) rule lists the
    /// name in `enable_filters`; the filter listed last runs first. A name already
    /// registered for that side, or a built-in one (`debug_log`), is refused.
    ///
    /// ```no_run
    /// use aimrt_plugin_api::channel::{FilterSide, Next, Publication};
    /// # fn init(registrar: &mut aimrt_plugin_api::Registrar<'_>) -> Result<(), aimrt_plugin_api::Error> {
    /// // Holds back every message whose context has `mute: yes`.
    /// registrar.register_channel_filter("mute", FilterSide::Publish, |msg: &Publication<'_>, next: Next<'_>| {
    ///     if msg.get("mute") == Some("yes") {
    ///         return Ok(());
    ///     }
    ///     next.pass()
    /// })?;
    /// # Ok(()) }
    /// ```
    pub fn register_channel_filter<F: crate::channel::ChannelFilter>(
        &mut self,
        name: &str,
        side: crate::channel::FilterSide,
        filter: F,
    ) -> Result<(), Error> {
        self.raw
            .register_channel_filter(name, side, crate::ffi::RawChannelFilter::new(filter))
            .map_err(Error::Registration)
    }

    /// Registers an RPC filter for `side` under `name` (ABI 1.9; AimRT's
    /// `RegisterClientFilter` / `RegisterServerFilter`). A module function runs it when
    /// its `clients_options` (client) or `servers_options` (server) rule lists the name in
    /// `enable_filters`; the filter listed last runs first. A name already registered for
    /// that side, or a built-in one (`debug_log`, `time_cost`), is refused, and so is every
    /// name on an `aimrt_main` older than 1.9.
    ///
    /// ```no_run
    /// use aimrt_plugin_api::rpc::{CallFilterSide, CallNext, FilterCall};
    /// # fn init(registrar: &mut aimrt_plugin_api::Registrar<'_>) -> Result<(), aimrt_plugin_api::Error> {
    /// // Stamps `caller` with the calling module on every call.
    /// registrar.register_rpc_filter("caller", CallFilterSide::Client, |call: &FilterCall<'_>, next: CallNext<'_>| {
    ///     let mut ctx = next.context();
    ///     ctx.set_meta("caller", call.module());
    ///     next.pass_with(&ctx)
    /// })?;
    /// # Ok(()) }
    /// ```
    pub fn register_rpc_filter<F: crate::rpc::CallFilter>(
        &mut self,
        name: &str,
        side: crate::rpc::CallFilterSide,
        filter: F,
    ) -> Result<(), Error> {
        self.raw
            .register_rpc_filter(name, side, crate::ffi::RawRpcFilter::new(filter))
            .map_err(Error::Registration)
    }

    /// Registers a log backend type (ABI 1.10; AimRT's `RegisterLoggerBackendGenFunc`):
    /// each `aimrt.log.backends` entry of type `type_name` gets a backend from `factory`,
    /// called with the entry's options less the keys the runtime reads (`module_filter`,
    /// `pattern`, `log_executor_name`). The backend is handed every line the entry's
    /// `module_filter` admits ([`LogEntry`](crate::LogEntry): the line formatted with
    /// its `pattern`, and since 1.11 its parts), on the log thread. `console`,
    /// `rotate_file` and a type already registered are refused, and so is every type on
    /// an `aimrt_main` older than 1.10.
    ///
    /// ```no_run
    /// use aimrt_plugin_api::{BackendOptions, LogBackend, LogEntry};
    /// # fn init(registrar: &mut aimrt_plugin_api::Registrar<'_>) -> Result<(), aimrt_plugin_api::Error> {
    /// /// Writes each line to stderr.
    /// struct Stderr;
    /// impl LogBackend for Stderr {
    ///     fn write(&mut self, entry: &LogEntry<'_>) -> Result<(), String> {
    ///         eprintln!("{}", entry.formatted);
    ///         Ok(())
    ///     }
    /// }
    /// registrar.register_log_backend_type("stderr", |_: &BackendOptions| Ok(Stderr))?;
    /// # Ok(()) }
    /// ```
    pub fn register_log_backend_type<F, B>(
        &mut self,
        type_name: &str,
        factory: F,
    ) -> Result<(), Error>
    where
        F: Fn(&crate::BackendOptions) -> Result<B, Error> + Send + Sync + 'static,
        B: crate::LogBackend,
    {
        self.raw
            .register_log_backend_type(crate::ffi::RawLogBackendType::new(type_name, factory))
            .map_err(Error::Registration)
    }
}

/// One entry of AimRT's `type_support_pkgs` option (`{path: ./libexample_pb_ts.so}`), for
/// a plugin's options struct.
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct TypeSupportPkg {
    /// The library.
    pub path: String,
}

/// The message types of the type support packages a plugin loaded
/// ([`Registrar::load_type_support_pkgs`]), by name.
#[derive(Debug, Default)]
pub struct TypeSupports {
    tables: Vec<(String, &'static crate::ffi::TypeSupportVtable)>,
}

impl TypeSupports {
    /// The table of `msg_type`; `Err` says it is in no package, names the closest loaded
    /// one and lists them all.
    pub fn get(&self, msg_type: &str) -> Result<&'static crate::ffi::TypeSupportVtable, String> {
        if let Some((_, ts)) = self.tables.iter().find(|(n, _)| n == msg_type) {
            return Ok(ts);
        }
        let loaded: Vec<&str> = self.tables.iter().map(|(n, _)| n.as_str()).collect();
        Err(format!(
            "msg_type '{msg_type}' is in no type support pkg{}; loaded: {}",
            crate::suggest::did_you_mean(msg_type, loaded.iter().copied()),
            if loaded.is_empty() {
                "none (add type_support_pkgs)".to_owned()
            } else {
                loaded.join(", ")
            }
        ))
    }
}
