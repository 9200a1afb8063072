//! Hands the target triple to the crate so every library's descriptor can carry it.
fn main() {
    let target = std::env::var("TARGET").unwrap_or_else(|_| "unknown".to_owned());
    println!("cargo:rustc-env=AIMRT_TARGET={target}");
    println!("cargo:rerun-if-changed=build.rs");
}
