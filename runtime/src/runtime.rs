//! The runtime: config → plugins → executors → modules → run → shutdown in reverse.

use aimrt_plugin_api::rpc::CallFilterSide;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use aimrt_plugin_api::ffi::{RawControl, RawExecutor, RawLogger};
use aimrt_plugin_api::{LogLevel, Module, Plugin, ThreadFactory};

use crate::app::App;
use crate::channel::ChannelManager;
use crate::config::{Config, GuardThreadSection, ThreadSection};
use crate::control::Control;
use crate::executor::serial::SerialQueue;
use crate::executor::ExecutorManager;
use crate::log::settings::{BackendKind, LogSettings};
use crate::log::{LogHub, Logger};
use crate::module::ModuleManager;
use crate::plugin::{HostHandles, PluginManager};
use crate::report;
use crate::rpc::calls::RpcRegistry;
use crate::rpc::RpcManager;
use crate::thread::HostThreads;
use crate::Error;

/// How to run.
#[derive(Debug, Default, Clone)]
pub struct RuntimeOptions {
    /// The YAML config (`--cfg_file_path`); `None` (and no `cfg_yaml`) starts with an
    /// empty config.
    pub cfg_file_path: Option<PathBuf>,
    /// The YAML config as text, instead of a file (app mode); setting both is an error.
    /// `${VAR}` substitution applies as to a file, and relative paths in it are relative
    /// to the working directory.
    pub cfg_yaml: Option<String>,
    /// Stop after this long (`--running_duration`); `None` runs until shutdown is requested.
    pub running_duration: Option<Duration>,
    /// Write the effective config here after initialization (`--dump_cfg_file`).
    pub dump_cfg_file: Option<PathBuf>,
    /// Write the initialization report here after initialization (`--dump_init_report`).
    pub dump_init_report: Option<PathBuf>,
}

#[derive(Debug, Default)]
pub(crate) struct Shared {
    pub(crate) stop: AtomicBool,
    pub(crate) main: OnceLock<Arc<SerialQueue>>,
    /// Start-up has ended (with the runtime running, or stopped by an error).
    pub(crate) started: AtomicBool,
}

/// Requests a graceful shutdown from any thread (e.g. a signal handler thread).
#[derive(Debug, Clone)]
pub struct ShutdownHandle(pub(crate) Arc<Shared>);

impl ShutdownHandle {
    /// Asks the runtime to shut down; returns `false` if it was already asked.
    pub fn request(&self) -> bool {
        let first = !self.0.stop.swap(true, Ordering::SeqCst);
        if let Some(main) = self.0.main.get() {
            main.request_stop();
        }
        // A step of start-up can take long (a plugin waiting for its peer, a module's
        // initialize): say at once that the request was heard and when it takes effect.
        if first && !self.0.started.load(Ordering::SeqCst) {
            tracing::info!(target: "aimrt", "Received shutdown signal during start-up: AimRT shuts down as soon as the step under way ends; a second signal exits at once.");
        }
        first
    }
}

/// The aimrt-rs runtime, as `aimrt_main` runs it.
///
/// ```no_run
/// let runtime = aimrt_runtime::Runtime::new(aimrt_runtime::RuntimeOptions {
///     cfg_file_path: Some("config/demo.yaml".into()),
///     running_duration: Some(std::time::Duration::from_secs(1)),
///     ..Default::default()
/// });
/// runtime.run().expect("runtime failed");
/// ```
pub struct Runtime {
    options: RuntimeOptions,
    builtins: Vec<Box<dyn Plugin>>,
    modules: Vec<Box<dyn Module>>,
    shared: Arc<Shared>,
    hub: Arc<LogHub>,
}

impl std::fmt::Debug for Runtime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Runtime")
            .field("options", &self.options)
            .finish_non_exhaustive()
    }
}

