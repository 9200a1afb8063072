//! `simple_thread`: one thread, strict FIFO, AimRT's `queue_threshold`.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::{JoinHandle, ThreadId};
use std::time::{Duration, Instant};

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorArgs, ExecutorStats, Task, TaskOutcome,
};
use serde::Deserialize;

/// The options of AimRT's `simple_thread`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct SimpleThreadOptions {
    #[serde(default)]
    thread_sched_policy: String,
    #[serde(default)]
    thread_bind_cpu: Vec<u32>,
    #[serde(default = "default_threshold")]
    queue_threshold: u32,
    #[serde(default = "default_interval")]
    threshold_alarm_interval_ms: i32,
}

fn default_threshold() -> u32 {
    10_000
}
fn default_interval() -> i32 {
    1000
}

#[derive(Debug)]
struct State {
    queue: VecDeque<Task>,
    /// Queued plus running (AimRT counts the running task against the threshold).
    in_flight: u64,
    accepting: bool,
    stop: bool,
}

#[derive(Debug)]
struct Shared {
    name: String,
    threshold: u64,
    alarm_interval: Option<Duration>,
    state: Mutex<State>,
    ready: Condvar,
    worker: Mutex<Option<ThreadId>>,
    last_alarm: Mutex<Option<Instant>>,
    submitted: AtomicU64,
    run: AtomicU64,
    refused: AtomicU64,
    panicked: AtomicU64,
}

/// One worker thread serving a FIFO queue. `thread_safe` is true.
#[derive(Debug)]
pub(crate) struct SimpleThread {
    shared: Arc<Shared>,
    handle: Mutex<Option<JoinHandle<()>>>,
}

impl SimpleThread {
    pub(crate) fn create(args: ExecutorArgs<'_>) -> Result<Arc<SimpleThread>, Error> {
        let o: SimpleThreadOptions = args.options()?;
        let shared = Arc::new(Shared {
            name: args.name.to_owned(),
            threshold: u64::from(o.queue_threshold),
            // AimRT's negative interval silences the warning only; the limit still holds.
            alarm_interval: u64::try_from(o.threshold_alarm_interval_ms)
                .ok()
                .map(Duration::from_millis),
            state: Mutex::new(State {
                queue: VecDeque::new(),
                in_flight: 0,
                accepting: true,
                stop: false,
            }),
            ready: Condvar::new(),
            worker: Mutex::new(None),
            last_alarm: Mutex::new(None),
            submitted: AtomicU64::new(0),
            run: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            panicked: AtomicU64::new(0),
        });
        let worker = shared.clone();
        let handle = args
            .threads
            .spawn(
                args.name,
                &o.thread_sched_policy,
                &o.thread_bind_cpu,
                move || worker.serve(),
            )
            .map_err(|e| Error::msg(format!("cannot spawn the worker thread: {e}")))?;
        Ok(Arc::new(SimpleThread {
            shared,
            handle: Mutex::new(Some(handle)),
        }))
    }
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn serve(&self) {
        *self.worker.lock().unwrap_or_else(|e| e.into_inner()) = Some(std::thread::current().id());
        let mut st = self.lock();
        loop {
            if !st.queue.is_empty() {
                let batch = std::mem::take(&mut st.queue);
                drop(st);
                for task in batch {
                    if task.run(&self.name) == TaskOutcome::Panicked {
                        self.panicked.fetch_add(1, Ordering::Relaxed);
                    }
                    self.run.fetch_add(1, Ordering::Relaxed);
                    self.lock().in_flight -= 1;
                }
                st = self.lock();
                continue;
            }
            if st.stop {
                break;
            }
            st = self.ready.wait(st).unwrap_or_else(|e| e.into_inner());
        }
        drop(st);
        *self.worker.lock().unwrap_or_else(|e| e.into_inner()) = None;
    }

    fn alarm(&self, text: &str) {
        let Some(interval) = self.alarm_interval else {
            return;
        };
        let mut last = self.last_alarm.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        if last.is_none_or(|l| now.duration_since(l) >= interval) {
            *last = Some(now);
            drop(last);
            tracing::warn!(target: "aimrt", "simple thread executor '{}': {text} (refused so far: {})", self.name, self.refused.load(Ordering::Relaxed));
        }
    }
}

impl Executor for SimpleThread {
    fn type_name(&self) -> &str {
        "simple_thread"
    }

    fn name(&self) -> &str {
        &self.shared.name
    }

    fn thread_safe(&self) -> bool {
        true
    }

    fn is_in_current_executor(&self) -> bool {
        *self.shared.worker.lock().unwrap_or_else(|e| e.into_inner())
            == Some(std::thread::current().id())
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        let s = &self.shared;
        let mut st = s.lock();
        if !st.accepting {
            drop(st);
            drop(task);
            s.refused.fetch_add(1, Ordering::Relaxed);
            s.alarm("task refused: the executor is shut down");
            return Err(ExecuteError::ShutDown);
        }
        if st.in_flight >= s.threshold {
            drop(st);
            drop(task);
            s.refused.fetch_add(1, Ordering::Relaxed);
            s.alarm(&format!(
                "task refused: queue_threshold {} reached",
                s.threshold
            ));
            return Err(ExecuteError::QueueFull);
        }
        st.in_flight += 1;
        let near_full = st.in_flight * 100 >= s.threshold * 95;
        st.queue.push_back(task);
        drop(st);
        s.submitted.fetch_add(1, Ordering::Relaxed);
        s.ready.notify_one();
        if near_full {
            s.alarm("queue is at 95% of queue_threshold");
        }
        Ok(())
    }

