//! Generates AimRT's example protocol with `aimrt-codegen`: prost types, their proto3 JSON
//! as AimRT prints it, `Message` impls, and `ExampleService`'s traits and client.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // rpc.proto, common.proto and benchmark.proto are AimRT's, unmodified (rpc.proto imports
    // "common.proto" from its own folder, hence that folder as the include path).
    aimrt_codegen::compile(
        &[
            "proto/example/example.proto",
            "proto/example/common.proto",
            "proto/example/rpc.proto",
            "proto/example/benchmark.proto",
        ],
        &["proto/example"],
    )?;
    // record_playback_plugin's control service, AimRT's file unmodified.
    aimrt_codegen::compile(
        &["proto/record_playback_plugin/record_playback.proto"],
        &["proto/record_playback_plugin"],
    )?;
    Ok(())
}
