//! Logging: per-module loggers with levels, AimRT's pattern language, the `console` and
//! `rotate_file` backends, and the bounded pipeline between them.
//!
//! Every logger is a [`LogSink`] exported to libraries as a host log sink. A line at or
//! above its logger's level is formatted on the calling thread, once per backend whose
//! `module_filter` accepts the logger (backends with the same pattern share the text), and
//! queued for the log thread. The queue holds [`QUEUE_CAPACITY`] lines; a line that finds
//! it full is dropped and counted, and the log thread reports the count (rate-limited) in
//! the log itself. The log thread writes in batches and flushes whenever the queue runs
//! empty; a `rotate_file` backend with `enable_sync` is flushed after every line and
//! fsynced every `sync_interval_ms` by the log thread itself (so an fsync never races a
//! write). At shutdown it is stopped last: it writes everything queued, flushes (and, with
//! `enable_sync`, fsyncs) and is joined — no sleeps.
//!
//! Before the config is read and after shutdown, lines go synchronously to stderr in
//! AimRT's bootstrap layout `[%c.%f][%l][%t][%g:%R @%F]%v`.

pub(crate) mod pattern;
pub(crate) mod settings;
mod sink;

use std::collections::BTreeMap;
use std::io::Write;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock, Weak};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::plugin::LogBackendType;
use aimrt_plugin_api::ffi::{LevelWatchers, LevelsChanged};
use aimrt_plugin_api::{LogLevel, LogLine, LogSink};
use crossbeam_channel::{Receiver, Sender};
use regex::Regex;

use self::pattern::{Pattern, Record, BOOTSTRAP};
use self::settings::{BackendKind, LogSettings};
use self::sink::{Console, Parts, RotateFile, Sink};

/// Lines the log queue holds before new ones are dropped (AimRT's guard-thread limit).
pub(crate) const QUEUE_CAPACITY: usize = 10_000;

/// How often the log thread reports dropped lines at most.
const DROP_REPORT_INTERVAL: Duration = Duration::from_secs(1);

enum Cmd {
    Line {
        backend: usize,
        level: LogLevel,
        text: String,
        /// The line's parts, for a backend that takes them.
        parts: Option<Box<Parts>>,
    },
    Stop,
}

/// A backend as seen by logging threads: which loggers, which layout.
struct Front {
    pattern: Pattern,
    filter: Option<Regex>,
    /// The backend takes each line's parts too (a plugin's).
    parts: bool,
}

impl Front {
    fn accepts(&self, logger: &str) -> bool {
        self.filter.as_ref().is_none_or(|f| f.is_match(logger))
    }
}

/// State shared by logging threads and the log thread.
struct Shared {
    fronts: Vec<Front>,
    dropped: AtomicU64,
}

/// A running pipeline: the queue and the log thread.
struct Pipeline {
    shared: Arc<Shared>,
    tx: Sender<Cmd>,
    thread: Mutex<Option<JoinHandle<Totals>>>,
}

/// What the log thread did, reported when it stops.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Totals {
    pub(crate) written: u64,
    pub(crate) dropped: u64,
    pub(crate) write_errors: u64,
}

enum Mode {
    Stderr,
    /// No backend is configured: only warnings and errors are written, to stderr.
    StderrWarnings,
    Pipeline(Arc<Pipeline>),
}

/// Where lines go, shared by every logger.
pub(crate) struct LogHub {
    mode: RwLock<Mode>,
    stderr: Mutex<()>,
    /// Every logger made ([`Logger::new`]), by name: a name may have several (a plugin's
    /// library and its core), which share a level.
    loggers: Mutex<BTreeMap<String, Vec<Weak<Logger>>>>,
    /// What libraries asked to be told of level changes (ABI 1.13).
    watchers: LevelWatchers,
    /// The started backends' `module_filter`s: `(type, at, filter)`, `None` for every
    /// logger.
    filters: Mutex<Vec<(String, String, Option<Regex>)>>,
    /// The options plugins' backends reported reading, by index in `aimrt.log.backends`.
    reported: Mutex<BTreeMap<usize, serde_json::Value>>,
}

impl std::fmt::Debug for LogHub {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LogHub").finish_non_exhaustive()
    }
}

