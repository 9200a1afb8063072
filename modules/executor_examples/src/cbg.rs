//! `CbgModule`: callback groups of the `events_cbg` plugin at work. Once a second:
//!
//! - two producers on the reentrant group (they may run at once) post 500 callbacks each
//!   to the mutually exclusive group, whose callbacks update a counter with no lock and
//!   check that none of them ever overlaps another;
//! - the group on a dedicated thread reports its thread's name, policy and CPUs as the OS
//!   reports them;
//! - with `sim_group` (a group with a `time_executor`), a loop on it logs the group's
//!   clock once a *simulated* second.
//!
//! ```yaml
//! CbgModule:
//!   exclusive_group: control_group   # events_cbg_group, kind: mutually_exclusive
//!   reentrant_group: worker_group    # events_cbg_group, kind: reentrant
//!   dedicated_group: rt_group        # events_cbg_group with dedicated_thread
//!   sim_group: sim_group             # optional: events_cbg_group with time_executor
//! ```

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};
use serde::Deserialize;

use crate::real_time::{cpu_set, sched_policy};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Cfg {
    exclusive_group: String,
    reentrant_group: String,
    dedicated_group: String,
    #[serde(default)]
    sim_group: String,
}

const PER_PRODUCER: u64 = 500;

/// What the exclusive group's callbacks share (touched only from that group).
#[derive(Debug, Default)]
struct Shared {
    busy: AtomicBool,
    overlaps: AtomicU64,
    callbacks: AtomicU64,
}

/// The callback group example.
#[derive(Debug, Default)]
pub struct CbgModule {
    groups: Option<(ExecutorRef, ExecutorRef, ExecutorRef)>,
    sim: Option<ExecutorRef>,
    loops: crate::Loops,
}

impl Module for CbgModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("CbgModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: Cfg = core.config()?;
        let exclusive = crate::thread_safe_executor(&core, &cfg.exclusive_group)?;
        let reentrant = core.executor(&cfg.reentrant_group)?;
        let dedicated = crate::timer_executor(&core, &cfg.dedicated_group)?;
        tracing::info!(
            "Groups: '{}' thread safe {}, '{}' thread safe {}, '{}' thread safe {}",
            exclusive.name(),
            exclusive.thread_safe(),
            reentrant.name(),
            reentrant.thread_safe(),
            dedicated.name(),
            dedicated.thread_safe()
        );
        self.groups = Some((exclusive, reentrant, dedicated));
        if !cfg.sim_group.is_empty() {
            self.sim = Some(crate::timer_executor(&core, &cfg.sim_group)?);
        }
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some((exclusive, reentrant, dedicated)) = self.groups else {
            return Err(Error::msg("start before initialize"));
        };
        let shared = Arc::new(Shared::default());
        self.loops.spawn_loop(exclusive, move |count| {
            // The previous round's result, then the next round.
            let done = shared.callbacks.swap(0, Ordering::SeqCst);
            let overlaps = shared.overlaps.swap(0, Ordering::SeqCst);
            if count > 0 {
                tracing::info!(
                    "Loop count: {count}, '{}' ran {done} callbacks from 2 producers on '{}', {overlaps} overlapping",
                    exclusive.name(),
                    reentrant.name()
                );
            }
            for _ in 0..2 {
                let shared = shared.clone();
                let posted = reentrant.execute(move || {
                    for _ in 0..PER_PRODUCER {
                        let shared = shared.clone();
                        let _ = exclusive.execute(move || {
                            if shared.busy.swap(true, Ordering::AcqRel) {
                                shared.overlaps.fetch_add(1, Ordering::Relaxed);
                            }
                            shared.callbacks.fetch_add(1, Ordering::Relaxed);
                            shared.busy.store(false, Ordering::Release);
                        });
                    }
                });
                if let Err(e) = posted {
                    tracing::warn!("cannot post a producer: {e}");
                }
            }
        })?;
        self.loops.spawn_loop(dedicated, move |count| {
            let comm = std::fs::read_to_string("/proc/thread-self/comm")
                .map_or_else(|e| format!("unknown ({e})"), |s| s.trim().to_owned());
            tracing::info!(
                "Loop count: {}, group '{}' on thread '{comm}', sched policy: {}, bind cpu: {}",
                count + 1,
                dedicated.name(),
                sched_policy(),
                cpu_set()
            );
        })?;
        if let Some(sim) = self.sim {
            self.loops.spawn_loop(sim, move |count| {
                let now = chrono::DateTime::<chrono::Local>::from(sim.now())
                    .format("%Y-%m-%d %H:%M:%S%.3f");
                tracing::info!(
                    "Loop count: {}, group '{}' clock: {now}",
                    count + 1,
                    sim.name()
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
