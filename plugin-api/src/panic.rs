//! Panic containment and the panic hook every library installs.
//!
//! Each library has its own `std` and therefore its own default panic hook, which would
//! print `thread '…' panicked at …` to stderr. The hook installed here instead:
//! - inside a containment shim ([`contain`]), stores the message and location so the shim
//!   can report them (as a status, an error, or one log line with context);
//! - elsewhere (a library's own thread), logs them at Error through the current module's
//!   or the library's logger.

use std::cell::{Cell, RefCell};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Once;

thread_local! {
    static CONTAINED: Cell<u32> = const { Cell::new(0) };
    static LAST: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Runs `f`; a panic becomes `Err("<message> (at <file:line:col>)")`.
pub(crate) fn contain<R>(f: impl FnOnce() -> R) -> Result<R, String> {
    CONTAINED.with(|c| c.set(c.get() + 1));
    let result = catch_unwind(AssertUnwindSafe(f));
    CONTAINED.with(|c| c.set(c.get() - 1));
    result.map_err(|payload| {
        LAST.with(|l| l.borrow_mut().take())
            .unwrap_or_else(|| payload_text(payload.as_ref()))
    })
}

/// Why `__private::contain_on_helper` has no value to return.
#[derive(Debug, thiserror::Error)]
pub enum HelperFailed {
    /// The helper thread did not start.
    #[error("cannot start a thread: {0}")]
    Spawn(std::io::Error),
    /// The work panicked: its message, without its place.
    #[error("{0}")]
    Panicked(String),
    /// The work did not finish within the limit; the helper is left behind.
    #[error("it did not finish within {} s", .0.as_secs_f64())]
    TimedOut(std::time::Duration),
}

/// Runs `f` on a helper thread named `name` (with a small stack), its panic contained,
/// and waits at most `limit` for it. For work in a dependency that may hang instead of
/// failing, e.g. tokio's runtime build when the system refuses a worker thread: the caller
/// gets an error and goes on, and the helper stays behind, blocked.
pub(crate) fn contain_on_helper<R: Send + 'static>(
    name: &str,
    limit: std::time::Duration,
    f: impl FnOnce() -> R + Send + 'static,
) -> Result<R, HelperFailed> {
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    std::thread::Builder::new()
        .name(name.to_owned())
        .stack_size(256 * 1024)
        .spawn(move || {
            let _ = tx.send(contain(f));
        })
        .map_err(HelperFailed::Spawn)?;
    match rx.recv_timeout(limit) {
        Ok(Ok(value)) => Ok(value),
        Ok(Err(panic)) => Err(HelperFailed::Panicked(
            panic
                .rsplit_once(" (at ")
                .map_or(panic.as_str(), |(said, _)| said)
                .to_owned(),
        )),
        Err(_) => Err(HelperFailed::TimedOut(limit)),
    }
}

fn payload_text(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_owned()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "panic with a non-string payload".to_owned()
    }
}

/// A source path in cargo's registry from the crate's folder on
/// (`/root/.cargo/registry/src/index.crates.io-…/tokio-1.54.1/src/x.rs` becomes
/// `tokio-1.54.1/src/x.rs`): the user's home and cargo's index name say nothing. Other
/// paths stay as they are.
fn from_crate_folder(file: &str) -> &str {
    file.split_once("/registry/src/")
        .and_then(|(_, index_on)| index_on.split_once('/'))
        .map_or(file, |(_, crate_on)| crate_on)
}

/// Replaces this library's panic hook (once).
pub(crate) fn install_hook() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        std::panic::set_hook(Box::new(|info| {
            let message = payload_text(info.payload());
            let text = match info.location() {
                Some(loc) => format!(
                    "{message} (at {}:{}:{})",
                    from_crate_folder(loc.file()),
                    loc.line(),
                    loc.column()
                ),
                None => message,
            };
            if CONTAINED.with(|c| c.get()) > 0 {
                LAST.with(|l| *l.borrow_mut() = Some(text));
            } else {
                let thread = std::thread::current();
                let name = thread.name().unwrap_or("<unnamed>");
                tracing::error!(target: "aimrt", "thread '{name}' panicked: {text}");
            }
        }));
    });
}

/// How many call sites the panic limiter tracks; more share one slot.
const MAX_SITES: usize = 1024;

