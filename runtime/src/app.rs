//! App mode: a started runtime whose main-thread executor the application drives from its
//! own thread with the `spin*` calls of ROS 2's executors (seed 001).

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use aimrt_plugin_api::Executor;

use crate::executor::serial::{Limit, SerialQueue, Until};
use crate::log::LogHub;
use crate::runtime::{shutdown, Parts, Shared, ShutdownHandle};

/// A signed span of time for the `spin*` calls, as rclcpp's `std::chrono::nanoseconds`:
/// a [`Duration`] converts into it, and a negative value means "forever" to
/// [`Spinner::spin_once`] and is an error to [`Spinner::spin_some`] and
/// [`Spinner::spin_all`].
///
/// ```
/// use aimrt_runtime::SpinDuration;
/// use std::time::Duration;
/// assert_eq!(SpinDuration::from(Duration::from_millis(2)).as_nanos(), 2_000_000);
/// assert!(SpinDuration::FOREVER.as_nanos() < 0);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SpinDuration(i64);

impl SpinDuration {
    /// No time: `spin_once` does not wait; `spin_some` / `spin_all` have no time limit.
    pub const ZERO: SpinDuration = SpinDuration(0);
    /// `spin_once` waits for work as long as it takes.
    pub const FOREVER: SpinDuration = SpinDuration(-1);

    /// A span of `nanos` nanoseconds (negative allowed).
    pub const fn from_nanos(nanos: i64) -> SpinDuration {
        SpinDuration(nanos)
    }

    /// The span in nanoseconds.
    pub const fn as_nanos(self) -> i64 {
        self.0
    }

    /// The span as a `Duration` when it is positive.
    fn positive(self) -> Option<Duration> {
        (self.0 > 0).then(|| Duration::from_nanos(self.0.unsigned_abs()))
    }
}

impl From<Duration> for SpinDuration {
    /// Saturates at `i64::MAX` nanoseconds (about 292 years).
    fn from(d: Duration) -> SpinDuration {
        SpinDuration(i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
    }
}

/// Why a `spin*` call was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SpinError {
    /// Another `spin*` call serves the main-thread executor now.
    #[error("{call}: the main thread executor '{executor}' is already being spun {by}; spin from one thread at a time (cancel() ends the running spin)")]
    AlreadySpinning {
        /// The refused call (`spin`, `spin_once`, ...).
        call: &'static str,
        /// The main-thread executor's name.
        executor: String,
        /// Who spins it: another thread, or a task of that spin on this thread.
        by: String,
    },
    /// A negative `max_duration`.
    #[error("{call}: max_duration must be >= 0 (0 means no time limit), got {nanos} ns")]
    NegativeDuration {
        /// The refused call.
        call: &'static str,
        /// The duration given.
        nanos: i64,
    },
}

/// The `spin*` calls on the main-thread executor, for any thread: cheap to clone, so one
/// thread can [`cancel`](Spinner::cancel) what another spins.
///
/// Rules (seed 001's, see `docs/app_mode.md`): one spin at a time — a `spin*` while one
/// runs (on another thread, or from a task of that spin) is
/// [`SpinError::AlreadySpinning`]; every spin returns after the task it is running when
/// [`Spinner::cancel`] is called; `cancel` with no spin running does nothing.
#[derive(Clone)]
pub struct Spinner {
    main: Arc<SerialQueue>,
    shared: Arc<Shared>,
}

impl std::fmt::Debug for Spinner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Spinner")
            .field("executor", &self.main.name())
            .field("spinning", &self.is_spinning())
            .finish()
    }
}

impl Spinner {
    fn run(&self, call: &'static str, until: Until) -> Result<usize, SpinError> {
        self.main.spin(until).map_err(|busy| {
            let by = if busy.by == Some(std::thread::current().id()) {
                "by this thread (a spin called from one of the main thread's own tasks)".to_owned()
            } else {
                format!("by thread {:?}", busy.by)
            };
            SpinError::AlreadySpinning {
                call,
                executor: self.main.name().to_owned(),
                by,
            }
        })
    }

    /// Serves the main-thread executor until [`cancel`](Self::cancel) or a shutdown request
    /// ([`ShutdownHandle::request`], e.g. from a signal); queued tasks still run before it
    /// returns on a shutdown request, not on cancel.
    pub fn spin(&self) -> Result<(), SpinError> {
        if self.shared.stop.load(Ordering::SeqCst) {
            return Ok(());
        }
        let until = Until {
            deadline: None,
            limit: Limit::None,
            wait: true,
        };
        self.run("spin", until).map(drop)
    }

    /// Runs the next task, waiting up to `timeout` for one (negative: as long as it takes;
    /// zero: only if one is queued). Returns whether a task ran. Returns early on cancel
    /// or a shutdown request.
    pub fn spin_once(&self, timeout: impl Into<SpinDuration>) -> Result<bool, SpinError> {
        let timeout = timeout.into();
        let deadline = if timeout.0 < 0 {
            None
        } else {
            Some(Instant::now() + timeout.positive().unwrap_or_default())
        };
        let until = Until {
            deadline,
            limit: Limit::One,
            wait: true,
        };
        self.run("spin_once", until).map(|n| n == 1)
    }

    /// Runs the tasks queued when it is called, each once, never waiting for more; tasks
    /// queued meanwhile wait for the next spin. Before each task it checks `max_duration`
    /// (zero: no limit) and returns once it has passed. Returns how many ran.
    pub fn spin_some(&self, max_duration: impl Into<SpinDuration>) -> Result<usize, SpinError> {
        let until = self.until_no_work("spin_some", max_duration.into(), Limit::QueuedAtStart)?;
        self.run("spin_some", until)
    }