#[derive(Default)]
pub(crate) struct Parts {
    plugins: PluginManager,
    rpc: RpcManager,
    /// Module service and client functions.
    calls: Arc<RpcRegistry>,
    executors: ExecutorManager,
    modules: ModuleManager,
    channel: Option<Arc<ChannelManager>>,
    main: Option<Arc<SerialQueue>>,
    guard: Option<(Arc<SerialQueue>, JoinHandle<()>)>,
}

impl Runtime {
    /// A runtime with `options` and no built-in plugins.
    pub fn new(options: RuntimeOptions) -> Runtime {
        Runtime {
            options,
            builtins: Vec::new(),
            modules: Vec::new(),
            shared: Arc::new(Shared::default()),
            hub: LogHub::global(),
        }
    }

    /// Adds a statically linked plugin. Its executor types are registered after those of
    /// the config's plugins; a type a plugin already registered is skipped (the plugin wins).
    pub fn builtin_plugin(&mut self, plugin: Box<dyn Plugin>) -> &mut Self {
        self.builtins.push(plugin);
        self
    }

    /// Adds a module object built in code (no pkg library). Modules registered in code
    /// are initialized and started before those of the config's pkgs, in registration
    /// order; `aimrt.module.modules` entries (`enable`, `log_lvl`, `cfg_file_path`) apply
    /// to them by name as to any module.
    ///
    /// ```no_run
    /// use aimrt_plugin_api::{CoreRef, Error, LogLevel, Module, ModuleInfo};
    /// struct Hello;
    /// impl Module for Hello {
    ///     fn info(&self) -> ModuleInfo { ModuleInfo::new("Hello") }
    ///     fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
    ///         core.logger().log(LogLevel::Info, "hello from code");
    ///         Ok(())
    ///     }
    /// }
    /// let mut runtime = aimrt_runtime::Runtime::new(Default::default());
    /// runtime.register_module(Box::new(Hello));
    /// runtime.run().expect("runtime failed");
    /// ```
    pub fn register_module(&mut self, module: Box<dyn Module>) -> &mut Self {
        self.modules.push(module);
        self
    }

    /// A handle to request shutdown.
    pub fn shutdown_handle(&self) -> ShutdownHandle {
        ShutdownHandle(self.shared.clone())
    }

    /// Runs to completion: initialize, start, serve the main thread until shutdown is
    /// requested or the running duration ends, then shut down in reverse order.
    pub fn run(self) -> Result<(), Error> {
        let deadline = self.options.running_duration.map(|d| Instant::now() + d);
        let timed = self.options.running_duration.is_some();
        let app = self.start()?;
        if app.stop_requested() {
            // A signal during start-up: shut down at once.
        } else if timed {
            tracing::info!(target: "aimrt", "AimRT start completed, will waiting for async shutdown.");
        } else {
            tracing::info!(target: "aimrt", "AimRT startup completed, will wait for shutdown.");
        }
        app.serve_until_shutdown(deadline);
        app.shutdown();
        Ok(())
    }

    /// Initializes and starts everything (app mode): plugins, executors, the modules
    /// registered in code and then those of the config's pkgs. The returned [`App`] drives
    /// the main-thread executor with its `spin*` calls and shuts down with
    /// [`App::shutdown`] (or when dropped). On failure everything started so far is shut
    /// down again before the error is returned.
    ///
    /// ```no_run
    /// let mut runtime = aimrt_runtime::Runtime::new(aimrt_runtime::RuntimeOptions {
    ///     cfg_yaml: Some("aimrt: {main_thread: {name: main}}".into()),
    ///     ..Default::default()
    /// });
    /// let app = runtime.start().expect("start failed");
    /// app.spin_all(std::time::Duration::from_millis(10)).unwrap();
    /// app.shutdown();
    /// ```
    pub fn start(mut self) -> Result<App, Error> {
        let core = Logger::new("core", LogLevel::Info, &self.hub);
        aimrt_plugin_api::__private::install_host(RawLogger::leak(core.clone()));
        // Large messages reuse freed memory instead of faulting fresh pages in each time.
        aimrt_plugin_api::ffi::keep_freed_memory();
        let mut parts = Parts::default();
        let started = self.start_up(&mut parts, &core);
        self.shared.started.store(true, Ordering::SeqCst);
        match started {
            Ok(main) => Ok(App::new(parts, main, self.shared.clone(), self.hub.clone())),
            Err(e) => {
                tracing::info!(target: "aimrt", "AimRT start shutdown.");
                shutdown(&mut parts);
                self.hub.stop();
                Err(e)
            }
        }
    }

