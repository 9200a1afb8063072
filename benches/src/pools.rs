//! Everything a scenario submits work to: the standard executors, built the way
//! `aimrt_main` builds them, and the baselines they are compared with.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use aimrt_plugin_api::{ExecutorArgs, ExecutorRef, ThreadFactory};

type Job = Box<dyn FnOnce() + Send>;

/// A fixed pool of threads fed by one unbounded crossbeam channel of boxed closures: the
/// practical limit for "post a closure to N threads".
pub(crate) struct CrossbeamPool {
    tx: Option<crossbeam_channel::Sender<Job>>,
    threads: Vec<JoinHandle<()>>,
}

impl CrossbeamPool {
    pub(crate) fn new(n: usize) -> CrossbeamPool {
        let (tx, rx) = crossbeam_channel::unbounded::<Job>();
        let threads = (0..n)
            .map(|_| {
                let rx = rx.clone();
                std::thread::spawn(move || {
                    while let Ok(job) = rx.recv() {
                        job();
                    }
                })
            })
            .collect();
        CrossbeamPool {
            tx: Some(tx),
            threads,
        }
    }

    fn submit(&self, job: Job) {
        if let Some(tx) = &self.tx {
            let _ = tx.send(job);
        }
    }

    fn stop(mut self) {
        self.tx.take();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// A job queue with a "stop" flag, and the condvar its workers wait on.
type JobQueue = Arc<(Mutex<(VecDeque<Job>, bool)>, std::sync::Condvar)>;

/// How a [`CondvarPool`] worker takes work from the queue.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Take {
    /// One job at a time: the classic pool, and the wake-up latency baseline.
    One,
    /// AimRT's `simple_thread` design (`aimrt-executors.md` §3.4): one worker swaps the
    /// whole queue out and runs the batch outside the lock; with `n` workers each takes
    /// its share (`len / n`, at least one) so that all can work.
    Batch,
}

/// Threads sharing a `Mutex<VecDeque>` and a `Condvar`; `submit` pushes and notifies under
/// the lock, as AimRT does on every push.
pub(crate) struct CondvarPool {
    shared: JobQueue,
    threads: Vec<JoinHandle<()>>,
}

impl CondvarPool {
    pub(crate) fn new(n: usize, take: Take) -> CondvarPool {
        let shared: JobQueue = Arc::default();
        let threads = (0..n)
            .map(|_| {
                let s = shared.clone();
                std::thread::spawn(move || {
                    let mut batch = VecDeque::new();
                    loop {
                        {
                            let (m, cv) = &*s;
                            let mut q = m.lock().unwrap_or_else(|e| e.into_inner());
                            while q.0.is_empty() {
                                if q.1 {
                                    return;
                                }
                                q = cv.wait(q).unwrap_or_else(|e| e.into_inner());
                            }
                            let share = match take {
                                Take::One => 1,
                                Take::Batch if n == 1 => q.0.len(),
                                Take::Batch => (q.0.len() / n).max(1),
                            };
                            if share == q.0.len() {
                                std::mem::swap(&mut q.0, &mut batch);
                            } else {
                                batch.extend(q.0.drain(..share));
                            }
                        }
                        for job in batch.drain(..) {
                            job();
                        }
                    }
                })
            })
            .collect();
        CondvarPool { shared, threads }
    }

    fn submit(&self, job: Job) {
        let (m, cv) = &*self.shared;
        let mut q = m.lock().unwrap_or_else(|e| e.into_inner());
        q.0.push_back(job);
        cv.notify_one();
    }

    fn stop(self) {
        {
            let (m, cv) = &*self.shared;
            m.lock().unwrap_or_else(|e| e.into_inner()).1 = true;
            cv.notify_all();
        }
        for t in self.threads {
            let _ = t.join();
        }
    }
}

/// What a [`RingPool`]'s threads share.
struct RingShared {
    queue: crossbeam_queue::SegQueue<Job>,
    /// Workers asleep (or about to be) on `cv`.
    sleepers: AtomicUsize,
    lock: Mutex<bool>,
    cv: std::sync::Condvar,
}

/// The best raw multi-producer multi-consumer queue design for a pool (issue 21): a
/// lock-free unbounded queue (crossbeam's `SegQueue`, one CAS per push and per pop) that
/// workers pop one job at a time; an idle worker spins and yields briefly
/// (crossbeam's `Backoff`), then sleeps on a condvar. A producer pays a lock and a notify
/// only while a worker sleeps, never per job otherwise.
pub(crate) struct RingPool {
    shared: Arc<RingShared>,
    threads: Vec<JoinHandle<()>>,
}

impl RingPool {
    pub(crate) fn new(n: usize) -> RingPool {
        let shared = Arc::new(RingShared {
            queue: crossbeam_queue::SegQueue::new(),
            sleepers: AtomicUsize::new(0),
            lock: Mutex::new(false),
            cv: std::sync::Condvar::new(),
        });
        let threads = (0..n)
            .map(|_| {
                let s = shared.clone();
                std::thread::spawn(move || s.work())
            })
            .collect();
        RingPool { shared, threads }
    }

