//! The runtime's control handle (ABI 1.13, host → plugin): the loggers' levels, read and
//! set while the process runs, and the modules' parameters. What AimRT's
//! `log_control_plugin` and `parameter_plugin` reach through the C++ core object.

use std::ffi::c_void;
use std::sync::Arc;

use super::core::{collect_text, RawCore, TextCallback};
use super::{contain, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::log::LogLevel;

/// Called once per logger with its name and level ([`LogLevel`] as a number).
pub type LevelCallback = unsafe extern "C" fn(ctx: *mut c_void, name: StrView, level: u32);

/// The runtime's control handle: valid for the process's life, usable from any thread.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawControl {
    /// The operations.
    pub vtable: *const ControlVtable,
    /// The host's object.
    pub obj: *const c_void,
}

// SAFETY: the host's control object is thread-safe and never freed (exported by `leak`
// from a `Send + Sync` value, or by a foreign host honouring the same rule).
unsafe impl Send for RawControl {}
// SAFETY: see `Send`.
unsafe impl Sync for RawControl {}

/// Control operations.
#[repr(C)]
pub struct ControlVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Calls `each` with every logger's name and level, names in byte order.
    pub log_levels: unsafe extern "C" fn(obj: *const c_void, ctx: *mut c_void, each: LevelCallback),
    /// Sets the level of every logger named `name`: `OK`, `NOT_FOUND` (no such logger) or
    /// `INVALID` (not a level); why, in `err`.
    pub set_log_level: unsafe extern "C" fn(
        obj: *const c_void,
        name: StrView,
        level: u32,
        err: ErrorSink,
    ) -> Status,
    /// Calls `each` with the name of every module initialized so far, in byte order.
    pub modules: unsafe extern "C" fn(obj: *const c_void, ctx: *mut c_void, each: TextCallback),
    /// Writes the core of module `name` to `out` (`OK`), or returns `NOT_FOUND`. The core
    /// is valid for the process's life; a plugin uses it for the module's parameters.
    pub module_core:
        unsafe extern "C" fn(obj: *const c_void, name: StrView, out: *mut RawCore) -> Status,
}

/// What the runtime implements behind the control handle.
pub trait ControlHost: Send + Sync + 'static {
    /// Every logger's name and level, names in byte order.
    fn log_levels(&self) -> Vec<(String, LogLevel)>;
    /// Sets the level of the loggers named `name`; false when there is none.
    fn set_log_level(&self, name: &str, level: LogLevel) -> bool;
    /// The names of the modules initialized so far, in byte order.
    fn modules(&self) -> Vec<String>;
    /// The core of module `name`.
    fn module_core(&self, name: &str) -> Option<RawCore>;
}

struct Export<C>(C);

impl<C: ControlHost> Export<C> {
    const VTABLE: ControlVtable = ControlVtable {
        header: Header::of::<ControlVtable>(),
        log_levels: Self::log_levels,
        set_log_level: Self::set_log_level,
        modules: Self::modules,
        module_core: Self::module_core,
    };

    /// # Safety
    /// `obj` is the leaked `Arc<C>` of [`RawControl::leak`].
    unsafe fn get<'a>(obj: *const c_void) -> &'a C {
        // SAFETY: per the contract; leaked, so valid forever.
        unsafe { &*obj.cast::<C>() }
    }

    unsafe extern "C" fn log_levels(obj: *const c_void, ctx: *mut c_void, each: LevelCallback) {
        // SAFETY: a live control object.
        let c = unsafe { Self::get(obj) };
        for (name, level) in contain(|| c.log_levels()).unwrap_or_default() {
            // SAFETY: the caller's callback with its `ctx`; the view is valid for the call.
            unsafe { each(ctx, StrView::new(&name), level as u32) };
        }
    }

    unsafe extern "C" fn set_log_level(
        obj: *const c_void,
        name: StrView,
        level: u32,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: a live control object; the view is valid for this call.
        let (c, name) = unsafe { (Self::get(obj), name.to_string_lossy()) };
        let Some(level) = LogLevel::from_u32(level) else {
            err.report(&format!(
                "{level} is not a log level (0 Trace … 5 Fatal, 6 Off)"
            ));
            return Status::INVALID;
        };
        match contain(|| c.set_log_level(&name, level)) {
            Ok(true) => Status::OK,
            Ok(false) => {
                let names: Vec<String> = contain(|| c.log_levels())
                    .unwrap_or_default()
                    .into_iter()
                    .map(|(n, _)| n)
                    .collect();
                let known: Vec<&str> = names.iter().map(String::as_str).collect();
                err.report(&crate::suggest::no_such("logger", &[&name], &known));
                Status::NOT_FOUND
            }
            Err(panic) => {
                err.report(&panic);
                Status::FAILED
            }
        }
    }

    unsafe extern "C" fn modules(obj: *const c_void, ctx: *mut c_void, each: TextCallback) {
        // SAFETY: a live control object.
        let c = unsafe { Self::get(obj) };
        for name in contain(|| c.modules()).unwrap_or_default() {
            // SAFETY: the caller's callback with its `ctx`; the view is valid for the call.
            unsafe { each(ctx, StrView::new(&name)) };
        }
    }

