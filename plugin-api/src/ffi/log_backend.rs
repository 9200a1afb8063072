//! Log backend types a plugin registers (ABI 1.10; AimRT's `RegisterLoggerBackendGenFunc`):
//! the plugin exports a factory as a [`RawLogBackendType`]; for each `aimrt.log.backends`
//! entry of that type the host creates a [`RawLogBackend`] and hands it every line that
//! entry's `module_filter` admits, on the log thread: since 1.11 as a [`RawLogEntry`]
//! (the line formatted with the backend's `pattern`, and its parts), before as the formatted
//! line alone.

use std::ffi::c_void;
use std::sync::Mutex;
use std::time::{Duration, SystemTime};

use super::rpc::report;
use super::{contain, filter::filter_status, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::{BackendOptions, Error, LogLevel};

/// Log backend type operations.
#[repr(C)]
pub struct LogBackendTypeVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The type the config names (`backends: [{type: udp_lines}]`).
    pub type_name: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// Creates a backend from `options_json` (the entry's options without `module_filter`,
    /// `pattern` and `log_executor_name`, which the host reads), at `location`: `out`
    /// gets it.
    pub create: unsafe extern "C" fn(
        obj: *const c_void,
        options_json: StrView,
        location: StrView,
        out: *mut RawLogBackend,
        err: ErrorSink,
    ) -> Status,
    /// Frees the type.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
}

/// A log backend type contributed by a plugin.
#[repr(C)]
pub struct RawLogBackendType {
    /// The operations.
    pub vtable: *const LogBackendTypeVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: type objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawLogBackendType {}
// SAFETY: see `Send`.
unsafe impl Sync for RawLogBackendType {}

/// Log backend operations, called from one thread at a time (the log thread).
#[repr(C)]
pub struct LogBackendVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Writes one formatted line (without a newline) of `level` ([`LogLevel`]'s number).
    pub write: unsafe extern "C" fn(
        obj: *const c_void,
        level: u32,
        line: StrView,
        err: ErrorSink,
    ) -> Status,
    /// Hands what it buffered on (called when the queue runs empty, and at shutdown).
    pub flush: unsafe extern "C" fn(obj: *const c_void, err: ErrorSink) -> Status,
    /// Frees the backend.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
    /// 1.11: writes one line with its parts. The host calls this instead of `write` when
    /// the table has it.
    pub write_entry: unsafe extern "C" fn(
        obj: *const c_void,
        entry: *const RawLogEntry,
        err: ErrorSink,
    ) -> Status,
    /// 1.11: the options as the factory read them (JSON, defaults filled in), written to
    /// `out`; nothing written when it did not say (`--dump_cfg_file` then shows them as
    /// written).
    pub reported_options: unsafe extern "C" fn(obj: *const c_void, out: ErrorSink),
}

/// One log line and its parts (1.11), borrowed for the call.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct RawLogEntry {
    /// Size and minor of this struct: a reader reads a field only if `size` covers it.
    pub header: Header,
    /// [`LogLevel`]'s number.
    pub level: u32,
    /// The source line of the logging call (0: unknown).
    pub source_line: u32,
    /// When it was logged: nanoseconds since 1970-01-01 UTC.
    pub time_ns: u64,
    /// The logging thread's kernel id.
    pub thread_id: i64,
    /// The logger: `core`, a plugin's or a module's name.
    pub module: StrView,
    /// The source file of the logging call.
    pub file: StrView,
    /// The function, or module path, of the logging call.
    pub function: StrView,
    /// The message alone.
    pub message: StrView,
    /// The whole line, formatted with the backend's `pattern` (no newline).
    pub formatted: StrView,
}

