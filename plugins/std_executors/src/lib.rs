//! AimRT's standard executor types as a plugin. `aimrt_main` links this crate and
//! registers [`plugin()`] statically; `aimrt-std-executors-so` exports the same plugin
//! from a shared library for runtimes that do not link it.
//!
//! | type | threads | `thread_safe` | timers | limit |
//! |---|---|---|---|---|
//! | `simple_thread` | 1 | yes | no | `queue_threshold` |
//! | `tbb_thread` | `thread_num` | `thread_num == 1` | no | `queue_threshold` |
//! | `asio_thread` | `thread_num` | `thread_num == 1` | deadline timers | none |
//! | `asio_strand` | the bound `asio_thread`'s | yes | deadline timers | none |
//! | `time_wheel` | 1 timer thread | bound's, or yes | timing wheel (`dt_us` ticks) | none |
//!
//! The crate also builds `time_manipulator` executors ([`create_time_manipulator`]) for the
//! `time_manipulator_plugin`, which registers that type; this plugin does not.
//!
//! Options, defaults and every difference from AimRT: `docs/executors.md`.
//!
//! ```
//! let plugin = aimrt_std_executors::plugin();
//! assert_eq!(plugin.name(), "std_executors");
//! ```
#![forbid(unsafe_code)]

mod asio_thread;
mod common;
mod simple_thread;
mod strand;
mod swap_queue;
mod tbb_thread;
mod time_manipulator;
mod time_wheel;
mod wheel;

use aimrt_plugin_api::{Error, ExecutorArgs, ExecutorRef, Plugin, PluginOptions, Registrar};

pub use crate::time_manipulator::{
    check_time_ratio, create_time_manipulator, TimeManipulator, TimeRatioError, MAX_TIME_RATIO,
};

#[derive(Debug, Default)]
struct StdExecutors;

impl Plugin for StdExecutors {
    fn name(&self) -> &str {
        "std_executors"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _options: &PluginOptions,
    ) -> Result<(), Error> {
        registrar.register_executor_type("simple_thread", &[], simple_thread::create)?;
        registrar.register_executor_type("tbb_thread", &[], tbb_thread::create)?;
        registrar.register_executor_type("asio_thread", &[], asio_thread::create)?;
        registrar.register_executor_type(
            "asio_strand",
            &["bind_asio_thread_executor_name"],
            strand::create,
        )?;
        registrar.register_executor_type("time_wheel", &["bind_executor"], time_wheel::create)
    }
}

/// The standard executors plugin.
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(StdExecutors)
}

/// The standard executor types, as `aimrt.executor.executors[].type` names them.
pub const TYPES: [&str; 5] = [
    "simple_thread",
    "tbb_thread",
    "asio_thread",
    "asio_strand",
    "time_wheel",
];

/// Builds and starts one standard executor outside a runtime, the way `aimrt_main` does
/// (for tests, benchmarks and tools). `args.bound` holds the executors its bind key names
/// (`asio_strand`: the `asio_thread`; `time_wheel`: the optional `bind_executor`). The
/// executor is never freed; stop it with `raw().shutdown()`.
///
/// ```
/// use aimrt_plugin_api::{ExecutorArgs, ThreadFactory};
/// let exec = aimrt_std_executors::create_executor("asio_thread", ExecutorArgs {
///     name: "work", options_json: r#"{"thread_num": 2}"#, location: "example",
///     bound: Vec::new(), threads: ThreadFactory::plain(),
/// }).unwrap();
/// assert!(!exec.thread_safe());
/// exec.raw().shutdown();
/// ```
pub fn create_executor(type_name: &str, args: ExecutorArgs<'_>) -> Result<ExecutorRef, Error> {
    let exec = match type_name {
        "simple_thread" => ExecutorRef::leak(simple_thread::create(args)?),
        "tbb_thread" => ExecutorRef::leak(tbb_thread::create(args)?),
        "asio_thread" => ExecutorRef::leak(asio_thread::create(args)?),
        "asio_strand" => ExecutorRef::leak(strand::create(args)?),
        "time_wheel" => ExecutorRef::leak(time_wheel::create(args)?),
        other => {
            return Err(Error::msg(format!(
                "unknown standard executor type '{other}'; the types are {}",
                TYPES.join(", ")
            )))
        }
    };
    exec.raw().start().map_err(Error::msg)?;
    Ok(exec)
}

fn default_thread_num() -> u32 {
    1
}

fn default_queue_threshold() -> u32 {
    10_000
}

fn default_alarm_interval() -> i32 {
    1000
}

fn default_timeout_alarm_threshold_us() -> u64 {
    1_000_000
}

/// `thread_num` must be in `1 ..= MAX_THREAD_NUM`.
fn thread_num(args: &ExecutorArgs<'_>, n: u32) -> Result<usize, Error> {
    if n == 0 {
        return Err(common::options_error(args, "thread_num must be at least 1"));
    }
    if n > aimrt_plugin_api::MAX_THREAD_NUM {
        return Err(common::options_error(
            args,
            format!(
                "thread_num {n} is over the limit of {} threads per executor",
                aimrt_plugin_api::MAX_THREAD_NUM
            ),
        ));
    }
    Ok(n as usize)
}
