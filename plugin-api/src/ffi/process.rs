//! Process-wide settings of the C library that the host applies once, at start-up.

/// Freed heap memory below this size stays in the process for reuse (glibc's
/// `M_TRIM_THRESHOLD`).
pub const KEEP_FREED_BYTES: usize = 64 << 20;
/// Allocations below this size come from the heap, not from a fresh `mmap` (glibc's
/// `M_MMAP_THRESHOLD`, at its largest).
pub const HEAP_ALLOCATION_LIMIT: usize = 32 << 20;

/// Tells glibc's allocator to keep freed memory for reuse: allocations up to
/// [`HEAP_ALLOCATION_LIMIT`] come from the heap, and free memory up to
/// [`KEEP_FREED_BYTES`] is not returned to the kernel. Without this, every large message
/// (over 128 KiB by default) is a fresh `mmap` whose pages fault in one by one; on a
/// virtual machine a 1 MiB buffer costs about a millisecond of page faults, each time.
/// Fixed thresholds also stop glibc's dynamic threshold from moving while the process
/// runs. Returns whether glibc took both settings (`false` elsewhere than glibc).
///
/// ```
/// let _ = aimrt_plugin_api::ffi::keep_freed_memory();
/// ```
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let trim = libc::c_int::try_from(KEEP_FREED_BYTES).unwrap_or(libc::c_int::MAX);
        let mmap = libc::c_int::try_from(HEAP_ALLOCATION_LIMIT).unwrap_or(libc::c_int::MAX);
        // SAFETY: mallopt takes two plain integers and only changes thresholds of the
        // allocator; glibc serializes it with its arenas, so any thread may call it at any
        // time, and no memory is touched.
        let trimmed = unsafe { libc::mallopt(libc::M_TRIM_THRESHOLD, trim) };
        // SAFETY: as above.
        let mapped = unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, mmap) };
        trimmed == 1 && mapped == 1
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}
