//! The runtime's control handle for plugins (ABI 1.13): read and set the loggers' levels
//! while the process runs, and reach each module's parameters — what AimRT's
//! `log_control_plugin` and `parameter_plugin` do through the C++ core.

use crate::ffi::RawControl;
use crate::{Error, LogLevel, ParameterRef};

/// The runtime's control handle, from [`Registrar::control`](crate::Registrar::control).
/// Copyable; usable from any thread, for the process's life.
///
/// ```
/// # use aimrt_plugin_api::{Error, LogLevel, RuntimeControl};
/// fn quiet_everyone(control: RuntimeControl) -> Result<(), Error> {
///     for (logger, level) in control.log_levels() {
///         if level < LogLevel::Warn {
///             control.set_log_level(&logger, LogLevel::Warn)?;
///         }
///     }
///     // The parameters of a module, by its name.
///     if let Some(params) = control.module_parameters("ControlledModule") {
///         params.set("mode", "quiet");
///     }
///     Ok(())
/// }
/// ```
#[derive(Clone, Copy)]
pub struct RuntimeControl {
    raw: RawControl,
}

impl std::fmt::Debug for RuntimeControl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RuntimeControl").finish_non_exhaustive()
    }
}

impl RuntimeControl {
    pub(crate) fn new(raw: RawControl) -> RuntimeControl {
        RuntimeControl { raw }
    }

    /// Every logger's name and current level, names in byte order: `core`, each plugin's
    /// and each module's (a module's logger exists from its `initialize` on).
    pub fn log_levels(&self) -> Vec<(String, LogLevel)> {
        self.raw.log_levels()
    }

    /// Sets the level of logger `name` from now on, in every library (lines already
    /// formatted are written). An unknown name is an error that lists the loggers.
    pub fn set_log_level(&self, name: &str, level: LogLevel) -> Result<(), Error> {
        self.raw
            .set_log_level(name, level)
            .map_err(|(_, why)| Error::msg(why))
    }

    /// The names of the modules initialized so far, in byte order.
    pub fn modules(&self) -> Vec<String> {
        self.raw.modules()
    }

    /// The parameters of module `name` (the store its own
    /// [`CoreRef::parameter`](crate::CoreRef::parameter) returns); `None` when no module
    /// of that name was initialized.
    pub fn module_parameters(&self, name: &str) -> Option<ParameterRef> {
        ParameterRef::new(self.raw.module_core(name)?).ok()
    }
}
