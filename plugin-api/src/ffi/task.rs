//! The task that crosses into an executor: a closure in a `#[repr(C)]` value.
//!
//! Layout: a `&'static` ops table, the creating module's tag, and an inline buffer of
//! four words. A closure that fits (size ≤ 32 bytes, alignment ≤ a word) is stored
//! inline, without allocating; a larger one is boxed and the box pointer stored inline.
//! The value is moved bitwise (Rust closures are always movable), run or dropped exactly
//! once, and always by code of the library that created it: the ops table points there.
//! Running returns whether the closure panicked; the panic is contained and logged on the
//! creating side, attributed to the creating module and naming the executor.

use std::ffi::c_void;
use std::mem::{ManuallyDrop, MaybeUninit};
use std::ptr;

use super::context;
use super::{contain, Header, StrView};

/// Words in the inline closure buffer.
pub const INLINE_WORDS: usize = 4;

/// The raw, `#[repr(C)]` form of a [`Task`] as it crosses the ABI.
#[repr(C)]
pub struct RawTask {
    /// The operations for this closure type, in the creating library.
    pub ops: *const TaskOps,
    /// Opaque tag of the creating module (meaningful only to the creating library).
    pub tag: *const c_void,
    /// The closure itself, or a pointer to its box.
    pub buf: [MaybeUninit<usize>; INLINE_WORDS],
}

/// Operations of one closure type. Both entries consume the task's contents.
#[repr(C)]
pub struct TaskOps {
    /// Size and minor of this table.
    pub header: Header,
    /// Bit 0 ([`TaskOps::FLAG_INLINE`]): the closure is stored inline.
    pub flags: u32,
    /// Runs the closure; returns 0 when it returned, 1 when it panicked.
    pub run: unsafe extern "C" fn(task: *mut RawTask, executor_name: StrView) -> u32,
    /// Drops the closure without running it.
    pub drop: unsafe extern "C" fn(task: *mut RawTask),
}

impl TaskOps {
    /// The closure is stored in the task's buffer, not boxed.
    pub const FLAG_INLINE: u32 = 1;
}

/// What happened when a task ran.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TaskOutcome {
    /// The closure returned.
    Completed,
    /// The closure panicked; the panic was contained and logged by the creating library.
    Panicked,
}

/// A unit of work for an executor: a `FnOnce() + Send + 'static` closure in a form that
/// crosses library boundaries.
///
/// It is run ([`Task::run`]) or dropped exactly once. Small closures (up to four words)
/// are stored inline and do not allocate.
///
/// ```
/// use aimrt_plugin_api::{Task, TaskOutcome};
/// let task = Task::new(|| println!("hello"));
/// assert!(task.is_inline());
/// assert_eq!(task.run("doc"), TaskOutcome::Completed);
/// ```
pub struct Task {
    raw: RawTask,
}

// SAFETY: a task is only ever built from a `Send` closure (`Task::new`) or adopted from a
// raw task whose creator guaranteed the same (`Task::from_raw`'s contract).
unsafe impl Send for Task {}

struct Ops<F>(F);

