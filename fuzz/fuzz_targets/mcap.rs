//! Any bytes as one MCAP file of a bag played back (record_playback_plugin's reader):
//! read to its end or its damage, never a panic, a hang or an allocation of what a
//! damaged length claims (libFuzzer's `-rss_limit_mb` catches that).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    aimrt_record_playback::__fuzz::read_mcap(data);
});
