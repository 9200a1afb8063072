//! Logging: per-module loggers with levels, and the console backend.
//!
//! Every logger is a [`LogSink`] exported to libraries as a host log sink. Lines are
//! formatted with AimRT's default pattern `[%c.%f][%l][%t][%n][%g:%R @%F]%v` and written
//! synchronously (one locked write per line, so lines never interleave or get lost).
//! Before the config is read, and after shutdown, the core logger writes to stderr.

use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicU32, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};

use aimrt_plugin_api::{LogLevel, LogLine, LogSink};

const TO_STDERR: u8 = 0;
const TO_CONSOLE: u8 = 1;
const DISCARD: u8 = 2;

/// Where lines go, shared by every logger.
#[derive(Debug)]
pub(crate) struct LogHub {
    mode: AtomicU8,
    color: AtomicU8,
    out: Mutex<()>,
}

impl LogHub {
    /// The process's hub: libraries keep the loggers they were given for the process's
    /// life, so every runtime in one process shares where lines go.
    pub(crate) fn global() -> Arc<LogHub> {
        static HUB: std::sync::OnceLock<Arc<LogHub>> = std::sync::OnceLock::new();
        HUB.get_or_init(|| {
            Arc::new(LogHub {
                mode: AtomicU8::new(TO_STDERR),
                color: AtomicU8::new(0),
                out: Mutex::new(()),
            })
        })
        .clone()
    }

    /// Sends lines to the console backend (stdout), colored if asked and stdout is a tty.
    pub(crate) fn use_console(&self, color: bool) {
        let color = color && std::io::stdout().is_terminal();
        self.color.store(color as u8, Ordering::Relaxed);
        self.mode.store(TO_CONSOLE, Ordering::Release);
    }

    /// No backend configured: lines are discarded (AimRT's behaviour).
    pub(crate) fn discard(&self) {
        self.mode.store(DISCARD, Ordering::Release);
    }

    /// Back to stderr (after shutdown).
    pub(crate) fn use_stderr(&self) {
        self.mode.store(TO_STDERR, Ordering::Release);
    }

    fn write(&self, logger: &str, line: &LogLine<'_>) {
        let mode = self.mode.load(Ordering::Acquire);
        if mode == DISCARD {
            return;
        }
        let text = format_line(logger, line);
        let _guard = self.out.lock().unwrap_or_else(|e| e.into_inner());
        if mode == TO_CONSOLE {
            let mut out = std::io::stdout().lock();
            if self.color.load(Ordering::Relaxed) == 1 {
                let _ = writeln!(out, "{}{text}\x1b[0m", color_of(line.level));
            } else {
                let _ = writeln!(out, "{text}");
            }
            let _ = out.flush();
        } else {
            let _ = writeln!(std::io::stderr().lock(), "{text}");
        }
    }
}

fn color_of(level: LogLevel) -> &'static str {
    match level {
        LogLevel::Debug => "\x1b[0;34m",
        LogLevel::Info => "\x1b[0;32m",
        LogLevel::Warn => "\x1b[1;33m",
        LogLevel::Error => "\x1b[0;35m",
        LogLevel::Fatal => "\x1b[0;31m",
        LogLevel::Trace | LogLevel::Off => "",
    }
}

thread_local! {
    static TID: u64 = {
        let id = format!("{:?}", std::thread::current().id());
        id.trim_start_matches("ThreadId(").trim_end_matches(')').parse().unwrap_or(0)
    };
}

/// AimRT's default pattern: `[%c.%f][%l][%t][%n][%g:%R @%F]%v`.
pub(crate) fn format_line(logger: &str, line: &LogLine<'_>) -> String {
    let now = chrono::Local::now();
    format!(
        "[{}][{}][{}][{}][{}:{} @{}]{}",
        now.format("%Y-%m-%d %H:%M:%S%.6f"),
        line.level,
        TID.with(|t| *t),
        logger,
        line.file,
        line.line,
        line.target,
        line.message
    )
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
        Arc::new(Logger {
            name: name.to_owned(),
            level: AtomicU32::new(level as u32),
            hub: hub.clone(),
        })
    }

    pub(crate) fn set_level(&self, level: LogLevel) {
        self.level.store(level as u32, Ordering::Relaxed);
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_has_aimrt_default_layout() {
        let text = format_line(
            "demo",
            &LogLine {
                level: LogLevel::Info,
                file: "src/lib.rs",
                line: 7,
                target: "demo_pkg",
                message: "hello",
            },
        );
        // [YYYY-mm-dd HH:MM:SS.uuuuuu][Info][tid][demo][src/lib.rs:7 @demo_pkg]hello
        assert_eq!(&text[0..1], "[");
        assert_eq!(&text[20..21], ".");
        assert_eq!(&text[27..34], "][Info]");
        assert!(
            text.ends_with("][demo][src/lib.rs:7 @demo_pkg]hello"),
            "{text}"
        );
    }

    #[test]
    fn level_filters_lines() {
        let hub = LogHub::global();
        let l = Logger::new("m", LogLevel::Warn, &hub);
        assert_eq!(l.level(), LogLevel::Warn);
        l.set_level(LogLevel::Off);
        assert_eq!(l.level(), LogLevel::Off);
    }
}
