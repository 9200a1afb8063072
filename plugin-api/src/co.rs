//! Async tasks on any executor: AimRT's coroutine interface (`co::Schedule`,
//! `co::ScheduleAfter`, `co::AsyncScope`, `co::SyncWait`) as Rust futures.
//!
//! - [`spawn`] runs a future as a task on an executor; every wake-up is an ordinary task
//!   posted through the executor's ABI, so no `Waker` ever crosses a library boundary and
//!   any executor — built in, from a plugin, in another library — can drive a future.
//! - [`schedule`]`(&exec).await` moves the rest of the task onto `exec`;
//!   [`schedule_after`]`(&exec, d).await` does so once `d` has passed on `exec`'s clock (a
//!   sleep that blocks no thread).
//! - [`AsyncScope`] tracks spawned tasks; `scope.complete()` resolves once all have ended.
//! - [`block_on`] drives a future on the calling thread, e.g. in a module hook.
//!
//! Nothing hangs silently: when an executor refuses a wake-up (queue full, shut down) or
//! drops it (shut down before a `schedule_after` was due), the task ends and its
//! [`JoinHandle`] returns a [`JoinError`] saying which executor and why. A panic in a
//! future is contained like a panic in a task: logged once with its location, and
//! reported as [`JoinError::Panicked`].
//!
//! ```no_run
//! # fn demo(a: aimrt_plugin_api::ExecutorRef, b: aimrt_plugin_api::ExecutorRef) {
//! use aimrt_plugin_api::co;
//! let handle = co::spawn(a, async move {
//!     tracing::info!("on a");
//!     co::schedule(&b).await?;
//!     tracing::info!("now on b");
//!     co::schedule_after(&b, std::time::Duration::from_millis(100)).await?;
//!     Ok::<_, aimrt_plugin_api::Error>(42)
//! });
//! assert_eq!(co::block_on(handle).unwrap().unwrap(), 42);
//! # }
//! ```

use std::cell::RefCell;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll, Wake, Waker};
use std::time::{Duration, Instant, SystemTime};

use async_task::{FallibleTask, Runnable};

use crate::error::{Error, ExecuteError};
use crate::executor::ExecutorRef;
use crate::ffi::context;

