//! Log levels, the host-side sink trait, and the `tracing` forwarder every library installs.

use std::fmt::Write as _;
use std::str::FromStr;

use tracing_core::field::{Field, Visit};
use tracing_core::span::{Attributes, Id, Record};
use tracing_core::subscriber::Interest;
use tracing_core::{Event, Metadata, Subscriber};

use crate::ffi::context;

/// AimRT's log levels, in order. `Off` disables a logger.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum LogLevel {
    /// Finest detail.
    Trace = 0,
    /// Debugging detail.
    Debug = 1,
    /// Normal operation.
    Info = 2,
    /// Something unexpected that the runtime handled.
    Warn = 3,
    /// An operation failed.
    Error = 4,
    /// The process cannot go on.
    Fatal = 5,
    /// Nothing is logged.
    Off = 6,
}

impl LogLevel {
    /// All levels, in order.
    pub const ALL: [LogLevel; 7] = [
        LogLevel::Trace,
        LogLevel::Debug,
        LogLevel::Info,
        LogLevel::Warn,
        LogLevel::Error,
        LogLevel::Fatal,
        LogLevel::Off,
    ];

    /// The level with this number.
    pub fn from_u32(n: u32) -> Option<LogLevel> {
        LogLevel::ALL.get(n as usize).copied()
    }

    /// AimRT's spelling: `Trace`, `Debug`, `Info`, `Warn`, `Error`, `Fatal`, `Off`.
    pub fn name(self) -> &'static str {
        match self {
            LogLevel::Trace => "Trace",
            LogLevel::Debug => "Debug",
            LogLevel::Info => "Info",
            LogLevel::Warn => "Warn",
            LogLevel::Error => "Error",
            LogLevel::Fatal => "Fatal",
            LogLevel::Off => "Off",
        }
    }

    fn from_tracing(level: &tracing_core::Level) -> LogLevel {
        match *level {
            tracing_core::Level::TRACE => LogLevel::Trace,
            tracing_core::Level::DEBUG => LogLevel::Debug,
            tracing_core::Level::INFO => LogLevel::Info,
            tracing_core::Level::WARN => LogLevel::Warn,
            tracing_core::Level::ERROR => LogLevel::Error,
        }
    }
}

impl std::fmt::Display for LogLevel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// An unknown level name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown log level '{0}'; expected one of Trace, Debug, Info, Warn, Error, Fatal, Off (any case)")]
pub struct ParseLevelError(pub String);

impl FromStr for LogLevel {
    type Err = ParseLevelError;

    /// Case-insensitive, as AimRT (`INFO`, `info` and `Info` are the same level).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        LogLevel::ALL
            .into_iter()
            .find(|l| l.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| ParseLevelError(s.to_owned()))
    }
}

/// One log line handed to a [`LogSink`].
#[derive(Debug, Clone, Copy)]
pub struct LogLine<'a> {
    /// Severity.
    pub level: LogLevel,
    /// Source file.
    pub file: &'a str,
    /// Source line (0 if unknown).
    pub line: u32,
    /// Rust module path of the call site.
    pub target: &'a str,
    /// The formatted message.
    pub message: &'a str,
}

/// What the host implements to receive log lines (one sink per module or library).
pub trait LogSink: Send + Sync + 'static {
    /// The sink's current level; lines below it are not sent.
    fn level(&self) -> LogLevel;
    /// Writes one line.
    fn log(&self, line: &LogLine<'_>);
    /// Calls `changed` after any logger's level changed at run time (ABI 1.13), so that a
    /// library forgets the levels it derived; a sink whose level never changes ignores it.
    fn watch_levels(&self, changed: crate::ffi::LevelsChanged) {
        let _ = changed;
    }
}

/// The `tracing` subscriber every library installs: it sends each event to the logger of
/// the current module (or the library's default logger).
#[derive(Debug, Default)]
pub(crate) struct Forwarder;

impl Subscriber for Forwarder {
    fn register_callsite(&self, _: &'static Metadata<'static>) -> Interest {
        // Levels differ per module and may change: ask `enabled` every time.
        Interest::sometimes()
    }

    fn max_level_hint(&self) -> Option<tracing_core::LevelFilter> {
        // The most verbose of this library's loggers: call sites below it are skipped by
        // `tracing` itself, without asking `enabled` (a dependency's trace call sites on
        // a hot path then cost nothing). Recomputed whenever a logger is added.
        Some(match context::most_verbose() {
            None | Some(LogLevel::Trace) => tracing_core::LevelFilter::TRACE,
            Some(LogLevel::Debug) => tracing_core::LevelFilter::DEBUG,
            Some(LogLevel::Info) => tracing_core::LevelFilter::INFO,
            Some(LogLevel::Warn) => tracing_core::LevelFilter::WARN,
            Some(LogLevel::Error | LogLevel::Fatal) => tracing_core::LevelFilter::ERROR,
            Some(LogLevel::Off) => tracing_core::LevelFilter::OFF,
        })
    }

    fn enabled(&self, meta: &Metadata<'_>) -> bool {
        if !meta.is_event() {
            return false;
        }
        match context::current_logger() {
            Some(logger) => LogLevel::from_tracing(meta.level()) >= logger.level(),
            None => true,
        }
    }

    fn new_span(&self, _: &Attributes<'_>) -> Id {
        Id::from_u64(1)
    }

