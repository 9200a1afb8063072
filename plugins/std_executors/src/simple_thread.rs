//! `simple_thread`: one thread, strict FIFO, AimRT's `queue_threshold`.

use std::sync::Arc;

use aimrt_plugin_api::{Error, ExecutorArgs};
use serde::Deserialize;

use crate::common::{Admission, Clock};
use crate::swap_queue::{SwapQueue, SwapSpec};

/// The options of AimRT's `simple_thread`.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct SimpleThreadOptions {
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
}

/// Builds a `simple_thread`: a [`SwapQueue`] with an in-flight limit, no timers.
pub(crate) fn create(args: ExecutorArgs<'_>) -> Result<Arc<SwapQueue>, Error> {
    let o: SimpleThreadOptions = args.read_options()?;
    SwapQueue::new(
        SwapSpec {
            type_name: "simple_thread",
            label: "simple thread",
            name: args.name,
            threads: 1,
            // A negative alarm interval silences the warning only; the limit still holds.
            admission: Admission::new(
                Some(u64::from(o.queue_threshold)),
                o.threshold_alarm_interval_ms,
            ),
            sched_policy: &o.thread_sched_policy,
            bind_cpu: &o.thread_bind_cpu,
            strict: o.thread_policy_strict,
            timers: None,
            clock: Clock::new(false),
        },
        args.threads,
    )
    .map(Arc::new)
}
