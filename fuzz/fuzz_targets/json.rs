//! Any bytes as the JSON of protobuf messages (an HTTP body, a channel message in
//! `json`): pbjson's reader with ours around it (`null` members absent, the error's
//! path and words). An error, never a panic; a message that reads is written as JSON
//! that reads back to the same message (compared by its protobuf bytes).
#![no_main]

use aimrt_plugin_api::channel::Message;
use aimrt_protocols::parameter_plugin::LoadParameterReq;
use aimrt_protocols::record_playback_plugin::UpdateRecordActionReq;
use aimrt_protocols::sensor::{CompressedImage, ImuState, JointStateArray};

fn round_trip<M: Message>(data: &[u8]) {
    let Ok(read) = M::decode("json", data) else {
        return;
    };
    let json = read.encode("json").expect("a message read from JSON writes as JSON");
    let again = M::decode("json", &json).unwrap_or_else(|e| {
        panic!("our JSON does not read back: {e}: {}", String::from_utf8_lossy(&json))
    });
    assert_eq!(
        read.encode("pb").expect("pb"),
        again.encode("pb").expect("pb"),
        "JSON round trip changed the message: {}",
        String::from_utf8_lossy(&json)
    );
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    round_trip::<ImuState>(data);
    round_trip::<JointStateArray>(data);
    round_trip::<CompressedImage>(data);
    round_trip::<LoadParameterReq>(data);
    round_trip::<UpdateRecordActionReq>(data);
});
