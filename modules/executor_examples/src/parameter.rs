//! `ParameterModule`: AimRT's parameter example. Every 500 ms on `work_thread_pool` it
//! sets `key-<n>` to `val-<n>` in its parameters and reads it back.

use std::time::Duration;

use aimrt_plugin_api::{create_timer, CoreRef, Error, ExecutorRef, Module, ModuleInfo};
use aimrt_plugin_api::{ParameterRef, Timer};

/// Sets and reads back one parameter a period; at shutdown, says how many it holds.
#[derive(Debug, Default)]
pub struct ParameterModule {
    setup: Option<(ExecutorRef, ParameterRef)>,
    timer: Option<Timer>,
}

impl Module for ParameterModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("ParameterModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let exec = crate::timer_executor(&core, "work_thread_pool")?;
        self.setup = Some((exec, core.parameter()?));
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some((exec, params)) = self.setup else {
            return Err(Error::msg("start before initialize"));
        };
        let mut count = 0;
        let timer = create_timer(
            exec,
            Duration::from_millis(500),
            move |_| {
                count += 1;
                let (key, val) = (format!("key-{count}"), format!("val-{count}"));
                params.set(&key, &val);
                tracing::info!("Set parameter, key: '{key}', val: '{val}'");
                let got = params.get(&key).unwrap_or_default();
                tracing::info!("Get parameter, key: '{key}', val: '{got}'");
            },
            true,
        )?;
        self.timer = Some(timer);
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        if let Some(timer) = &self.timer {
            timer.cancel();
        }
        if let Some((_, params)) = self.setup {
            tracing::info!("Parameters held: {}", params.keys().len());
        }
        tracing::info!("Shutdown succeeded.");
    }
}
