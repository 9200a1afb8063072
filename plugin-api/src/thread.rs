//! Threads for executors: every thread an executor creates goes through the runtime's
//! thread factory, which applies name, scheduling policy and CPU affinity.

use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;

use crate::ffi::RawThreadFactory;
use crate::Error;

/// The most threads one executor may ask for (`thread_num`). More is refused with this
/// limit named, before any thread is spawned: a typo such as `100000` would otherwise
/// spend seconds creating threads until the OS refuses one.
pub const MAX_THREAD_NUM: u32 = 1024;

/// Thread settings, as AimRT's `thread_sched_policy` / `thread_bind_cpu` options.
#[derive(Debug, Clone, Copy)]
pub struct ThreadSettingsRef<'a> {
    /// The thread name (before shortening).
    pub name: &'a str,
    /// `""`, `SCHED_OTHER`, `SCHED_FIFO:<1-99>` or `SCHED_RR:<1-99>`.
    pub sched_policy: &'a str,
    /// CPUs to bind to; empty for no binding.
    pub bind_cpu: &'a [u32],
    /// A refused setting is an error (the thread is not started) instead of a warning.
    pub strict: bool,
}

impl<'a> ThreadSettingsRef<'a> {
    /// Settings for a thread named `name` with no policy and no binding.
    pub fn named(name: &'a str) -> ThreadSettingsRef<'a> {
        ThreadSettingsRef {
            name,
            sched_policy: "",
            bind_cpu: &[],
            strict: false,
        }
    }
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

    /// A factory over `configurator`, exported for good (the host makes one at start and
    /// hands it to every plugin through [`ThreadFactory::raw`]).
    pub fn leak<T: ThreadConfigurator>(configurator: Arc<T>) -> ThreadFactory {
        ThreadFactory {
            raw: Some(RawThreadFactory::leak(configurator)),
        }
    }

    /// The raw handle (a null vtable for [`ThreadFactory::plain`]).
    pub fn raw(&self) -> RawThreadFactory {
        self.raw.unwrap_or(RawThreadFactory {
            vtable: std::ptr::null(),
            obj: std::ptr::null(),
        })
    }

    fn apply(&self, settings: &ThreadSettingsRef<'_>) -> Result<(), String> {
        self.raw
            .map_or(Ok(()), |raw| raw.configure_current(settings))
    }

    /// What the caller does with a refusal: an error when strict, else one warning.
    fn judge(settings: &ThreadSettingsRef<'_>, result: Result<(), String>) -> Result<(), Error> {
        match result {
            Ok(()) => Ok(()),
            Err(reason) if settings.strict => Err(Error::Thread {
                thread: settings.name.to_owned(),
                reason: format!("{reason} (thread_policy_strict is true)"),
            }),
            Err(reason) => {
                tracing::warn!(target: "aimrt", "thread '{}': {reason}; it runs with the settings that could be applied", settings.name);
                Ok(())
            }
        }
    }

    /// Applies policy and CPU binding to the calling thread (the name is left alone): for
    /// a thread the caller did not spawn, such as the runtime's main thread. A refusal is a
    /// warning, or an error with `strict`.
    pub fn configure_current(&self, settings: ThreadSettingsRef<'_>) -> Result<(), Error> {
        Self::judge(&settings, self.apply(&settings))
    }

    /// Spawns a thread named `settings.name` (shortened as AimRT does) and applies its
    /// policy and CPU binding before `f` runs. A refused setting is one warning naming the
    /// thread and the OS's reason, and the thread runs with what could be applied; with
    /// `strict` it is an error and `f` never runs.
    ///
    /// ```
    /// use aimrt_plugin_api::{ThreadFactory, ThreadSettingsRef};
    /// let handle = ThreadFactory::plain()
    ///     .spawn(ThreadSettingsRef::named("worker"), || {})
    ///     .unwrap();
    /// handle.join().unwrap();
    /// ```
    pub fn spawn<F>(&self, settings: ThreadSettingsRef<'_>, f: F) -> Result<JoinHandle<()>, Error>
    where
        F: FnOnce() + Send + 'static,
    {
        let factory = *self;
        let name = settings.name.to_owned();
        let policy = settings.sched_policy.to_owned();
        let cpus = settings.bind_cpu.to_vec();
        let strict = settings.strict;
        let (tx, rx) = mpsc::sync_channel(1);
        let handle = std::thread::Builder::new()
            .name(thread_name(&name))
            .spawn(move || {
                let result = factory.apply(&ThreadSettingsRef {
                    name: &name,
                    sched_policy: &policy,
                    bind_cpu: &cpus,
                    strict,
                });
                let go = result.is_ok() || !strict;
                let _ = tx.send(result);
                if go {
                    f();
                }
            })
            .map_err(|e| Error::Thread {
                thread: settings.name.to_owned(),
                reason: format!("cannot create the thread: {e}"),
            })?;
        let result = rx
            .recv()
            .unwrap_or_else(|_| Err("the thread ended while its settings were applied".into()));
        match Self::judge(&settings, result) {
            Ok(()) => Ok(handle),
            Err(e) => {
                let _ = handle.join();
                Err(e)
            }
        }
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
            .spawn(ThreadSettingsRef::named("worker_x"), || {
                assert_eq!(std::thread::current().name(), Some("worker_x"));
            })
            .unwrap();
        h.join().unwrap();
    }
}