impl<F: FnOnce() + Send + 'static> Ops<F> {
    const INLINE: bool = size_of::<F>() <= INLINE_WORDS * size_of::<usize>()
        && align_of::<F>() <= align_of::<usize>();

    const OPS: TaskOps = TaskOps {
        header: Header::of::<TaskOps>(),
        flags: if Self::INLINE {
            TaskOps::FLAG_INLINE
        } else {
            0
        },
        run: Self::run,
        drop: Self::drop,
    };

    /// Moves the closure out of the task's buffer.
    ///
    /// # Safety
    /// `task` points to a live task built by `Task::new::<F>` whose contents were not
    /// taken yet; afterwards they count as taken.
    unsafe fn take(task: *mut RawTask) -> F {
        // SAFETY: per the contract, `buf` holds either an `F` (inline) or a `*mut F` from
        // `Box::into_raw`, written by `Task::new::<F>` with matching `INLINE`.
        unsafe {
            let buf = ptr::addr_of_mut!((*task).buf).cast::<u8>();
            if Self::INLINE {
                ptr::read(buf.cast::<F>())
            } else {
                *Box::from_raw(ptr::read(buf.cast::<*mut F>()))
            }
        }
    }

    unsafe extern "C" fn run(task: *mut RawTask, executor_name: StrView) -> u32 {
        // SAFETY: the executor calls `run` once on a task it owns (ABI contract).
        let f = unsafe { Self::take(task) };
        // SAFETY: as above, the task is live for this call.
        let tag = unsafe { (*task).tag };
        let outcome = context::with_module_tag(tag, || contain(f));
        match outcome {
            Ok(()) => 0,
            Err(message) => {
                // SAFETY: the executor passes a view of its name valid for this call.
                let executor = unsafe { executor_name.to_string_lossy() };
                context::with_module_tag(tag, || {
                    crate::panic::log_panic(
                        &format!("task on executor '{executor}'"),
                        &executor,
                        &message,
                    );
                });
                1
            }
        }
    }

    unsafe extern "C" fn drop(task: *mut RawTask) {
        // SAFETY: the owner calls `drop` once on a task it owns instead of `run`.
        let f = unsafe { Self::take(task) };
        // SAFETY: as above.
        let tag = unsafe { (*task).tag };
        // Captures may log or panic while dropping: attribute and contain that too.
        let _ = context::with_module_tag(tag, || contain(move || std::mem::drop(f)));
    }
}

impl Task {
    /// Wraps a closure. It remembers the current module so that its logs are attributed
    /// to that module wherever it runs.
    pub fn new<F: FnOnce() + Send + 'static>(f: F) -> Task {
        let mut raw = RawTask {
            ops: &Ops::<F>::OPS,
            tag: context::current_module_tag(),
            buf: [MaybeUninit::uninit(); INLINE_WORDS],
        };
        let buf = raw.buf.as_mut_ptr().cast::<u8>();
        if Ops::<F>::INLINE {
            // SAFETY: `INLINE` guarantees that `F` fits and that the word-aligned buffer is
            // aligned enough for it.
            unsafe { ptr::write(buf.cast::<F>(), f) };
        } else {
            let boxed = Box::into_raw(Box::new(f));
            // SAFETY: a pointer fits in the first word of the buffer.
            unsafe { ptr::write(buf.cast::<*mut F>(), boxed) };
        }
        Task { raw }
    }

    /// Whether the closure is stored inline (no allocation).
    pub fn is_inline(&self) -> bool {
        // SAFETY: `ops` points to a `'static` table (set by `new` or adopted via `from_raw`).
        unsafe { (*self.raw.ops).flags & TaskOps::FLAG_INLINE != 0 }
    }

    /// Runs the closure on the current thread, consuming the task. `executor_name` is
    /// used if the closure panics (the panic is contained and logged).
    pub fn run(self, executor_name: &str) -> TaskOutcome {
        let mut this = ManuallyDrop::new(self);
        // SAFETY: `ops` was set by `Task::new` or adopted via `from_raw`; the task is owned
        // here and not used again (ManuallyDrop).
        let code = unsafe { ((*this.raw.ops).run)(&mut this.raw, StrView::new(executor_name)) };
        if code == 0 {
            TaskOutcome::Completed
        } else {
            TaskOutcome::Panicked
        }
    }

    /// Hands the task over to the ABI; the receiver must run or drop it exactly once.
    pub fn into_raw(self) -> RawTask {
        let this = ManuallyDrop::new(self);
        // SAFETY: bitwise move out of a value that will never be dropped.
        unsafe { ptr::read(&this.raw) }
    }

    /// Adopts a task received through the ABI.
    ///
    /// # Safety
    /// `raw` must come from [`Task::into_raw`] (in any library) and not have been run,
    /// dropped or adopted before.
    pub unsafe fn from_raw(raw: RawTask) -> Task {
        Task { raw }
    }
}

