//! Process limits `aimrt_main` adjusts at start.

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
