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

fn payload_text(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_owned()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "panic with a non-string payload".to_owned()
    }
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
                    loc.file(),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contain_returns_value_or_message() {
        assert_eq!(contain(|| 5), Ok(5));
        let err = contain(|| -> u32 { panic!("bad {}", 7) }).unwrap_err();
        assert!(err.contains("bad 7"), "{err}");
    }

    #[test]
    fn hook_records_location_inside_contain() {
        install_hook();
        let err = contain(|| panic!("located")).unwrap_err();
        assert!(err.starts_with("located (at "), "{err}");
        assert!(err.contains("panic.rs"), "{err}");
    }
}