/// One log line a [`LogBackend`] writes: the line formatted with its backend's `pattern`,
/// and the parts it was made of, for a backend that lays lines out itself (JSON, a
/// structured collector).
///
/// ```
/// use aimrt_plugin_api::{LogLevel, LogEntry};
///
/// let entry = LogEntry::new(LogLevel::Warn, "[Warn] disk almost full");
/// assert_eq!(entry.formatted, "[Warn] disk almost full");
/// assert_eq!(entry.module, "");
/// ```
#[derive(Debug, Clone, Copy)]
#[non_exhaustive]
pub struct LogEntry<'a> {
    /// The line's level.
    pub level: LogLevel,
    /// When it was logged.
    pub time: SystemTime,
    /// The logging thread's kernel id (0: unknown).
    pub thread_id: i64,
    /// The logger: `core`, a plugin's or a module's name.
    pub module: &'a str,
    /// The source file of the logging call (empty: unknown).
    pub file: &'a str,
    /// The source line of the logging call (0: unknown).
    pub source_line: u32,
    /// The function, or module path, of the logging call.
    pub function: &'a str,
    /// The message alone.
    pub message: &'a str,
    /// The whole line, formatted with the backend's `pattern` (no newline).
    pub formatted: &'a str,
}

impl<'a> LogEntry<'a> {
    /// An entry of `formatted` alone, logged now, its parts unknown (empty): what a test
    /// of a backend, or a host of ABI 1.10, hands a backend.
    pub fn new(level: LogLevel, formatted: &'a str) -> LogEntry<'a> {
        LogEntry {
            level,
            time: SystemTime::now(),
            thread_id: 0,
            module: "",
            file: "",
            source_line: 0,
            function: "",
            message: formatted,
            formatted,
        }
    }

    /// Reads an entry the host passed.
    ///
    /// # Safety
    /// Every view of `raw` must be readable for `'a`.
    unsafe fn from_raw(raw: &RawLogEntry) -> LogEntry<'a> {
        fn text<'a>(v: StrView) -> &'a str {
            // SAFETY: readable for `'a` (the caller's promise).
            unsafe { v.as_str() }.unwrap_or("")
        }
        LogEntry {
            level: LogLevel::from_u32(raw.level).unwrap_or(LogLevel::Info),
            time: SystemTime::UNIX_EPOCH + Duration::from_nanos(raw.time_ns),
            thread_id: raw.thread_id,
            module: text(raw.module),
            file: text(raw.file),
            source_line: raw.source_line,
            function: text(raw.function),
            message: text(raw.message),
            formatted: text(raw.formatted),
        }
    }

    /// The entry as it crosses to a plugin, borrowing this one.
    pub(crate) fn to_raw(self) -> RawLogEntry {
        let time_ns = self
            .time
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
        RawLogEntry {
            header: Header::of::<RawLogEntry>(),
            level: self.level as u32,
            source_line: self.source_line,
            time_ns,
            thread_id: self.thread_id,
            module: StrView::new(self.module),
            file: StrView::new(self.file),
            function: StrView::new(self.function),
            message: StrView::new(self.message),
            formatted: StrView::new(self.formatted),
        }
    }
}