    /// Everything up to running; returns the main-thread queue.
    fn start_up(
        &mut self,
        parts: &mut Parts,
        core: &Arc<Logger>,
    ) -> Result<Arc<SerialQueue>, Error> {
        let config = match (&self.options.cfg_yaml, &self.options.cfg_file_path) {
            (Some(_), Some(path)) => {
                return Err(Error::Cli(format!(
                    "both cfg_yaml and cfg_file_path ({}) are set; give the config one way",
                    path.display()
                )))
            }
            (Some(text), None) => Config::parse("<cfg_yaml>", text, |k| std::env::var(k).ok())?,
            (None, Some(path)) => Config::load(path)?,
            (None, None) => Config::default(),
        };
        let log = self.configure_log(&config, core)?;
        let (core_lvl, module_lvl) = (log.core_lvl, log.module_lvl);
        for (section, why) in config.ignored_sections() {
            tracing::warn!(target: "aimrt", "{}: section '{section}' {why}; it is ignored", config.file);
        }
        // The main thread's queue exists from here on, so that a stop requested at any
        // later step returns a runtime that shuts down what was started.
        let main_cfg = config
            .aimrt
            .main_thread
            .as_ref()
            .map_or_else(ThreadSection::default, Clone::clone);
        let guard_cfg = config
            .aimrt
            .guard_thread
            .as_ref()
            .map_or_else(GuardThreadSection::default, Clone::clone);
        for (key, name) in [
            ("aimrt.main_thread.name", &main_cfg.name),
            ("aimrt.guard_thread.name", &guard_cfg.name),
        ] {
            crate::config::check_name(&name.value)
                .map_err(|m| config.error(name, format!("{key}: {m}")))?;
        }
        if main_cfg.name.value == guard_cfg.name.value {
            return Err(config.error(
                &guard_cfg.name,
                format!(
                    "aimrt.main_thread.name and aimrt.guard_thread.name are both '{}'; give them different names",
                    main_cfg.name.value
                ),
            ));
        }
        let main = Arc::new(SerialQueue::new(
            crate::executor::serial::MAIN_THREAD_TYPE,
            &main_cfg.name.value,
            None,
            1000,
        ));
        let _ = self.shared.main.set(main.clone());
        parts.main = Some(main.clone());
        let stopped = || self.shared.stop.load(Ordering::SeqCst);
        if stopped() {
            return Ok(main);
        }
        let factory = ThreadFactory::leak(Arc::new(HostThreads::new()));
        let threads = factory.raw();
        let control = Arc::new(Control::new(self.hub.clone()));
        parts.plugins.load(
            &config,
            std::mem::take(&mut self.builtins),
            HostHandles {
                threads,
                control: RawControl::leak(control.clone()),
            },
            core_lvl,
            &self.hub,
            &self.shared.stop,
        )?;
        if stopped() {
            return Ok(main);
        }
        tracing::info!(target: "aimrt", "Plugin manager init complete");
        // Backends of types plugins registered: the pipeline starts again with them.
        if log
            .backends
            .iter()
            .any(|b| matches!(b.kind, BackendKind::Plugin { .. }))
        {
            let types = &parts.plugins.log_backend_types;
            self.hub.start(&log, Some(types)).map_err(|e| Error::Log {
                location: e.at,
                message: e.message,
            })?;
        }

        // The main thread's settings apply to the thread that runs the runtime.
        factory
            .configure_current(main_cfg.settings())
            .map_err(Error::Thread)?;
        // A negative alarm interval silences the warning only; the limit still holds.
        let threshold = Some(u64::from(guard_cfg.queue_threshold));
        let guard = Arc::new(SerialQueue::new(
            "guard_thread",
            &guard_cfg.name.value,
            threshold,
            guard_cfg.threshold_alarm_interval_ms,
        ));
        let served = guard.clone();
        let handle = factory
            .spawn(guard_cfg.settings(), move || served.serve(None))
            .map_err(Error::Thread)?;
        parts.guard = Some((guard, handle));

        let reserved = [main_cfg.name.value.as_str(), guard_cfg.name.value.as_str()];
        parts
            .executors
            .build(&config, &parts.plugins.executor_types, &reserved, threads)?;
        parts
            .executors
            .add_runtime_executor(&main_cfg.name.value, RawExecutor::new(main.clone()));
        check_log_sync(&log, &parts.executors.table())?;
        tracing::info!(target: "aimrt", "Executor manager init complete");
        parts.rpc.configure(
            &config,
            &parts.plugins.services,
            crate::rpc::FromPlugins {
                backends: std::mem::take(&mut parts.plugins.rpc_backends),
                passed_keys: parts.plugins.passed_keys.clone(),
                filters: std::mem::take(&mut parts.plugins.rpc_filters),
            },
            &parts.calls,
            &parts.executors.table(),
        )?;
        tracing::info!(target: "aimrt", "Rpc manager init complete");
        let channel = Arc::new(ChannelManager::configure(
            &config,
            &parts.executors.table(),
            std::mem::take(&mut parts.plugins.channel_backends),
            std::mem::take(&mut parts.plugins.channel_filters),
        )?);
        parts.channel = Some(channel.clone());
        parts
            .plugins
            .bind_cores(&channel, &parts.executors.table())?;
        tracing::info!(target: "aimrt", "Channel manager init complete");

        parts.modules.load(
            &config,
            std::mem::take(&mut self.modules),
            core_lvl,
            &self.hub,
        )?;
        let services = crate::module::Services {
            executors: Arc::new(parts.executors.table()),
            channel: channel.clone(),
            calls: parts.calls.clone(),
            control,
        };
        parts
            .modules
            .initialize(&config, &services, module_lvl, &self.hub, &self.shared.stop)?;
        // A stop requested during initialize: nothing more starts; the caller sees the
        // request and shuts down what was initialized, as after a signal during run.
        if self.shared.stop.load(Ordering::SeqCst) {
            return Ok(main);
        }
        tracing::info!(target: "aimrt", "Module manager init complete");
        self.hub.warn_unmatched_filters();
        self.dump(&config, parts)?;

        parts.plugins.start()?;
        parts.rpc.start()?;
        parts.calls.start().map_err(|e| Error::Rpc {
            backend: "local".into(),
            message: format!("cannot start the RPC deadline thread: {e}"),
        })?;
        channel.start()?;
        parts.modules.start(&self.shared.stop)?;
        parts.plugins.start_cores();
        if !self.shared.stop.load(Ordering::SeqCst) {
            parts.plugins.post_start();
        }
        if !self.shared.stop.load(Ordering::SeqCst) {
            tracing::info!(target: "aimrt", "Module manager start completed.");
        }
        Ok(main)
    }

