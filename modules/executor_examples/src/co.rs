//! `ExecutorCoModule`: AimRT's coroutine example, as async tasks (`ExecutorCoLoopModule`
//! is in `schedule_loop.rs`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use aimrt_plugin_api::co::{self, AsyncScope};
use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};

/// A simple task, a task hopping between executors, 10 000 increments and a 1 s loop,
/// all as async tasks of one scope.
#[derive(Debug, Default)]
pub struct ExecutorCoModule {
    executors: Option<(ExecutorRef, ExecutorRef, ExecutorRef)>,
    loops: crate::Loops,
}

impl Module for ExecutorCoModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("ExecutorCoModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        self.executors = Some((
            core.executor("work_executor")?,
            crate::thread_safe_executor(&core, "thread_safe_executor")?,
            crate::timer_executor(&core, "time_schedule_executor")?,
        ));
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some((work, safe, time)) = self.executors else {
            return Err(Error::msg("start before initialize"));
        };
        let scope = &self.loops.scope;
        scope.spawn(work, async {
            tracing::info!("This is a simple task");
        })?;

        // One task, three executors.
        scope.spawn(work, async move {
            tracing::info!(
                "Now run in work_executor: {}",
                work.is_in_current_executor()
            );
            co::schedule(&safe).await?;
            tracing::info!(
                "Now run in thread_safe_executor: {}",
                safe.is_in_current_executor()
            );
            co::schedule(&time).await?;
            tracing::info!(
                "Now run in time_schedule_executor: {}",
                time.is_in_current_executor()
            );
            Ok::<_, Error>(())
        })?;

        // 10 000 tasks of an inner scope, each moving onto the thread-safe executor.
        scope.spawn(work, async move {
            let inner = AsyncScope::new();
            let n = Arc::new(AtomicU64::new(0));
            for _ in 0..10_000 {
                let n = n.clone();
                let spawned = inner.spawn(work, async move {
                    co::schedule(&safe).await?;
                    let v = n.load(Ordering::Relaxed);
                    n.store(v + 1, Ordering::Relaxed);
                    Ok::<_, Error>(())
                });
                if let Err(e) = spawned {
                    tracing::warn!("{e}");
                }
            }
            inner.complete().await;
            tracing::info!("Value of n is {}", n.load(Ordering::Relaxed));
        })?;

        self.loops
            .spawn_loop(time, |count| tracing::info!("Loop count : {count}"))?;
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        self.loops.stop();
        tracing::info!("Shutdown succeeded.");
    }
}
