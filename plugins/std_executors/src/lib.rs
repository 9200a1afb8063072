//! AimRT's standard executor types as a plugin. `aimrt_main` links this crate and
//! registers [`plugin()`] statically; `aimrt-std-executors-so` exports the same plugin
//! from a shared library for runtimes that do not link it.
//!
//! Types so far: `simple_thread` (one thread, FIFO, `queue_threshold`).
//!
//! ```
//! let plugin = aimrt_std_executors::plugin();
//! assert_eq!(plugin.name(), "std_executors");
//! ```
#![forbid(unsafe_code)]

mod simple_thread;

use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar};

#[derive(Debug, Default)]
struct StdExecutors;

impl Plugin for StdExecutors {
    fn name(&self) -> &str {
        "std_executors"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _options: &PluginOptions,
    ) -> Result<(), Error> {
        registrar.register_executor_type("simple_thread", &[], simple_thread::SimpleThread::create)
    }
}

/// The standard executors plugin.
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(StdExecutors)
}