    fn shutdown(&self) {
        {
            let mut st = self.shared.lock();
            st.accepting = false;
            st.stop = true;
        }
        self.shared.ready.notify_all();
        let handle = self.handle.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            if h.thread().id() != std::thread::current().id() {
                let _ = h.join();
            }
        }
    }

    fn stats(&self) -> ExecutorStats {
        let s = &self.shared;
        ExecutorStats {
            submitted: s.submitted.load(Ordering::Relaxed),
            run: s.run.load(Ordering::Relaxed),
            refused: s.refused.load(Ordering::Relaxed),
            panicked: s.panicked.load(Ordering::Relaxed),
            queue_depth: s.lock().in_flight,
            ..ExecutorStats::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use aimrt_plugin_api::{DynamicLatch, ThreadFactory};
    use std::sync::atomic::AtomicUsize;

    fn make(options: &str) -> Arc<SimpleThread> {
        SimpleThread::create(ExecutorArgs {
            name: "simple_thread_executor",
            options_json: options,
            location: "test",
            bound: Vec::new(),
            threads: ThreadFactory::plain(),
        })
        .unwrap()
    }

    #[test]
    fn properties_match_aimrt() {
        let e = make("null");
        assert_eq!(e.type_name(), "simple_thread");
        assert_eq!(e.name(), "simple_thread_executor");
        assert!(e.thread_safe());
        assert!(!e.supports_timer_schedule());
        assert!(!e.is_in_current_executor());
        e.shutdown();
    }

    #[test]
    fn runs_fifo_on_its_thread_and_drains_at_shutdown() {
        let e = make("{}");
        let seen = Arc::new(Mutex::new(Vec::new()));
        let inside = Arc::new(AtomicUsize::new(0));
        for i in 0..1000 {
            let (s, e2, inside) = (seen.clone(), e.clone(), inside.clone());
            e.execute(Task::new(move || {
                if e2.is_in_current_executor() {
                    inside.fetch_add(1, Ordering::SeqCst);
                }
                s.lock().unwrap().push(i);
            }))
            .unwrap();
        }
        e.shutdown();
        assert_eq!(*seen.lock().unwrap(), (0..1000).collect::<Vec<_>>());
        assert_eq!(inside.load(Ordering::SeqCst), 1000);
        assert_eq!(e.execute(Task::new(|| {})), Err(ExecuteError::ShutDown));
        let s = e.stats();
        assert_eq!(
            (s.submitted, s.run, s.refused, s.queue_depth),
            (1000, 1000, 1, 0)
        );
    }

    #[test]
    fn threshold_counts_the_running_task_and_negative_interval_keeps_the_limit() {
        for interval in [1000, -1] {
            let e = make(&format!(
                "{{\"queue_threshold\": 2, \"threshold_alarm_interval_ms\": {interval}}}"
            ));
            let gate = DynamicLatch::new();
            assert!(gate.try_add(1));
            let started = DynamicLatch::new();
            assert!(started.try_add(1));
            let (g, st) = (gate.clone(), started.clone());
            e.execute(Task::new(move || {
                st.count_down(1).unwrap();
                assert!(g.wait_timeout(Duration::from_secs(20)));
            }))
            .unwrap();
            assert!(started.wait_timeout(Duration::from_secs(20)));
            e.execute(Task::new(|| {})).unwrap();
            assert_eq!(e.execute(Task::new(|| {})), Err(ExecuteError::QueueFull));
            gate.count_down(1).unwrap();
            e.shutdown();
            assert_eq!(e.stats().refused, 1);
        }
    }

    #[test]
    fn panicking_task_is_counted_and_worker_goes_on() {
        let e = make("null");
        e.execute(Task::new(|| panic!("task boom"))).unwrap();
        let ran = Arc::new(AtomicUsize::new(0));
        let r = ran.clone();
        e.execute(Task::new(move || {
            r.fetch_add(1, Ordering::SeqCst);
        }))
        .unwrap();
        e.shutdown();
        assert_eq!(ran.load(Ordering::SeqCst), 1);
        assert_eq!(e.stats().panicked, 1);
    }

    #[test]
    fn unknown_option_is_refused() {
        let err = SimpleThread::create(ExecutorArgs {
            name: "x",
            options_json: "{\"thread_num\": 2}",
            location: "cfg.yaml:3:5",
            bound: Vec::new(),
            threads: ThreadFactory::plain(),
        })
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("cfg.yaml:3:5") && err.contains("thread_num"),
            "{err}"
        );
    }
}