/// Why an async task did not produce its value.
#[non_exhaustive]
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum JoinError {
    /// An executor refused to run the task's next step; the task was dropped.
    #[error("async task stopped: executor '{executor}' refused to run it: {source}")]
    Refused {
        /// The executor.
        executor: String,
        /// Why it refused.
        source: ExecuteError,
    },
    /// An executor accepted the task's next step but dropped it without running it (it
    /// shut down first); the task was dropped.
    #[error("async task stopped: executor '{executor}' shut down before running it")]
    Dropped {
        /// The executor.
        executor: String,
    },
    /// The future panicked (already logged with its location).
    #[error("async task panicked: {0}")]
    Panicked(String),
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

thread_local! {
    /// The task whose step runs on this thread (set around `Runnable::run`).
    static HOME: RefCell<Option<Arc<Home>>> = const { RefCell::new(None) };
}

/// Where a task's next step runs, and how it ended if it did not complete.
struct Home {
    next: Mutex<Step>,
    /// The first reason the task was stopped.
    stopped: Mutex<Option<JoinError>>,
    /// The module that spawned the task (its logs are attributed to it).
    module_tag: usize,
}

#[derive(Clone, Copy)]
struct Step {
    executor: ExecutorRef,
    /// Run the next step at this time instead of right away (once).
    at: Option<SystemTime>,
}

impl Home {
    fn stop(&self, reason: JoinError) {
        lock(&self.stopped).get_or_insert(reason);
    }

    fn in_module<R>(&self, f: impl FnOnce() -> R) -> R {
        context::with_module_tag(self.module_tag as *const std::ffi::c_void, f)
    }

    /// The schedule function of every task: posts `runnable` as a task to the executor of
    /// the next step. A refused or dropped post cancels the task and records why.
    fn schedule(self: &Arc<Self>, runnable: Runnable) {
        let step = {
            let mut next = lock(&self.next);
            let step = *next;
            next.at = None;
            step
        };
        let wake = Arc::new(Mutex::new(Wake1 {
            runnable: Some(runnable),
            submitting: true,
            dropped: false,
        }));
        let guard = StepGuard {
            wake: wake.clone(),
            home: self.clone(),
            executor: step.executor,
            ran: false,
        };
        let task = move || {
            let mut guard = guard;
            guard.run();
        };
        let result = step.executor.post(step.at, crate::Task::new(task));
        let leftover = {
            let mut w = lock(&wake);
            w.submitting = false;
            match result {
                Err(source) => {
                    self.stop(JoinError::Refused {
                        executor: step.executor.name().to_owned(),
                        source,
                    });
                    w.runnable.take()
                }
                Ok(()) if w.dropped => {
                    self.stop(JoinError::Dropped {
                        executor: step.executor.name().to_owned(),
                    });
                    w.runnable.take()
                }
                Ok(()) => None,
            }
        };
        // Dropping the runnable cancels the task: its future is dropped, in its module.
        self.in_module(|| drop(leftover));
    }
}

/// One wake-up in flight.
struct Wake1 {
    runnable: Option<Runnable>,
    /// The post is still inside `execute`: a drop now is settled by the poster, who then
    /// knows the executor's answer.
    submitting: bool,
    dropped: bool,
}

/// Owned by the posted task: runs the step, or settles a drop without run.
struct StepGuard {
    wake: Arc<Mutex<Wake1>>,
    home: Arc<Home>,
    executor: ExecutorRef,
    ran: bool,
}

impl StepGuard {
    fn run(&mut self) {
        self.ran = true;
        let Some(runnable) = lock(&self.wake).runnable.take() else {
            return;
        };
        let prev = HOME.with(|h| h.replace(Some(self.home.clone())));
        self.home.in_module(|| runnable.run());
        HOME.with(|h| *h.borrow_mut() = prev);
    }
}

impl Drop for StepGuard {
    fn drop(&mut self) {
        if self.ran {
            return;
        }
        let leftover = {
            let mut w = lock(&self.wake);
            if w.submitting {
                w.dropped = true;
                None
            } else {
                self.home.stop(JoinError::Dropped {
                    executor: self.executor.name().to_owned(),
                });
                w.runnable.take()
            }
        };
        self.home.in_module(|| drop(leftover));
    }
}

/// A future whose panics are caught, logged and returned.
struct Contained<F> {
    inner: Pin<Box<F>>,
}

impl<F: Future> Future for Contained<F> {
    type Output = Result<F::Output, String>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let inner = &mut self.inner;
        match crate::panic::contain(|| inner.as_mut().poll(cx)) {
            Ok(Poll::Ready(v)) => Poll::Ready(Ok(v)),
            Ok(Poll::Pending) => Poll::Pending,
            Err(message) => {
                crate::panic::log_panic("async task", "", &message);
                Poll::Ready(Err(message))
            }
        }
    }
}

/// Awaits (or [`join`](JoinHandle::join)s) a spawned task's result. Dropping it detaches
/// the task, which runs on.
pub struct JoinHandle<T> {
    task: Option<FallibleTask<Result<T, String>>>,
    home: Arc<Home>,
}

impl<T> std::fmt::Debug for JoinHandle<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("JoinHandle")
            .field("finished", &self.is_finished())
            .finish()
    }
}

