//! SIGINT/SIGTERM: the first asks for a graceful shutdown, a second during shutdown exits
//! at once (status 128 + signal). Handled on a thread fed by signal-hook's self-pipe,
//! never inside the signal handler.
//!
//! A repeat within [`SAME_REQUEST`] (500 ms) of the first is the same request delivered twice, not
//! a second one: `timeout(1)` sends its signal both to the process and to the process's
//! group, so a process run under it gets two SIGTERMs microseconds apart. Taken as a
//! second request, that repeat cut every such run's graceful shutdown short whenever the
//! first had been handled before the second arrived (an MCAP bag left without its
//! summary, a zenoh session not closed).

use std::time::{Duration, Instant};

use signal_hook::consts::{SIGINT, SIGTERM};
use signal_hook::iterator::Signals;

/// A signal this soon after the first request is taken as that request again.
const SAME_REQUEST: Duration = Duration::from_millis(500);

/// What one received signal does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    /// The first: shutdown was requested.
    Requested,
    /// The first request again, within [`SAME_REQUEST`] of it.
    Repeat,
    /// A signal during shutdown: exit at once. `second`: this thread had taken a signal
    /// as the request (else `--running_duration` or a module asked first).
    Exit { second: bool },
}

/// The signals seen so far.
#[derive(Debug, Default)]
struct Seen {
    /// When this thread requested the shutdown (`None`: not yet, or another way did).
    requested_at: Option<Instant>,
}

impl Seen {
    /// One signal at `now`; `requested` is what asking for the shutdown returned
    /// (`false`: it had been asked for already).
    fn signal(&mut self, now: Instant, requested: bool) -> Verdict {
        if requested {
            self.requested_at = Some(now);
            return Verdict::Requested;
        }
        match self.requested_at {
            Some(at) if now.saturating_duration_since(at) < SAME_REQUEST => Verdict::Repeat,
            at => Verdict::Exit {
                second: at.is_some(),
            },
        }
    }
}

/// Calls `request` on the first SIGINT/SIGTERM (it returns `false` when shutdown was
/// already requested); on a second signal, exits the process immediately. A repeat
/// within 500 ms of the first is that request again (said on stderr).
pub fn on_signals(request: impl Fn() -> bool + Send + 'static) -> std::io::Result<()> {
    let mut signals = Signals::new([SIGINT, SIGTERM])?;
    std::thread::Builder::new()
        .name("aimrt_signal".into())
        .spawn(move || {
            let mut seen = Seen::default();
            for sig in signals.forever() {
                match seen.signal(Instant::now(), request()) {
                    Verdict::Requested => {}
                    Verdict::Repeat => crate::say_err(format_args!(
                        "Received signal {sig} again within {} ms of the first: the same request (timeout(1) sends it twice); send it again later to exit at once.",
                        SAME_REQUEST.as_millis()
                    )),
                    Verdict::Exit { second } => {
                        crate::say_err(format_args!(
                            "Received signal {sig} {}: exiting at once.",
                            if second {
                                "again during shutdown"
                            } else {
                                "during a shutdown that --running_duration or a module asked for"
                            }
                        ));
                        std::process::exit(128 + sig);
                    }
                }
            }
        })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_repeat_soon_after_the_first_is_the_same_request_and_a_later_one_exits() {
        let t0 = Instant::now();
        let mut seen = Seen::default();
        assert_eq!(seen.signal(t0, true), Verdict::Requested);
        // timeout(1)'s second SIGTERM, microseconds later; then one just inside the window.
        assert_eq!(
            seen.signal(t0 + Duration::from_micros(20), false),
            Verdict::Repeat
        );
        assert_eq!(
            seen.signal(t0 + SAME_REQUEST - Duration::from_millis(1), false),
            Verdict::Repeat
        );
        // The window counts from the request, not from the last repeat.
        assert_eq!(
            seen.signal(t0 + SAME_REQUEST, false),
            Verdict::Exit { second: true }
        );
    }

    #[test]
    fn a_signal_during_a_shutdown_requested_another_way_exits_at_once() {
        // `--running_duration` or a module asked first: nothing here to repeat.
        let mut seen = Seen::default();
        assert_eq!(
            seen.signal(Instant::now(), false),
            Verdict::Exit { second: false }
        );
    }
}
