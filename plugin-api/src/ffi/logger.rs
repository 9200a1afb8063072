//! The host log sink: how a library's log lines reach the host.

use std::ffi::c_void;
use std::sync::Arc;

use super::{contain, Header, StrView};
use crate::log::{LogLevel, LogSink};

/// One log line as it crosses the ABI. All views are valid for the call only.
#[repr(C)]
pub struct LogRecord {
    /// Size and minor of this record.
    pub header: Header,
    /// [`LogLevel`] as a number (Trace = 0 … Fatal = 5).
    pub level: u32,
    /// Source line, 0 if unknown.
    pub line: u32,
    /// Source file.
    pub file: StrView,
    /// Rust module path or function that logged.
    pub target: StrView,
    /// The formatted message.
    pub message: StrView,
}

/// A logger object of the host: one per module (named after it, with its level), one per
/// library for lines logged outside any module.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawLogger {
    /// The operations.
    pub vtable: *const LoggerVtable,
    /// The host's object.
    pub obj: *const c_void,
}

// SAFETY: host logger objects are thread-safe by ABI contract (built by `RawLogger::leak`
// from a `Send + Sync` sink, or by a foreign host honouring the same rule), and are never
// freed (loggers live as long as the process).
unsafe impl Send for RawLogger {}
// SAFETY: see `Send`.
unsafe impl Sync for RawLogger {}

/// Logger operations.
#[repr(C)]
pub struct LoggerVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The logger's current level ([`LogLevel`] as a number; 6 = Off).
    pub level: unsafe extern "C" fn(obj: *const c_void) -> u32,
    /// Writes one line (the callee filters by level again).
    pub log: unsafe extern "C" fn(obj: *const c_void, record: *const LogRecord),
    /// (1.13) Registers `changed`, which the host calls, from any thread, after it changed
    /// the level of any logger while the process runs: the library then forgets what it
    /// derived from the levels (the most verbose level a line can pass).
    pub watch_levels: unsafe extern "C" fn(obj: *const c_void, changed: LevelsChanged),
}

/// What a library registers with [`LoggerVtable::watch_levels`].
pub type LevelsChanged = unsafe extern "C" fn();

/// The callbacks libraries registered through [`LoggerVtable::watch_levels`]: what a host
/// calls after it changed a level at run time.
#[derive(Debug, Default)]
pub struct LevelWatchers(std::sync::Mutex<Vec<LevelsChanged>>);

impl LevelWatchers {
    /// Adds `changed` (once: a library registers each of its loggers' hosts).
    pub fn add(&self, changed: LevelsChanged) {
        let mut v = self.0.lock().unwrap_or_else(|e| e.into_inner());
        if !v.iter().any(|c| std::ptr::fn_addr_eq(*c, changed)) {
            v.push(changed);
        }
    }

    /// Calls every callback added, on this thread, with no lock held.
    pub fn notify(&self) {
        let all = self.0.lock().unwrap_or_else(|e| e.into_inner()).clone();
        for changed in all {
            // SAFETY: a library registered this function of its own; libraries are never
            // unloaded, and the function takes no arguments and catches its panics.
            unsafe { changed() };
        }
    }
}

/// Where `watch_levels` ends: a logger table of ABI 1.0 to 1.12 is shorter.
const WATCH_LEVELS_END: usize =
    std::mem::offset_of!(LoggerVtable, watch_levels) + size_of::<LevelsChanged>();

struct Export<S>(S);

impl<S: LogSink> Export<S> {
    const VTABLE: LoggerVtable = LoggerVtable {
        header: Header::of::<LoggerVtable>(),
        level: Self::level,
        log: Self::log,
        watch_levels: Self::watch_levels,
    };

    unsafe extern "C" fn watch_levels(obj: *const c_void, changed: LevelsChanged) {
        // SAFETY: as in `level`.
        let sink = unsafe { &*obj.cast::<S>() };
        let _ = contain(|| sink.watch_levels(changed));
    }

    unsafe extern "C" fn level(obj: *const c_void) -> u32 {
        // SAFETY: `obj` is the leaked `Arc<S>` of `RawLogger::leak::<S>`.
        let sink = unsafe { &*obj.cast::<S>() };
        contain(|| sink.level() as u32).unwrap_or(LogLevel::Off as u32)
    }

    unsafe extern "C" fn log(obj: *const c_void, record: *const LogRecord) {
        // SAFETY: as in `level`.
        let sink = unsafe { &*obj.cast::<S>() };
        // SAFETY: the caller passes a record valid for this call.
        let rec = unsafe { &*record };
        // SAFETY: views in the record are valid for this call.
        let (file, target, message) = unsafe {
            (
                rec.file.to_string_lossy(),
                rec.target.to_string_lossy(),
                rec.message.to_string_lossy(),
            )
        };
        let level = LogLevel::from_u32(rec.level).unwrap_or(LogLevel::Error);
        let _ = contain(|| {
            sink.log(&crate::log::LogLine {
                level,
                file: &file,
                line: rec.line,
                target: &target,
                message: &message,
            })
        });
    }
}

impl RawLogger {
    /// Exports a sink. The sink is leaked on purpose: libraries may log until the process
    /// exits, so a logger is never freed.
    pub fn leak<S: LogSink>(sink: Arc<S>) -> RawLogger {
        RawLogger {
            vtable: &Export::<S>::VTABLE,
            obj: Arc::into_raw(sink).cast(),
        }
    }

    /// The logger's level.
    pub fn level(&self) -> LogLevel {
        // SAFETY: a `RawLogger` is built by `leak` or received from the host, whose
        // vtable and object stay valid forever (loggers are never freed).
        let n = unsafe { ((*self.vtable).level)(self.obj) };
        LogLevel::from_u32(n).unwrap_or(LogLevel::Off)
    }

    /// Has the host call `changed` whenever it changes a logger's level at run time; a
    /// host older than ABI 1.13 changes none, and this does nothing there.
    pub fn watch_levels(&self, changed: LevelsChanged) {
        // SAFETY: see `level`.
        let vt = unsafe { &*self.vtable };
        if vt.header.has(WATCH_LEVELS_END) {
            // SAFETY: see `level`; the table has the entry.
            unsafe { (vt.watch_levels)(self.obj, changed) }
        }
    }

    /// Writes one line.
    pub fn log(&self, line: &crate::log::LogLine<'_>) {
        let record = LogRecord {
            header: Header::of::<LogRecord>(),
            level: line.level as u32,
            line: line.line,
            file: StrView::new(line.file),
            target: StrView::new(line.target),
            message: StrView::new(line.message),
        };
        // SAFETY: see `level`; the record and its views outlive the call.
        unsafe { ((*self.vtable).log)(self.obj, &record) }
    }
}

impl std::fmt::Debug for RawLogger {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawLogger").field("obj", &self.obj).finish()
    }
}
