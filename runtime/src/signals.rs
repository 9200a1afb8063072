//! SIGINT/SIGTERM: the first asks for a graceful shutdown, a second during shutdown exits
//! at once (status 128 + signal). Handled on a thread fed by signal-hook's self-pipe,
//! never inside the signal handler.

use signal_hook::consts::{SIGINT, SIGTERM};
use signal_hook::iterator::Signals;

/// Calls `request` on the first SIGINT/SIGTERM (it returns `false` when shutdown was
/// already requested); on a second signal, exits the process immediately.
pub fn on_signals(request: impl Fn() -> bool + Send + 'static) -> std::io::Result<()> {
    let mut signals = Signals::new([SIGINT, SIGTERM])?;
    std::thread::Builder::new()
        .name("aimrt_signal".into())
        .spawn(move || {
            for sig in signals.forever() {
                if !request() {
                    crate::say_err(format_args!(
                        "Received signal {sig} again during shutdown: exiting at once."
                    ));
                    std::process::exit(128 + sig);
                }
            }
        })?;
    Ok(())
}
