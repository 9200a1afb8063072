//! Any HTTP/2 frames (after the client preface) as one connection to grpc_plugin's
//! server: an answer or a closed connection, never a panic or a hang.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = aimrt_grpc::__fuzz::serve_bytes(data);
});