    /// Runs tasks, also those queued meanwhile, until none is left or `max_duration` has
    /// passed (checked before each task; zero: no limit). Returns how many ran.
    pub fn spin_all(&self, max_duration: impl Into<SpinDuration>) -> Result<usize, SpinError> {
        let until = self.until_no_work("spin_all", max_duration.into(), Limit::None)?;
        self.run("spin_all", until)
    }

    fn until_no_work(
        &self,
        call: &'static str,
        max: SpinDuration,
        limit: Limit,
    ) -> Result<Until, SpinError> {
        if max.0 < 0 {
            return Err(SpinError::NegativeDuration { call, nanos: max.0 });
        }
        Ok(Until {
            deadline: max.positive().map(|d| Instant::now() + d),
            limit,
            wait: false,
        })
    }

    /// Makes the running spin return after its current task, from any thread. Returns
    /// whether a spin was running (with none, nothing happens: a later spin is not
    /// affected).
    pub fn cancel(&self) -> bool {
        self.main.cancel()
    }

    /// Whether a `spin*` call serves the main-thread executor now.
    pub fn is_spinning(&self) -> bool {
        self.main.is_spinning()
    }
}

/// A started runtime in app mode (from [`Runtime::start`](crate::Runtime::start)): the
/// application drives the main-thread executor with the `spin*` calls (see [`Spinner`])
/// and ends with [`App::shutdown`], which shuts everything down in reverse order (dropping
/// the `App` does the same).
///
/// ```no_run
/// use aimrt_runtime::{Runtime, RuntimeOptions};
/// let runtime = Runtime::new(RuntimeOptions {
///     cfg_file_path: Some("config/helloworld_app_mode.yaml".into()),
///     ..Default::default()
/// });
/// let app = runtime.start().expect("start failed");
/// let handle = app.shutdown_handle();
/// aimrt_runtime::on_signals(move || handle.request()).unwrap();
/// app.spin().unwrap(); // until Ctrl-C
/// app.shutdown();
/// ```
pub struct App {
    parts: Parts,
    spinner: Spinner,
    hub: Arc<LogHub>,
    down: bool,
}

impl std::fmt::Debug for App {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("App")
            .field("spinner", &self.spinner)
            .finish_non_exhaustive()
    }
}

impl App {
    pub(crate) fn new(
        parts: Parts,
        main: Arc<SerialQueue>,
        shared: Arc<Shared>,
        hub: Arc<LogHub>,
    ) -> App {
        App {
            parts,
            spinner: Spinner { main, shared },
            hub,
            down: false,
        }
    }

    /// A handle to spin or cancel from other threads.
    pub fn spinner(&self) -> Spinner {
        self.spinner.clone()
    }

    /// A handle to request shutdown: it ends [`App::spin`] (e.g. from a signal handler).
    pub fn shutdown_handle(&self) -> ShutdownHandle {
        ShutdownHandle(self.spinner.shared.clone())
    }

    /// See [`Spinner::spin`].
    pub fn spin(&self) -> Result<(), SpinError> {
        self.spinner.spin()
    }

    /// See [`Spinner::spin_once`].
    pub fn spin_once(&self, timeout: impl Into<SpinDuration>) -> Result<bool, SpinError> {
        self.spinner.spin_once(timeout)
    }

    /// See [`Spinner::spin_some`].
    pub fn spin_some(&self, max_duration: impl Into<SpinDuration>) -> Result<usize, SpinError> {
        self.spinner.spin_some(max_duration)
    }

    /// See [`Spinner::spin_all`].
    pub fn spin_all(&self, max_duration: impl Into<SpinDuration>) -> Result<usize, SpinError> {
        self.spinner.spin_all(max_duration)
    }

    /// See [`Spinner::cancel`].
    pub fn cancel(&self) -> bool {
        self.spinner.cancel()
    }

    /// See [`Spinner::is_spinning`].
    pub fn is_spinning(&self) -> bool {
        self.spinner.is_spinning()
    }

    /// `aimrt_main`'s loop: serves the main thread until a shutdown request or `deadline`.
    /// Whether a shutdown was requested (a signal, or `ShutdownHandle::request`).
    pub(crate) fn stop_requested(&self) -> bool {
        self.spinner.shared.stop.load(Ordering::SeqCst)
    }

    pub(crate) fn serve_until_shutdown(&self, deadline: Option<Instant>) {
        let shared = &self.spinner.shared;
        if !shared.stop.load(Ordering::SeqCst) {
            self.spinner.main.serve(deadline);
        }
        if shared.stop.load(Ordering::SeqCst) {
            tracing::info!(target: "aimrt", "Received shutdown signal.");
        }
    }

    /// Shuts everything down in reverse order (modules, channel, plugins, executors), ends
    /// any spin still running on another thread, and flushes the log last.
    pub fn shutdown(mut self) {
        self.shut_down();
    }

    fn shut_down(&mut self) {
        if std::mem::replace(&mut self.down, true) {
            return;
        }
        // A spin still waiting on another thread returns; later spins find nothing to do.
        self.spinner.shared.stop.store(true, Ordering::SeqCst);
        self.spinner.main.request_stop();
        tracing::info!(target: "aimrt", "AimRT start shutdown.");
        shutdown(&mut self.parts);
        // The log pipeline is flushed last: everything logged so far is written.
        self.hub.stop();
    }
}

impl Drop for App {
    fn drop(&mut self) {
        self.shut_down();
    }
}
