//! Any bytes as what net_plugin reads from a peer: a tcp stream's frames and each frame's
//! body (AimRT's channel and RPC layout, meta included), and the same bytes as one UDP
//! datagram's body. An error, never a panic; frames never hold more than the stream.
#![no_main]

use aimrt_net::wire::{split_frames, Body, Frame};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = Body::decode(data);
    let mut stream = data.to_vec();
    if let Ok(frames) = split_frames(&mut stream, 1 << 16) {
        let mut held = stream.len();
        for frame in &frames {
            held += 6;
            if let Frame::Body(body) = frame {
                held += body.len();
                let _ = Body::decode(body);
            }
        }
        assert_eq!(held, data.len(), "frames and the rest are the stream");
    }
});
