//! `RealTimeModule`: AimRT's real-time example. On each executor, a loop prints the
//! scheduling policy and CPU affinity of the thread it runs on, as the OS reports them.

use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};

const EXECUTORS: [&str; 3] = ["sched_fifo_thread", "sched_other_thread", "sched_rr_thread"];

/// A 1 s loop on each real-time executor.
#[derive(Debug, Default)]
pub struct RealTimeModule {
    executors: Vec<ExecutorRef>,
    loops: crate::Loops,
}

/// The calling thread's policy (`SCHED_FIFO:80`) as the OS reports it.
pub(crate) fn sched_policy() -> String {
    use thread_priority::unix::{
        thread_native_id, thread_schedule_policy_param, NormalThreadSchedulePolicy,
        RealtimeThreadSchedulePolicy, ThreadSchedulePolicy,
    };
    match thread_schedule_policy_param(thread_native_id()) {
        Ok((ThreadSchedulePolicy::Realtime(p), param)) => {
            let name = match p {
                RealtimeThreadSchedulePolicy::Fifo => "SCHED_FIFO",
                RealtimeThreadSchedulePolicy::RoundRobin => "SCHED_RR",
                #[allow(unreachable_patterns)]
                _ => "SCHED_DEADLINE",
            };
            format!("{name}:{}", param.sched_priority)
        }
        Ok((ThreadSchedulePolicy::Normal(p), _)) => match p {
            NormalThreadSchedulePolicy::Other => "SCHED_OTHER".to_owned(),
            NormalThreadSchedulePolicy::Batch => "SCHED_BATCH".to_owned(),
            NormalThreadSchedulePolicy::Idle => "SCHED_IDLE".to_owned(),
        },
        Err(e) => format!("unknown ({e:?})"),
    }
}

/// The CPUs the calling thread may run on, as the OS reports them.
pub(crate) fn cpu_set() -> String {
    use nix::sched::{sched_getaffinity, CpuSet};
    use nix::unistd::Pid;
    match sched_getaffinity(Pid::from_raw(0)) {
        Ok(set) => {
            let cpus: Vec<String> = (0..CpuSet::count())
                .filter(|&i| set.is_set(i).unwrap_or(false))
                .map(|i| i.to_string())
                .collect();
            format!("[{}]", cpus.join(", "))
        }
        Err(e) => format!("unknown ({e})"),
    }
}

impl Module for RealTimeModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("RealTimeModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        self.executors = EXECUTORS
            .iter()
            .map(|n| crate::timer_executor(&core, n))
            .collect::<Result<_, _>>()?;
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        for &exec in &self.executors {
            self.loops.spawn_loop(exec, move |count| {
                tracing::info!(
                    "Loop count: {}, executor name: {}, sched policy: {}, bind cpu: {}",
                    count + 1,
                    exec.name(),
                    sched_policy(),
                    cpu_set()
                );
            })?;
        }
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        self.loops.stop();
        tracing::info!("Shutdown succeeded.");
    }
}
