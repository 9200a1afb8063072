//! The executor vtable, its exporter (any [`Executor`] → [`RawExecutor`]) and importer.

use std::ffi::c_void;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use super::task::RawTask;
use super::{contain, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::{ExecuteError, Executor, Task};

/// Work accounting of one executor.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExecutorStats {
    /// Size and minor of this struct.
    pub header: Header,
    /// Tasks accepted (`execute` and `execute_at` that returned OK).
    pub submitted: u64,
    /// Tasks that ran (completed or panicked).
    pub run: u64,
    /// Tasks refused (queue full, shut down, no timer support) and dropped.
    pub refused: u64,
    /// Tasks that panicked.
    pub panicked: u64,
    /// Tasks queued or running now.
    pub queue_depth: u64,
    /// Timed tasks dropped at shutdown because their time had not come.
    pub dropped_at_shutdown: u64,
}

impl Default for ExecutorStats {
    fn default() -> Self {
        ExecutorStats {
            header: Header::of::<ExecutorStats>(),
            submitted: 0,
            run: 0,
            refused: 0,
            panicked: 0,
            queue_depth: 0,
            dropped_at_shutdown: 0,
        }
    }
}

/// Executor operations, in this order (append-only).
#[repr(C)]
pub struct ExecutorVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The executor type, e.g. `simple_thread`; valid until `destroy`.
    pub type_name: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// The executor name from the config; valid until `destroy`.
    pub name: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// No two of its tasks ever run at the same time.
    pub thread_safe: unsafe extern "C" fn(obj: *const c_void) -> bool,
    /// The calling thread is running one of its tasks.
    pub is_in_current_executor: unsafe extern "C" fn(obj: *const c_void) -> bool,
    /// `execute_at` is supported.
    pub supports_timer_schedule: unsafe extern "C" fn(obj: *const c_void) -> bool,
    /// Takes the task (always): queues it, or drops it and returns why.
    pub execute: unsafe extern "C" fn(obj: *const c_void, task: RawTask) -> Status,
    /// The executor's clock, nanoseconds since 1970-01-01 UTC.
    pub now: unsafe extern "C" fn(obj: *const c_void) -> u64,
    /// Takes the task (always): runs it at `at_ns` on the executor's clock, or drops it.
    pub execute_at: unsafe extern "C" fn(obj: *const c_void, at_ns: u64, task: RawTask) -> Status,
    /// Called once by the runtime after every executor is built.
    pub start: unsafe extern "C" fn(obj: *const c_void, err: ErrorSink) -> Status,
    /// Stops taking work, runs what is queued, joins its threads. Idempotent.
    pub shutdown: unsafe extern "C" fn(obj: *const c_void),
    /// Frees the executor; no other entry is called afterwards.
    pub destroy: unsafe extern "C" fn(obj: *const c_void),
    /// Writes the work accounting.
    pub stats: unsafe extern "C" fn(obj: *const c_void, out: *mut ExecutorStats),
}

/// An executor object and its operations. Copyable handle; the runtime owns the object
/// and destroys it at the end of shutdown, after every module has shut down.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawExecutor {
    /// The operations.
    pub vtable: *const ExecutorVtable,
    /// The executor.
    pub obj: *const c_void,
}

// SAFETY: executors are thread-safe by contract (the exporter requires `Executor: Send +
// Sync`; foreign implementations must honour the same rule).
unsafe impl Send for RawExecutor {}
// SAFETY: see `Send`.
unsafe impl Sync for RawExecutor {}

/// Arguments of an executor type's factory.
#[repr(C)]
pub struct ExecutorCreateArgs {
    /// Size and minor of this struct.
    pub header: Header,
    /// The executor name from the config.
    pub name: StrView,
    /// The executor's `options` node as JSON text (`null` when absent).
    pub options_json: StrView,
    /// Where the options are, `file:line:col`, for error messages.
    pub location: StrView,
    /// The executors named by the type's bind keys, in bind-key order (absent keys are
    /// null executors).
    pub bound: *const RawExecutor,
    /// Length of `bound`.
    pub bound_len: usize,
    /// The runtime's thread factory.
    pub threads: super::RawThreadFactory,
    /// (1.8) Where the factory hands back its options as it read them, defaults filled
    /// in, as JSON, at most once (AimRT's `options_node = options_`): `--dump_cfg_file`
    /// writes them in place of what the config wrote.
    pub options_out: ErrorSink,
}

impl ExecutorCreateArgs {
    /// The end of [`options_out`](Self::options_out): a host of ABI 1.7 or older passes
    /// shorter arguments.
    pub(crate) const OPTIONS_OUT_END: usize =
        std::mem::offset_of!(ExecutorCreateArgs, options_out) + size_of::<ErrorSink>();
}

