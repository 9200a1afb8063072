//! Any bytes as what net_plugin reads from a peer: a tcp stream's frames and each frame's
//! body (AimRT's channel and RPC layout, meta included), and the same bytes as one UDP
//! datagram's body. An error, never a panic; frames never hold more than the stream.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| aimrt_net::wire::read_any(data));