impl Drop for Task {
    fn drop(&mut self) {
        // SAFETY: a live, owned task; `drop` consumes its contents exactly once.
        unsafe { ((*self.raw.ops).drop)(&mut self.raw) }
    }
}

impl std::fmt::Debug for Task {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Task").finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    struct CountDrop(Arc<AtomicUsize>);
    impl Drop for CountDrop {
        fn drop(&mut self) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
    }

    #[test]
    fn raw_task_layout_is_six_words() {
        assert_eq!(
            size_of::<RawTask>(),
            (2 + INLINE_WORDS) * size_of::<usize>()
        );
        assert_eq!(align_of::<RawTask>(), align_of::<usize>());
    }

    #[test]
    fn small_closure_is_inline_and_runs_once() {
        let hits = Arc::new(AtomicUsize::new(0));
        let h = hits.clone();
        let task = Task::new(move || {
            h.fetch_add(1, Ordering::SeqCst);
        });
        assert!(task.is_inline());
        assert_eq!(task.run("t"), TaskOutcome::Completed);
        assert_eq!(hits.load(Ordering::SeqCst), 1);
        assert_eq!(
            Arc::strong_count(&hits),
            1,
            "captures dropped after the run"
        );
    }

    #[test]
    fn large_closure_is_boxed_and_runs_once() {
        let hits = Arc::new(AtomicUsize::new(0));
        let h = hits.clone();
        let big = [7u64; 16];
        let task = Task::new(move || {
            h.fetch_add(big.iter().sum::<u64>() as usize, Ordering::SeqCst);
        });
        assert!(!task.is_inline());
        assert_eq!(task.run("t"), TaskOutcome::Completed);
        assert_eq!(hits.load(Ordering::SeqCst), 7 * 16);
    }

    #[test]
    fn over_aligned_closure_is_boxed() {
        #[repr(align(32))]
        #[derive(Clone, Copy)]
        struct Wide(u8);
        let w = Wide(3);
        let task = Task::new(move || {
            let whole = w; // capture the whole over-aligned value, not just its field
            assert_eq!(whole.0, 3);
        });
        assert!(!task.is_inline());
        assert_eq!(task.run("t"), TaskOutcome::Completed);
    }

    #[test]
    fn dropped_task_drops_captures_without_running() {
        for size in [1usize, 64] {
            let drops = Arc::new(AtomicUsize::new(0));
            let ran = Arc::new(AtomicUsize::new(0));
            let guard = CountDrop(drops.clone());
            let r = ran.clone();
            let pad = vec![0u8; size];
            let task = Task::new(move || {
                let _keep = (&guard, &pad);
                r.fetch_add(1, Ordering::SeqCst);
            });
            drop(task);
            assert_eq!(drops.load(Ordering::SeqCst), 1);
            assert_eq!(ran.load(Ordering::SeqCst), 0);
        }
    }

    #[test]
    fn raw_round_trip_keeps_the_closure() {
        let hits = Arc::new(AtomicUsize::new(0));
        let h = hits.clone();
        let raw = Task::new(move || {
            h.fetch_add(1, Ordering::SeqCst);
        })
        .into_raw();
        // SAFETY: `raw` comes from `into_raw` and is adopted once.
        let task = unsafe { Task::from_raw(raw) };
        assert_eq!(task.run("t"), TaskOutcome::Completed);
        assert_eq!(hits.load(Ordering::SeqCst), 1);
    }

    #[test]
    fn panic_is_reported_and_captures_dropped() {
        let drops = Arc::new(AtomicUsize::new(0));
        let guard = CountDrop(drops.clone());
        let task = Task::new(move || {
            let _g = &guard;
            panic!("boom");
        });
        assert_eq!(task.run("t"), TaskOutcome::Panicked);
        assert_eq!(drops.load(Ordering::SeqCst), 1);
    }
}
