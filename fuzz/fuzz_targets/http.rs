//! Any bytes as one HTTP connection to net_plugin's server: an answer (or none), never a
//! panic or a hang.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = aimrt_net::__fuzz::serve_bytes(data);
});
