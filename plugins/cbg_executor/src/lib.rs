//! `cbg_executor_plugin`: callback groups on a shared thread pool, after ROS 2's
//! `EventsCBGExecutor` (seed 001), as an ordinary aimrt-rs executor plugin. It uses only
//! `aimrt-plugin-api`; the runtime knows nothing about it.
//!
//! Two executor types:
//!
//! | type | what | `thread_safe` | timers |
//! |---|---|---|---|
//! | `events_cbg` | the pool: `thread_num` threads (0 = CPUs, at least 2); tasks posted to it directly form its own reentrant group | `thread_num == 1` | yes |
//! | `events_cbg_group` | one callback group on a pool (`bind_events_cbg`), `kind: mutually_exclusive` (default) or `reentrant`; optionally on a `dedicated_thread`, optionally with timers on a `time_executor`'s clock | exclusive: yes, reentrant: no | yes |
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: cbg_executor_plugin
//!         path: ./target/debug/libaimrt_cbg_executor_plugin.so
//!   executor:
//!     executors:
//!       - name: cbg_pool
//!         type: events_cbg
//!         options: {thread_num: 2, on_panic: log}
//!       - name: control_group
//!         type: events_cbg_group
//!         options: {bind_events_cbg: cbg_pool, kind: mutually_exclusive}
//!       - name: perception_group
//!         type: events_cbg_group
//!         options: {bind_events_cbg: cbg_pool, kind: reentrant}
//! ```
//!
//! Scheduling, timers, dedicated threads and every option: `docs/cbg_executor.md`.
#![deny(unsafe_code)]

mod sched;

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use aimrt_plugin_api::{
    Error, ExecuteError, Executor, ExecutorArgs, ExecutorRef, ExecutorStats, Plugin, PluginOptions,
    Registrar, Task,
};
use serde::Deserialize;

pub use crate::sched::OnPanic;
use crate::sched::{GroupCore, GroupId, Scheduler, ThreadSpec};

/// The pool type's name.
pub const POOL_TYPE: &str = "events_cbg";
/// The group type's name.
pub const GROUP_TYPE: &str = "events_cbg_group";

/// Options of `events_cbg`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct PoolOptions {
    #[serde(default)]
    thread_num: u32,
    #[serde(default = "default_on_panic")]
    on_panic: OnPanic,
    #[serde(default)]
    thread_sched_policy: String,
    #[serde(default)]
    thread_bind_cpu: Vec<u32>,
    #[serde(default)]
    thread_policy_strict: bool,
}

fn default_on_panic() -> OnPanic {
    OnPanic::Log
}

/// A group's kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum Kind {
    MutuallyExclusive,
    Reentrant,
}

/// `dedicated_thread` of a group.
#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Dedicated {
    #[serde(default)]
    thread_sched_policy: String,
    #[serde(default)]
    thread_bind_cpu: Vec<u32>,
    #[serde(default)]
    thread_policy_strict: bool,
}

/// Options of `events_cbg_group`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct GroupOptions {
    #[serde(default)]
    bind_events_cbg: String,
    #[serde(default = "default_kind")]
    kind: Kind,
    #[serde(default)]
    dedicated_thread: Option<Dedicated>,
    #[serde(default)]
    time_executor: String,
}

fn default_kind() -> Kind {
    Kind::MutuallyExclusive
}

fn options_error(args: &ExecutorArgs<'_>, message: impl Into<String>) -> Error {
    Error::Options {
        what: format!("options of executor '{}' at {}", args.name, args.location),
        message: message.into(),
    }
}

/// An `events_cbg` pool, or an `events_cbg_group` on one.
#[derive(Debug)]
pub struct CbgExecutor {
    type_name: &'static str,
    core: Arc<GroupCore>,
    sched: Arc<Scheduler>,
    gid: GroupId,
    /// The scheduler is this executor's own (a pool, or a group on a dedicated thread).
    owns_scheduler: bool,
    /// Timers follow this executor's clock.
    time: Option<ExecutorRef>,
    threads: aimrt_plugin_api::ThreadFactory,
}

