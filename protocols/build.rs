//! Compiles the `.proto` files with protox (pure Rust, no `protoc`), generates Rust types
//! with prost and their proto3 JSON mapping with pbjson, as AimRT prints it: proto field
//! names, 64-bit integers as strings, fields at their default value included.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // rpc.proto and common.proto are AimRT's, unmodified (rpc.proto imports
    // "common.proto" from its own folder, hence that folder as the include path).
    let protos = [
        "proto/example/example.proto",
        "proto/example/common.proto",
        "proto/example/rpc.proto",
    ];
    for p in protos {
        println!("cargo:rerun-if-changed={p}");
    }
    let fds = protox::compile(protos, ["proto/example"])?;
    let descriptors = prost::Message::encode_to_vec(&fds);
    prost_build::Config::new().compile_fds(fds)?;
    pbjson_build::Builder::new()
        .register_descriptors(&descriptors)?
        .preserve_proto_field_names()
        .emit_fields()
        .build(&[".aimrt"])?;
    Ok(())
}
