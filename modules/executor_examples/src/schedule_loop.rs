//! `ExecutorCoLoopModule` and `TimeManipulatorModule`: an async loop on
//! `time_schedule_executor` that waits one second of that executor's time
//! (`schedule_after`) per round. The first is AimRT's coroutine loop example; the second
//! logs the executor's `now()`, to watch a `time_manipulator` speed up, slow down and pause
//! (the curl lines are in `docs/time-manipulator.md`).

use std::time::UNIX_EPOCH;

use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};

/// One of the two loop modules; what a round logs is the difference.
#[derive(Debug)]
pub struct ScheduleLoopModule {
    name: &'static str,
    round: fn(ExecutorRef, u64),
    time: Option<ExecutorRef>,
    loops: crate::Loops,
}

impl ScheduleLoopModule {
    fn new(name: &'static str, round: fn(ExecutorRef, u64)) -> ScheduleLoopModule {
        ScheduleLoopModule {
            name,
            round,
            time: None,
            loops: crate::Loops::default(),
        }
    }

    /// `ExecutorCoLoopModule`: logs `Loop count : N`.
    pub fn co_loop() -> ScheduleLoopModule {
        ScheduleLoopModule::new("ExecutorCoLoopModule", |_, count| {
            tracing::info!("Loop count : {} -------------------------", count + 1);
        })
    }

    /// `TimeManipulatorModule`: logs `Loop count : N, now : <date> (<epoch seconds>)`.
    pub fn time_manipulator() -> ScheduleLoopModule {
        ScheduleLoopModule::new("TimeManipulatorModule", |time, count| {
            let now = time.now();
            let secs = now.duration_since(UNIX_EPOCH).unwrap_or_default();
            let date = chrono::DateTime::<chrono::Local>::from(now).format("%Y-%m-%d %H:%M:%S%.3f");
            tracing::info!(
                "Loop count : {}, now : {date} ({}.{:03})",
                count + 1,
                secs.as_secs(),
                secs.subsec_millis()
            );
        })
    }
}

impl Module for ScheduleLoopModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new(self.name)
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
        let round = self.round;
        self.loops
            .spawn_loop(time, move |count| round(time, count))?;
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        self.loops.stop();
        tracing::info!("Shutdown succeeded.");
    }
}