thread_local! {
    /// Whether this thread is the log thread (which writes to the backends).
    static ON_LOG_THREAD: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// A backend that could not be opened.
#[derive(Debug)]
pub(crate) struct OpenError {
    /// `file:line:col` of the backend's `type`.
    pub(crate) at: String,
    pub(crate) message: String,
}

impl LogHub {
    /// The process's hub: libraries keep the loggers they were given for the process's
    /// life, so every runtime in one process shares where lines go.
    pub(crate) fn global() -> Arc<LogHub> {
        static HUB: std::sync::OnceLock<Arc<LogHub>> = std::sync::OnceLock::new();
        HUB.get_or_init(|| Arc::new(LogHub::new())).clone()
    }

    fn new() -> LogHub {
        LogHub {
            mode: RwLock::new(Mode::Stderr),
            stderr: Mutex::new(()),
            loggers: Mutex::default(),
            watchers: LevelWatchers::default(),
            filters: Mutex::default(),
            reported: Mutex::default(),
        }
    }

    /// The options plugins' backends reported reading, by index in `aimrt.log.backends`
    /// (`--dump_cfg_file`).
    pub(crate) fn reported_options(&self) -> BTreeMap<usize, serde_json::Value> {
        self.reported
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Opens the configured backends and starts the log thread; with no backend, lines
    /// below Warn are discarded (AimRT's behaviour) and warnings and errors go to stderr. A
    /// pipeline already running is stopped first. Backends of plugin types are made from
    /// `plugin_types` once plugins are loaded; before (`None`) they are left out.
    pub(crate) fn start(
        &self,
        settings: &LogSettings,
        plugin_types: Option<&BTreeMap<String, LogBackendType>>,
    ) -> Result<(), OpenError> {
        let mut sinks: Vec<Box<dyn Sink>> = Vec::new();
        let mut fronts = Vec::new();
        let mut sync_every = Vec::new();
        let mut started = Vec::new();
        let mut reported = BTreeMap::new();
        for (index, b) in settings.backends.iter().enumerate() {
            let sink: Box<dyn Sink> = match &b.kind {
                BackendKind::Console { color } => Box::new(Console::new(*color)),
                BackendKind::RotateFile(o) => {
                    Box::new(RotateFile::open(o.clone()).map_err(|e| OpenError {
                        at: b.at.clone(),
                        message: format!(
                            "rotate_file cannot open '{}': {e}; check 'path' and its permissions",
                            o.path.join(&o.filename).display()
                        ),
                    })?)
                }
                BackendKind::Plugin {
                    type_name,
                    options_json,
                    location,
                } => {
                    let Some(types) = plugin_types else {
                        continue;
                    };
                    let Some(ty) = types.get(type_name) else {
                        let known: Vec<&str> = settings::BACKEND_TYPES
                            .into_iter()
                            .chain(types.keys().map(String::as_str))
                            .collect();
                        return Err(OpenError {
                            at: b.at.clone(),
                            message: format!(
                                "unknown log backend type '{type_name}'{}; the types are {} (a plugin registers more)",
                                aimrt_plugin_api::__private::did_you_mean(type_name, known.iter().copied()),
                                known.join(", ")
                            ),
                        });
                    };
                    let backend =
                        ty.raw
                            .create(options_json, location)
                            .map_err(|message| OpenError {
                                at: b.at.clone(),
                                message,
                            })?;
                    let owner = format!("log backend '{type_name}' of '{}'", ty.owner);
                    let read = backend.reported_options();
                    if let Some(v) =
                        read.and_then(|j| crate::config::ReportedOptions::parse(&owner, &j))
                    {
                        reported.insert(index, v);
                    }
                    Box::new(sink::PluginSink(backend))
                }
            };
            let parts = sink.takes_parts();
            sinks.push(sink);
            sync_every.push(match &b.kind {
                BackendKind::RotateFile(o) => o.sync.as_ref().map(|(_, every)| *every),
                BackendKind::Console { .. } | BackendKind::Plugin { .. } => None,
            });
            fronts.push(Front {
                pattern: b.pattern.clone(),
                filter: b.module_filter.clone(),
                parts,
            });
            started.push((
                b.kind.type_name().to_owned(),
                b.at.clone(),
                b.module_filter.clone(),
            ));
        }
        *self.filters.lock().unwrap_or_else(|e| e.into_inner()) = started;
        *self.reported.lock().unwrap_or_else(|e| e.into_inner()) = reported;
        self.stop();
        if sinks.is_empty() {
            *self.mode.write().unwrap_or_else(|e| e.into_inner()) = Mode::StderrWarnings;
            return Ok(());
        }
        self.launch(fronts, sinks, sync_every)
            .map(drop)
            .map_err(|e| OpenError {
                at: settings.backends[0].at.clone(),
                message: format!("cannot start the log thread: {e}"),
            })
    }

    /// Starts the log thread over `sinks` (each fsynced every `sync_every[i]`, if set) and
    /// sends lines to it.
    fn launch(
        &self,
        fronts: Vec<Front>,
        sinks: Vec<Box<dyn Sink>>,
        sync_every: Vec<Option<Duration>>,
    ) -> std::io::Result<Arc<Pipeline>> {
        let now = Instant::now();
        let syncs = sync_every
            .into_iter()
            .map(|every| every.map(|e| (e, now + e)))
            .collect();
        let shared = Arc::new(Shared {
            fronts,
            dropped: AtomicU64::new(0),
        });
        let (tx, rx) = crossbeam_channel::bounded(QUEUE_CAPACITY);
        let writer = Writer {
            rx,
            lost: sinks.iter().map(|_| None).collect(),
            sinks,
            syncs,
            shared: shared.clone(),
            totals: Totals::default(),
            reported: 0,
            last_report: None,
        };
        let thread = std::thread::Builder::new()
            .name("aimrt_log".to_owned())
            .spawn(move || writer.run())?;
        let pipeline = Arc::new(Pipeline {
            shared,
            tx,
            thread: Mutex::new(Some(thread)),
        });
        *self.mode.write().unwrap_or_else(|e| e.into_inner()) = Mode::Pipeline(pipeline.clone());
        Ok(pipeline)
    }

    /// Stops the pipeline, if one runs: lines logged from now on go to stderr; every line
    /// already queued is written and flushed before this returns. Returns the pipeline's
    /// totals.
    /// Warns about each backend whose `module_filter` matches none of the loggers made so
    /// far (the runtime's, its plugins' and its modules'): such a backend writes nothing,
    /// which is most often a filter written as a prefix (`Logger` for `Logger.*`).
    /// Said in the log when a backend shows the runtime's (`core`) lines, else on stderr.
    pub(crate) fn warn_unmatched_filters(&self) {
        let loggers = self.loggers.lock().unwrap_or_else(|e| e.into_inner());
        let names: Vec<&String> = loggers.keys().collect();
        let filters = self.filters.lock().unwrap_or_else(|e| e.into_inner());
        let shows_core = filters
            .iter()
            .any(|(_, _, f)| f.as_ref().is_none_or(|f| f.is_match("core")));
        for (kind, at, filter) in filters.iter() {
            let Some(filter) = filter else { continue };
            if names.iter().any(|n| filter.is_match(n)) {
                continue;
            }
            let pattern = filter.as_str();
            // Compiled to match whole names: `^(?:…)$` around the user's text.
            let text = pattern
                .strip_prefix("^(?:")
                .and_then(|p| p.strip_suffix(")$"))
                .unwrap_or(pattern);
            let example = if names.iter().any(|n| n.starts_with(text)) {
                format!(" (e.g. '{text}.*')")
            } else if names.iter().any(|n| n.contains(text)) {
                format!(" (e.g. '.*{text}.*')")
            } else {
                String::new()
            };
            let list: Vec<&str> = names.iter().map(|n| n.as_str()).collect();
            let message = format!("log backend '{kind}' at {at}: module_filter '{text}' matches none of this process's loggers ({}), so the backend writes nothing; the filter must match a whole name{example}", list.join(", "));
            if shows_core {
                tracing::warn!(target: "aimrt", "{message}");
            } else {
                let _guard = self.stderr.lock().unwrap_or_else(|e| e.into_inner());
                let _ = writeln!(std::io::stderr().lock(), "aimrt log: {message}");
            }
        }
    }

    /// Every logger's name and level, names in byte order.
    pub(crate) fn levels(&self) -> Vec<(String, LogLevel)> {
        let loggers = self.loggers.lock().unwrap_or_else(|e| e.into_inner());
        loggers
            .iter()
            .filter_map(|(name, all)| {
                let live = all.iter().find_map(Weak::upgrade)?;
                Some((name.clone(), live.level()))
            })
            .collect()
    }

    /// Sets the level of every logger named `name` and tells every library: the level it
    /// had, or `None` when there is no such logger.
    pub(crate) fn set_level(&self, name: &str, level: LogLevel) -> Option<LogLevel> {
        let targets: Vec<Arc<Logger>> = {
            let loggers = self.loggers.lock().unwrap_or_else(|e| e.into_inner());
            loggers
                .get(name)
                .map(|all| all.iter().filter_map(Weak::upgrade).collect())
                .unwrap_or_default()
        };
        let before = targets.first()?.level();
        for logger in &targets {
            logger.level.store(level as u32, Ordering::Relaxed);
        }
        aimrt_plugin_api::__private::levels_changed();
        self.watchers.notify();
        Some(before)
    }

    pub(crate) fn stop(&self) -> Option<Totals> {
        let old = std::mem::replace(
            &mut *self.mode.write().unwrap_or_else(|e| e.into_inner()),
            Mode::Stderr,
        );
        let Mode::Pipeline(pipeline) = old else {
            return None;
        };
        // Every logging thread that saw the pipeline has finished its send (the write
        // lock above waited for them), so Stop is the last command.
        let _ = pipeline.tx.send(Cmd::Stop);
        let handle = pipeline
            .thread
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        let totals = handle.and_then(|h| h.join().ok()).unwrap_or_default();
        if totals.dropped > 0 || totals.write_errors > 0 {
            self.to_stderr(
                "core",
                &LogLine {
                    level: LogLevel::Warn,
                    file: file!(),
                    line: line!(),
                    target: module_path!(),
                    message: &format!(
                        "log pipeline: {} lines written, {} dropped (queue of {QUEUE_CAPACITY} full), {} write errors",
                        totals.written, totals.dropped, totals.write_errors
                    ),
                },
            );
        }
        Some(totals)
    }

    fn write(&self, logger: &str, line: &LogLine<'_>) {
        if ON_LOG_THREAD.with(std::cell::Cell::get) {
            // A line a plugin's backend logs while it writes: queued, it would come back
            // to the same backend, line after line. Warnings and errors go to stderr.
            if line.level >= LogLevel::Warn {
                self.to_stderr(logger, line);
            }
            return;
        }
        let mode = self.mode.read().unwrap_or_else(|e| e.into_inner());
        let pipeline = match &*mode {
            Mode::StderrWarnings if line.level >= LogLevel::Warn => {
                return self.to_stderr(logger, line)
            }
            Mode::StderrWarnings => return,
            Mode::Stderr => return self.to_stderr(logger, line),
            Mode::Pipeline(p) => p,
        };
        let record = record(logger, line);
        let fronts = &pipeline.shared.fronts;
        let send = |backend: usize, text: String| {
            let cmd = Cmd::Line {
                backend,
                level: line.level,
                text,
                parts: fronts[backend].parts.then(|| Box::new(Parts::of(&record))),
            };
            if pipeline.tx.try_send(cmd).is_err() {
                pipeline.shared.dropped.fetch_add(1, Ordering::Relaxed);
            }
        };
        let format = |front: &Front| {
            let mut text = String::with_capacity(128 + line.message.len());
            front.pattern.format(&record, &mut text);
            text
        };
        // Formatted once per run of backends with the same pattern; the last one sent
        // takes the text without a copy.
        let mut pending: Option<(usize, String)> = None;
        for (index, front) in fronts.iter().enumerate() {
            if !front.accepts(logger) {
                continue;
            }
            let text = match pending.take() {
                Some((prev, text)) if fronts[prev].pattern == front.pattern => {
                    send(prev, text.clone());
                    text
                }
                Some((prev, text)) => {
                    send(prev, text);
                    format(front)
                }
                None => format(front),
            };
            pending = Some((index, text));
        }
        if let Some((index, text)) = pending {
            send(index, text);
        }
    }

    fn to_stderr(&self, _logger: &str, line: &LogLine<'_>) {
        static BOOT: std::sync::OnceLock<Pattern> = std::sync::OnceLock::new();
        let pattern = BOOT.get_or_init(|| {
            Pattern::parse(BOOTSTRAP).unwrap_or_else(|_| Pattern::default_pattern())
        });
        let mut text = String::with_capacity(128);
        pattern.format(&record("", line), &mut text);
        text.push('\n');
        let _guard = self.stderr.lock().unwrap_or_else(|e| e.into_inner());
        let _ = std::io::stderr().lock().write_all(text.as_bytes());
    }
}

fn record<'a>(logger: &'a str, line: &LogLine<'a>) -> Record<'a> {
    thread_local! {
        static TID: i32 = nix::unistd::gettid().as_raw();
    }
    Record {
        time: chrono::Local::now(),
        level: line.level,
        thread: TID.with(|t| *t),
        name: logger,
        file: line.file,
        line: line.line,
        function: line.target,
        message: line.message,
    }
}

/// The log thread's state.
struct Writer {
    rx: Receiver<Cmd>,
    sinks: Vec<Box<dyn Sink>>,
    /// Per sink: the fsync period and the next fsync.
    syncs: Vec<Option<(Duration, Instant)>>,
    shared: Arc<Shared>,
    totals: Totals,
    /// Dropped lines already reported in the log.
    reported: u64,
    last_report: Option<Instant>,
    /// Per sink: lines whose write failed since the last that succeeded, when the first
    /// failed, and why; written as one line into the sink once it takes lines again.
    lost: Vec<Option<Gap>>,
}

/// Lines a sink could not take (a full disk, say).
struct Gap {
    lines: u64,
    since: chrono::DateTime<chrono::Local>,
    error: String,
}

impl Writer {
    fn run(mut self) -> Totals {
        ON_LOG_THREAD.with(|on| on.set(true));
        loop {
            let next_sync = self.syncs.iter().flatten().map(|(_, at)| *at).min();
            let received = match next_sync {
                Some(at) => self.rx.recv_deadline(at).map_err(|e| e.is_timeout()),
                None => self.rx.recv().map_err(|_| false),
            };
            let cmd = match received {
                Ok(cmd) => cmd,
                Err(true) => {
                    self.sync_due();
                    continue;
                }
                Err(false) => break,
            };
            if !self.handle(cmd) {
                break;
            }
            // Write everything queued, then flush once.
            let mut stop = false;
            while let Ok(cmd) = self.rx.try_recv() {
                if !self.handle(cmd) {
                    stop = true;
                    break;
                }
            }
            self.report_drops(stop);
            for i in 0..self.sinks.len() {
                let r = self.sinks[i].flush();
                self.check(i, r);
            }
            if stop {
                break;
            }
            self.sync_due();
        }
        // Stopped: put what was written on disk where fsync was asked for.
        for i in 0..self.sinks.len() {
            let r = self.sinks[i].sync();
            self.check(i, r);
        }
        self.totals.dropped = self.shared.dropped.load(Ordering::Relaxed);
        self.totals
    }

    /// Fsyncs the sinks whose period has come (`enable_sync`), and schedules the next.
    fn sync_due(&mut self) {
        let now = Instant::now();
        for i in 0..self.sinks.len() {
            if let Some((every, at)) = self.syncs[i] {
                if at <= now {
                    self.syncs[i] = Some((every, now + every));
                    let r = self.sinks[i].sync();
                    self.check(i, r);
                }
            }
        }
    }

    /// Handles one command; false on Stop.
    fn handle(&mut self, cmd: Cmd) -> bool {
        match cmd {
            Cmd::Line {
                backend,
                level,
                text,
                parts,
            } => {
                if self.lost[backend].is_some() && !self.write_gap(backend) {
                    self.lose(backend, "the gap report could not be written".to_owned());
                    return true;
                }
                match self.sinks[backend].write(level, &text, parts.as_deref()) {
                    Ok(()) => self.totals.written += 1,
                    Err(e) => {
                        self.lose(backend, e.to_string());
                        self.check(backend, Err(e));
                    }
                }
            }
            Cmd::Stop => return false,
        }
        true
    }

    /// Counts a line `backend` could not take.
    fn lose(&mut self, backend: usize, error: String) {
        self.lost[backend]
            .get_or_insert_with(|| Gap {
                lines: 0,
                since: chrono::Local::now(),
                error,
            })
            .lines += 1;
    }

    /// Writes, into the sink that lost lines, one line saying how many and when; returns
    /// whether it was written (then the gap is closed).
    fn write_gap(&mut self, backend: usize) -> bool {
        let Some(gap) = &self.lost[backend] else {
            return true;
        };
        let format = "%Y-%m-%d %H:%M:%S%.3f";
        let message = format!(
            "{} log lines were lost between {} and {}: writing them failed ({})",
            gap.lines,
            gap.since.format(format),
            chrono::Local::now().format(format),
            gap.error
        );
        match self.core_line(backend, &message) {
            Ok(()) => {
                self.totals.written += 1;
                self.lost[backend] = None;
                true
            }
            Err(e) => {
                self.check(backend, Err(e));
                false
            }
        }
    }

    /// Writes a Warn line of the runtime's own (`core`) into sink `backend`, in its pattern.
    fn core_line(&mut self, backend: usize, message: &str) -> std::io::Result<()> {
        let line = LogLine {
            level: LogLevel::Warn,
            file: file!(),
            line: line!(),
            target: module_path!(),
            message,
        };
        let (record, front) = (record("core", &line), &self.shared.fronts[backend]);
        let mut text = String::new();
        front.pattern.format(&record, &mut text);
        let parts = front.parts.then(|| Parts::of(&record));
        self.sinks[backend].write(LogLevel::Warn, &text, parts.as_ref())
    }

    /// Counts a write error; the first one is reported on stderr (the log may be what
    /// failed).
    fn check(&mut self, backend: usize, result: std::io::Result<()>) {
        if let Err(e) = result {
            self.totals.write_errors += 1;
            if self.totals.write_errors == 1 {
                let _ = writeln!(
                    std::io::stderr().lock(),
                    "aimrt log: backend {backend} failed to write: {e}; further errors are only counted"
                );
            }
        }
    }

    /// Logs how many lines were dropped since the last report, at most once per
    /// [`DROP_REPORT_INTERVAL`] (always when `last`).
    fn report_drops(&mut self, last: bool) {
        let dropped = self.shared.dropped.load(Ordering::Relaxed);
        if dropped == self.reported {
            return;
        }
        if !last
            && self
                .last_report
                .is_some_and(|t| t.elapsed() < DROP_REPORT_INTERVAL)
        {
            return;
        }
        let message = format!(
            "{} log lines were dropped: the log queue ({QUEUE_CAPACITY} lines) was full",
            dropped - self.reported
        );
        self.reported = dropped;
        self.last_report = Some(Instant::now());
        for i in 0..self.sinks.len() {
            if self.shared.fronts[i].accepts("core") {
                let r = self.core_line(i, &message);
                if r.is_ok() {
                    self.totals.written += 1;
                }
                self.check(i, r);
            }
        }
    }
}

/// One named logger with its own level.
#[derive(Debug)]
pub(crate) struct Logger {
    name: String,
    level: AtomicU32,
    hub: Arc<LogHub>,
}

impl Logger {
    pub(crate) fn new(name: &str, level: LogLevel, hub: &Arc<LogHub>) -> Arc<Logger> {
        let logger = Arc::new(Logger {
            name: name.to_owned(),
            level: AtomicU32::new(level as u32),
            hub: hub.clone(),
        });
        let mut loggers = hub.loggers.lock().unwrap_or_else(|e| e.into_inner());
        let same = loggers.entry(name.to_owned()).or_default();
        same.retain(|w| w.strong_count() > 0);
        same.push(Arc::downgrade(&logger));
        logger
    }

    /// Sets the level. Libraries read their loggers' levels when the loggers are added
    /// (the runtime sets levels before it loads any); this library (the host's) reads
    /// them again now.
    pub(crate) fn set_level(&self, level: LogLevel) {
        self.level.store(level as u32, Ordering::Relaxed);
        aimrt_plugin_api::__private::levels_changed();
    }
}

impl LogSink for Logger {
    fn level(&self) -> LogLevel {
        LogLevel::from_u32(self.level.load(Ordering::Relaxed)).unwrap_or(LogLevel::Off)
    }

    fn log(&self, line: &LogLine<'_>) {
        let level = self.level();
        if line.level >= level && level != LogLevel::Off {
            self.hub.write(&self.name, line);
        }
    }

    fn watch_levels(&self, changed: LevelsChanged) {
        self.hub.watchers.add(changed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    #[test]
    fn level_filters_lines() {
        let hub = LogHub::global();
        let l = Logger::new("m", LogLevel::Warn, &hub);
        assert_eq!(l.level(), LogLevel::Warn);
        l.set_level(LogLevel::Off);
        assert_eq!(l.level(), LogLevel::Off);
    }

    #[test]
    fn levels_are_set_by_name_for_every_logger_of_that_name_and_watchers_hear_of_it() {
        use std::sync::atomic::AtomicUsize;
        static HEARD: AtomicUsize = AtomicUsize::new(0);
        extern "C" fn heard() {
            HEARD.fetch_add(1, Ordering::SeqCst);
        }
        let hub = Arc::new(LogHub::new());
        let library = Logger::new("plugin_x", LogLevel::Info, &hub);
        let core = Logger::new("plugin_x", LogLevel::Info, &hub);
        let module = Logger::new("Module", LogLevel::Warn, &hub);
        // A library registers its function once per logger it gets: called once a change.
        library.watch_levels(heard);
        module.watch_levels(heard);
        assert_eq!(
            hub.levels(),
            [
                ("Module".to_owned(), LogLevel::Warn),
                ("plugin_x".to_owned(), LogLevel::Info)
            ]
        );
        assert_eq!(
            hub.set_level("plugin_x", LogLevel::Trace),
            Some(LogLevel::Info)
        );
        assert_eq!(
            (library.level(), core.level()),
            (LogLevel::Trace, LogLevel::Trace)
        );
        assert_eq!(module.level(), LogLevel::Warn);
        assert_eq!(HEARD.load(Ordering::SeqCst), 1);
        assert_eq!(hub.set_level("nobody", LogLevel::Trace), None);
        assert_eq!(HEARD.load(Ordering::SeqCst), 1);
        // A logger that is gone is not listed.
        drop(module);
        assert_eq!(hub.levels(), [("plugin_x".to_owned(), LogLevel::Trace)]);
        assert_eq!(hub.set_level("Module", LogLevel::Error), None);
    }

    fn hub() -> LogHub {
        LogHub::new()
    }

    fn line(message: &str) -> LogLine<'_> {
        LogLine {
            level: LogLevel::Info,
            file: "a.rs",
            line: 1,
            target: "t",
            message,
        }
    }

    fn settings(dir: &std::path::Path, extra: &str) -> LogSettings {
        let text = format!(
            "aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {{path: '{}', filename: a.log, pattern: '%n %v'{extra}}}\n",
            dir.display()
        );
        LogSettings::from_config(&Config::parse("cfg.yaml", &text, |_| None).unwrap()).unwrap()
    }

    #[test]
    fn pipeline_writes_everything_in_order_and_flushes_at_stop() {
        let dir = tempfile::tempdir().unwrap();
        let hub = hub();
        hub.start(&settings(dir.path(), ""), None).unwrap();
        // Fewer lines than the queue holds: none can be dropped.
        for i in 0..2000 {
            hub.write("M", &line(&format!("line {i}")));
        }
        let totals = hub.stop().unwrap();
        let text = std::fs::read_to_string(dir.path().join("a.log")).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2000);
        assert_eq!(totals.written, 2000);
        assert_eq!(totals.dropped, 0);
        let mut last = None;
        for l in &lines {
            let n: u32 = l.strip_prefix("M line ").unwrap().parse().unwrap();
            assert!(last.is_none_or(|p| p < n), "out of order at {l}");
            last = Some(n);
        }
        // After stop, the hub is back on stderr and a second stop is a no-op.
        assert!(hub.stop().is_none());
    }

    /// A sink that holds the log thread in its first write until released.
    struct Gate {
        entered: crossbeam_channel::Sender<()>,
        release: crossbeam_channel::Receiver<()>,
        lines: Arc<Mutex<Vec<String>>>,
    }

    impl Sink for Gate {
        fn write(&mut self, _: LogLevel, text: &str, _: Option<&Parts>) -> std::io::Result<()> {
            if self.lines.lock().unwrap().is_empty() {
                let _ = self.entered.send(());
                let _ = self.release.recv();
            }
            self.lines.lock().unwrap().push(text.to_owned());
            Ok(())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn full_queue_drops_and_counts_and_reports() {
        let (entered_tx, entered) = crossbeam_channel::bounded(1);
        let (release, release_rx) = crossbeam_channel::bounded(1);
        let lines = Arc::new(Mutex::new(Vec::new()));
        let hub = hub();
        let front = Front {
            pattern: Pattern::parse("%v").unwrap(),
            filter: None,
            parts: false,
        };
        let gate = Gate {
            entered: entered_tx,
            release: release_rx,
            lines: lines.clone(),
        };
        hub.launch(vec![front], vec![Box::new(gate)], vec![None])
            .unwrap();
        hub.write("M", &line("first"));
        entered
            .recv_timeout(Duration::from_secs(10))
            .expect("the log thread took the first line");
        // The log thread is stuck in its first write: the queue takes exactly its capacity.
        let extra = 2 * QUEUE_CAPACITY as u64;
        for i in 0..extra {
            hub.write("M", &line(&format!("{i}")));
        }
        release.send(()).unwrap();
        let totals = hub.stop().unwrap();
        let dropped = extra - QUEUE_CAPACITY as u64;
        assert_eq!(totals.dropped, dropped);
        let lines = lines.lock().unwrap();
        // first + the queued lines + one report.
        assert_eq!(lines.len(), 1 + QUEUE_CAPACITY + 1);
        assert_eq!(totals.written, lines.len() as u64);
        assert_eq!(lines[QUEUE_CAPACITY], format!("{}", QUEUE_CAPACITY - 1));
        assert_eq!(
            lines[QUEUE_CAPACITY + 1],
            format!(
                "{dropped} log lines were dropped: the log queue ({QUEUE_CAPACITY} lines) was full"
            )
        );
    }

    /// A sink whose writes fail while `full` is set, like a file on a full disk.
    struct Disk {
        full: Arc<std::sync::atomic::AtomicBool>,
        lines: Arc<Mutex<Vec<String>>>,
    }

    impl Sink for Disk {
        fn write(&mut self, _: LogLevel, text: &str, _: Option<&Parts>) -> std::io::Result<()> {
            if self.full.load(Ordering::SeqCst) {
                return Err(std::io::Error::other("No space left on device"));
            }
            self.lines.lock().unwrap().push(text.to_owned());
            Ok(())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn lines_lost_to_a_full_disk_leave_one_line_in_the_file_when_writing_resumes() {
        let full = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let lines = Arc::new(Mutex::new(Vec::new()));
        let hub = hub();
        let front = Front {
            pattern: Pattern::parse("%v").unwrap(),
            filter: None,
            parts: false,
        };
        let disk = Disk {
            full: full.clone(),
            lines: lines.clone(),
        };
        hub.launch(vec![front], vec![Box::new(disk)], vec![None])
            .unwrap();
        let wait_for = |n: usize| {
            let end = Instant::now() + Duration::from_secs(10);
            while lines.lock().unwrap().len() < n && Instant::now() < end {
                std::thread::sleep(Duration::from_millis(1));
            }
        };
        hub.write("M", &line("before"));
        wait_for(1);
        full.store(true, Ordering::SeqCst);
        for i in 0..3 {
            hub.write("M", &line(&format!("lost {i}")));
        }
        // The log thread has tried all three once the queue is empty again.
        let end = Instant::now() + Duration::from_secs(10);
        while let Mode::Pipeline(p) = &*hub.mode.read().unwrap() {
            if p.tx.is_empty() || Instant::now() > end {
                break;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        std::thread::sleep(Duration::from_millis(50));
        full.store(false, Ordering::SeqCst);
        hub.write("M", &line("after"));
        let totals = hub.stop().unwrap();
        let lines = lines.lock().unwrap();
        assert_eq!(lines.len(), 3, "{lines:?}");
        assert_eq!(lines[0], "before");
        assert!(
            lines[1].starts_with("3 log lines were lost between ")
                && lines[1].ends_with(": writing them failed (No space left on device)"),
            "{}",
            lines[1]
        );
        assert_eq!(lines[2], "after");
        assert_eq!(totals.written, 3);
        assert_eq!(totals.write_errors, 3);
    }

    /// Counts fsyncs.
    struct Syncs(Arc<AtomicU64>);

    impl Sink for Syncs {
        fn write(&mut self, _: LogLevel, _: &str, _: Option<&Parts>) -> std::io::Result<()> {
            Ok(())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
        fn sync(&mut self) -> std::io::Result<()> {
            self.0.fetch_add(1, Ordering::SeqCst);
            Ok(())
        }
    }

    /// Keeps what each line's parts say (a plugin's backend takes them); `.1` is the
    /// logging thread's id.
    struct PartsSink(Arc<Mutex<Vec<String>>>, i32);

    impl Sink for PartsSink {
        fn takes_parts(&self) -> bool {
            true
        }
        fn write(
            &mut self,
            level: LogLevel,
            text: &str,
            parts: Option<&Parts>,
        ) -> std::io::Result<()> {
            let Some(parts) = parts else {
                self.0.lock().unwrap().push(format!("no parts: {text}"));
                return Ok(());
            };
            let e = parts.entry(level, text);
            let age = std::time::SystemTime::now()
                .duration_since(e.time)
                .unwrap_or_default();
            self.0.lock().unwrap().push(format!(
                "{} [{}] {}:{} {} '{}' own thread: {}, recent: {}",
                e.level.name(),
                e.module,
                e.file,
                e.source_line,
                e.function,
                e.message,
                e.thread_id == i64::from(self.1),
                age < Duration::from_secs(60)
            ));
            if e.message == "fail" {
                return Err(std::io::Error::other("refused"));
            }
            Ok(())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_sink_that_takes_parts_gets_each_lines_parts_and_the_gap_report_has_them_too() {
        let got = Arc::new(Mutex::new(Vec::new()));
        let hub = hub();
        let front = Front {
            pattern: Pattern::parse("%n: %v").unwrap(),
            filter: None,
            parts: true,
        };
        let tid = nix::unistd::gettid().as_raw();
        let sink = PartsSink(got.clone(), tid);
        hub.launch(vec![front], vec![Box::new(sink)], vec![None])
            .unwrap();
        hub.write("Mod", &line("one"));
        hub.write("Mod", &line("fail"));
        hub.write("Other", &line("two"));
        hub.stop();
        let got = got.lock().unwrap();
        assert_eq!(got.len(), 4, "{got:?}");
        assert_eq!(
            got[0],
            "Info [Mod] a.rs:1 t 'one' own thread: true, recent: true"
        );
        assert_eq!(
            got[1],
            "Info [Mod] a.rs:1 t 'fail' own thread: true, recent: true"
        );
        // The report of the lost line, the runtime's own line, comes with its parts.
        assert!(
            got[2].starts_with("Warn [core] ")
                && got[2].contains("'1 log lines were lost between")
                && got[2].ends_with("own thread: false, recent: true"),
            "{got:?}"
        );
        assert_eq!(
            got[3],
            "Info [Other] a.rs:1 t 'two' own thread: true, recent: true"
        );
    }

    #[test]
    fn enable_sync_fsyncs_periodically_while_idle_and_at_stop() {
        let count = Arc::new(AtomicU64::new(0));
        let hub = hub();
        let front = Front {
            pattern: Pattern::parse("%v").unwrap(),
            filter: None,
            parts: false,
        };
        hub.launch(
            vec![front],
            vec![Box::new(Syncs(count.clone()))],
            vec![Some(Duration::from_millis(5))],
        )
        .unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while count.load(Ordering::SeqCst) < 3 {
            assert!(Instant::now() < deadline, "no periodic fsync");
            std::thread::sleep(Duration::from_millis(1));
        }
        let before = count.load(Ordering::SeqCst);
        hub.stop();
        assert!(count.load(Ordering::SeqCst) > before, "no fsync at stop");
    }

    #[test]
    fn backends_sharing_a_pattern_each_get_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let text = format!(
            "aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {{path: '{0}', filename: a.log, pattern: '%n %v'}}\n      - type: rotate_file\n        options: {{path: '{0}', filename: b.log, pattern: '%v'}}\n      - type: rotate_file\n        options: {{path: '{0}', filename: c.log, pattern: '%v'}}\n",
            dir.path().display()
        );
        let settings =
            LogSettings::from_config(&Config::parse("cfg.yaml", &text, |_| None).unwrap()).unwrap();
        let hub = hub();
        hub.start(&settings, None).unwrap();
        hub.write("M", &line("one"));
        hub.stop();
        let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
        assert_eq!(read("a.log"), "M one\n");
        assert_eq!(read("b.log"), "one\n");
        assert_eq!(read("c.log"), "one\n");
    }

    #[test]
    fn module_filter_selects_loggers() {
        let dir = tempfile::tempdir().unwrap();
        let hub = hub();
        hub.start(&settings(dir.path(), ", module_filter: 'Keep.*'"), None)
            .unwrap();
        hub.write("KeepMe", &line("yes"));
        hub.write("DropMe", &line("no"));
        hub.write("core", &line("no"));
        hub.stop();
        let text = std::fs::read_to_string(dir.path().join("a.log")).unwrap();
        assert_eq!(text, "KeepMe yes\n");
    }

    #[test]
    fn unopenable_file_is_an_error_naming_the_backend() {
        let dir = tempfile::tempdir().unwrap();
        let blocker = dir.path().join("file");
        std::fs::write(&blocker, "").unwrap();
        let err = hub().start(&settings(&blocker, ""), None).unwrap_err();
        assert!(err.at.starts_with("cfg.yaml:4:"), "{err:?}");
        assert!(err.message.contains("rotate_file cannot open"), "{err:?}");
    }
}
