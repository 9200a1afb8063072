//! AimRT's logger example package (`liblogger_pkg.so`), for the `examples_cpp_logger_*`
//! configs:
//!
//! - `LoggerModule` logs one line at every level from Trace to Error on `work_executor`,
//!   every `interval_ms` (default 1000), until shutdown.
//! - `LoggerBenchModule` logs `log_bench_num` Info lines of each size in `log_data_size`
//!   on `work_executor` and reports the time per line.
//!
//! ```yaml
//! LoggerModule:
//!   interval_ms: 1000        # optional
//! LoggerBenchModule:
//!   log_data_size: [64, 256, 1024, 4096]
//!   log_bench_num: 5000
//! ```
#![deny(unsafe_code)]

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};
use serde::Deserialize;

/// The executor both modules log from, as in AimRT's configs.
const WORK_EXECUTOR: &str = "work_executor";

/// A stop flag a sleeping loop can be woken from.
#[derive(Debug, Default)]
struct Stop {
    stopped: Mutex<bool>,
    changed: Condvar,
}

impl Stop {
    /// Sleeps up to `d`; true if stop was requested.
    fn sleep(&self, d: Duration) -> bool {
        let guard = self.stopped.lock().unwrap_or_else(|e| e.into_inner());
        let (guard, _) = self
            .changed
            .wait_timeout_while(guard, d, |stopped| !*stopped)
            .unwrap_or_else(|e| e.into_inner());
        *guard
    }

    fn request(&self) {
        *self.stopped.lock().unwrap_or_else(|e| e.into_inner()) = true;
        self.changed.notify_all();
    }
}

/// One long-running job on an executor, waited for at shutdown.
#[derive(Debug, Default)]
struct Background(Option<std::sync::mpsc::Receiver<()>>);

impl Background {
    fn run(&mut self, exec: ExecutorRef, job: impl FnOnce() + Send + 'static) -> Result<(), Error> {
        let (done_tx, done) = std::sync::mpsc::channel();
        self.0 = Some(done);
        exec.execute(move || {
            job();
            let _ = done_tx.send(());
        })
    }

    /// Waits up to `limit` for the job; false if it is still running.
    fn wait(&mut self, limit: Duration) -> bool {
        self.0
            .take()
            .is_none_or(|done| done.recv_timeout(limit).is_ok())
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LoggerConfig {
    #[serde(default = "default_interval_ms")]
    interval_ms: u64,
}

fn default_interval_ms() -> u64 {
    1000
}

/// Logs every level in a loop.
#[derive(Debug, Default)]
pub struct LoggerModule {
    work: Option<ExecutorRef>,
    interval: Duration,
    stop: Arc<Stop>,
    job: Background,
}

impl Module for LoggerModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo {
            name: "LoggerModule".into(),
            description: "logs every level in a loop".into(),
            ..ModuleInfo::default()
        }
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: LoggerConfig = core.config()?;
        self.interval = Duration::from_millis(cfg.interval_ms.max(1));
        self.work = Some(core.executor(WORK_EXECUTOR)?);
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(work) = self.work else {
            return Err(Error::msg("start before initialize"));
        };
        let stop = self.stop.clone();
        let interval = self.interval;
        self.job.run(work, move || {
            let mut count = 0u64;
            loop {
                count += 1;
                tracing::trace!("Test trace log, loop count: {count}");
                tracing::debug!("Test debug log, loop count: {count}");
                tracing::info!("Test info log, loop count: {count}");
                tracing::warn!("Test warn log, loop count: {count}");
                tracing::error!("Test error log, loop count: {count}");
                if stop.sleep(interval) {
                    break;
                }
            }
            tracing::info!("Exit loop after {count} rounds.");
        })?;
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        self.stop.request();
        if !self.job.wait(Duration::from_secs(5)) {
            tracing::warn!("The log loop did not stop within 5 s.");
        }
        tracing::info!("Shutdown succeeded.");
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BenchConfig {
    #[serde(default = "default_sizes")]
    log_data_size: Vec<usize>,
    #[serde(default = "default_bench_num")]
    log_bench_num: u32,
}

fn default_sizes() -> Vec<usize> {
    vec![64, 256, 1024, 4096]
}

fn default_bench_num() -> u32 {
    5000
}

/// Measures the cost of a log call per message size.
#[derive(Debug, Default)]
pub struct LoggerBenchModule {
    work: Option<ExecutorRef>,
    sizes: Vec<usize>,
    num: u32,
    job: Background,
}

impl Module for LoggerBenchModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo {
            name: "LoggerBenchModule".into(),
            description: "measures the cost of a log call".into(),
            ..ModuleInfo::default()
        }
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: BenchConfig = core.config()?;
        self.sizes = cfg.log_data_size;
        self.num = cfg.log_bench_num;
        self.work = Some(core.executor(WORK_EXECUTOR)?);
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(work) = self.work else {
            return Err(Error::msg("start before initialize"));
        };
        let (sizes, num) = (self.sizes.clone(), self.num);
        self.job.run(work, move || {
            for size in sizes {
                let data = "x".repeat(size);
                let start = Instant::now();
                for _ in 0..num {
                    tracing::info!("{data}");
                }
                let took = start.elapsed();
                tracing::info!(
                    "Bench: {num} lines of {size} bytes in {:.3} ms, {:.3} us per line",
                    took.as_secs_f64() * 1e3,
                    took.as_secs_f64() * 1e6 / f64::from(num.max(1))
                );
            }
            tracing::info!("Bench completed.");
        })?;
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        if !self.job.wait(Duration::from_secs(30)) {
            tracing::warn!("The bench did not finish within 30 s.");
        }
        tracing::info!("Shutdown succeeded.");
    }
}

aimrt_plugin_api::export_modules!(LoggerModule, LoggerBenchModule);