impl CbgExecutor {
    /// The pool's number of threads (1 for a group on a dedicated thread).
    pub fn thread_count(&self) -> usize {
        self.sched.thread_count()
    }
}

/// Builds an `events_cbg` pool from `args` (its threads start with `Executor::start`).
///
/// ```
/// use aimrt_plugin_api::{Executor, ExecutorArgs, ThreadFactory};
/// let pool = aimrt_cbg_executor::create_pool(ExecutorArgs {
///     name: "cbg_pool", options_json: r#"{"thread_num": 0}"#, location: "example",
///     bound: Vec::new(), threads: ThreadFactory::plain(),
/// }).unwrap();
/// assert!(pool.thread_count() >= 2, "0 means the number of CPUs, at least 2");
/// pool.shutdown();
/// ```
pub fn create_pool(args: ExecutorArgs<'_>) -> Result<Arc<CbgExecutor>, Error> {
    let o: PoolOptions = args.read_options()?;
    let count = match o.thread_num {
        0 => std::thread::available_parallelism()
            .map_or(2, |n| n.get())
            .max(2),
        n if n > aimrt_plugin_api::MAX_THREAD_NUM => {
            return Err(options_error(
                &args,
                format!(
                    "thread_num {n} is over the limit of {} threads per executor",
                    aimrt_plugin_api::MAX_THREAD_NUM
                ),
            ))
        }
        n => n as usize,
    };
    let core = GroupCore::new(args.name, count == 1);
    let spec = ThreadSpec {
        count,
        sched_policy: o.thread_sched_policy,
        bind_cpu: o.thread_bind_cpu,
        strict: o.thread_policy_strict,
    };
    let sched = Scheduler::new(args.name, POOL_TYPE, spec, o.on_panic, core.clone());
    Ok(Arc::new(CbgExecutor {
        type_name: POOL_TYPE,
        core,
        sched,
        gid: 0,
        owns_scheduler: true,
        time: None,
        threads: args.threads,
    }))
}

/// Builds an `events_cbg_group` on `pool`. `args.bound` holds the executors its bind keys
/// name: `[bind_events_cbg, time_executor]` (the first is checked to be `pool`).
///
/// ```
/// use aimrt_plugin_api::{Executor, ExecutorArgs, ExecutorRef, ThreadFactory};
/// let args = |name, options_json| ExecutorArgs {
///     name, options_json, location: "example", bound: Vec::new(), threads: ThreadFactory::plain(),
/// };
/// let pool = aimrt_cbg_executor::create_pool(args("pool", r#"{"thread_num": 2}"#)).unwrap();
/// let group = aimrt_cbg_executor::create_group(
///     &pool,
///     args("group", r#"{"bind_events_cbg": "pool", "kind": "reentrant"}"#),
/// ).unwrap();
/// assert!(!group.thread_safe());
/// group.shutdown();
/// pool.shutdown();
/// ```
pub fn create_group(
    pool: &Arc<CbgExecutor>,
    args: ExecutorArgs<'_>,
) -> Result<Arc<CbgExecutor>, Error> {
    let o: GroupOptions = args.read_options()?;
    if o.bind_events_cbg.is_empty() {
        return Err(options_error(
            &args,
            "bind_events_cbg is required: name the events_cbg pool this group belongs to",
        ));
    }
    let exclusive = o.kind == Kind::MutuallyExclusive;
    let time = if o.time_executor.is_empty() {
        None
    } else {
        let Some(Some(t)) = args.bound.get(1).copied() else {
            return Err(options_error(
                &args,
                format!("time_executor '{}' was not resolved", o.time_executor),
            ));
        };
        if !t.supports_timer_schedule() {
            return Err(options_error(
                &args,
                format!(
                    "time_executor '{}' is a {} executor, which has no timers; name one that has (e.g. time_manipulator)",
                    t.name(),
                    t.type_name()
                ),
            ));
        }
        Some(t)
    };
    let core = GroupCore::new(args.name, exclusive);
    let (sched, gid, owns_scheduler) = match o.dedicated_thread {
        Some(d) => {
            if !exclusive {
                return Err(options_error(
                    &args,
                    "a reentrant group cannot have a dedicated_thread: one thread never runs two callbacks at once; use kind: mutually_exclusive or drop dedicated_thread",
                ));
            }
            let spec = ThreadSpec {
                count: 1,
                sched_policy: d.thread_sched_policy,
                bind_cpu: d.thread_bind_cpu,
                strict: d.thread_policy_strict,
            };
            let sched = Scheduler::new(
                args.name,
                GROUP_TYPE,
                spec,
                pool.sched.on_panic(),
                core.clone(),
            );
            (sched, 0, true)
        }
        None => {
            let gid = pool.sched.add_group(core.clone());
            (pool.sched.clone(), gid, false)
        }
    };
    Ok(Arc::new(CbgExecutor {
        type_name: GROUP_TYPE,
        core,
        sched,
        gid,
        owns_scheduler,
        time,
        threads: args.threads,
    }))
}

