//! Threads for executors: every thread an executor creates goes through the runtime's
//! thread factory, which applies name, scheduling policy and CPU affinity.

use std::io;
use std::thread::JoinHandle;

use crate::ffi::RawThreadFactory;

/// Thread settings, as AimRT's `thread_sched_policy` / `thread_bind_cpu` options.
#[derive(Debug, Clone, Copy)]
pub struct ThreadSettingsRef<'a> {
    /// The thread name (before shortening).
    pub name: &'a str,
    /// `""`, `SCHED_OTHER`, `SCHED_FIFO:<1-99>` or `SCHED_RR:<1-99>`.
    pub sched_policy: &'a str,
    /// CPUs to bind to; empty for no binding.
    pub bind_cpu: &'a [u32],
}

/// What the runtime implements to configure threads.
pub trait ThreadConfigurator: Send + Sync + 'static {
    /// Applies `settings` to the calling thread; `Err` says which setting was refused and
    /// why (the thread still runs).
    fn configure_current(&self, settings: &ThreadSettingsRef<'_>) -> Result<(), String>;
}

/// AimRT's thread-name rule: names of 15 bytes or more become `first8 + ".." + last5`.
///
/// ```
/// assert_eq!(aimrt_plugin_api::thread_name("short_name"), "short_name");
/// assert_eq!(
///     aimrt_plugin_api::thread_name("long_thread_name_more_than_15_characters_long"),
///     "long_thr.._long"
/// );
/// ```
pub fn thread_name(name: &str) -> String {
    if name.len() < 15 {
        return name.to_owned();
    }
    let head: String = name.chars().take(8).collect();
    let tail: Vec<char> = name.chars().rev().take(5).collect();
    let tail: String = tail.into_iter().rev().collect();
    format!("{head}..{tail}")
}

/// The runtime's thread factory, as plugins get it.
#[derive(Debug, Clone, Copy)]
pub struct ThreadFactory {
    raw: Option<RawThreadFactory>,
}

impl std::fmt::Debug for RawThreadFactory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RawThreadFactory")
    }
}

impl ThreadFactory {
    pub(crate) fn from_raw(raw: RawThreadFactory) -> ThreadFactory {
        ThreadFactory {
            raw: (!raw.vtable.is_null()).then_some(raw),
        }
    }

    /// A factory that only names threads (for tests and tools without a runtime).
    pub fn plain() -> ThreadFactory {
        ThreadFactory { raw: None }
    }

    /// Spawns a thread named `name` (shortened as AimRT does) with the given policy and
    /// CPU binding. A refused setting is a warning naming the thread and the reason; the
    /// thread runs regardless.
    pub fn spawn<F>(
        &self,
        name: &str,
        sched_policy: &str,
        bind_cpu: &[u32],
        f: F,
    ) -> io::Result<JoinHandle<()>>
    where
        F: FnOnce() + Send + 'static,
    {
        let raw = self.raw;
        let full_name = name.to_owned();
        let policy = sched_policy.to_owned();
        let cpus = bind_cpu.to_vec();
        std::thread::Builder::new().name(thread_name(name)).spawn(move || {
            if let Some(raw) = raw {
                let settings = ThreadSettingsRef {
                    name: &full_name,
                    sched_policy: &policy,
                    bind_cpu: &cpus,
                };
                if let Err(why) = raw.configure_current(&settings) {
                    tracing::warn!(target: "aimrt", "thread '{full_name}': {why}; it runs with the settings that could be applied");
                }
            }
            f();
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_shortened_like_aimrt() {
        assert_eq!(thread_name("short_name"), "short_name");
        assert_eq!(thread_name("fourteen_chars"), "fourteen_chars");
        assert_eq!(thread_name("fifteen_chars_x"), "fifteen_..ars_x");
        assert_eq!(
            thread_name("long_thread_name_more_than_15_characters_long"),
            "long_thr.._long"
        );
    }

    #[test]
    fn plain_factory_names_the_thread() {
        let h = ThreadFactory::plain()
            .spawn("worker_x", "", &[], || {
                assert_eq!(std::thread::current().name(), Some("worker_x"));
            })
            .unwrap();
        h.join().unwrap();
    }
}