/// A log backend a plugin's type created.
#[repr(C)]
pub struct RawLogBackend {
    /// The operations.
    pub vtable: *const LogBackendVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: backend objects are `Send` (required by the exporter) and called from one thread
// at a time.
unsafe impl Send for RawLogBackend {}

/// A log backend: where a plugin writes the lines of one `aimrt.log.backends` entry.
///
/// ```
/// use aimrt_plugin_api::{LogBackend, LogLevel, LogEntry};
///
/// /// Keeps the last line, and the module of the last warning.
/// #[derive(Default)]
/// struct Last {
///     line: Option<String>,
///     warned_by: Option<String>,
/// }
///
/// impl LogBackend for Last {
///     fn write(&mut self, entry: &LogEntry<'_>) -> Result<(), String> {
///         self.line = Some(entry.formatted.to_owned());
///         if entry.level >= LogLevel::Warn {
///             self.warned_by = Some(entry.module.to_owned());
///         }
///         Ok(())
///     }
/// }
///
/// let mut last = Last::default();
/// last.write(&LogEntry::new(LogLevel::Info, "[Info] ready")).unwrap();
/// assert_eq!(last.line.as_deref(), Some("[Info] ready"));
/// ```
pub trait LogBackend: Send + 'static {
    /// Writes one line: `entry.formatted` is the line formatted with the entry's
    /// `pattern` (no newline), the other fields its parts. An error counts the line as
    /// lost; the runtime reports the losses when writing works again.
    fn write(&mut self, entry: &LogEntry<'_>) -> Result<(), String>;
    /// Hands buffered lines on (when the log queue runs empty, and at shutdown).
    fn flush(&mut self) -> Result<(), String> {
        Ok(())
    }
}

struct TypeObj<F> {
    name: String,
    factory: F,
}

impl<F, B> TypeObj<F>
where
    F: Fn(&BackendOptions) -> Result<B, Error> + Send + Sync + 'static,
    B: LogBackend,
{
    const VTABLE: LogBackendTypeVtable = LogBackendTypeVtable {
        header: Header::of::<LogBackendTypeVtable>(),
        type_name: Self::type_name,
        create: Self::create,
        drop: Self::drop,
    };

    unsafe extern "C" fn type_name(obj: *const c_void) -> StrView {
        // SAFETY: a live `Box<TypeObj<F>>` pointer (vtable contract).
        StrView::new(&unsafe { &*obj.cast::<TypeObj<F>>() }.name)
    }

    unsafe extern "C" fn create(
        obj: *const c_void,
        options_json: StrView,
        location: StrView,
        out: *mut RawLogBackend,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: a live object; the views are valid for this call.
        let (this, options) = unsafe {
            let this = &*obj.cast::<TypeObj<F>>();
            let options = BackendOptions::new(
                format!("log backend '{}'", this.name),
                options_json.to_string_lossy(),
                location.to_string_lossy(),
            );
            (this, options)
        };
        let (made, reported) = super::init_reporting(|| contain(|| (this.factory)(&options)));
        let result = made.map(|made| {
            made.map(|b| {
                let obj = BackendObj {
                    backend: Mutex::new(b),
                    reported: Mutex::new(reported),
                };
                let raw = RawLogBackend {
                    vtable: &BackendObj::<B>::VTABLE,
                    obj: Box::into_raw(Box::new(obj)).cast_const().cast(),
                };
                // SAFETY: the host passes a writable `out`.
                unsafe { out.write(raw) };
            })
        });
        report(err, result)
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<TypeObj<F>>()) };
        let _ = contain(move || std::mem::drop(b));
    }
}

/// The backend behind a lock that is never contended (one thread calls it at a time):
/// `write` takes `&mut self` without `unsafe`.
struct BackendObj<B> {
    backend: Mutex<B>,
    /// The options as the factory read them.
    reported: Mutex<Option<String>>,
}

impl<B: LogBackend> BackendObj<B> {
    const VTABLE: LogBackendVtable = LogBackendVtable {
        header: Header::of::<LogBackendVtable>(),
        write: Self::write,
        flush: Self::flush,
        drop: Self::drop,
        write_entry: Self::write_entry,
        reported_options: Self::reported_options,
    };

    fn with(
        obj: *const c_void,
        f: impl FnOnce(&mut B) -> Result<(), String>,
    ) -> Result<Result<(), String>, String> {
        // SAFETY: a live `Box<BackendObj<B>>` pointer (vtable contract).
        let this = unsafe { &*obj.cast::<BackendObj<B>>() };
        contain(|| f(&mut this.backend.lock().unwrap_or_else(|e| e.into_inner())))
    }

    unsafe extern "C" fn write(
        obj: *const c_void,
        level: u32,
        line: StrView,
        err: ErrorSink,
    ) -> Status {
        let level = LogLevel::from_u32(level).unwrap_or(LogLevel::Info);
        // SAFETY: the view is valid for this call.
        let line = unsafe { line.as_str() }.unwrap_or("");
        let entry = LogEntry::new(level, line);
        filter_status(Self::with(obj, |b| b.write(&entry)), err)
    }

    unsafe extern "C" fn write_entry(
        obj: *const c_void,
        entry: *const RawLogEntry,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: the host passes an entry whose views are valid for this call.
        let entry = unsafe { LogEntry::from_raw(&*entry) };
        filter_status(Self::with(obj, |b| b.write(&entry)), err)
    }

    unsafe extern "C" fn flush(obj: *const c_void, err: ErrorSink) -> Status {
        filter_status(Self::with(obj, |b| b.flush()), err)
    }