pub(crate) fn system_time_to_ns(t: SystemTime) -> u64 {
    match t.duration_since(UNIX_EPOCH) {
        Ok(d) => u64::try_from(d.as_nanos()).unwrap_or(u64::MAX),
        Err(_) => 0,
    }
}

pub(crate) fn ns_to_system_time(ns: u64) -> SystemTime {
    UNIX_EPOCH + Duration::from_nanos(ns)
}

struct Export<E>(E);

impl<E: Executor> Export<E> {
    const VTABLE: ExecutorVtable = ExecutorVtable {
        header: Header::of::<ExecutorVtable>(),
        type_name: Self::type_name,
        name: Self::name,
        thread_safe: Self::thread_safe,
        is_in_current_executor: Self::is_in_current_executor,
        supports_timer_schedule: Self::supports_timer_schedule,
        execute: Self::execute,
        now: Self::now,
        execute_at: Self::execute_at,
        start: Self::start,
        shutdown: Self::shutdown,
        destroy: Self::destroy,
        stats: Self::stats,
    };

    /// # Safety
    /// `obj` is the pointer of a live `RawExecutor::new::<E>` (not destroyed).
    unsafe fn get<'a>(obj: *const c_void) -> &'a E {
        // SAFETY: per the contract, `obj` came from `Arc::into_raw` of an `Arc<E>` that is
        // still alive.
        unsafe { &*obj.cast::<E>() }
    }

    unsafe extern "C" fn type_name(obj: *const c_void) -> StrView {
        // SAFETY: the caller holds a live handle (vtable contract).
        let e = unsafe { Self::get(obj) };
        contain(|| StrView::new(e.type_name())).unwrap_or(StrView::EMPTY)
    }

    unsafe extern "C" fn name(obj: *const c_void) -> StrView {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        contain(|| StrView::new(e.name())).unwrap_or(StrView::EMPTY)
    }

    unsafe extern "C" fn thread_safe(obj: *const c_void) -> bool {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        contain(|| e.thread_safe()).unwrap_or(false)
    }

    unsafe extern "C" fn is_in_current_executor(obj: *const c_void) -> bool {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        contain(|| e.is_in_current_executor()).unwrap_or(false)
    }

    unsafe extern "C" fn supports_timer_schedule(obj: *const c_void) -> bool {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        contain(|| e.supports_timer_schedule()).unwrap_or(false)
    }

    unsafe extern "C" fn execute(obj: *const c_void, task: RawTask) -> Status {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        // SAFETY: the caller hands over a task from `Task::into_raw`, owned by us now.
        let task = unsafe { Task::from_raw(task) };
        contain(|| status_of(e.execute(task))).unwrap_or(Status::FAILED)
    }

    unsafe extern "C" fn now(obj: *const c_void) -> u64 {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        contain(|| system_time_to_ns(e.now())).unwrap_or(0)
    }

    unsafe extern "C" fn execute_at(obj: *const c_void, at_ns: u64, task: RawTask) -> Status {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        // SAFETY: as in `execute`.
        let task = unsafe { Task::from_raw(task) };
        contain(|| status_of(e.execute_at(ns_to_system_time(at_ns), task)))
            .unwrap_or(Status::FAILED)
    }

    unsafe extern "C" fn start(obj: *const c_void, err: ErrorSink) -> Status {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        match contain(|| e.start()) {
            Ok(Ok(())) => Status::OK,
            Ok(Err(message)) => {
                err.report(&message.to_string());
                Status::FAILED
            }
            Err(panic) => {
                err.report(&format!("panicked in start: {panic}"));
                Status::FAILED
            }
        }
    }

    unsafe extern "C" fn shutdown(obj: *const c_void) {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        if let Err(panic) = contain(|| e.shutdown()) {
            tracing::error!(target: "aimrt", "executor '{}' panicked in shutdown: {panic}", e.name());
        }
    }

    unsafe extern "C" fn destroy(obj: *const c_void) {
        // SAFETY: `destroy` is called once, last; `obj` came from `Arc::into_raw`.
        let arc = unsafe { Arc::from_raw(obj.cast::<E>()) };
        let _ = contain(move || drop(arc));
    }

    unsafe extern "C" fn stats(obj: *const c_void, out: *mut ExecutorStats) {
        // SAFETY: as above.
        let e = unsafe { Self::get(obj) };
        if let Ok(stats) = contain(|| e.stats()) {
            // SAFETY: the caller passes a writable `ExecutorStats` whose header says how
            // many bytes it has; we write only when it is at least as large as ours.
            unsafe {
                if (*out).header.has(size_of::<ExecutorStats>()) {
                    *out = ExecutorStats {
                        header: (*out).header,
                        ..stats
                    };
                }
            }
        }
    }
}

