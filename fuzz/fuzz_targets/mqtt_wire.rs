//! Any bytes as an mqtt_plugin payload from a foreign publisher: a channel message, an RPC
//! request, an RPC answer. An error, never a panic; what reads writes back byte for byte.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| aimrt_mqtt::wire::read_any(data));