    unsafe extern "C" fn reported_options(obj: *const c_void, out: ErrorSink) {
        // SAFETY: a live `Box<BackendObj<B>>` pointer (vtable contract).
        let this = unsafe { &*obj.cast::<BackendObj<B>>() };
        super::hand_back(&this.reported, out);
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<BackendObj<B>>()) };
        let _ = contain(move || std::mem::drop(b));
    }
}

impl RawLogBackendType {
    /// Exports a log backend type named `name` whose backends `factory` makes.
    pub(crate) fn new<F, B>(name: &str, factory: F) -> RawLogBackendType
    where
        F: Fn(&BackendOptions) -> Result<B, Error> + Send + Sync + 'static,
        B: LogBackend,
    {
        RawLogBackendType {
            vtable: &TypeObj::<F>::VTABLE,
            obj: Box::into_raw(Box::new(TypeObj {
                name: name.to_owned(),
                factory,
            }))
            .cast_const()
            .cast(),
        }
    }

    fn vt(&self) -> &LogBackendTypeVtable {
        // SAFETY: the vtable is `'static` (its library is never unloaded).
        unsafe { &*self.vtable }
    }

    /// The type's name (host use).
    pub fn type_name(&self) -> String {
        // SAFETY: a live object; the view lives as long as it.
        unsafe { (self.vt().type_name)(self.obj).to_string_lossy() }
    }

    /// Creates a backend from `options_json` at `location` (host use).
    pub fn create(&self, options_json: &str, location: &str) -> Result<RawLogBackend, String> {
        let mut out = std::mem::MaybeUninit::<RawLogBackend>::uninit();
        let mut slot = ErrorSlot::default();
        // SAFETY: a live object; the views, `out` and the sink outlive the call.
        let status = unsafe {
            (self.vt().create)(
                self.obj,
                StrView::new(options_json),
                StrView::new(location),
                out.as_mut_ptr(),
                slot.sink(),
            )
        };
        slot.result(status)?;
        // SAFETY: an OK status means `create` wrote `out`.
        Ok(unsafe { out.assume_init() })
    }
}

impl Drop for RawLogBackendType {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { (self.vt().drop)(self.obj) }
    }
}

impl RawLogBackend {
    fn vt(&self) -> &LogBackendVtable {
        // SAFETY: the vtable is `'static` (its library is never unloaded).
        unsafe { &*self.vtable }
    }

    /// Writes one line (host use, from one thread at a time): the entry to a backend of
    /// 1.11 or later, its formatted line to one of 1.10.
    pub fn write(&self, entry: &LogEntry<'_>) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let vt = self.vt();
        let has_entry = vt
            .header
            .has(std::mem::offset_of!(LogBackendVtable, write_entry) + size_of::<usize>());
        let status = if has_entry {
            let raw = entry.to_raw();
            // SAFETY: a live object; the entry's views and the sink outlive the call.
            unsafe { (vt.write_entry)(self.obj, &raw, slot.sink()) }
        } else {
            let line = StrView::new(entry.formatted);
            // SAFETY: a live object; the view and the sink outlive the call.
            unsafe { (vt.write)(self.obj, entry.level as u32, line, slot.sink()) }
        };
        slot.result(status)
    }

    /// The options as the backend's factory read them, as JSON (host use); `None` when it
    /// did not say, or the table is of 1.10.
    pub fn reported_options(&self) -> Option<String> {
        let vt = self.vt();
        let end = std::mem::offset_of!(LogBackendVtable, reported_options) + size_of::<usize>();
        if !vt.header.has(end) {
            return None;
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: a live object whose table has the entry; the sink outlives the call.
        unsafe { (vt.reported_options)(self.obj, slot.sink()) };
        slot.taken()
    }

    /// Flushes (host use).
    pub fn flush(&self) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: a live object; the sink outlives the call.
        let status = unsafe { (self.vt().flush)(self.obj, slot.sink()) };
        slot.result(status)
    }
}

impl Drop for RawLogBackend {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { (self.vt().drop)(self.obj) }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    struct Collect(Arc<Mutex<Vec<String>>>, bool);

