//! Library-local "current module": which module's logger a line or a panic belongs to.
//!
//! Each library has its own copy of this state (its own `thread_local!`s). Shims set the
//! current module around every hook and callback; a task records the module that created
//! it (its tag) and restores it while it runs, so lines logged on a foreign executor still
//! carry the right module name and level.

use std::cell::Cell;
use std::ffi::c_void;
use std::sync::{Mutex, OnceLock};

use super::RawLogger;
use crate::log::LogLevel;

/// A module as its own library knows it. Leaked: tags point to it for the process's life.
#[derive(Debug)]
pub(crate) struct ModuleCtx {
    pub(crate) name: String,
    pub(crate) logger: RawLogger,
}

thread_local! {
    static CURRENT: Cell<*const ModuleCtx> = const { Cell::new(std::ptr::null()) };
}

static DEFAULT_LOGGER: OnceLock<RawLogger> = OnceLock::new();

/// The loggers of this library's modules, for [`most_verbose`].
static MODULE_LOGGERS: Mutex<Vec<RawLogger>> = Mutex::new(Vec::new());

/// Sets the logger used outside any module (once; later calls are ignored).
pub(crate) fn set_default_logger(logger: RawLogger) {
    if DEFAULT_LOGGER.set(logger).is_ok() {
        logger.watch_levels(levels_changed_by_host);
    }
    levels_changed();
}

/// What the host calls after it changed a level at run time (ABI 1.13).
unsafe extern "C" fn levels_changed_by_host() {
    let _ = super::contain(levels_changed);
}

/// Leaks a module context and returns its tag.
pub(crate) fn new_module(name: String, logger: RawLogger) -> &'static ModuleCtx {
    MODULE_LOGGERS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .push(logger);
    levels_changed();
    Box::leak(Box::new(ModuleCtx { name, logger }))
}

/// The most verbose level a line logged in this library can pass: the lowest level of
/// the default logger and the modules' loggers. `None` before the host set the default
/// logger (until then every line goes to stderr).
pub(crate) fn most_verbose() -> Option<LogLevel> {
    let default = DEFAULT_LOGGER.get()?;
    let modules = MODULE_LOGGERS.lock().unwrap_or_else(|e| e.into_inner());
    modules
        .iter()
        .chain(std::iter::once(default))
        .map(RawLogger::level)
        .min()
}

/// Has `tracing` ask again, through [`most_verbose`], which levels can pass in this
/// library; call sites of levels below it then cost a comparison, not a call.
pub(crate) fn levels_changed() {
    tracing_core::callsite::rebuild_interest_cache();
}

/// The tag of the current module (null outside any module).
pub(crate) fn current_module_tag() -> *const c_void {
    CURRENT.with(|c| c.get().cast())
}

/// Runs `f` with `tag` as the current module, restoring the previous one afterwards (also
/// when `f` unwinds).
pub(crate) fn with_module_tag<R>(tag: *const c_void, f: impl FnOnce() -> R) -> R {
    struct Restore(*const ModuleCtx);
    impl Drop for Restore {
        fn drop(&mut self) {
            CURRENT.with(|c| c.set(self.0));
        }
    }
    let prev = CURRENT.with(|c| c.replace(tag.cast()));
    let _restore = Restore(prev);
    f()
}

/// Runs `f` inside `module`.
pub(crate) fn with_module<R>(module: &'static ModuleCtx, f: impl FnOnce() -> R) -> R {
    with_module_tag((module as *const ModuleCtx).cast(), f)
}

/// The logger for a line logged now on this thread: the current module's, else the
/// library's default, else none (before the host initialised the library).
pub(crate) fn current_logger() -> Option<RawLogger> {
    let ptr = CURRENT.with(|c| c.get());
    if ptr.is_null() {
        DEFAULT_LOGGER.get().copied()
    } else {
        // SAFETY: non-null tags are only ever set from `&'static ModuleCtx` (leaked by
        // `new_module` in this library), so the pointer is valid forever.
        Some(unsafe { (*ptr).logger })
    }
}

/// Name of the current module, if any.
pub(crate) fn current_module_name() -> Option<&'static str> {
    let ptr = CURRENT.with(|c| c.get());
    // SAFETY: see `current_logger`.
    (!ptr.is_null()).then(|| unsafe { (*ptr).name.as_str() })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_module_tag_is_restored_after_the_call_also_when_it_unwinds() {
        let (a, b) = (8usize as *const c_void, 16usize as *const c_void);
        assert!(current_module_tag().is_null());
        with_module_tag(a, || {
            assert_eq!(current_module_tag(), a);
            with_module_tag(b, || assert_eq!(current_module_tag(), b));
            assert_eq!(current_module_tag(), a);
            let unwound = std::panic::catch_unwind(|| {
                with_module_tag(b, || panic!("inside b"));
            });
            assert!(unwound.is_err());
            assert_eq!(current_module_tag(), a);
        });
        assert!(current_module_tag().is_null());
    }
}
