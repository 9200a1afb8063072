//! Any bytes as an `aimrt_main` config: an error or `Ok`, never a panic or a hang.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = aimrt_runtime::check_config("fuzz.yaml", text);
    }
});