    /// The dumps AimRT writes after a successful initialization.
    fn dump(&self, config: &Config, parts: &Parts) -> Result<(), Error> {
        let write = |path: &PathBuf, text: &str, flag: &'static str| {
            std::fs::write(path, text).map_err(|source| Error::Dump {
                path: path.clone(),
                flag,
                source,
            })
        };
        if let Some(path) = &self.options.dump_cfg_file {
            let reported = crate::config::ReportedOptions {
                plugins: parts.plugins.normalized_options.clone(),
                executors: parts.executors.normalized_options.clone(),
                channel_backends: (parts.channel.as_ref())
                    .map(|c| c.reported_options())
                    .unwrap_or_default(),
                rpc_backends: parts.rpc.reported_options(),
                log_backends: self.hub.reported_options(),
            };
            let text = config
                .normalized(&reported)
                .map_err(|reason| Error::DumpFormat {
                    path: path.clone(),
                    reason,
                })?;
            write(path, &text, "dump_cfg_file_path")?;
            tracing::info!(target: "aimrt", "Dumped the normalized config to {}", path.display());
        }
        if let Some(path) = &self.options.dump_init_report {
            write(
                path,
                &self.init_report(config, parts),
                "dump_init_report_path",
            )?;
            tracing::info!(target: "aimrt", "Dumped the initialization report to {}", path.display());
        }
        Ok(())
    }

    fn init_report(&self, config: &Config, parts: &Parts) -> String {
        let s = |v: &str| v.to_owned();
        let exe = std::env::current_exe().map_or_else(|_| s("?"), |p| p.display().to_string());
        let base = report::table(
            &[
                vec![s("Version"), s(crate::VERSION)],
                vec![s("Cfg File Path"), config.file.clone()],
                vec![s("Executable Path"), exe],
                vec![s("Process PID"), std::process::id().to_string()],
            ],
            false,
        );
        let mut plugins = vec![vec![s("name"), s("path")]];
        plugins.extend(
            parts
                .plugins
                .sources
                .iter()
                .map(|(n, p)| vec![n.clone(), p.clone()]),
        );
        let mut types = vec![vec![s("type"), s("registered by")]];
        types.extend(
            parts
                .plugins
                .executor_types
                .iter()
                .map(|(t, ty)| vec![t.clone(), ty.owner.clone()]),
        );
        let mut executors = vec![vec![
            s("name"),
            s("type"),
            s("thread safe"),
            s("support time schedule"),
            s("options"),
        ]];
        executors.extend(parts.executors.report_rows());
        let backends: Vec<&str> = config
            .aimrt
            .log
            .as_ref()
            .map(|l| {
                l.backends
                    .iter()
                    .map(|b| b.type_name.value.as_str())
                    .collect()
            })
            .unwrap_or_default();
        let plugin_services = parts.plugins.services.list();
        let mut services = vec![vec![s("function"), s("registered by")]];
        services.extend(
            plugin_services
                .iter()
                .map(|(f, o)| vec![f.clone(), o.clone()]),
        );
        let rpc_header = || vec![s("func"), s("module"), s("backends"), s("filters")];
        let (mut rpc_clients, mut rpc_servers) = (vec![rpc_header()], vec![rpc_header()]);
        rpc_clients.extend(parts.calls.rows(false, Vec::new()));
        rpc_servers.extend(parts.calls.rows(true, plugin_services));
        let mut modules = vec![vec![s("name"), s("pkg"), s("version")]];
        modules.extend(parts.modules.report_rows());
        let topic_header = || {
            let columns = ["topic", "msg type", "module", "backends", "filters"];
            columns.map(s).to_vec()
        };
        let (mut pub_topics, mut sub_topics) = (vec![topic_header()], vec![topic_header()]);
        let mut channel_backends = Vec::new();
        let rpc_filters = [CallFilterSide::Client, CallFilterSide::Server]
            .map(|side| parts.calls.filter_names(side));
        let builtin = || crate::channel::BUILT_IN_FILTERS.to_vec();
        let (mut pub_filters, mut sub_filters) = (builtin(), builtin());
        if let Some(c) = &parts.channel {
            channel_backends = c.backend_names();
            (pub_filters, sub_filters) = c.filter_names();
            pub_topics.extend(c.topic_rows(true));
            sub_topics.extend(c.topic_rows(false));
        }
        report::render(&[
            ("Base Info", base),
            ("Plugin List", report::table(&plugins, true)),
            ("Executor Type List", report::table(&types, true)),
            ("Executor List", report::table(&executors, true)),
            ("Log Backend List", report::list(backends)),
            ("Rpc Service List", report::table(&services, true)),
            (
                "Rpc Client Filter List",
                report::list(rpc_filters[0].iter().map(String::as_str)),
            ),
            (
                "Rpc Server Filter List",
                report::list(rpc_filters[1].iter().map(String::as_str)),
            ),
            ("Rpc Client Info", report::table(&rpc_clients, true)),
            ("Rpc Server Info", report::table(&rpc_servers, true)),
            ("Channel Backend List", report::list(channel_backends)),
            ("Channel Pub Filter List", report::list(pub_filters)),
            ("Channel Sub Filter List", report::list(sub_filters)),
            ("Channel Pub Topic Info", report::table(&pub_topics, true)),
            ("Channel Sub Topic Info", report::table(&sub_topics, true)),
            ("Module Info List", report::table(&modules, true)),
        ])
    }

    /// Validates `aimrt.log`, sets the core level and starts the log pipeline.
    fn configure_log(&self, config: &Config, core: &Arc<Logger>) -> Result<LogSettings, Error> {
        let settings = LogSettings::from_config(config)?;
        core.set_level(settings.core_lvl);
        self.hub.start(&settings, None).map_err(|e| Error::Log {
            location: e.at,
            message: e.message,
        })?;
        for warning in &settings.warnings {
            tracing::warn!(target: "aimrt", "{warning}");
        }
        Ok(settings)
    }
}