    fn submit(&self, job: Job) {
        let s = &*self.shared;
        s.queue.push(job);
        // Pairs with the fence in `work`: either the sleeper sees the job, or this sees
        // the sleeper.
        std::sync::atomic::fence(Ordering::SeqCst);
        if s.sleepers.load(Ordering::Relaxed) > 0 {
            let _g = s.lock.lock().unwrap_or_else(|e| e.into_inner());
            s.cv.notify_one();
        }
    }

    fn stop(self) {
        *self.shared.lock.lock().unwrap_or_else(|e| e.into_inner()) = true;
        self.shared.cv.notify_all();
        for t in self.threads {
            let _ = t.join();
        }
    }
}

impl RingShared {
    fn work(&self) {
        loop {
            if let Some(job) = self.queue.pop() {
                job();
                continue;
            }
            let backoff = crossbeam_utils::Backoff::new();
            let mut found = None;
            while !backoff.is_completed() {
                backoff.snooze();
                found = self.queue.pop();
                if found.is_some() {
                    break;
                }
            }
            if let Some(job) = found {
                job();
                continue;
            }
            let mut stopped = self.lock.lock().unwrap_or_else(|e| e.into_inner());
            self.sleepers.fetch_add(1, Ordering::Relaxed);
            std::sync::atomic::fence(Ordering::SeqCst);
            let job = loop {
                if let Some(job) = self.queue.pop() {
                    break Some(job);
                }
                if *stopped {
                    break None;
                }
                stopped = self.cv.wait(stopped).unwrap_or_else(|e| e.into_inner());
            };
            self.sleepers.fetch_sub(1, Ordering::Relaxed);
            drop(stopped);
            match job {
                Some(job) => job(),
                None => return,
            }
        }
    }
}

/// The strand a user would write first: a mutex-protected queue drained by one job at a
/// time on the crossbeam pool.
pub(crate) struct NaiveStrand {
    pool: CrossbeamPool,
    state: Arc<StrandState>,
}

struct StrandState {
    queue: Mutex<(VecDeque<Job>, bool)>,
}

impl StrandState {
    fn drain(self: Arc<Self>) {
        loop {
            let job = {
                let mut q = self.queue.lock().unwrap_or_else(|e| e.into_inner());
                match q.0.pop_front() {
                    Some(j) => j,
                    None => {
                        q.1 = false;
                        return;
                    }
                }
            };
            job();
        }
    }
}

impl NaiveStrand {
    fn submit(&self, job: Job) {
        let start = {
            let mut q = self.state.queue.lock().unwrap_or_else(|e| e.into_inner());
            q.0.push_back(job);
            !std::mem::replace(&mut q.1, true)
        };
        if start {
            let s = self.state.clone();
            self.pool.submit(Box::new(move || s.drain()));
        }
    }
}

/// One thing scenarios submit closures to.
pub(crate) enum Target {
    /// A standard executor, and every executor to shut down afterwards.
    Executor(ExecutorRef, Vec<ExecutorRef>),
    Crossbeam(CrossbeamPool),
    Condvar(CondvarPool),
    Ring(RingPool),
    Tokio(tokio::runtime::Runtime),
    Rayon(rayon::ThreadPool),
    NaiveStrand(NaiveStrand),
}

/// Tasks the executors under test refused (must stay 0).
pub(crate) static REFUSED: AtomicU64 = AtomicU64::new(0);

impl Target {
    #[inline]
    pub(crate) fn submit<F: FnOnce() + Send + 'static>(&self, f: F) {
        match self {
            Target::Executor(e, _) => {
                if e.execute(f).is_err() {
                    REFUSED.fetch_add(1, Ordering::Relaxed);
                }
            }
            Target::Crossbeam(p) => p.submit(Box::new(f)),
            Target::Condvar(p) => p.submit(Box::new(f)),
            Target::Ring(p) => p.submit(Box::new(f)),
            Target::Tokio(rt) => {
                rt.spawn(async move { f() });
            }
            Target::Rayon(p) => p.spawn(f),
            Target::NaiveStrand(s) => s.submit(Box::new(f)),
        }
    }

    /// The executor, if this is one.
    pub(crate) fn executor(&self) -> Option<ExecutorRef> {
        match self {
            Target::Executor(e, _) => Some(*e),
            _ => None,
        }
    }

    pub(crate) fn stop(self) {
        match self {
            Target::Executor(_, owned) => {
                for e in owned {
                    let stats = e.stats();
                    REFUSED.fetch_add(stats.refused, Ordering::Relaxed);
                    e.raw().shutdown();
                }
            }
            Target::Crossbeam(p) => p.stop(),
            Target::Condvar(p) => p.stop(),
            Target::Ring(p) => p.stop(),
            Target::Tokio(rt) => rt.shutdown_background(),
            Target::Rayon(p) => drop(p),
            Target::NaiveStrand(s) => s.pool.stop(),
        }
    }
}