impl Executor for CbgExecutor {
    fn type_name(&self) -> &str {
        self.type_name
    }

    fn name(&self) -> &str {
        &self.core.name
    }

    fn thread_safe(&self) -> bool {
        self.core.exclusive
    }

    fn is_in_current_executor(&self) -> bool {
        self.sched.in_group(self.gid)
    }

    fn supports_timer_schedule(&self) -> bool {
        true
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        self.sched.submit(self.gid, task)
    }

    fn now(&self) -> SystemTime {
        match &self.time {
            Some(t) => t.now(),
            None => self.sched.now(),
        }
    }

    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        let Some(time) = &self.time else {
            return self.sched.submit_at(self.gid, at, task);
        };
        // The time executor decides when; the group runs it.
        let (sched, gid) = (self.sched.clone(), self.gid);
        let forward = move || {
            // A refusal (group shut down) is counted and warned about by the group.
            let _ = sched.submit(gid, task);
        };
        match time.execute_at(at, forward) {
            Ok(()) => Ok(()),
            Err(Error::Execute { source, .. }) => Err(source),
            Err(_) => Err(ExecuteError::Refused(u32::MAX)),
        }
    }

    fn start(&self) -> Result<(), Error> {
        if self.owns_scheduler {
            self.sched.start(self.threads)?;
        }
        Ok(())
    }

    fn shutdown(&self) {
        if self.owns_scheduler {
            self.sched.shutdown();
        } else {
            self.sched.close_group(self.gid);
        }
    }

    fn stats(&self) -> ExecutorStats {
        self.sched.stats(self.gid)
    }
}

/// The pools this plugin built, by name, so groups can find theirs.
type Pools = Arc<Mutex<BTreeMap<String, Arc<CbgExecutor>>>>;

#[derive(Debug, Default)]
struct CbgPlugin {
    pools: Pools,
}

impl Plugin for CbgPlugin {
    fn name(&self) -> &str {
        "cbg_executor_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _options: &PluginOptions,
    ) -> Result<(), Error> {
        let pools = self.pools.clone();
        registrar.register_executor_type(POOL_TYPE, &[], move |args| {
            let pool = create_pool(args)?;
            pools
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(pool.name().to_owned(), pool.clone());
            Ok(pool)
        })?;
        let pools = self.pools.clone();
        registrar.register_executor_type(
            GROUP_TYPE,
            &["bind_events_cbg", "time_executor"],
            move |args| {
                let bound = args.bound.first().copied().flatten();
                let pool = bound.and_then(|b| {
                    pools
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .get(b.name())
                        .cloned()
                });
                match (bound, pool) {
                    (_, Some(pool)) => create_group(&pool, args),
                    (Some(b), None) => Err(options_error(
                        &args,
                        format!(
                            "bind_events_cbg '{}' is a {} executor; it must name an {POOL_TYPE} pool",
                            b.name(),
                            b.type_name()
                        ),
                    )),
                    (None, None) => Err(options_error(
                        &args,
                        "bind_events_cbg is required: name the events_cbg pool this group belongs to",
                    )),
                }
            },
        )
    }
}

/// The plugin: registers `events_cbg` and `events_cbg_group`.
///
/// ```
/// assert_eq!(aimrt_cbg_executor::plugin().name(), "cbg_executor_plugin");
/// ```
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(CbgPlugin::default())
}
