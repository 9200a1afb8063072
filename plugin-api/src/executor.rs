//! Executors: the trait plugins implement and the handle modules use.

use std::sync::Arc;
use std::time::{Duration, SystemTime};

use serde::de::DeserializeOwned;

use crate::ffi::{ExecutorStats, RawExecutor};
use crate::{DynamicLatch, Error, ExecuteError, Task, ThreadFactory};

/// The executor contract every executor type implements (seed 000 / AimRT's
/// `ExecutorBase`). `thread_safe` means "no two of its tasks ever run at the same time".
///
/// Refusing work: `execute`/`execute_at` take the task in every case; on refusal they drop
/// it and return why. Implementations count what they accept, run, refuse and what panics
/// ([`ExecutorStats`]).
pub trait Executor: Send + Sync + 'static {
    /// The type name, e.g. `simple_thread`.
    fn type_name(&self) -> &str;
    /// The name from the config.
    fn name(&self) -> &str;
    /// No two tasks ever run at the same time.
    fn thread_safe(&self) -> bool;
    /// The calling thread is running one of this executor's tasks.
    fn is_in_current_executor(&self) -> bool;
    /// `execute_at` is supported.
    fn supports_timer_schedule(&self) -> bool {
        false
    }
    /// Queues a task.
    fn execute(&self, task: Task) -> Result<(), ExecuteError>;
    /// The executor's clock (wall-clock anchored).
    fn now(&self) -> SystemTime {
        SystemTime::now()
    }
    /// Runs a task at `at` on the executor's clock.
    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        let _ = at;
        drop(task);
        Err(ExecuteError::NoTimerSupport)
    }
    /// Called once after every executor is built.
    fn start(&self) -> Result<(), Error> {
        Ok(())
    }
    /// Stops taking work, runs what is queued, joins its threads. Idempotent.
    fn shutdown(&self);
    /// Work accounting.
    fn stats(&self) -> ExecutorStats {
        ExecutorStats::default()
    }
}

/// A handle to a named executor, as modules and plugins use it. Cheap to copy; valid for
/// the process's life: the runtime shuts its executors down at its end but never frees
/// them, so a handle kept past shutdown gets [`ExecuteError::ShutDown`] for new work and
/// the executor's final [`stats`](ExecutorRef::stats).
///
/// ```no_run
/// # fn demo(exec: aimrt_plugin_api::ExecutorRef) -> Result<(), aimrt_plugin_api::Error> {
/// exec.execute(|| tracing::info!("on the executor"))?;
/// # Ok(()) }
/// ```
#[derive(Clone, Copy)]
pub struct ExecutorRef {
    raw: RawExecutor,
}

impl ExecutorRef {
    /// Wraps a raw handle.
    ///
    /// # Safety
    /// `raw` must be non-null and point to a live executor: its vtable valid for the
    /// process's life, the object never destroyed while a copy of the handle may be used
    /// (the runtime's executors never are).
    pub unsafe fn from_raw(raw: RawExecutor) -> ExecutorRef {
        ExecutorRef { raw }
    }

    /// Exports `executor` for good and returns a handle to it: for tests and tools that
    /// drive an executor without a runtime. The executor is never destroyed, so the handle
    /// stays valid; call `raw().shutdown()` to stop its threads.
    ///
    /// ```
    /// # use std::sync::Arc;
    /// # use aimrt_plugin_api::{ExecuteError, Executor, ExecutorRef, Task};
    /// struct Inline;
    /// impl Executor for Inline {
    ///     fn type_name(&self) -> &str { "inline" }
    ///     fn name(&self) -> &str { "inline" }
    ///     fn thread_safe(&self) -> bool { false }
    ///     fn is_in_current_executor(&self) -> bool { false }
    ///     fn execute(&self, task: Task) -> Result<(), ExecuteError> { task.run("inline"); Ok(()) }
    ///     fn shutdown(&self) {}
    /// }
    /// let exec = ExecutorRef::leak(Arc::new(Inline));
    /// assert_eq!(exec.type_name(), "inline");
    /// exec.execute(|| println!("ran")).unwrap();
    /// ```
    pub fn leak<E: Executor>(executor: Arc<E>) -> ExecutorRef {
        ExecutorRef {
            raw: RawExecutor::new(executor),
        }
    }

    /// The raw handle.
    pub fn raw(&self) -> RawExecutor {
        self.raw
    }

    /// The type name, e.g. `simple_thread`.
    pub fn type_name(&self) -> &str {
        self.raw.type_name()
    }

    /// The executor's name.
    pub fn name(&self) -> &str {
        self.raw.name()
    }

    /// No two of its tasks ever run at the same time.
    pub fn thread_safe(&self) -> bool {
        self.raw.thread_safe()
    }

    /// The calling thread is running one of its tasks.
    pub fn is_in_current_executor(&self) -> bool {
        self.raw.is_in_current_executor()
    }

    /// `execute_at` / `execute_after` are supported.
    pub fn supports_timer_schedule(&self) -> bool {
        self.raw.supports_timer_schedule()
    }

    fn result(&self, status: crate::ffi::Status) -> Result<(), Error> {
        ExecuteError::from_status(status).map_err(|source| Error::Execute {
            executor: self.name().to_owned(),
            source,
        })
    }

    /// Runs `future` as an async task on this executor ([`co::spawn`](crate::co::spawn)).
    pub fn spawn<F>(&self, future: F) -> crate::co::JoinHandle<F::Output>
    where
        F: std::future::Future + Send + 'static,
        F::Output: Send + 'static,
    {
        crate::co::spawn(*self, future)
    }