/// Checks `sync_executor_name` of each `rotate_file` backend with `enable_sync`: it must
/// name an executor with timers, as in AimRT. (The fsync itself runs on the log thread,
/// ordered with the writes; see docs/logging.md.)
fn check_log_sync(
    settings: &LogSettings,
    executors: &HashMap<String, RawExecutor>,
) -> Result<(), Error> {
    for backend in &settings.backends {
        let BackendKind::RotateFile(options) = &backend.kind else {
            continue;
        };
        let Some((name, _)) = &options.sync else {
            continue;
        };
        let fail = |message: String| Error::Log {
            location: backend.at.clone(),
            message,
        };
        let Some(raw) = executors.get(name) else {
            return Err(fail(format!(
                "rotate_file sync_executor_name '{name}' is not an executor{}; name one from aimrt.executor.executors that supports timers",
                aimrt_plugin_api::__private::did_you_mean(name, executors.keys().map(String::as_str))
            )));
        };
        if !raw.supports_timer_schedule() {
            return Err(fail(format!(
                "rotate_file sync_executor_name '{name}' is a {} executor, which has no timers; use one that has (e.g. asio_thread or time_wheel)",
                raw.type_name()
            )));
        }
    }
    Ok(())
}

/// Reverse of start-up: modules, plugins, main thread queue, executors, guard thread.
pub(crate) fn shutdown(parts: &mut Parts) {
    // No outside call reaches a service while modules and executors shut down; the
    // modules' own calls still go out through every backend, as in AimRT.
    parts.calls.stopping();
    parts.modules.shutdown();
    tracing::info!(target: "aimrt", "Module manager shutdown.");
    // Calls still in flight are answered; none is taken any more.
    parts.calls.close();
    parts.rpc.shutdown();
    parts.plugins.services.report();
    if let Some(channel) = parts.channel.take() {
        channel.shutdown();
        tracing::info!(target: "aimrt", "Channel manager shutdown.");
    }
    parts.plugins.shutdown();
    if let Some(main) = parts.main.take() {
        main.close_and_drain();
    }
    parts.executors.shutdown();
    tracing::info!(target: "aimrt", "Executor manager shutdown.");
    if let Some((guard, handle)) = parts.guard.take() {
        guard.request_stop();
        let _ = handle.join();
        guard.close_and_drain();
    }
}
