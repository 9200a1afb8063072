//! `ExecutorModule`: AimRT's basic executor example.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::{CoreRef, DynamicLatch, Error, ExecutorRef, Module, ModuleInfo};

/// A simple task, 10 000 increments on a thread-safe executor, and a 1 s loop.
#[derive(Debug, Default)]
pub struct ExecutorModule {
    executors: Option<Executors>,
    run: Arc<AtomicBool>,
}

#[derive(Debug, Clone, Copy)]
struct Executors {
    work: ExecutorRef,
    thread_safe: ExecutorRef,
    time_schedule: ExecutorRef,
}

impl Module for ExecutorModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("ExecutorModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        self.executors = Some(Executors {
            work: core.executor("work_executor")?,
            thread_safe: crate::thread_safe_executor(&core, "thread_safe_executor")?,
            time_schedule: crate::timer_executor(&core, "time_schedule_executor")?,
        });
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(e) = self.executors else {
            return Err(Error::msg("start before initialize"));
        };
        // A simple task.
        e.work.execute(|| tracing::info!("This is a simple task"))?;

        // 10 000 increments on a thread-safe executor: no two run at once.
        let n = Arc::new(AtomicU64::new(0));
        let latch = DynamicLatch::new();
        for _ in 0..10_000 {
            let n = n.clone();
            if !e.thread_safe.try_execute(&latch, move || {
                let v = n.load(Ordering::Relaxed);
                n.store(v + 1, Ordering::Relaxed);
            }) {
                tracing::warn!("thread_safe_executor refused a task");
            }
        }
        latch.close_and_wait();
        tracing::info!("Value of n is {}", n.load(Ordering::Relaxed));

        // A loop: each round schedules the next one second later.
        self.run.store(true, Ordering::SeqCst);
        time_schedule_loop(e.time_schedule, self.run.clone(), 0);
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        self.run.store(false, Ordering::SeqCst);
        tracing::info!("Shutdown succeeded.");
    }
}

fn time_schedule_loop(exec: ExecutorRef, run: Arc<AtomicBool>, count: u64) {
    if !run.load(Ordering::SeqCst) {
        return;
    }
    tracing::info!("Loop count : {count}");
    let next = move || time_schedule_loop(exec, run, count + 1);
    if let Err(e) = exec.execute_after(Duration::from_secs(1), next) {
        tracing::warn!("the loop stops: {e}");
    }
}