    /// Queues `task` now, or at `at`.
    pub(crate) fn post(&self, at: Option<SystemTime>, task: Task) -> Result<(), ExecuteError> {
        ExecuteError::from_status(match at {
            Some(at) => self.raw.execute_at(at, task),
            None => self.raw.execute(task),
        })
    }

    /// Queues `f`. On refusal `f` is dropped and the error says why.
    pub fn execute(&self, f: impl FnOnce() + Send + 'static) -> Result<(), Error> {
        self.execute_task(Task::new(f))
    }

    /// Queues a prepared [`Task`].
    pub fn execute_task(&self, task: Task) -> Result<(), Error> {
        self.result(self.raw.execute(task))
    }

    /// The executor's clock.
    pub fn now(&self) -> SystemTime {
        self.raw.now()
    }

    /// Runs `f` at `at` on the executor's clock.
    pub fn execute_at(
        &self,
        at: SystemTime,
        f: impl FnOnce() + Send + 'static,
    ) -> Result<(), Error> {
        self.result(self.raw.execute_at(at, Task::new(f)))
    }

    /// Runs `f` once `dt` has passed on the executor's clock.
    pub fn execute_after(
        &self,
        dt: Duration,
        f: impl FnOnce() + Send + 'static,
    ) -> Result<(), Error> {
        self.execute_at(self.now() + dt, f)
    }

    /// Queues `f` if `latch` is open: the latch counts the task and is counted down when
    /// the task finishes — also when it panics or the executor drops it. Returns `true`
    /// when the latch and the executor both accepted the task.
    ///
    /// ```no_run
    /// # fn demo(exec: aimrt_plugin_api::ExecutorRef) {
    /// let latch = aimrt_plugin_api::DynamicLatch::new();
    /// for _ in 0..10 {
    ///     exec.try_execute(&latch, || {});
    /// }
    /// latch.close_and_wait();
    /// # }
    /// ```
    pub fn try_execute(&self, latch: &DynamicLatch, f: impl FnOnce() + Send + 'static) -> bool {
        if !latch.try_add(1) {
            return false;
        }
        let guard = latch.count_down_guard();
        self.execute(move || {
            let _guard = guard;
            f();
        })
        .is_ok()
    }

    /// Work accounting.
    pub fn stats(&self) -> ExecutorStats {
        self.raw.stats()
    }
}

impl std::fmt::Debug for ExecutorRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ExecutorRef")
            .field("name", &self.name())
            .field("type", &self.type_name())
            .finish()
    }
}

/// What an executor type's factory gets.
#[derive(Debug)]
pub struct ExecutorArgs<'a> {
    /// The executor name from the config.
    pub name: &'a str,
    /// The `options` node as JSON text (`null` when absent).
    pub options_json: &'a str,
    /// Where the options are, `file:line:col`.
    pub location: &'a str,
    /// The executors named by the type's bind keys, in bind-key order (`None` for an
    /// absent key).
    pub bound: Vec<Option<ExecutorRef>>,
    /// The runtime's thread factory: create every thread through it.
    pub threads: ThreadFactory,
}

impl ExecutorArgs<'_> {
    /// Reads the options into `T` (a missing `options` reads as `{}`, so `#[serde(default)]`
    /// fields get their defaults). With `#[serde(deny_unknown_fields)]` a typo is an error
    /// that names the key and the closest known one.
    ///
    /// ```
    /// # use aimrt_plugin_api::{ExecutorArgs, ThreadFactory};
    /// #[derive(Debug, serde::Deserialize)]
    /// #[serde(deny_unknown_fields)]
    /// struct Opts { #[serde(default)] thread_num: u32 }
    /// let args = ExecutorArgs {
    ///     name: "pool", options_json: r#"{"thread_nm": 2}"#, location: "cfg.yaml:7:9",
    ///     bound: Vec::new(), threads: ThreadFactory::plain(),
    /// };
    /// let err = args.options::<Opts>().unwrap_err().to_string();
    /// assert!(err.contains("cfg.yaml:7:9") && err.contains("did you mean 'thread_num'"), "{err}");
    /// ```
    pub fn options<T: DeserializeOwned>(&self) -> Result<T, Error> {
        crate::suggest::read_options(self.options_json, || {
            format!("options of executor '{}' at {}", self.name, self.location)
        })
    }

    /// Reads the options into `T` ([`options`](Self::options)) and hands them back to the
    /// runtime as read, defaults filled in (ABI 1.8; AimRT's `options_node = options_`):
    /// `--dump_cfg_file` writes them in place of what the config wrote. Call it from the
    /// factory itself; on an `aimrt_main` older than 1.8, or outside a factory call, it
    /// only reads.
    ///
    /// ```
    /// # use aimrt_plugin_api::{ExecutorArgs, ThreadFactory};
    /// #[derive(Debug, serde::Deserialize, serde::Serialize)]
    /// #[serde(deny_unknown_fields)]
    /// struct Opts { #[serde(default = "one")] thread_num: u32 }
    /// fn one() -> u32 { 1 }
    /// let args = ExecutorArgs {
    ///     name: "pool", options_json: "null", location: "cfg.yaml:7:9",
    ///     bound: Vec::new(), threads: ThreadFactory::plain(),
    /// };
    /// assert_eq!(args.read_options::<Opts>().unwrap().thread_num, 1);
    /// ```
    pub fn read_options<T: DeserializeOwned + serde::Serialize>(&self) -> Result<T, Error> {
        let options: T = self.options()?;
        crate::ffi::report_options(&options);
        Ok(options)
    }
}
