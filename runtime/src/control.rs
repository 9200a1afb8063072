//! The control handle plugins get from the registrar (ABI 1.13): the loggers' levels and
//! the modules' parameters while the process runs.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use aimrt_plugin_api::ffi::{ControlHost, RawCore};
use aimrt_plugin_api::LogLevel;

use crate::log::LogHub;

/// One runtime's control: its log hub, and the cores of its modules as they initialize.
pub(crate) struct Control {
    hub: Arc<LogHub>,
    modules: Mutex<BTreeMap<String, RawCore>>,
}

impl Control {
    pub(crate) fn new(hub: Arc<LogHub>) -> Control {
        Control {
            hub,
            modules: Mutex::default(),
        }
    }

    /// Records the core of module `name` (leaked: valid for the process's life).
    pub(crate) fn add_module(&self, name: &str, core: RawCore) {
        self.map().insert(name.to_owned(), core);
    }

    fn map(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, RawCore>> {
        self.modules.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl ControlHost for Control {
    fn log_levels(&self) -> Vec<(String, LogLevel)> {
        self.hub.levels()
    }

    fn set_log_level(&self, name: &str, level: LogLevel) -> bool {
        let Some(before) = self.hub.set_level(name, level) else {
            return false;
        };
        tracing::info!(target: "aimrt", "Log level of '{name}': {before} -> {level}");
        true
    }

    fn modules(&self) -> Vec<String> {
        self.map().keys().cloned().collect()
    }

    fn module_core(&self, name: &str) -> Option<RawCore> {
        self.map().get(name).copied()
    }
}
