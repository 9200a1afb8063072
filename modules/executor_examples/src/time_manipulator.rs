//! `TimeManipulatorModule`: an async loop on a `time_manipulator` executor that logs the
//! executor's `now()` every simulated second. Speed it up, slow it down or pause it with
//! the curl lines of `docs/time-manipulator.md`.

use std::time::UNIX_EPOCH;

use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};

/// Logs `Loop count : N, now : <date> (<epoch seconds>)` once per simulated second.
#[derive(Debug, Default)]
pub struct TimeManipulatorModule {
    time: Option<ExecutorRef>,
    loops: crate::Loops,
}

impl Module for TimeManipulatorModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("TimeManipulatorModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        self.time = Some(crate::timer_executor(&core, "time_schedule_executor")?);
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(time) = self.time else {
            return Err(Error::msg("start before initialize"));
        };
        self.loops.spawn_loop(time, move |count| {
            let now = time.now();
            let secs = now.duration_since(UNIX_EPOCH).unwrap_or_default();
            let date = chrono::DateTime::<chrono::Local>::from(now).format("%Y-%m-%d %H:%M:%S%.3f");
            tracing::info!(
                "Loop count : {}, now : {date} ({}.{:03})",
                count + 1,
                secs.as_secs(),
                secs.subsec_millis()
            );
        })?;
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        self.loops.stop();
        tracing::info!("Shutdown succeeded.");
    }
}
