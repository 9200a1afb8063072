//! Log backend types a plugin registers (ABI 1.10; AimRT's `RegisterLoggerBackendGenFunc`):
//! the plugin exports a factory as a [`RawLogBackendType`]; for each `aimrt.log.backends`
//! entry of that type the host creates a [`RawLogBackend`] and hands it every line that
//! entry's `module_filter` admits, formatted with its `pattern`, on the log thread.

use std::ffi::c_void;
use std::sync::Mutex;

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
/// use aimrt_plugin_api::{LogBackend, LogLevel};
///
/// /// Keeps the last line.
/// struct Last(Option<String>);
///
/// impl LogBackend for Last {
///     fn write(&mut self, _: LogLevel, line: &str) -> Result<(), String> {
///         self.0 = Some(line.to_owned());
///         Ok(())
///     }
/// }
/// ```
pub trait LogBackend: Send + 'static {
    /// Writes one formatted line (no newline). An error counts the line as lost; the
    /// runtime reports the losses when writing works again.
    fn write(&mut self, level: LogLevel, line: &str) -> Result<(), String>;
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
        let result = contain(|| {
            (this.factory)(&options).map(|b| {
                let raw = RawLogBackend {
                    vtable: &BackendObj::<B>::VTABLE,
                    obj: Box::into_raw(Box::new(BackendObj(Mutex::new(b))))
                        .cast_const()
                        .cast(),
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
struct BackendObj<B>(Mutex<B>);

impl<B: LogBackend> BackendObj<B> {
    const VTABLE: LogBackendVtable = LogBackendVtable {
        header: Header::of::<LogBackendVtable>(),
        write: Self::write,
        flush: Self::flush,
        drop: Self::drop,
    };

    fn with(
        obj: *const c_void,
        f: impl FnOnce(&mut B) -> Result<(), String>,
    ) -> Result<Result<(), String>, String> {
        // SAFETY: a live `Box<BackendObj<B>>` pointer (vtable contract).
        let this = unsafe { &*obj.cast::<BackendObj<B>>() };
        contain(|| f(&mut this.0.lock().unwrap_or_else(|e| e.into_inner())))
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
        filter_status(Self::with(obj, |b| b.write(level, line)), err)
    }

    unsafe extern "C" fn flush(obj: *const c_void, err: ErrorSink) -> Status {
        filter_status(Self::with(obj, |b| b.flush()), err)
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

    /// Writes one line (host use, from one thread at a time).
    pub fn write(&self, level: LogLevel, line: &str) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: a live object; the view and the sink outlive the call.
        let status =
            unsafe { (self.vt().write)(self.obj, level as u32, StrView::new(line), slot.sink()) };
        slot.result(status)
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
        fn write(&mut self, level: LogLevel, line: &str) -> Result<(), String> {
            if self.1 {
                return Err("the disk is full".into());
            }
            self.0
                .lock()
                .unwrap()
                .push(format!("{}: {line}", level.name()));
            Ok(())
        }
    }

    #[derive(serde::Deserialize)]
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
            let opts: Opts = o.get()?;
            Ok(Collect(l.clone(), opts.fail))
        });
        assert_eq!(ty.type_name(), "collect");
        let ok = ty.create("{}", "cfg.yaml:3:9").unwrap();
        ok.write(LogLevel::Warn, "a line").unwrap();
        ok.flush().unwrap();
        assert_eq!(*lines.lock().unwrap(), ["Warn: a line"]);
        let failing = ty.create(r#"{"fail": true}"#, "cfg.yaml:3:9").unwrap();
        assert_eq!(
            failing.write(LogLevel::Info, "x"),
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
}
