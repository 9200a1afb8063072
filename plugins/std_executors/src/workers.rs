//! `asio_thread` and `tbb_thread` by thread count: one worker runs on the swap-queue
//! engine (`simple_thread`'s, which drains a backlog several times faster than a channel
//! can), more on the channel pool (which several workers share without a lock).

use std::time::SystemTime;

use aimrt_plugin_api::{Error, ExecuteError, Executor, ExecutorStats, Task, ThreadFactory};

use crate::common::Admission;
use crate::pool::{Pool, PoolSpec};
use crate::swap_queue::{SwapQueue, SwapSpec};

/// A pool of `thread_num` workers; see the module doc.
#[derive(Debug)]
pub(crate) enum Workers {
    One(SwapQueue),
    Many(Pool),
}

impl Workers {
    pub(crate) fn new(spec: PoolSpec<'_>, factory: ThreadFactory) -> Result<Workers, Error> {
        if spec.threads != 1 {
            return Pool::new(spec, factory).map(Workers::Many);
        }
        SwapQueue::new(
            SwapSpec {
                type_name: spec.type_name,
                label: spec.label,
                name: spec.name,
                admission: Admission::new(spec.limit, spec.queue_alarm_ms),
                sched_policy: spec.sched_policy,
                bind_cpu: spec.bind_cpu,
                strict: spec.strict,
                timers: spec.timers,
                clock: spec.clock,
            },
            factory,
        )
        .map(Workers::One)
    }
}

/// Calls `$call` on whichever engine this is.
macro_rules! each {
    ($self:ident, $e:ident => $call:expr) => {
        match $self {
            Workers::One($e) => $call,
            Workers::Many($e) => $call,
        }
    };
}

impl Executor for Workers {
    fn type_name(&self) -> &str {
        each!(self, e => e.type_name())
    }

    fn name(&self) -> &str {
        each!(self, e => e.name())
    }

    fn thread_safe(&self) -> bool {
        each!(self, e => e.thread_safe())
    }

    fn is_in_current_executor(&self) -> bool {
        each!(self, e => e.is_in_current_executor())
    }

    fn supports_timer_schedule(&self) -> bool {
        each!(self, e => e.supports_timer_schedule())
    }

    fn now(&self) -> SystemTime {
        each!(self, e => e.now())
    }

    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        each!(self, e => e.execute(task))
    }

    fn execute_at(&self, at: SystemTime, task: Task) -> Result<(), ExecuteError> {
        each!(self, e => e.execute_at(at, task))
    }

    fn start(&self) -> Result<(), Error> {
        each!(self, e => e.start())
    }

    fn stats(&self) -> ExecutorStats {
        each!(self, e => e.stats())
    }

    fn shutdown(&self) {
        each!(self, e => e.shutdown())
    }
}
