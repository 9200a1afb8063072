//! Executors shared by this crate's unit tests.

use std::sync::Arc;

use crate::{ExecuteError, Executor, ExecutorRef, Task};

/// Runs every task inline on the caller's thread; no timers.
pub(crate) struct Inline;

impl Executor for Inline {
    fn type_name(&self) -> &str {
        "plain"
    }
    fn name(&self) -> &str {
        "plain"
    }
    fn thread_safe(&self) -> bool {
        true
    }
    fn is_in_current_executor(&self) -> bool {
        false
    }
    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        task.run("plain");
        Ok(())
    }
    fn shutdown(&self) {}
}

/// A handle to a fresh [`Inline`] executor.
pub(crate) fn inline() -> ExecutorRef {
    ExecutorRef::leak(Arc::new(Inline))
}
