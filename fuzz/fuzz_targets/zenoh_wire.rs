//! Any bytes as a zenoh_plugin payload from a foreign peer: a channel message, an RPC
//! request and an RPC answer (both forms of AimRT's error answer). An error, never a
//! panic; a channel message that reads encodes again to bytes that read the same.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| aimrt_zenoh::wire::read_any(data));