/// Logs a contained panic at Error as `<what> panicked: <message>`, at most once a second
/// per `scope` (an executor) and call site (the `at file:line:col` of the message); the
/// line after a quiet spell says how many were left out. A task that panics in a loop thus
/// writes one line a second, not one per panic.
pub(crate) fn log_panic(what: &str, scope: &str, message: &str) {
    use std::collections::HashMap;
    use std::sync::Mutex;
    use std::time::{Duration, Instant};
    static SITES: Mutex<Option<HashMap<String, (Instant, u64)>>> = Mutex::new(None);
    let site = message.rsplit_once(" (at ").map_or(message, |(_, s)| s);
    let mut key = format!("{scope}\u{0}{site}");
    let now = Instant::now();
    let held = {
        let mut sites = SITES.lock().unwrap_or_else(|e| e.into_inner());
        let map = sites.get_or_insert_with(HashMap::new);
        if !map.contains_key(&key) && map.len() >= MAX_SITES {
            key = String::new();
        }
        match map.get_mut(&key) {
            Some((last, held)) if now.duration_since(*last) < Duration::from_secs(1) => {
                *held += 1;
                return;
            }
            Some((last, held)) => {
                *last = now;
                std::mem::take(held)
            }
            None => {
                map.insert(key, (now, 0));
                0
            }
        }
    };
    if held > 0 {
        tracing::error!(target: "aimrt", "{what} panicked: {message} ({held} more panic(s) at this place since the last report were not logged)");
    } else {
        tracing::error!(target: "aimrt", "{what} panicked: {message}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contain_on_helper_returns_value_message_or_time_out() {
        let limit = std::time::Duration::from_secs(5);
        assert_eq!(contain_on_helper("t_ok", limit, || 7).unwrap(), 7);
        match contain_on_helper("t_panic", limit, || -> u32 { panic!("bad {}", 8) }) {
            Err(HelperFailed::Panicked(m)) => assert_eq!(m, "bad 8"),
            other => panic!("{other:?}"),
        }
        let short = std::time::Duration::from_millis(50);
        let (hold, held) = std::sync::mpsc::channel::<()>();
        let err = contain_on_helper("t_hang", short, move || held.recv()).unwrap_err();
        assert!(
            matches!(err, HelperFailed::TimedOut(d) if d == short),
            "{err:?}"
        );
        assert_eq!(err.to_string(), "it did not finish within 0.05 s");
        drop(hold);
    }

    #[test]
    fn a_registry_path_is_shown_from_the_crate_folder_on() {
        assert_eq!(
            from_crate_folder("/root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f/tokio-1.54.1/src/runtime/blocking/pool.rs"),
            "tokio-1.54.1/src/runtime/blocking/pool.rs"
        );
        assert_eq!(
            from_crate_folder("plugins/net/src/tcp.rs"),
            "plugins/net/src/tcp.rs"
        );
        assert_eq!(
            from_crate_folder("/x/registry/src/index"),
            "/x/registry/src/index"
        );
    }

    #[test]
    fn contain_returns_value_or_message() {
        assert_eq!(contain(|| 5), Ok(5));
        let err = contain(|| -> u32 { panic!("bad {}", 7) }).unwrap_err();
        assert!(err.contains("bad 7"), "{err}");
    }

    #[test]
    fn containment_counts_nest_and_unwind_back_to_zero() {
        install_hook();
        let depth = || CONTAINED.with(|c| c.get());
        let inner = contain(|| {
            assert_eq!(depth(), 1);
            let err = contain(|| -> u32 {
                assert_eq!(depth(), 2);
                panic!("inner")
            })
            .unwrap_err();
            assert!(err.starts_with("inner (at "), "{err}");
            assert_eq!(depth(), 1);
            contain(depth)
        });
        assert_eq!(inner, Ok(Ok(2)));
        assert_eq!(depth(), 0);
    }

    #[test]
    fn hook_records_location_inside_contain() {
        install_hook();
        let err = contain(|| panic!("located")).unwrap_err();
        assert!(err.starts_with("located (at "), "{err}");
        assert!(err.contains("panic.rs"), "{err}");
    }

    #[test]
    fn panics_in_a_loop_are_logged_once_a_second_per_place_with_a_count() {
        install_hook();
        // One call site for every panic below.
        let boom = |executor: &str| crate::Task::new(|| panic!("again")).run(executor);
        let ((), lines) = crate::log::capture_logs(|| {
            for _ in 0..500 {
                boom("looping");
            }
            // The same place on another executor is reported on its own.
            boom("other");
            std::thread::sleep(std::time::Duration::from_millis(1100));
            boom("looping");
        });
        let panics: Vec<&String> = lines.iter().filter(|l| l.contains("panicked")).collect();
        assert_eq!(panics.len(), 3, "{panics:#?}");
        assert!(panics[0].starts_with("task on executor 'looping' panicked: again (at "));
        assert!(panics[1].starts_with("task on executor 'other' panicked"));
        assert!(
            panics[2].contains(
                "(499 more panic(s) at this place since the last report were not logged)"
            ),
            "{}",
            panics[2]
        );
    }
}