    fn record(&self, _: &Id, _: &Record<'_>) {}

    fn record_follows_from(&self, _: &Id, _: &Id) {}

    fn event(&self, event: &Event<'_>) {
        let meta = event.metadata();
        let mut text = MessageText::default();
        event.record(&mut text);
        if let Some(rewrite) = REWRITE.get() {
            if !rewrite(meta.target(), &mut text.0) {
                return;
            }
        }
        let line = LogLine {
            level: LogLevel::from_tracing(meta.level()),
            file: meta.file().unwrap_or(""),
            line: meta.line().unwrap_or(0),
            target: meta.target(),
            message: &text.0,
        };
        match context::current_logger() {
            Some(logger) => logger.log(&line),
            // Not initialised by a host yet: nowhere to send it but stderr.
            None => {
                // A closed stderr loses the line rather than panicking.
                use std::io::Write;
                let _ = writeln!(
                    std::io::stderr().lock(),
                    "[{}][{}] {}",
                    line.level,
                    line.target,
                    line.message
                );
            }
        }
    }

    fn enter(&self, _: &Id) {}

    fn exit(&self, _: &Id) {}
}

/// Formats an event as `message k=v k=v`.
#[derive(Default)]
struct MessageText(String);

impl Visit for MessageText {
    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            if self.0.is_empty() {
                let _ = write!(self.0, "{value:?}");
            } else {
                self.0 = format!("{value:?} {}", self.0);
            }
        } else {
            if !self.0.is_empty() {
                self.0.push(' ');
            }
            let _ = write!(self.0, "{}={value:?}", field.name());
        }
    }

    fn record_str(&mut self, field: &Field, value: &str) {
        if field.name() == "message" {
            self.record_debug(field, &format_args!("{value}"));
        } else {
            if !self.0.is_empty() {
                self.0.push(' ');
            }
            let _ = write!(self.0, "{}={value}", field.name());
        }
    }
}

/// This library's edit of the log lines of its dependencies ([`rewrite_log_lines`]).
static REWRITE: std::sync::OnceLock<fn(&str, &mut String) -> bool> = std::sync::OnceLock::new();

/// Has `rewrite` edit the message of every `tracing` event of this library (the plugin or
/// module and the crates linked into it) before it goes to the runtime's log, given the
/// event's target (its module path, e.g. `zenoh_link_tcp::unicast`); when it returns
/// `false` the line is not logged. For a dependency's words that mislead a user, or its
/// noise that leaves a user nothing to do; the plugin's own lines need none. Set once a
/// library: `false` when one was set before (that one stays).
///
/// ```
/// fn plain(target: &str, message: &mut String) -> bool {
///     if target.starts_with("noisy_dep") {
///         *message = message.replace(" Hint: reboot.", "");
///     }
///     !message.starts_with("retrying")
/// }
/// assert!(aimrt_plugin_api::rewrite_log_lines(plain));
/// assert!(!aimrt_plugin_api::rewrite_log_lines(plain));
/// ```
pub fn rewrite_log_lines(rewrite: fn(target: &str, message: &mut String) -> bool) -> bool {
    REWRITE.set(rewrite).is_ok()
}

/// Installs the forwarder as this library's global `tracing` subscriber (idempotent; a
/// library that already installed another subscriber keeps it).
pub(crate) fn install_forwarder() {
    let _ = tracing::subscriber::set_global_default(Forwarder);
}

/// Runs `f` and returns, besides its result, the message of every event logged on this
/// thread meanwhile (for tests that check what is logged).
pub fn capture_logs<R>(f: impl FnOnce() -> R) -> (R, Vec<String>) {
    use std::sync::{Arc, Mutex};
    use tracing_core::span;
    struct Capture(Arc<Mutex<Vec<String>>>);
    impl Subscriber for Capture {
        fn enabled(&self, _: &Metadata<'_>) -> bool {
            true
        }
        fn new_span(&self, _: &span::Attributes<'_>) -> span::Id {
            span::Id::from_u64(1)
        }
        fn record(&self, _: &span::Id, _: &span::Record<'_>) {}
        fn record_follows_from(&self, _: &span::Id, _: &span::Id) {}
        fn event(&self, event: &Event<'_>) {
            struct Message(String);
            impl Visit for Message {
                fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
                    if field.name() == "message" {
                        self.0 = format!("{value:?}");
                    }
                }
            }
            let mut m = Message(String::new());
            event.record(&mut m);
            self.0.lock().unwrap_or_else(|e| e.into_inner()).push(m.0);
        }
        fn enter(&self, _: &span::Id) {}
        fn exit(&self, _: &span::Id) {}
    }
    let lines = Arc::new(Mutex::new(Vec::new()));
    let dispatch = tracing_core::Dispatch::new(Capture(lines.clone()));
    let out = tracing_core::dispatcher::with_default(&dispatch, f);
    let lines = std::mem::take(&mut *lines.lock().unwrap_or_else(|e| e.into_inner()));
    (out, lines)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_parse_case_insensitively() {
        assert_eq!("INFO".parse::<LogLevel>(), Ok(LogLevel::Info));
        assert_eq!("trace".parse::<LogLevel>(), Ok(LogLevel::Trace));
        assert_eq!("Off".parse::<LogLevel>(), Ok(LogLevel::Off));
        assert!("Information".parse::<LogLevel>().is_err());
        assert!("".parse::<LogLevel>().is_err());
    }

    #[test]
    fn levels_round_trip_numbers() {
        for l in LogLevel::ALL {
            assert_eq!(LogLevel::from_u32(l as u32), Some(l));
        }
        assert_eq!(LogLevel::from_u32(7), None);
    }
}
