//! `TimerModule`: AimRT's timer example.

use std::time::{Duration, SystemTime};

use aimrt_plugin_api::{create_timer, CoreRef, Error, ExecutorRef, Module, ModuleInfo, Timer};

/// A 100 ms timer, reset at 350 ms and 600 ms, that cancels itself after 10 runs.
#[derive(Debug, Default)]
pub struct TimerModule {
    exec: Option<ExecutorRef>,
    timer: Option<Timer>,
}

fn ms_since(start: SystemTime, now: SystemTime) -> u128 {
    now.duration_since(start).unwrap_or_default().as_millis()
}

impl Module for TimerModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("TimerModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        self.exec = Some(crate::timer_executor(&core, "timer_executor")?);
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(exec) = self.exec else {
            return Err(Error::msg("start before initialize"));
        };
        let start = exec.now();
        let mut count = 0;
        let timer = create_timer(
            exec,
            Duration::from_millis(100),
            move |timer| {
                count += 1;
                let at = ms_since(start, timer.executor().now());
                tracing::info!("Executed {count} times, execute timepoint: {at} ms");
                if count >= 10 {
                    timer.cancel();
                    tracing::info!("Timer cancelled at timepoint: {at} ms");
                }
            },
            true,
        )?;
        tracing::info!("Timer created at timepoint: 0 ms");
        for reset_at in [350, 600] {
            let t = timer.clone();
            exec.execute_after(Duration::from_millis(reset_at), move || match t.reset() {
                Ok(()) => tracing::info!("Timer reset at timepoint: {reset_at} ms"),
                Err(e) => tracing::warn!("Timer reset failed: {e}"),
            })?;
        }
        self.timer = Some(timer);
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        if let Some(timer) = &self.timer {
            timer.cancel();
        }
        tracing::info!("Shutdown succeeded.");
    }
}