/// A standard executor of `ty` with `options` (JSON), and `queue_threshold` at its maximum.
pub(crate) fn executor(
    ty: &str,
    name: &str,
    options: &str,
    bound: Vec<Option<ExecutorRef>>,
) -> ExecutorRef {
    aimrt_std_executors::create_executor(
        ty,
        ExecutorArgs {
            name,
            options_json: options,
            location: "bench",
            bound,
            threads: ThreadFactory::plain(),
        },
    )
    .unwrap_or_else(|e| panic!("cannot build {ty}: {e}"))
}

pub(crate) const MAX_Q: &str = r#""queue_threshold": 4294967295"#;

/// A named way to build a fresh target.
#[derive(Clone, Copy)]
pub(crate) struct Variant {
    pub(crate) name: &'static str,
    /// Workers (1 for a strand: it serialises).
    pub(crate) workers: usize,
    pub(crate) make: fn() -> Target,
}

pub(crate) fn simple_thread() -> Target {
    let e = executor("simple_thread", "simple", &format!("{{{MAX_Q}}}"), vec![]);
    Target::Executor(e, vec![e])
}
pub(crate) fn asio_thread1() -> Target {
    let e = executor("asio_thread", "asio1", r#"{"thread_num": 1}"#, vec![]);
    Target::Executor(e, vec![e])
}
pub(crate) fn asio_thread2() -> Target {
    let e = executor("asio_thread", "asio2", r#"{"thread_num": 2}"#, vec![]);
    Target::Executor(e, vec![e])
}
pub(crate) fn tbb_thread2() -> Target {
    let e = executor(
        "tbb_thread",
        "tbb2",
        &format!(r#"{{"thread_num": 2, {MAX_Q}}}"#),
        vec![],
    );
    Target::Executor(e, vec![e])
}
pub(crate) fn asio_strand() -> Target {
    let pool = executor("asio_thread", "pool", r#"{"thread_num": 2}"#, vec![]);
    let s = executor("asio_strand", "strand", "{}", vec![Some(pool)]);
    Target::Executor(s, vec![s, pool])
}
/// An unbound wheel: timed tasks run on the wheel's own thread.
pub(crate) fn time_wheel(dt_us: u32) -> Target {
    let w = executor(
        "time_wheel",
        "wheel",
        &format!(r#"{{"dt_us": {dt_us}}}"#),
        vec![],
    );
    Target::Executor(w, vec![w])
}
pub(crate) fn crossbeam1() -> Target {
    Target::Crossbeam(CrossbeamPool::new(1))
}
pub(crate) fn crossbeam2() -> Target {
    Target::Crossbeam(CrossbeamPool::new(2))
}
pub(crate) fn ring1() -> Target {
    Target::Ring(RingPool::new(1))
}
pub(crate) fn ring2() -> Target {
    Target::Ring(RingPool::new(2))
}
pub(crate) fn condvar1() -> Target {
    Target::Condvar(CondvarPool::new(1, Take::One))
}
/// AimRT's `simple_thread` design with one worker.
pub(crate) fn swap_queue1() -> Target {
    Target::Condvar(CondvarPool::new(1, Take::Batch))
}
/// AimRT's `simple_thread` design with two workers on one queue.
pub(crate) fn swap_queue2() -> Target {
    Target::Condvar(CondvarPool::new(2, Take::Batch))
}
pub(crate) fn time_wheel_100() -> Target {
    time_wheel(100)
}
pub(crate) fn time_wheel_1000() -> Target {
    time_wheel(1000)
}
pub(crate) fn tokio2() -> Target {
    Target::Tokio(
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_time()
            .build()
            .expect("tokio runtime"),
    )
}
pub(crate) fn rayon2() -> Target {
    Target::Rayon(
        rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .expect("rayon pool"),
    )
}
pub(crate) fn naive_strand() -> Target {
    Target::NaiveStrand(NaiveStrand {
        pool: CrossbeamPool::new(2),
        state: Arc::new(StrandState {
            queue: Mutex::new((VecDeque::new(), false)),
        }),
    })
}

/// Spinning threads at `SCHED_IDLE`, one per CPU: they keep vCPUs out of halt and yield to
/// any real work.
pub(crate) struct Burners {
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
}

impl Burners {
    pub(crate) fn start(idle_priority: bool, count: usize) -> Burners {
        let stop = Arc::new(AtomicBool::new(false));
        let threads = (0..count)
            .map(|_| {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    if idle_priority {
                        use thread_priority::unix::{
                            set_thread_priority_and_policy, thread_native_id,
                            NormalThreadSchedulePolicy, ThreadSchedulePolicy,
                        };
                        let _ = set_thread_priority_and_policy(
                            thread_native_id(),
                            thread_priority::ThreadPriority::Min,
                            ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Idle),
                        );
                    }
                    while !stop.load(Ordering::Relaxed) {
                        std::hint::spin_loop();
                    }
                })
            })
            .collect();
        Burners { stop, threads }
    }

    pub(crate) fn stop(self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads {
            let _ = t.join();
        }
    }
}