impl<T> JoinHandle<T> {
    /// Whether the task has ended (completed, panicked or stopped).
    pub fn is_finished(&self) -> bool {
        self.task.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Blocks the calling thread until the task ends. Not from a task of the executor the
    /// task needs, if that executor has a single thread: that would wait forever.
    pub fn join(self) -> Result<T, JoinError> {
        block_on(self)
    }
}

impl<T> Future for JoinHandle<T> {
    type Output = Result<T, JoinError>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let Some(task) = self.task.as_mut() else {
            return Poll::Pending;
        };
        let out = match Pin::new(task).poll(cx) {
            Poll::Pending => return Poll::Pending,
            Poll::Ready(Some(Ok(v))) => Ok(v),
            Poll::Ready(Some(Err(message))) => Err(JoinError::Panicked(message)),
            Poll::Ready(None) => {
                Err(lock(&self.home.stopped)
                    .clone()
                    .unwrap_or(JoinError::Dropped {
                        executor: lock(&self.home.next).executor.name().to_owned(),
                    }))
            }
        };
        self.task = None;
        Poll::Ready(out)
    }
}

impl<T> Drop for JoinHandle<T> {
    fn drop(&mut self) {
        if let Some(task) = self.task.take() {
            task.detach();
        }
    }
}

/// Runs `future` as a task on `executor`; the returned handle gives its output.
pub fn spawn<F>(executor: ExecutorRef, future: F) -> JoinHandle<F::Output>
where
    F: Future + Send + 'static,
    F::Output: Send + 'static,
{
    let home = Arc::new(Home {
        next: Mutex::new(Step { executor, at: None }),
        stopped: Mutex::new(None),
        module_tag: context::current_module_tag() as usize,
    });
    let scheduler = home.clone();
    let (runnable, task) = async_task::spawn(
        Contained {
            inner: Box::pin(future),
        },
        move |runnable| scheduler.schedule(runnable),
    );
    runnable.schedule();
    JoinHandle {
        task: Some(task.fallible()),
        home,
    }
}

/// Moves the rest of the current task onto `executor`: after `.await`, the code runs as a
/// task of `executor`. Outside a spawned task (in [`block_on`], or a foreign runtime) it
/// cannot move the caller; it then waits until `executor` has run a task.
pub fn schedule(executor: &ExecutorRef) -> Schedule {
    Schedule {
        executor: *executor,
        delay: None,
        state: ScheduleState::Start,
    }
}

/// Like [`schedule`], once `delay` has passed on `executor`'s clock (measured from the
/// first poll): a sleep that blocks no thread. `executor` must support timers, else the
/// await returns an error.
pub fn schedule_after(executor: &ExecutorRef, delay: Duration) -> Schedule {
    Schedule {
        executor: *executor,
        delay: Some(delay),
        state: ScheduleState::Start,
    }
}

/// The future of [`schedule`] and [`schedule_after`].
#[derive(Debug)]
pub struct Schedule {
    executor: ExecutorRef,
    delay: Option<Duration>,
    state: ScheduleState,
}

#[derive(Debug)]
enum ScheduleState {
    Start,
    /// The task's next step was sent to the executor (due at the deadline, if any).
    Moved(Option<SystemTime>),
    /// Waiting for a task posted to the executor to wake the caller.
    Waiting(Arc<Mutex<Option<Result<(), Error>>>>),
    Done,
}

/// Wakes the waiter of a [`Schedule`] outside a task; settles with an error if dropped
/// without running.
struct Notify {
    slot: Arc<Mutex<Option<Result<(), Error>>>>,
    waker: Waker,
    executor: ExecutorRef,
}

impl Notify {
    fn settle(&self, r: Result<(), Error>) {
        lock(&self.slot).get_or_insert(r);
        self.waker.wake_by_ref();
    }
}

impl Drop for Notify {
    fn drop(&mut self) {
        let r = Err(Error::Execute {
            executor: self.executor.name().to_owned(),
            source: ExecuteError::ShutDown,
        });
        self.settle(r);
    }
}

