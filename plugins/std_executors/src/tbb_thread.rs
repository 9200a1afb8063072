//! `tbb_thread`: a pool of `thread_num` workers over the swap queue with AimRT's
//! `queue_threshold`; no timers.

use std::sync::Arc;

use aimrt_plugin_api::{Error, ExecutorArgs};
use serde::Deserialize;

use crate::common::{Admission, Clock};
use crate::swap_queue::{SwapQueue, SwapSpec};

/// The options of AimRT's `tbb_thread`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct TbbThreadOptions {
    #[serde(default = "crate::default_thread_num")]
    thread_num: u32,
    #[serde(default)]
    thread_sched_policy: String,
    #[serde(default)]
    thread_bind_cpu: Vec<u32>,
    #[serde(default)]
    thread_policy_strict: bool,
    #[serde(default = "crate::default_queue_threshold")]
    queue_threshold: u32,
    #[serde(default = "crate::default_alarm_interval")]
    threshold_alarm_interval_ms: i32,
    /// AimRT's docs list it for tbb_thread but its code ignores it: accepted with a warning.
    #[serde(default)]
    timeout_alarm_threshold_us: Option<u64>,
}

/// Builds a `tbb_thread`: a [`SwapQueue`] of `thread_num` workers with an in-flight limit.
pub(crate) fn create(args: ExecutorArgs<'_>) -> Result<Arc<SwapQueue>, Error> {
    let o: TbbThreadOptions = args.read_options()?;
    let threads = crate::thread_num(&args, o.thread_num)?;
    if o.timeout_alarm_threshold_us.is_some() {
        tracing::warn!(target: "aimrt", "executor '{}' at {}: option 'timeout_alarm_threshold_us' has no effect on tbb_thread (AimRT documents it but ignores it too)", args.name, args.location);
    }
    SwapQueue::new(
        SwapSpec {
            type_name: "tbb_thread",
            label: "tbb thread",
            name: args.name,
            threads,
            admission: Admission::new(
                Some(u64::from(o.queue_threshold)),
                o.threshold_alarm_interval_ms,
            ),
            timers: None,
            clock: Clock::new(false),
            sched_policy: &o.thread_sched_policy,
            bind_cpu: &o.thread_bind_cpu,
            strict: o.thread_policy_strict,
        },
        args.threads,
    )
    .map(Arc::new)
}
