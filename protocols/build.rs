//! Compiles the `.proto` files with protox (pure Rust, no `protoc`) and generates Rust
//! types with prost, deriving serde for the `json` format.

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
    prost_build::Config::new()
        .type_attribute(
            ".",
            "#[derive(serde::Serialize, serde::Deserialize)] #[serde(default)]",
        )
        .compile_fds(fds)?;
    Ok(())
}