    unsafe extern "C" fn module_core(
        obj: *const c_void,
        name: StrView,
        out: *mut RawCore,
    ) -> Status {
        // SAFETY: a live control object; the view is valid for this call.
        let (c, name) = unsafe { (Self::get(obj), name.to_string_lossy()) };
        match contain(|| c.module_core(&name)) {
            Ok(Some(core)) => {
                // SAFETY: `out` is writable (vtable contract).
                unsafe { out.write(core) };
                Status::OK
            }
            Ok(None) => Status::NOT_FOUND,
            Err(_) => Status::FAILED,
        }
    }
}

unsafe extern "C" fn collect_level(ctx: *mut c_void, name: StrView, level: u32) {
    // SAFETY: `ctx` is the caller's `Vec<(String, LogLevel)>`, alive for the call
    // (`RawControl::log_levels`); the view is valid for this call.
    unsafe {
        (*ctx.cast::<Vec<(String, LogLevel)>>()).push((
            name.to_string_lossy(),
            LogLevel::from_u32(level).unwrap_or(LogLevel::Off),
        ))
    };
}

impl RawControl {
    /// Exports a control host; leaked, as plugins may use it until the process ends.
    pub fn leak<C: ControlHost>(c: Arc<C>) -> RawControl {
        RawControl {
            vtable: &Export::<C>::VTABLE,
            obj: Arc::into_raw(c).cast(),
        }
    }

    fn vt(&self) -> &ControlVtable {
        // SAFETY: a control handle comes from `leak` (here or in the host) and is valid
        // forever.
        unsafe { &*self.vtable }
    }

    pub(crate) fn log_levels(&self) -> Vec<(String, LogLevel)> {
        let mut out: Vec<(String, LogLevel)> = Vec::new();
        // SAFETY: live handle; `out` outlives the call and matches `collect_level`.
        unsafe { (self.vt().log_levels)(self.obj, (&raw mut out).cast(), collect_level) };
        out
    }

    pub(crate) fn set_log_level(
        &self,
        name: &str,
        level: LogLevel,
    ) -> Result<(), (Status, String)> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live handle; the view and the sink outlive the call.
        let status = unsafe {
            (self.vt().set_log_level)(self.obj, StrView::new(name), level as u32, slot.sink())
        };
        slot.result(status).map_err(|why| (status, why))
    }

    pub(crate) fn modules(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        // SAFETY: live handle; `out` outlives the call and matches `collect_text`.
        unsafe { (self.vt().modules)(self.obj, (&raw mut out).cast(), collect_text) };
        out
    }

    pub(crate) fn module_core(&self, name: &str) -> Option<RawCore> {
        let mut out = std::mem::MaybeUninit::<RawCore>::uninit();
        // SAFETY: live handle; the view and `out` outlive the call.
        let status =
            unsafe { (self.vt().module_core)(self.obj, StrView::new(name), out.as_mut_ptr()) };
        // SAFETY: `OK` means the callee wrote `out`.
        status.is_ok().then(|| unsafe { out.assume_init() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    /// Two loggers and no module.
    struct Host(Mutex<Vec<(String, LogLevel)>>);

    impl ControlHost for Host {
        fn log_levels(&self) -> Vec<(String, LogLevel)> {
            self.0.lock().unwrap().clone()
        }
        fn set_log_level(&self, name: &str, level: LogLevel) -> bool {
            let mut all = self.0.lock().unwrap();
            let found = all.iter_mut().find(|(n, _)| n == name);
            found.map(|(_, l)| *l = level).is_some()
        }
        fn modules(&self) -> Vec<String> {
            Vec::new()
        }
        fn module_core(&self, _: &str) -> Option<RawCore> {
            None
        }
    }

    #[test]
    fn levels_cross_both_ways_and_refusals_say_why() {
        let raw = RawControl::leak(Arc::new(Host(Mutex::new(vec![
            ("LoggerModule".into(), LogLevel::Info),
            ("core".into(), LogLevel::Info),
        ]))));
        raw.set_log_level("LoggerModule", LogLevel::Trace)
            .expect("a logger there is");
        assert_eq!(
            raw.log_levels(),
            [
                ("LoggerModule".to_owned(), LogLevel::Trace),
                ("core".to_owned(), LogLevel::Info)
            ]
        );
        let (status, why) = raw
            .set_log_level("LogerModule", LogLevel::Debug)
            .unwrap_err();
        assert_eq!(status, Status::NOT_FOUND);
        assert_eq!(
            why,
            "no logger 'LogerModule'; did you mean 'LoggerModule'? (the loggers: LoggerModule, core)"
        );
        // A number that is no level, as a foreign plugin might pass.
        let mut slot = ErrorSlot::default();
        // SAFETY: a live handle; the view and the sink outlive the call.
        let status =
            unsafe { (raw.vt().set_log_level)(raw.obj, StrView::new("core"), 9, slot.sink()) };
        assert_eq!(status, Status::INVALID);
        assert!(slot
            .result(status)
            .unwrap_err()
            .contains("9 is not a log level"));
        assert!(raw.modules().is_empty());
        assert!(raw.module_core("LoggerModule").is_none());
    }
}