    impl LogBackend for Collect {
        fn write(&mut self, entry: &LogEntry<'_>) -> Result<(), String> {
            if self.1 {
                return Err("the disk is full".into());
            }
            let at = entry
                .time
                .duration_since(SystemTime::UNIX_EPOCH)
                .unwrap_or_default()
                .as_nanos();
            self.0.lock().unwrap().push(format!(
                "{}: {} | {} {} {}:{} {} {at} {}",
                entry.level.name(),
                entry.formatted,
                entry.module,
                entry.thread_id,
                entry.file,
                entry.source_line,
                entry.function,
                entry.message
            ));
            Ok(())
        }
    }

    #[derive(serde::Deserialize, serde::Serialize)]
    #[serde(deny_unknown_fields)]
    struct Opts {
        #[serde(default)]
        fail: bool,
    }

    #[test]
    fn a_type_makes_backends_from_their_options_that_write_and_fail_in_turn() {
        let lines = Arc::new(Mutex::new(Vec::new()));
        let l = lines.clone();
        let ty = RawLogBackendType::new("collect", move |o: &BackendOptions| {
            let opts: Opts = o.read()?;
            Ok(Collect(l.clone(), opts.fail))
        });
        assert_eq!(ty.type_name(), "collect");
        let ok = ty.create("{}", "cfg.yaml:3:9").unwrap();
        // The options as the factory read them, the default filled in.
        assert_eq!(ok.reported_options().as_deref(), Some(r#"{"fail":false}"#));
        ok.write(&sample()).unwrap();
        ok.flush().unwrap();
        assert_eq!(
            *lines.lock().unwrap(),
            ["Warn: [W] disk almost full | Mod 4242 src/m.rs:17 m::f 1700000000123456789 disk almost full"]
        );
        let failing = ty.create(r#"{"fail": true}"#, "cfg.yaml:3:9").unwrap();
        assert_eq!(
            failing.write(&LogEntry::new(LogLevel::Info, "x")),
            Err("the disk is full".into())
        );
        let err = ty
            .create(r#"{"fial": true}"#, "cfg.yaml:3:9")
            .err()
            .unwrap();
        assert!(
            err.contains("log backend 'collect'") && err.contains("cfg.yaml:3:9"),
            "{err}"
        );
        assert!(err.contains("fail"), "did you mean: {err}");
    }

    fn sample() -> LogEntry<'static> {
        LogEntry {
            level: LogLevel::Warn,
            time: SystemTime::UNIX_EPOCH + Duration::from_nanos(1_700_000_000_123_456_789),
            thread_id: 4242,
            module: "Mod",
            file: "src/m.rs",
            source_line: 17,
            function: "m::f",
            message: "disk almost full",
            formatted: "[W] disk almost full",
        }
    }

    #[test]
    fn a_backend_of_1_10_gets_the_formatted_line_alone() {
        let lines = Arc::new(Mutex::new(Vec::new()));
        let l = lines.clone();
        let ty = RawLogBackendType::new("collect", move |o: &BackendOptions| {
            let opts: Opts = o.read()?;
            Ok(Collect(l.clone(), opts.fail))
        });
        let backend = ty.create("{}", "cfg.yaml:3:9").unwrap();
        assert!(backend.reported_options().is_some());
        // The table as a plugin of 1.10 exports it: it ends before `write_entry`.
        // SAFETY: the vtable is `'static`.
        let mut old = LogBackendVtable {
            ..*unsafe { &*backend.vtable }
        };
        old.header = Header {
            size: std::mem::offset_of!(LogBackendVtable, write_entry) as u32,
            abi_minor: 10,
        };
        let old: &'static LogBackendVtable = Box::leak(Box::new(old));
        let backend = std::mem::ManuallyDrop::new(backend);
        let as_1_10 = RawLogBackend {
            vtable: old,
            obj: backend.obj,
        };
        as_1_10.write(&sample()).unwrap();
        assert_eq!(as_1_10.reported_options(), None, "not in a table of 1.10");
        let got = lines.lock().unwrap().clone();
        assert_eq!(got.len(), 1);
        assert!(
            got[0].starts_with("Warn: [W] disk almost full |  0 :0  "),
            "{got:?}"
        );
        assert!(got[0].ends_with(" [W] disk almost full"), "{got:?}");
    }
}