fn status_of(r: Result<(), ExecuteError>) -> Status {
    match r {
        Ok(()) => Status::OK,
        Err(e) => e.status(),
    }
}

impl RawExecutor {
    /// Exports an executor: the handle holds a reference to it, given back only by
    /// `destroy` (which the runtime never calls: its executors live for the process).
    pub fn new<E: Executor>(executor: Arc<E>) -> RawExecutor {
        RawExecutor {
            vtable: &Export::<E>::VTABLE,
            obj: Arc::into_raw(executor).cast(),
        }
    }

    /// A null handle (no executor), e.g. for an absent bind key.
    pub const fn null() -> RawExecutor {
        RawExecutor {
            vtable: std::ptr::null(),
            obj: std::ptr::null(),
        }
    }

    /// Whether this is the null handle.
    pub fn is_null(&self) -> bool {
        self.vtable.is_null()
    }

    fn vt(&self) -> &ExecutorVtable {
        assert!(!self.is_null(), "null executor handle");
        // SAFETY: non-null vtables of executor handles point to `'static` tables (ours, or
        // a loaded library's, and libraries are never unloaded).
        unsafe { &*self.vtable }
    }

    /// The executor type, e.g. `asio_thread`.
    pub fn type_name(&self) -> &str {
        // SAFETY: the handle is live (the runtime never frees its executors; a handle
        // made otherwise is live by `ExecutorRef::from_raw`'s contract); the returned view
        // lives as long as the executor.
        unsafe {
            (self.vt().type_name)(self.obj)
                .as_str()
                .unwrap_or("<invalid utf-8>")
        }
    }

    /// The executor name from the config.
    pub fn name(&self) -> &str {
        // SAFETY: as in `type_name`.
        unsafe {
            (self.vt().name)(self.obj)
                .as_str()
                .unwrap_or("<invalid utf-8>")
        }
    }

    /// No two of its tasks ever run at the same time.
    pub fn thread_safe(&self) -> bool {
        // SAFETY: live handle, see `type_name`.
        unsafe { (self.vt().thread_safe)(self.obj) }
    }

    /// The calling thread runs one of its tasks.
    pub fn is_in_current_executor(&self) -> bool {
        // SAFETY: live handle, see `type_name`.
        unsafe { (self.vt().is_in_current_executor)(self.obj) }
    }

    /// `execute_at` is supported.
    pub fn supports_timer_schedule(&self) -> bool {
        // SAFETY: live handle, see `type_name`.
        unsafe { (self.vt().supports_timer_schedule)(self.obj) }
    }

    /// Queues `task` (host use; a refused task is dropped by the callee).
    pub fn execute(&self, task: Task) -> Status {
        // SAFETY: live handle; the task is handed over and the callee owns it.
        unsafe { (self.vt().execute)(self.obj, task.into_raw()) }
    }

    pub(crate) fn now(&self) -> SystemTime {
        // SAFETY: live handle, see `type_name`.
        ns_to_system_time(unsafe { (self.vt().now)(self.obj) })
    }

    pub(crate) fn execute_at(&self, at: SystemTime, task: Task) -> Status {
        // SAFETY: live handle; the task is handed over.
        unsafe { (self.vt().execute_at)(self.obj, system_time_to_ns(at), task.into_raw()) }
    }

    /// Starts the executor (runtime use).
    pub fn start(&self) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live handle; the sink outlives the call.
        let status = unsafe { (self.vt().start)(self.obj, slot.sink()) };
        if status.is_ok() {
            Ok(())
        } else {
            Err(slot.take(|| format!("start returned {status}")))
        }
    }

    /// Shuts the executor down (runtime use): stop taking work, drain, join.
    pub fn shutdown(&self) {
        // SAFETY: live handle.
        unsafe { (self.vt().shutdown)(self.obj) }
    }

    /// Frees the executor. The runtime never calls it (a copy of an `ExecutorRef` may
    /// outlive the runtime); a host of its own that knows no copy remains may.
    ///
    /// # Safety
    /// No copy of this handle may be used afterwards.
    pub unsafe fn destroy(self) {
        // SAFETY: the caller guarantees this is the last use of any copy.
        unsafe { (self.vt().destroy)(self.obj) }
    }

    /// The executor's work accounting.
    pub fn stats(&self) -> ExecutorStats {
        let mut out = ExecutorStats::default();
        // SAFETY: live handle; `out` is a writable stats struct with our header.
        unsafe { (self.vt().stats)(self.obj, &mut out) };
        out
    }
}

impl std::fmt::Debug for RawExecutor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.is_null() {
            f.write_str("RawExecutor(null)")
        } else {
            f.debug_struct("RawExecutor")
                .field("name", &self.name())
                .field("type", &self.type_name())
                .finish()
        }
    }
}