impl Future for Schedule {
    type Output = Result<(), Error>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let exec = self.executor;
        match std::mem::replace(&mut self.state, ScheduleState::Done) {
            ScheduleState::Start => {
                let at = match self.delay {
                    None => None,
                    Some(_) if !exec.supports_timer_schedule() => {
                        return Poll::Ready(Err(Error::Execute {
                            executor: exec.name().to_owned(),
                            source: ExecuteError::NoTimerSupport,
                        }))
                    }
                    Some(d) => Some(exec.now() + d),
                };
                let moved = HOME.with(|h| {
                    h.borrow().as_ref().map(|home| {
                        *lock(&home.next) = Step { executor: exec, at };
                    })
                });
                if moved.is_some() {
                    self.state = ScheduleState::Moved(at);
                    cx.waker().wake_by_ref();
                    return Poll::Pending;
                }
                let slot = Arc::new(Mutex::new(None));
                let notify = Notify {
                    slot: slot.clone(),
                    waker: cx.waker().clone(),
                    executor: exec,
                };
                let task = move || notify.settle(Ok(()));
                let posted = match at {
                    Some(at) => exec.execute_at(at, task),
                    None => exec.execute(task),
                };
                if let Err(e) = posted {
                    return Poll::Ready(Err(e));
                }
                self.state = ScheduleState::Waiting(slot);
                Poll::Pending
            }
            ScheduleState::Moved(Some(at)) if exec.now() < at => {
                // Polled before the deadline (woken by something else): wait again.
                HOME.with(|h| {
                    if let Some(home) = h.borrow().as_ref() {
                        *lock(&home.next) = Step {
                            executor: exec,
                            at: Some(at),
                        };
                    }
                });
                self.state = ScheduleState::Moved(Some(at));
                cx.waker().wake_by_ref();
                Poll::Pending
            }
            ScheduleState::Moved(_) => Poll::Ready(Ok(())),
            ScheduleState::Waiting(slot) => {
                let settled = lock(&slot).take();
                match settled {
                    Some(r) => Poll::Ready(r),
                    None => {
                        self.state = ScheduleState::Waiting(slot);
                        Poll::Pending
                    }
                }
            }
            ScheduleState::Done => Poll::Ready(Ok(())),
        }
    }
}

struct ThreadWaker {
    thread: std::thread::Thread,
    woken: AtomicBool,
}

impl Wake for ThreadWaker {
    fn wake(self: Arc<Self>) {
        self.wake_by_ref();
    }

    fn wake_by_ref(self: &Arc<Self>) {
        self.woken.store(true, Ordering::Release);
        self.thread.unpark();
    }
}

/// Drives `future` to completion on the calling thread (AimRT's `co::SyncWait`), e.g.
/// `block_on(scope.complete())` in a module's `shutdown`. The future stays on this thread
/// ([`schedule`] inside it waits for the executor instead of moving). Do not call it from
/// a task of a single-threaded executor that the future needs: it would wait forever.
pub fn block_on<F: Future>(future: F) -> F::Output {
    match drive(future, None) {
        Some(v) => v,
        None => unreachable!("without a deadline the future is driven to completion"),
    }
}

/// [`block_on`] for at most `timeout`: `None` (and the future dropped) if it did not
/// complete in time. For shutdown paths that must not hang, e.g. a loop waiting on a
/// paused `time_manipulator`.
///
/// ```
/// use std::time::Duration;
/// use aimrt_plugin_api::co::block_on_timeout;
/// assert_eq!(block_on_timeout(async { 7 }, Duration::from_millis(10)), Some(7));
/// assert_eq!(block_on_timeout(std::future::pending::<()>(), Duration::from_millis(10)), None);
/// ```
pub fn block_on_timeout<F: Future>(future: F, timeout: Duration) -> Option<F::Output> {
    drive(future, Some(Instant::now() + timeout))
}

fn drive<F: Future>(future: F, deadline: Option<Instant>) -> Option<F::Output> {
    let mut future = std::pin::pin!(future);
    let parker = Arc::new(ThreadWaker {
        thread: std::thread::current(),
        woken: AtomicBool::new(false),
    });
    let waker = Waker::from(parker.clone());
    let mut cx = Context::from_waker(&waker);
    // Inside a task's step, the future polled here is not that task's.
    let outer = HOME.with(|h| h.borrow_mut().take());
    let out = 'outer: loop {
        if let Poll::Ready(v) = future.as_mut().poll(&mut cx) {
            break Some(v);
        }
        while !parker.woken.swap(false, Ordering::Acquire) {
            match deadline {
                None => std::thread::park(),
                Some(d) => {
                    let left = d.saturating_duration_since(Instant::now());
                    if left.is_zero() {
                        break 'outer None;
                    }
                    std::thread::park_timeout(left);
                }
            }
        }
    };
    HOME.with(|h| *h.borrow_mut() = outer);
    out
}

