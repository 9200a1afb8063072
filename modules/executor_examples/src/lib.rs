//! AimRT's executor examples in Rust, one pkg (`libexecutor_pkg.so`) with AimRT's module
//! names, for AimRT's `examples_cpp_executor_*` configs with only the pkg path changed:
//!
//! | module | what it shows | executors it uses |
//! |---|---|---|
//! | `ExecutorModule` | a simple task; 10 000 increments on a thread-safe executor; a 1 s loop of `execute_after` | `work_executor`, `thread_safe_executor`, `time_schedule_executor` |
//! | `ExecutorCoModule` | the same with async tasks, and one task hopping between executors | the same |
//! | `ExecutorCoLoopModule` | an async loop with `schedule_after` | `time_schedule_executor` |
//! | `TimerModule` | a 100 ms timer reset at 350 and 600 ms, cancelled after 10 runs | `timer_executor` |
//! | `TimeManipulatorModule` | an async loop logging the executor's `now()` every simulated second | `time_schedule_executor` (a `time_manipulator`) |
//! | `CbgModule` | callback groups of the `events_cbg` plugin: 1000 lock-free callbacks a second on an exclusive group from two producers on a reentrant one; a group on a dedicated real-time thread | `exclusive_group`, `reentrant_group`, `dedicated_group` |
//! | `ParameterModule` | AimRT's parameter example: sets `key-<n>` to `val-<n>` in its parameters every 500 ms and reads it back | `work_thread_pool` |
//! | `RealTimeModule` | a loop on each real-time executor printing its thread's policy and CPUs as the OS reports them | `sched_fifo_thread`, `sched_other_thread`, `sched_rr_thread` |
#![deny(unsafe_code)]

mod cbg;
mod co;
mod executor;
mod parameter;
mod real_time;
mod schedule_loop;
mod timer;

pub use cbg::CbgModule;
pub use co::ExecutorCoModule;
pub use executor::ExecutorModule;
pub use parameter::ParameterModule;
pub use real_time::RealTimeModule;
pub use schedule_loop::ScheduleLoopModule;
pub use timer::TimerModule;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::co::{block_on_timeout, schedule_after, AsyncScope};
use aimrt_plugin_api::{CoreRef, Error, ExecutorRef};

/// A module's async tasks: one scope, and a flag that ends its loops.
#[derive(Debug, Default)]
struct Loops {
    scope: AsyncScope,
    run: Arc<AtomicBool>,
}

impl Loops {
    /// Spawns a loop on `exec` that calls `round(0)`, `round(1)`, … once a second (a
    /// `schedule_after` each time) until [`stop`](Loops::stop).
    fn spawn_loop(
        &self,
        exec: ExecutorRef,
        mut round: impl FnMut(u64) + Send + 'static,
    ) -> Result<(), Error> {
        self.run.store(true, Ordering::SeqCst);
        let run = self.run.clone();
        self.scope.spawn(exec, async move {
            let mut count = 0;
            while run.load(Ordering::SeqCst) {
                round(count);
                count += 1;
                schedule_after(&exec, Duration::from_secs(1)).await?;
            }
            tracing::info!("Exit loop.");
            Ok::<_, Error>(())
        })?;
        Ok(())
    }

    /// Ends the loops and waits for every task of the scope (AimRT's
    /// `SyncWait(scope.complete())`), for at most 5 s: a loop waiting on a paused
    /// `time_manipulator` never wakes, and shutdown must not hang on it (the executor
    /// drops its pending wake-up when it shuts down).
    fn stop(&self) {
        self.run.store(false, Ordering::SeqCst);
        if block_on_timeout(self.scope.complete(), Duration::from_secs(5)).is_none() {
            tracing::warn!("a loop did not end within 5 s (is its executor's time paused?); it ends when the executor shuts down");
        }
    }
}

/// The executor `name`, which must support timers.
fn timer_executor(core: &CoreRef, name: &str) -> Result<ExecutorRef, Error> {
    let exec = core.executor(name)?;
    if !exec.supports_timer_schedule() {
        return Err(Error::msg(format!(
            "executor '{name}' ({}) does not support timer scheduling; use e.g. asio_thread",
            exec.type_name()
        )));
    }
    Ok(exec)
}

/// The executor `name`, which must be thread-safe.
fn thread_safe_executor(core: &CoreRef, name: &str) -> Result<ExecutorRef, Error> {
    let exec = core.executor(name)?;
    if !exec.thread_safe() {
        return Err(Error::msg(format!(
            "executor '{name}' ({}) is not thread-safe; use e.g. asio_strand or a one-thread asio_thread",
            exec.type_name()
        )));
    }
    Ok(exec)
}

aimrt_plugin_api::export_modules!(
    "ExecutorModule" => ExecutorModule::default,
    "ExecutorCoModule" => ExecutorCoModule::default,
    "ExecutorCoLoopModule" => ScheduleLoopModule::co_loop,
    "TimerModule" => TimerModule::default,
    "RealTimeModule" => RealTimeModule::default,
    "CbgModule" => CbgModule::default,
    "TimeManipulatorModule" => ScheduleLoopModule::time_manipulator,
    "ParameterModule" => ParameterModule::default,
);
