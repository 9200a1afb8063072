//! Any bytes as a zenoh_plugin payload from a foreign peer: a channel message, an RPC
//! request and an RPC answer (both forms of AimRT's error answer). An error, never a
//! panic; a channel message that reads encodes again to bytes that read the same.
#![no_main]

use aimrt_zenoh::wire::{encode_channel, ChannelView, Request, Response};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(view) = ChannelView::decode(data) {
        let again = encode_channel(view.serialization_type, view.meta.iter(), view.message)
            .expect("what was read fits the layout");
        assert_eq!(ChannelView::decode(&again).as_ref(), Ok(&view));
    }
    let _ = Request::decode(data);
    let _ = Response::decode(data);
});