/// Tracks spawned tasks so that a module can wait for all of them (AimRT's
/// `co::AsyncScope`).
///
/// ```no_run
/// # fn demo(exec: aimrt_plugin_api::ExecutorRef) -> Result<(), aimrt_plugin_api::Error> {
/// use aimrt_plugin_api::co::{block_on, AsyncScope};
/// let scope = AsyncScope::new();
/// scope.spawn(exec, async { tracing::info!("working") })?;
/// // in shutdown:
/// block_on(scope.complete());
/// # Ok(()) }
/// ```
#[derive(Debug, Default, Clone)]
pub struct AsyncScope {
    inner: Arc<ScopeInner>,
}

#[derive(Debug, Default)]
struct ScopeInner {
    state: Mutex<ScopeState>,
}

#[derive(Debug, Default)]
struct ScopeState {
    live: usize,
    closed: bool,
    waiters: Vec<Waker>,
}

/// Counts a task of a scope as ended when dropped (completed, panicked or stopped).
struct Member(Arc<ScopeInner>);

impl Drop for Member {
    fn drop(&mut self) {
        let waiters = {
            let mut s = lock(&self.0.state);
            s.live -= 1;
            if s.live == 0 {
                std::mem::take(&mut s.waiters)
            } else {
                Vec::new()
            }
        };
        waiters.into_iter().for_each(Waker::wake);
    }
}

impl AsyncScope {
    /// An empty, open scope.
    pub fn new() -> AsyncScope {
        AsyncScope::default()
    }

    /// Spawns `future` on `executor` as a member of the scope. Refused once
    /// [`complete`](AsyncScope::complete) was called.
    pub fn spawn<F>(&self, executor: ExecutorRef, future: F) -> Result<JoinHandle<F::Output>, Error>
    where
        F: Future + Send + 'static,
        F::Output: Send + 'static,
    {
        {
            let mut s = lock(&self.inner.state);
            if s.closed {
                return Err(Error::msg(
                    "the async scope is complete (complete() was called); it takes no new tasks",
                ));
            }
            s.live += 1;
        }
        let member = Member(self.inner.clone());
        Ok(spawn(executor, async move {
            let _member = member;
            future.await
        }))
    }

    /// Tasks spawned and not ended yet.
    pub fn live(&self) -> usize {
        lock(&self.inner.state).live
    }

    /// Closes the scope to new tasks; the future resolves once every task has ended.
    pub fn complete(&self) -> Complete {
        lock(&self.inner.state).closed = true;
        Complete {
            inner: self.inner.clone(),
        }
    }
}

/// The future of [`AsyncScope::complete`].
#[derive(Debug)]
pub struct Complete {
    inner: Arc<ScopeInner>,
}

