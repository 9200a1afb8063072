//! The demo module package (`libdemo_pkg.so`): logs from every lifecycle hook, posts a
//! simple task, and posts 10 000 increments of one counter to a thread-safe executor,
//! then logs the final count. The executor names come from the module's config, so the
//! same module runs under other configs:
//!
//! ```yaml
//! DemoModule:
//!   work_executor: work_thread          # any executor
//!   thread_safe_executor: work_thread   # an executor whose thread_safe() is true
//! ```
#![deny(unsafe_code)]

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::{CoreRef, DynamicLatch, Error, ExecutorRef, Module, ModuleInfo};
use serde::Deserialize;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct DemoConfig {
    work_executor: String,
    thread_safe_executor: String,
    #[serde(default = "default_increments")]
    increments: u64,
}

fn default_increments() -> u64 {
    10_000
}

/// The demo module.
#[derive(Debug, Default)]
pub struct DemoModule {
    work: Option<ExecutorRef>,
    safe: Option<ExecutorRef>,
    increments: u64,
}

impl Module for DemoModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo {
            name: "DemoModule".into(),
            major_version: 0,
            minor_version: 1,
            description: "aimrt-rs walking-skeleton demo".into(),
            ..ModuleInfo::default()
        }
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: DemoConfig = core.config()?;
        tracing::info!("Init: config file {}", core.config_file_path());
        let safe = core.executor(&cfg.thread_safe_executor)?;
        if !safe.thread_safe() {
            return Err(Error::msg(format!(
                "executor '{}' is not thread-safe; thread_safe_executor must name one whose tasks never run concurrently",
                safe.name()
            )));
        }
        self.work = Some(core.executor(&cfg.work_executor)?);
        self.safe = Some(safe);
        self.increments = cfg.increments;
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        tracing::info!("Start succeeded.");
        let (Some(work), Some(safe)) = (self.work, self.safe) else {
            return Err(Error::msg("start before initialize"));
        };
        // A simple task, waited for. With one executor for both (as in
        // config/demo_std_executors_so.yaml), it and the 10 000 increments can be 10 001
        // tasks in flight: a worker settles its in-flight count once per batch, after the
        // task's latch is released. That config therefore raises `queue_threshold`.
        let name = work.name().to_owned();
        let simple = DynamicLatch::new();
        if !work.try_execute(&simple, move || {
            tracing::info!("This is a simple task on executor '{name}'.")
        }) {
            return Err(Error::msg("the simple task was refused"));
        }
        simple.close();
        if !simple.wait_timeout(Duration::from_secs(30)) {
            return Err(Error::msg("the simple task did not run within 30 s"));
        }

        // 10 000 increments of one counter on a thread-safe executor: no lock needed,
        // because its tasks never run at the same time.
        let counter = Arc::new(AtomicU64::new(0));
        let latch = DynamicLatch::new();
        let mut refused = 0;
        for _ in 0..self.increments {
            let c = counter.clone();
            if !safe.try_execute(&latch, move || {
                // Load + store (not fetch_add): correct only because tasks never overlap.
                c.store(c.load(Ordering::Relaxed) + 1, Ordering::Relaxed);
            }) {
                refused += 1;
            }
        }
        latch.close();
        if !latch.wait_timeout(Duration::from_secs(30)) {
            return Err(Error::msg("the increments did not finish within 30 s"));
        }
        tracing::info!(
            "Thread-safe executor '{}': final count {} ({refused} refused)",
            safe.name(),
            counter.load(Ordering::Relaxed)
        );
        Ok(())
    }

    fn shutdown(&mut self) {
        tracing::info!("Shutdown succeeded.");
    }
}

aimrt_plugin_api::export_modules!(DemoModule);
