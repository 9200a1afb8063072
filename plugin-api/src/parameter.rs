//! A module's parameters (AimRT's `ParameterHandle`): a store of text values by text key,
//! one per module, that other modules cannot see.

use crate::ffi::core::{ParameterHandleVtable, RawCore};
use crate::Error;

/// A module's parameters, from [`CoreRef::parameter`](crate::CoreRef::parameter).
/// Copyable; usable from any thread, in any phase.
///
/// ```
/// # fn demo(core: aimrt_plugin_api::CoreRef) -> Result<(), aimrt_plugin_api::Error> {
/// let params = core.parameter()?;
/// params.set("speed", "0.5");
/// assert_eq!(params.get("speed").as_deref(), Some("0.5"));
/// assert_eq!(params.get("missing"), None);
/// assert!(params.remove("speed"));
/// assert!(params.keys().is_empty());
/// # Ok(())
/// # }
/// ```
#[derive(Clone, Copy)]
pub struct ParameterRef {
    core: RawCore,
    table: &'static ParameterHandleVtable,
}

impl std::fmt::Debug for ParameterRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ParameterRef").finish_non_exhaustive()
    }
}

impl ParameterRef {
    pub(crate) fn new(core: RawCore) -> Result<ParameterRef, Error> {
        match core.parameter() {
            Some(table) => Ok(ParameterRef { core, table }),
            None => Err(Error::msg(
                "this runtime has no module parameters (they came with ABI 1.6); run the module on a newer aimrt_main",
            )),
        }
    }

    /// The value of `key`; `None` when it is not set (AimRT: an empty string).
    pub fn get(&self, key: &str) -> Option<String> {
        self.core.parameter_get(self.table, key)
    }

    /// Sets `key` to `value`, creating it. An empty value is stored as one (AimRT's
    /// `SetParameter` removes an existing key given an empty value; use
    /// [`remove`](Self::remove)).
    pub fn set(&self, key: &str, value: &str) {
        self.core.parameter_set(self.table, key, value)
    }

    /// Removes `key`; whether it was set.
    pub fn remove(&self, key: &str) -> bool {
        self.core.parameter_remove(self.table, key)
    }

    /// Every key that is set, in byte order (AimRT's `ListParameter`).
    pub fn keys(&self) -> Vec<String> {
        self.core.parameter_keys(self.table)
    }
}
