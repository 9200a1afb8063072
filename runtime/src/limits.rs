//! Process limits and settings `aimrt_main` adjusts at start.

/// Raises the soft limit on open files to the hard limit, so a server with many clients
/// (net_plugin's `http_options.max_connections`, 4096 by default) is not cut short by a
/// soft limit of 1024. Returns the `(old, new)` soft limit.
///
/// ```
/// let (old, new) = aimrt_runtime::raise_open_file_limit().unwrap();
/// assert!(new >= old);
/// ```
pub fn raise_open_file_limit() -> std::io::Result<(u64, u64)> {
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    let (soft, hard) = getrlimit(Resource::RLIMIT_NOFILE).map_err(std::io::Error::from)?;
    // An unlimited hard limit cannot be a soft one (the kernel caps files at nr_open).
    let target = hard.min(1 << 20);
    if soft < target {
        setrlimit(Resource::RLIMIT_NOFILE, target, hard).map_err(std::io::Error::from)?;
        return Ok((soft, target));
    }
    Ok((soft, soft))
}

/// Turns off the backtraces that libraries' errors record (`RUST_LIB_BACKTRACE=0`) unless
/// the environment sets `RUST_LIB_BACKTRACE` itself; returns whether it did. What
/// `RUST_BACKTRACE` does for panics is unchanged.
///
/// With `RUST_BACKTRACE` set and `RUST_LIB_BACKTRACE` not, every error of a library that
/// records one (anyhow's, which zenoh creates, e.g. for each failed connect attempt) walks
/// the stack, and one that runs out of memory while doing so hangs the process instead of
/// aborting it: Rust's out-of-memory hook waits for the lock that the recording thread
/// holds itself (seen under `ulimit -v` with zenoh_plugin).
///
/// Call it first in `main`, before any thread starts: changing the environment while
/// another thread may read it is a data race.
///
/// ```
/// // In `main`, before anything else:
/// aimrt_runtime::no_library_backtraces();
/// assert!(std::env::var_os("RUST_LIB_BACKTRACE").is_some());
/// ```
pub fn no_library_backtraces() -> bool {
    if std::env::var_os("RUST_LIB_BACKTRACE").is_some() {
        return false;
    }
    std::env::set_var("RUST_LIB_BACKTRACE", "0");
    true
}