impl Future for Complete {
    type Output = ();

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        let mut s = lock(&self.inner.state);
        if s.live == 0 {
            return Poll::Ready(());
        }
        if !s.waiters.iter().any(|w| w.will_wake(cx.waker())) {
            s.waiters.push(cx.waker().clone());
        }
        Poll::Pending
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Executor, Task};
    use std::sync::atomic::AtomicUsize;
    use std::sync::mpsc;

    /// A one-thread executor with timers (a sleeping helper thread per timed task), which
    /// refuses once `limit` tasks were accepted and drops timed tasks when `drop_timed`.
    struct Worker {
        name: String,
        tx: Mutex<Option<mpsc::Sender<Task>>>,
        thread: Mutex<Option<std::thread::ThreadId>>,
        accepted: AtomicUsize,
        limit: usize,
        drop_timed: bool,
    }

    impl Worker {
        fn start(name: &str, limit: usize, drop_timed: bool) -> ExecutorRef {
            let (tx, rx) = mpsc::channel::<Task>();
            let worker = Arc::new(Worker {
                name: name.to_owned(),
                tx: Mutex::new(Some(tx)),
                thread: Mutex::new(None),
                accepted: AtomicUsize::new(0),
                limit,
                drop_timed,
            });
            let w = worker.clone();
            let handle = std::thread::spawn(move || {
                *w.thread.lock().unwrap() = Some(std::thread::current().id());
                let name = w.name.clone();
                drop(w);
                while let Ok(task) = rx.recv() {
                    task.run(&name);
                }
            });
            while worker.thread.lock().unwrap().is_none() {
                std::thread::yield_now();
            }
            drop(handle);
            ExecutorRef::leak(worker)
        }
    }

    impl Executor for Worker {
        fn type_name(&self) -> &str {
            "test_worker"
        }
        fn name(&self) -> &str {
            &self.name
        }
        fn thread_safe(&self) -> bool {
            true
        }
        fn is_in_current_executor(&self) -> bool {
            *self.thread.lock().unwrap() == Some(std::thread::current().id())
        }
        fn supports_timer_schedule(&self) -> bool {
            true
        }
        fn execute(&self, task: Task) -> Result<(), ExecuteError> {
            if self.accepted.fetch_add(1, Ordering::SeqCst) >= self.limit {
                return Err(ExecuteError::QueueFull);
            }
            let tx = self.tx.lock().unwrap().clone();
            tx.ok_or(ExecuteError::ShutDown)?
                .send(task)
                .map_err(|_| ExecuteError::ShutDown)
        }
        fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
            if self.drop_timed {
                drop(task); // accepted, then dropped: as a shutdown would
                return Ok(());
            }
            let tx = self
                .tx
                .lock()
                .unwrap()
                .clone()
                .ok_or(ExecuteError::ShutDown)?;
            std::thread::spawn(move || {
                if let Ok(d) = at.duration_since(SystemTime::now()) {
                    std::thread::sleep(d);
                }
                let _ = tx.send(task);
            });
            Ok(())
        }
        fn shutdown(&self) {
            self.tx.lock().unwrap().take();
        }
    }

    /// Runs `f` on a helper thread; fails the test if it takes over 10 s (a hang).
    fn within<R: Send + 'static>(f: impl FnOnce() -> R + Send + 'static) -> R {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(f());
        });
        rx.recv_timeout(Duration::from_secs(10))
            .expect("hung: no result within 10 s")
    }

    fn wait<T: Send + 'static>(h: JoinHandle<T>) -> Result<T, JoinError> {
        within(move || h.join())
    }

    fn worker(name: &str) -> ExecutorRef {
        Worker::start(name, usize::MAX, false)
    }

    #[test]
    fn spawn_runs_on_the_executor_and_returns_the_output() {
        let a = worker("a");
        let h = spawn(a, async move { a.is_in_current_executor() });
        assert_eq!(wait(h), Ok(true));
    }

    #[test]
    fn schedule_hops_between_executors() {
        let (a, b) = (worker("a"), worker("b"));
        let h = spawn(a, async move {
            let mut seen = vec![a.is_in_current_executor()];
            schedule(&b).await.unwrap();
            seen.push(b.is_in_current_executor() && !a.is_in_current_executor());
            schedule(&a).await.unwrap();
            seen.push(a.is_in_current_executor());
            seen
        });
        assert_eq!(wait(h), Ok(vec![true, true, true]));
    }

    #[test]
    fn schedule_after_sleeps_without_blocking_the_executor() {
        let a = worker("a");
        let start = std::time::Instant::now();
        let sleeper = spawn(a, async move {
            schedule_after(&a, Duration::from_millis(50)).await.unwrap();
            (start.elapsed(), a.is_in_current_executor())
        });
        // While it sleeps, the executor's only thread serves other tasks.
        let quick = spawn(a, async { 7 });
        assert_eq!(wait(quick), Ok(7));
        assert!(!sleeper.is_finished());
        let (slept, on_a) = wait(sleeper).unwrap();
        assert!(slept >= Duration::from_millis(50), "{slept:?}");
        assert!(on_a);
    }

    #[test]
    fn refused_wake_is_an_error_not_a_hang() {
        let a = worker("a");
        let full = Worker::start("full", 1, false); // takes one task, then refuses
        let h = spawn(a, async move {
            schedule(&full).await.unwrap(); // the 1st task: accepted
            schedule(&full).await.unwrap(); // the 2nd: refused → the task ends here
            unreachable!("the refused step never runs");
        });
        let err: JoinError = wait(h).unwrap_err();
        assert_eq!(
            err,
            JoinError::Refused {
                executor: "full".into(),
                source: ExecuteError::QueueFull
            }
        );
        // A refused first step too.
        let h = spawn(full, async { 1 });
        assert!(matches!(wait(h), Err(JoinError::Refused { .. })));
    }

    #[test]
    fn dropped_timed_step_is_an_error_not_a_hang() {
        let a = worker("a");
        let dropper = Worker::start("dropper", usize::MAX, true);
        let h = spawn(a, async move {
            schedule_after(&dropper, Duration::from_millis(1))
                .await
                .unwrap();
        });
        assert_eq!(
            wait(h),
            Err(JoinError::Dropped {
                executor: "dropper".into()
            })
        );
    }

    #[test]
    fn panicking_future_is_contained() {
        let a = worker("a");
        let h = spawn(a, async {
            panic!("kaputt");
        });
        match wait(h) {
            Err(JoinError::Panicked(m)) => assert!(m.contains("kaputt"), "{m}"),
            other => panic!("{other:?}"),
        }
        // The executor goes on.
        assert_eq!(wait(spawn(a, async { 1 })), Ok(1));
    }

    #[test]
    fn schedule_after_needs_timers() {
        let plain = crate::test_util::inline();
        let err =
            within(move || block_on(schedule_after(&plain, Duration::from_millis(1)))).unwrap_err();
        assert!(err.to_string().contains("does not support timer"), "{err}");
        // An inline executor drives a task to completion inside spawn.
        assert_eq!(wait(spawn(plain, async { 3 })), Ok(3));
    }

    #[test]
    fn block_on_waits_for_an_executor_without_moving() {
        let a = worker("a");
        within(move || {
            let here = std::thread::current().id();
            block_on(async {
                schedule(&a).await.unwrap();
                assert_eq!(std::thread::current().id(), here);
                schedule_after(&a, Duration::from_millis(5)).await.unwrap();
                assert!(!a.is_in_current_executor());
            })
        });
    }

    #[test]
    fn scope_complete_waits_for_every_task_and_closes() {
        let (a, b) = (worker("a"), worker("b"));
        let scope = AsyncScope::new();
        let done = Arc::new(AtomicUsize::new(0));
        for i in 0..20 {
            let done = done.clone();
            let exec = if i % 2 == 0 { a } else { b };
            scope
                .spawn(exec, async move {
                    schedule_after(&exec, Duration::from_millis(5))
                        .await
                        .unwrap();
                    done.fetch_add(1, Ordering::SeqCst);
                })
                .unwrap();
        }
        let complete = scope.complete();
        within(move || block_on(complete));
        assert_eq!(done.load(Ordering::SeqCst), 20);
        assert_eq!(scope.live(), 0);
        assert!(scope.spawn(a, async {}).is_err());
    }

    #[test]
    fn scope_completes_when_a_task_is_stopped_or_panics() {
        let a = worker("a");
        let dropper = Worker::start("dropper", usize::MAX, true);
        let scope = AsyncScope::new();
        scope
            .spawn(a, async move {
                let _ = schedule_after(&dropper, Duration::from_millis(1)).await;
            })
            .unwrap();
        scope.spawn(a, async { panic!("in scope") }).unwrap();
        let complete = scope.complete();
        within(move || block_on(complete));
        assert_eq!(scope.live(), 0);
    }
}
