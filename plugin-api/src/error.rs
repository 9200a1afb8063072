//! The crate's errors.

use crate::ffi::Status;

/// Why an executor refused a task. The task was dropped (its captures too).
#[non_exhaustive]
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ExecuteError {
    /// The queue is over the executor's `queue_threshold`.
    #[error("the executor's queue is full (over its queue_threshold)")]
    QueueFull,
    /// The executor has shut down (or not started taking work).
    #[error("the executor is shut down")]
    ShutDown,
    /// `execute_at`/`execute_after` on an executor without timer support.
    #[error("the executor does not support timer scheduling")]
    NoTimerSupport,
    /// The executor refused for another reason (a status this crate does not know).
    #[error("the executor refused the task ({})", crate::ffi::Status(*.0))]
    Refused(u32),
}

impl ExecuteError {
    pub(crate) fn status(self) -> Status {
        match self {
            ExecuteError::QueueFull => Status::QUEUE_FULL,
            ExecuteError::ShutDown => Status::SHUT_DOWN,
            ExecuteError::NoTimerSupport => Status::NO_TIMER_SUPPORT,
            ExecuteError::Refused(n) => Status(n),
        }
    }

    /// The error of an executor's status, `Ok` for [`Status::OK`].
    pub fn from_status(s: Status) -> Result<(), ExecuteError> {
        match s {
            Status::OK => Ok(()),
            Status::QUEUE_FULL => Err(ExecuteError::QueueFull),
            Status::SHUT_DOWN => Err(ExecuteError::ShutDown),
            Status::NO_TIMER_SUPPORT => Err(ExecuteError::NoTimerSupport),
            Status(n) => Err(ExecuteError::Refused(n)),
        }
    }
}

/// Errors of modules, plugins and the handles they use.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A message from module or plugin code.
    #[error("{0}")]
    Message(String),
    /// A task was refused.
    #[error("executor '{executor}': {source}")]
    Execute {
        /// The executor's name.
        executor: String,
        /// Why.
        #[source]
        source: ExecuteError,
    },
    /// No executor has this name.
    #[error("no executor named '{0}' (executors are declared under aimrt.executor.executors)")]
    ExecutorNotFound(String),
    /// Executor or plugin options, or a module's config, that do not match what is read.
    #[error("{what}: {message}")]
    Options {
        /// Whose options, and where they are.
        what: String,
        /// What is wrong and what would be right.
        message: String,
    },
    /// A thread could not be created or configured as asked.
    #[error("thread '{thread}': {reason}")]
    Thread {
        /// The thread's full name.
        thread: String,
        /// What was refused and the OS's reason.
        reason: String,
    },
    /// The runtime refused a registration.
    #[error("{0}")]
    Registration(String),
    /// The runtime refused a channel call (wrong phase, unregistered type, bad context).
    #[error("{0}")]
    Channel(String),
    /// The runtime refused an RPC registration (wrong phase, duplicate, no RPC support).
    #[error("{0}")]
    Rpc(String),
}

impl Error {
    /// An error with a message.
    pub fn msg(message: impl std::fmt::Display) -> Error {
        Error::Message(message.to_string())
    }
}
