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
    // AimRT's common robot messages (header, geometry, imu, image, joint and touch states),
    // unmodified: each file imports the others by bare name, hence the three folders.
    aimrt_codegen::compile(
        &[
            "proto/common/error.proto",
            "proto/common/header.proto",
            "proto/common/module.proto",
            "proto/geometry/quaternion.proto",
            "proto/geometry/vector3.proto",
            "proto/sensor/image.proto",
            "proto/sensor/imu.proto",
            "proto/sensor/joint_state.proto",
            "proto/sensor/touch_sensor_state.proto",
        ],
        &["proto/common", "proto/geometry", "proto/sensor"],
    )?;
    // record_playback_plugin's control service, AimRT's file unmodified.
    aimrt_codegen::compile(
        &["proto/record_playback_plugin/record_playback.proto"],
        &["proto/record_playback_plugin"],
    )?;
    // The control services of log_control_plugin and parameter_plugin: AimRT's package,
    // messages and field numbers, in files of ours. Their maps are ordered, so that an
    // answer lists loggers, modules and keys in byte order.
    aimrt_codegen::Builder::new()
        .btree_map(".aimrt.protocols.log_control_plugin")
        .btree_map(".aimrt.protocols.parameter_plugin")
        .compile(
            &[
                "proto/log_control_plugin/log_control.proto",
                "proto/parameter_plugin/parameter.proto",
            ],
            &["proto/log_control_plugin", "proto/parameter_plugin"],
        )?;
    // What topic_logger_plugin publishes: AimRT's package, messages and field numbers, in a
    // file of ours.
    aimrt_codegen::compile(
        &["proto/topic_logger_plugin/topic_logger.proto"],
        &["proto/topic_logger_plugin"],
    )?;
    Ok(())
}
