//! `asio_thread`: a pool of `thread_num` workers with deadline timers, unbounded.

use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::{Error, ExecutorArgs};
use serde::Deserialize;

use crate::common::{Admission, Clock};
use crate::swap_queue::{SwapQueue, SwapSpec, TimerSpec};

/// The options of AimRT's `asio_thread`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct AsioThreadOptions {
    #[serde(default = "crate::default_thread_num")]
    thread_num: u32,
    #[serde(default)]
    thread_sched_policy: String,
    #[serde(default)]
    thread_bind_cpu: Vec<u32>,
    #[serde(default)]
    thread_policy_strict: bool,
    #[serde(default = "crate::default_timeout_alarm_threshold_us")]
    timeout_alarm_threshold_us: u64,
    #[serde(default = "crate::default_alarm_interval")]
    timeout_alarm_interval_ms: i32,
    #[serde(default)]
    use_system_clock: bool,
}

/// Builds an `asio_thread`: a [`SwapQueue`] of `thread_num` workers with timers, no limit.
pub(crate) fn create(args: ExecutorArgs<'_>) -> Result<Arc<SwapQueue>, Error> {
    let o: AsioThreadOptions = args.read_options()?;
    let threads = crate::thread_num(&args, o.thread_num)?;
    SwapQueue::new(
        SwapSpec {
            type_name: "asio_thread",
            label: "asio thread",
            name: args.name,
            threads,
            admission: Admission::new(None, -1),
            timers: Some(TimerSpec {
                late_threshold: Duration::from_micros(o.timeout_alarm_threshold_us),
                late_alarm_ms: o.timeout_alarm_interval_ms,
            }),
            clock: Clock::new(o.use_system_clock),
            sched_policy: &o.thread_sched_policy,
            bind_cpu: &o.thread_bind_cpu,
            strict: o.thread_policy_strict,
        },
        args.threads,
    )
    .map(Arc::new)
}
