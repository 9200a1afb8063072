//! Build-time code generation for aimrt-rs modules, from `.proto` files, with no `protoc`:
//! the files are compiled by protox (a protobuf compiler in Rust), then
//!
//! - prost generates the Rust types (`<package>.rs`);
//! - pbjson generates their JSON as AimRT prints it: proto field names, 64-bit integers as
//!   strings, fields at their default value included (`<package>.serde.rs`);
//! - this crate generates, per package (`<package>.aimrt.rs`), the
//!   [`Message`](https://docs.rs/aimrt-plugin-api) impl of every message (type name
//!   `pb:<full name>`, formats `pb` and `json`) and, per service `S`, through prost-build's
//!   service generator:
//!   - `S_NAME`, the default service name (`<package>.<S>`);
//!   - traits `SSync`, `SAsync` and `SCo` to implement a service synchronously, with a
//!     completion handle, or with `async fn`s; each method's default answers
//!     `SVR_NOT_IMPLEMENTED` (1002), as AimRT's; `register` / `register_as` serve it;
//!   - `SClient`, a typed client: `register` / `register_as`, and one `RpcClient` per
//!     method, to call blocking, as a future or with a callback.
//!
//! `build.rs` of a module crate:
//!
//! ```no_run
//! fn main() -> Result<(), Box<dyn std::error::Error>> {
//!     aimrt_codegen::compile(&["proto/example/rpc.proto"], &["proto/example"])?;
//!     Ok(())
//! }
//! ```
//!
//! and its `lib.rs` (with `aimrt-plugin-api`'s `prost` feature, `prost`, `pbjson` and
//! `serde` as dependencies):
//!
//! ```ignore
//! pub mod example {
//!     aimrt_plugin_api::include_proto!("aimrt.protocols.example");
//! }
//! ```
//!
//! A `.proto` file that imports a package another crate generated takes that crate's types
//! with [`Builder::extern_path`] (AimRT's `DEP_PROTO_TARGETS`) instead of generating them
//! again. Google's well-known types (`google/protobuf/timestamp.proto`, …) need nothing:
//! they come from `aimrt_plugin_api::pbjson_types`, with the proto3 JSON mapping.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use heck::{ToSnakeCase, ToUpperCamelCase};
use prost_types::{DescriptorProto, FileDescriptorSet};

/// Why generation failed.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The `.proto` files do not compile.
    #[error("cannot compile the .proto files: {0}")]
    Compile(String),
    /// Writing the generated files failed.
    #[error("cannot generate code from the .proto files: {0}")]
    Generate(String),
    /// `OUT_DIR` is not set (not run from a build script) and no directory was given.
    #[error("OUT_DIR is not set: run from a build script, or use Builder::out_dir")]
    NoOutDir,
    /// An [`Builder::extern_path`] that is not a protobuf path and a Rust path.
    #[error("extern_path({proto:?}, {rust:?}): {why}")]
    ExternPath {
        /// The protobuf path given.
        proto: String,
        /// The Rust path given.
        rust: String,
        /// What is wrong, and what would be right.
        why: String,
    },
}

/// Compiles `protos` (searched in `includes`) into `OUT_DIR` with the defaults.
pub fn compile(protos: &[impl AsRef<Path>], includes: &[impl AsRef<Path>]) -> Result<(), Error> {
    Builder::new().compile(protos, includes)
}

/// The package of Google's well-known types, and where generated code takes them from.
const WELL_KNOWN_PACKAGE: &str = ".google.protobuf";
const WELL_KNOWN_RUST: &str = "::aimrt_plugin_api::pbjson_types";

/// Generation settings.
#[derive(Debug, Default)]
pub struct Builder {
    out_dir: Option<PathBuf>,
    /// (protobuf path, Rust path) of the packages and types another crate generates.
    extern_paths: Vec<(String, String)>,
    /// Protobuf paths whose map fields are `BTreeMap`s.
    btree_maps: Vec<String>,
}

impl Builder {
    /// The defaults: output to `OUT_DIR`.
    pub fn new() -> Builder {
        Builder::default()
    }

    /// Writes the files to `dir` instead of `OUT_DIR`.
    pub fn out_dir(mut self, dir: impl Into<PathBuf>) -> Builder {
        self.out_dir = Some(dir.into());
        self
    }

    /// Takes the messages of the protobuf package (or message) `proto_path` from the Rust
    /// path `rust_path`, a crate that generated them with this crate, instead of
    /// generating them again: AimRT's `DEP_PROTO_TARGETS`. Fields and methods of the
    /// packages generated here use those types; nothing of `proto_path` is generated here
    /// (no types, JSON or `Message` impls), so one message has one Rust type in the whole
    /// process. `proto_path` is fully qualified, with a leading dot.
    ///
    /// Google's well-known types (`.google.protobuf`: `Timestamp`, `Empty`, the wrappers,
    /// …) are taken from `aimrt_plugin_api::pbjson_types` unless `.google.protobuf` is
    /// given here.
    ///
    /// A `.proto` file that imports AimRT's `common.proto`, in a crate that depends on
    /// `aimrt-protocols`:
    ///
    /// ```no_run
    /// aimrt_codegen::Builder::new()
    ///     .extern_path(".aimrt.protocols.example", "::aimrt_protocols::example")
    ///     .compile(
    ///         &["proto/my_service.proto"],
    ///         &["proto", "/path/to/aimrt-rs/protocols/proto/example"],
    ///     )
    ///     .expect("generated");
    /// ```
    pub fn extern_path(
        mut self,
        proto_path: impl Into<String>,
        rust_path: impl Into<String>,
    ) -> Builder {
        self.extern_paths
            .push((proto_path.into(), rust_path.into()));
        self
    }

    /// Generates the map fields of the protobuf path `proto_path` (a package, a message or
    /// a field, fully qualified; `"."` for every one) as `BTreeMap`s instead of `HashMap`s,
    /// so that their JSON lists the keys in order. prost's `btree_map`.
    ///
    /// ```no_run
    /// aimrt_codegen::Builder::new()
    ///     .btree_map(".my.pkg")
    ///     .compile(&["proto/my_service.proto"], &["proto"])
    ///     .expect("generated");
    /// ```
    pub fn btree_map(mut self, proto_path: impl Into<String>) -> Builder {
        self.btree_maps.push(proto_path.into());
        self
    }

    /// Whether the fully qualified protobuf name `fq` (`.pkg.Msg`, or `.pkg`) is taken
    /// from another crate.
    fn is_extern(&self, fq: &str) -> bool {
        self.extern_paths.iter().any(|(p, _)| {
            fq.strip_prefix(p.as_str())
                .is_some_and(|rest| rest.is_empty() || rest.starts_with('.'))
        })
    }

    /// Refuses extern paths prost and pbjson would refuse later, or take wrongly.
    fn check_extern_paths(&self) -> Result<(), Error> {
        for (proto, rust) in &self.extern_paths {
            let why = if !proto.starts_with('.') || proto.len() < 2 {
                Some("the protobuf path is fully qualified, with a leading dot: e.g. \".aimrt.protocols.example\"")
            } else if proto.ends_with('.')
                || proto[1..].split('.').any(|part| {
                    part.is_empty() || !part.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                })
            {
                Some("the protobuf path is names joined by dots: e.g. \".aimrt.protocols.example\"")
            } else if rust.is_empty()
                || rust.ends_with(':')
                || rust.chars().any(char::is_whitespace)
            {
                Some("the Rust path names a module or type: e.g. \"::aimrt_protocols::example\"")
            } else {
                None
            };
            if let Some(why) = why {
                return Err(Error::ExternPath {
                    proto: proto.clone(),
                    rust: rust.clone(),
                    why: why.to_owned(),
                });
            }
        }
        Ok(())
    }

    /// Compiles `protos` (searched in `includes`) and writes the three files of each
    /// package. Prints `cargo:rerun-if-changed` for each file given.
    pub fn compile(
        mut self,
        protos: &[impl AsRef<Path>],
        includes: &[impl AsRef<Path>],
    ) -> Result<(), Error> {
        self.check_extern_paths()?;
        // Google's well-known types come from aimrt-plugin-api (pbjson-types: prost types
        // with the proto3 JSON mapping, and `Message` impls), unless given another home.
        if !self
            .extern_paths
            .iter()
            .any(|(p, _)| p == WELL_KNOWN_PACKAGE)
        {
            self.extern_paths
                .push((WELL_KNOWN_PACKAGE.to_owned(), WELL_KNOWN_RUST.to_owned()));
        }
        let out_dir = match &self.out_dir {
            Some(d) => d.clone(),
            None => std::env::var_os("OUT_DIR")
                .map(PathBuf::from)
                .ok_or(Error::NoOutDir)?,
        };
        for p in protos {
            println!("cargo:rerun-if-changed={}", p.as_ref().display());
        }
        let fds = protox::compile(protos, includes).map_err(|e| Error::Compile(e.to_string()))?;
        // pbjson panics on a file without a package, and include_proto! names a package.
        if let Some(file) = fds.file.iter().find(|f| f.package().is_empty()) {
            return Err(Error::Compile(format!(
                "{} has no package: aimrt-codegen names each package's generated files after it (include_proto!(\"my.pkg\")); add a line `package my.pkg;` to it",
                file.name()
            )));
        }
        let descriptors = prost::Message::encode_to_vec(&fds);
        // Every message's schema for recordings: the serialized set of the files compiled
        // here (the message's file and its dependencies among them), one copy per package.
        let mut sets = BTreeMap::new();
        for file in &fds.file {
            let package = file.package().to_owned();
            if sets.contains_key(&package) {
                continue;
            }
            let name = format!("{package}.fds.bin");
            let path = out_dir.join(&name);
            std::fs::write(&path, &descriptors)
                .map_err(|e| Error::Generate(format!("{}: {e}", path.display())))?;
            sets.insert(package, name);
        }
        let packages = self.message_impls(&fds, &sets);
        let mut config = prost_build::Config::new();
        config.out_dir(&out_dir);
        let mut json = pbjson_build::Builder::new();
        for (proto, rust) in &self.extern_paths {
            config.extern_path(proto, rust);
            json.extern_path(proto, rust);
        }
        json.exclude(self.extern_paths.iter().map(|(proto, _)| proto.clone()));
        config.btree_map(&self.btree_maps);
        json.btree_map(self.btree_maps.iter().cloned());
        // prost's own mapping (to prost-types, `Empty` as `()`) is replaced by the above.
        config.compile_well_known_types();
        config.service_generator(Box::new(Services));
        config
            .compile_fds(fds)
            .map_err(|e| Error::Generate(e.to_string()))?;
        let prefixes: Vec<String> = packages.keys().map(|p| format!(".{p}")).collect();
        json.out_dir(&out_dir)
            .register_descriptors(&descriptors)
            .map_err(|e| Error::Generate(e.to_string()))?
            .preserve_proto_field_names()
            .emit_fields()
            .build(&prefixes)
            .map_err(|e| Error::Generate(e.to_string()))?;
        for (package, code) in packages {
            let path = out_dir.join(format!("{package}.aimrt.rs"));
            std::fs::write(&path, code)
                .map_err(|e| Error::Generate(format!("{}: {e}", path.display())))?;
        }
        Ok(())
    }

    /// `prost_message!` lines of every message not taken from another crate, by package
    /// (a package taken whole has no entry); `sets` holds the file name of each package's
    /// descriptor set. `include_bytes!` takes that name as it stands: a relative path is
    /// resolved next to the file that contains it, the `.aimrt.rs` beside the set, so the
    /// generated code still builds after its target directory moved (a renamed checkout, a
    /// `CARGO_TARGET_DIR` shared by two checkouts, a cached CI folder), where an absolute
    /// path would name a file that is gone.
    fn message_impls(
        &self,
        fds: &FileDescriptorSet,
        sets: &BTreeMap<String, String>,
    ) -> BTreeMap<String, String> {
        let mut out: BTreeMap<String, String> = BTreeMap::new();
        for file in &fds.file {
            let package = file.package().to_owned();
            if self.is_extern(&format!(".{package}")) {
                continue;
            }
            let set = format!(
                "include_bytes!({:?})",
                sets.get(&package).map_or("", String::as_str)
            );
            let code = out.entry(package.clone()).or_insert_with(|| {
                "// @generated by aimrt-codegen: the Message impls of this package.\n".to_owned()
            });
            for m in &file.message_type {
                self.impls_of(m, "", &package, &set, code);
            }
        }
        out
    }

    /// The `prost_message!` line of `m` and of its nested messages, except maps' entries
    /// and messages taken from another crate.
    fn impls_of(
        &self,
        m: &DescriptorProto,
        rust_prefix: &str,
        proto_prefix: &str,
        set: &str,
        code: &mut String,
    ) {
        if m.options.as_ref().is_some_and(|o| o.map_entry()) {
            return;
        }
        let rust = format!(
            "{rust_prefix}{}",
            rust_ident(&m.name().to_upper_camel_case())
        );
        let full = if proto_prefix.is_empty() {
            m.name().to_owned()
        } else {
            format!("{proto_prefix}.{}", m.name())
        };
        if self.is_extern(&format!(".{full}")) {
            return;
        }
        let _ = writeln!(
            code,
            "::aimrt_plugin_api::prost_message!({rust}, \"{full}\", {set});"
        );
        let nested_prefix = format!("{rust_prefix}{}::", rust_ident(&m.name().to_snake_case()));
        for n in &m.nested_type {
            self.impls_of(n, &nested_prefix, &full, set, code);
        }
    }
}

/// `ident` as prost names it in Rust: a keyword raw (`r#type`, the module of the messages
/// nested in `message Type`), or with `_` where a raw identifier is not allowed (`Self_`),
/// a leading digit behind `_`.
fn rust_ident(ident: &str) -> String {
    match ident {
        "as" | "break" | "const" | "continue" | "else" | "enum" | "false" | "fn" | "for" | "if"
        | "impl" | "in" | "let" | "loop" | "match" | "mod" | "move" | "mut" | "pub" | "ref"
        | "return" | "static" | "struct" | "trait" | "true" | "type" | "unsafe" | "use"
        | "where" | "while" | "dyn" | "abstract" | "become" | "box" | "do" | "final" | "macro"
        | "override" | "priv" | "typeof" | "unsized" | "virtual" | "yield" | "async" | "await"
        | "try" => format!("r#{ident}"),
        "_" | "super" | "self" | "Self" | "extern" | "crate" => format!("{ident}_"),
        s if s.starts_with(|c: char| c.is_numeric()) => format!("_{ident}"),
        _ => ident.to_owned(),
    }
}

/// prost-build's service generator: traits and a client per service.
struct Services;

impl prost_build::ServiceGenerator for Services {
    fn generate(&mut self, service: prost_build::Service, buf: &mut String) {
        service_code(&service, buf);
    }
}

const API: &str = "::aimrt_plugin_api";

fn service_code(s: &prost_build::Service, buf: &mut String) {
    let name = &s.name;
    // Every file has a package (`compile` refuses one without).
    let full = format!("{}.{}", s.package, s.proto_name);
    let konst = format!("{}_NAME", name.to_snake_case().to_uppercase());
    let w = buf;
    let _ = writeln!(
        w,
        "/// The default service name of `{full}` (renamed with `register_as`)."
    );
    let _ = writeln!(w, "pub const {konst}: &str = \"{full}\";");

    // Sync.
    let _ = writeln!(w, "/// `{full}`, served synchronously: each method runs on the thread that delivers the call.");
    let _ = writeln!(
        w,
        "pub trait {name}Sync: ::core::marker::Send + ::core::marker::Sync + 'static {{"
    );
    for m in &s.methods {
        let _ = writeln!(
            w,
            "    /// `{}`; by default answers `SVR_NOT_IMPLEMENTED`.",
            m.proto_name
        );
        let _ = writeln!(w, "    fn {}(&self, ctx: &{API}::RpcContext, req: &{}) -> ::core::result::Result<{}, {API}::RpcStatus> {{", m.name, m.input_type, m.output_type);
        let _ = writeln!(w, "        let _ = (ctx, req);\n        ::core::result::Result::Err({API}::RpcStatus::SVR_NOT_IMPLEMENTED)\n    }}");
    }
    registration(w, &konst, s, |m| {
        format!(
            "registration.sync::<{}, {}, _>(\"{}\", move |ctx, req| service.{}(ctx, req));",
            m.input_type, m.output_type, m.proto_name, m.name
        )
    });
    let _ = writeln!(w, "}}");

    // Async (completion handle).
    let _ = writeln!(w, "/// `{full}`, served with a completion handle: answer through the `Reply`, now or later, from any thread.");
    let _ = writeln!(
        w,
        "pub trait {name}Async: ::core::marker::Send + ::core::marker::Sync + 'static {{"
    );
    for m in &s.methods {
        let _ = writeln!(
            w,
            "    /// `{}`; by default answers `SVR_NOT_IMPLEMENTED`.",
            m.proto_name
        );
        let _ = writeln!(w, "    fn {}(&self, ctx: {API}::RpcContext, req: ::std::sync::Arc<{}>, reply: {API}::rpc::Reply<{}>) {{", m.name, m.input_type, m.output_type);
        let _ = writeln!(w, "        let _ = (ctx, req);\n        reply.send(::core::result::Result::Err({API}::RpcStatus::SVR_NOT_IMPLEMENTED));\n    }}");
    }
    registration(w, &konst, s, |m| {
        format!("registration.then::<{}, {}, _>(\"{}\", move |ctx, req, reply| service.{}(ctx, req, reply));", m.input_type, m.output_type, m.proto_name, m.name)
    });
    let _ = writeln!(w, "}}");

    // Co (async fn).
    let _ = writeln!(w, "/// `{full}`, served with `async fn`s (AimRT's co service): a call starts on the delivering thread and goes on wherever it is woken.");
    let _ = writeln!(
        w,
        "pub trait {name}Co: ::core::marker::Send + ::core::marker::Sync + 'static {{"
    );
    for m in &s.methods {
        let _ = writeln!(
            w,
            "    /// `{}`; by default answers `SVR_NOT_IMPLEMENTED`.",
            m.proto_name
        );
        let _ = writeln!(w, "    fn {}(&self, ctx: {API}::RpcContext, req: ::std::sync::Arc<{}>) -> impl ::core::future::Future<Output = ::core::result::Result<{}, {API}::RpcStatus>> + ::core::marker::Send {{", m.name, m.input_type, m.output_type);
        let _ = writeln!(w, "        let _ = (ctx, req);\n        ::core::future::ready(::core::result::Result::Err({API}::RpcStatus::SVR_NOT_IMPLEMENTED))\n    }}");
    }
    registration(w, &konst, s, |m| {
        format!("registration.co::<{}, {}, _, _>(\"{}\", move |ctx, req| {{ let service = service.clone(); async move {{ service.{}(ctx, req).await }} }});", m.input_type, m.output_type, m.proto_name, m.name)
    });
    let _ = writeln!(w, "}}");

    // Client.
    let _ = writeln!(w, "/// A client of `{full}`: one `RpcClient` per method (call blocking, as a future or with a callback).");
    let _ = writeln!(w, "#[derive(Clone, Debug)]\npub struct {name}Client {{");
    for m in &s.methods {
        let _ = writeln!(
            w,
            "    {}: {API}::RpcClient<{}, {}>,",
            m.name, m.input_type, m.output_type
        );
    }
    let _ = writeln!(w, "}}\nimpl {name}Client {{");
    let _ = writeln!(w, "    /// Registers every method as a client function of the module (in `initialize`), under the default service name.");
    let _ = writeln!(w, "    pub fn register(rpc: &{API}::RpcRef) -> ::core::result::Result<Self, {API}::Error> {{\n        Self::register_as(rpc, {konst})\n    }}");
    let _ = writeln!(w, "    /// Registers every method under `service_name` (AimRT's renamed proxy); stops at the first failure.");
    let _ = writeln!(w, "    pub fn register_as(rpc: &{API}::RpcRef, service_name: &str) -> ::core::result::Result<Self, {API}::Error> {{");
    let _ = writeln!(w, "        ::core::result::Result::Ok(Self {{");
    for m in &s.methods {
        let _ = writeln!(w, "            {}: rpc.client(&{API}::rpc::full_func_name(\"pb\", service_name, \"{}\"))?,", m.name, m.proto_name);
    }
    let _ = writeln!(w, "        }})\n    }}");
    for m in &s.methods {
        let _ = writeln!(w, "    /// The client of `{}`.", m.proto_name);
        let _ = writeln!(
            w,
            "    pub fn {}(&self) -> &{API}::RpcClient<{}, {}> {{\n        &self.{}\n    }}",
            m.name, m.input_type, m.output_type, m.name
        );
        let _ = writeln!(
            w,
            "    /// The client of `{}`, to set its default context.",
            m.proto_name
        );
        let _ = writeln!(w, "    pub fn {}_mut(&mut self) -> &mut {API}::RpcClient<{}, {}> {{\n        &mut self.{}\n    }}", m.name, m.input_type, m.output_type, m.name);
    }
    let _ = writeln!(w, "}}");
}

fn registration(
    w: &mut String,
    konst: &str,
    s: &prost_build::Service,
    line: impl Fn(&prost_build::Method) -> String,
) {
    let _ = writeln!(w, "    /// Filters around every method (AimRT's `RegisterFilter`; the last is the outermost). None by default.");
    let _ = writeln!(w, "    fn filters(&self) -> ::std::vec::Vec<{API}::rpc::RpcFilter> {{\n        ::std::vec::Vec::new()\n    }}");
    let _ = writeln!(w, "    /// Registers every method as a service function of the module (in `initialize`), under the default service name.");
    let _ = writeln!(w, "    fn register(self: ::std::sync::Arc<Self>, rpc: &{API}::RpcRef) -> ::core::result::Result<(), {API}::Error> where Self: Sized {{\n        self.register_as(rpc, {konst})\n    }}");
    let _ = writeln!(w, "    /// Registers every method under `service_name` (AimRT's `RegisterService(name, service)`); goes on after a failure and returns the first.");
    let _ = writeln!(w, "    fn register_as(self: ::std::sync::Arc<Self>, rpc: &{API}::RpcRef, service_name: &str) -> ::core::result::Result<(), {API}::Error> where Self: Sized {{");
    let _ = writeln!(w, "        let mut registration = {API}::rpc::ServiceRegistration::new(rpc, \"pb\", service_name).with_filters(self.filters());");
    for m in &s.methods {
        let _ = writeln!(
            w,
            "        {{\n            let service = self.clone();\n            {}\n        }}",
            line(m)
        );
    }
    let _ = writeln!(w, "        registration.finish()\n    }}");
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `files` (name, text) written to a new folder; `compile` run on `protos` of them
    /// (the folder is the include path) into its `out/`.
    fn generate(
        files: &[(&str, &str)],
        protos: &[&str],
        builder: Builder,
    ) -> (tempfile::TempDir, Result<(), Error>) {
        let dir = tempfile::tempdir().expect("temp dir");
        for (name, text) in files {
            std::fs::write(dir.path().join(name), text).expect("write proto");
        }
        let out = dir.path().join("out");
        std::fs::create_dir(&out).expect("out dir");
        let protos: Vec<PathBuf> = protos.iter().map(|p| dir.path().join(p)).collect();
        let result = builder.out_dir(&out).compile(&protos, &[dir.path()]);
        (dir, result)
    }

    fn read(dir: &tempfile::TempDir, name: &str) -> String {
        std::fs::read_to_string(dir.path().join("out").join(name))
            .unwrap_or_else(|e| panic!("{name}: {e}"))
    }

    #[test]
    fn the_generated_code_names_its_descriptor_set_relative_to_itself() {
        let (dir, result) = generate(
            &[(
                "moved.proto",
                "syntax = \"proto3\";\npackage moved.pkg;\nmessage Ping { uint64 seq = 1; }\n",
            )],
            &["moved.proto"],
            Builder::new(),
        );
        result.expect("compile");
        assert!(dir.path().join("out/moved.pkg.fds.bin").is_file());
        let code = read(&dir, "moved.pkg.aimrt.rs");
        assert!(
            code.contains("include_bytes!(\"moved.pkg.fds.bin\")"),
            "the set is not named by its file name:\n{code}"
        );
        // Nothing of where it was generated: moving the folder must not break the build.
        let root = dir.path().display().to_string();
        assert!(
            !code.contains(&root),
            "the generated code names {root}:\n{code}"
        );
    }

    const DEP: &str = "syntax = \"proto3\";\npackage dep.pkg;\nmessage Thing { int32 x = 1; message Inner { string s = 1; } }\nservice DepService { rpc Echo(Thing) returns (Thing); }\n";
    const MINE: &str = "syntax = \"proto3\";\npackage my.pkg;\nimport \"dep.proto\";\nmessage Uses { dep.pkg.Thing thing = 1; dep.pkg.Thing.Inner inner = 2; }\nservice Greeter { rpc Get(dep.pkg.Thing) returns (Uses); }\n";

    #[test]
    fn an_extern_package_is_used_from_its_crate_and_not_generated_again() {
        let (dir, result) = generate(
            &[("dep.proto", DEP), ("mine.proto", MINE)],
            &["mine.proto"],
            Builder::new().extern_path(".dep.pkg", "::dep_crate::pkg"),
        );
        result.expect("compile");
        let types = read(&dir, "my.pkg.rs");
        for used in ["::dep_crate::pkg::Thing", "::dep_crate::pkg::thing::Inner"] {
            assert!(types.contains(used), "no {used}:\n{types}");
        }
        // The service's methods take the other crate's type too.
        assert!(
            types.contains("req: &::dep_crate::pkg::Thing"),
            "the service does not use the extern type:\n{types}"
        );
        let impls = read(&dir, "my.pkg.aimrt.rs");
        assert!(
            impls.contains("prost_message!(Uses, \"my.pkg.Uses\""),
            "{impls}"
        );
        assert!(!impls.contains("Thing"), "{impls}");
        let json = read(&dir, "my.pkg.serde.rs");
        assert!(json.contains("impl serde::Serialize for Uses"), "{json}");
        // Nothing of the extern package: its types, JSON and Message impls are its crate's.
        for name in ["dep.pkg.aimrt.rs", "dep.pkg.serde.rs"] {
            assert!(
                !dir.path().join("out").join(name).exists(),
                "{name} was generated"
            );
        }
        let dep_types =
            std::fs::read_to_string(dir.path().join("out/dep.pkg.rs")).unwrap_or_default();
        assert!(
            !dep_types.contains("pub struct Thing"),
            "the extern type was generated again:\n{dep_types}"
        );

        // Without the extern path, the imported package is generated here too.
        let (dir, result) = generate(
            &[("dep.proto", DEP), ("mine.proto", MINE)],
            &["mine.proto"],
            Builder::new(),
        );
        result.expect("compile");
        assert!(read(&dir, "dep.pkg.aimrt.rs").contains("prost_message!(Thing, \"dep.pkg.Thing\""));
        assert!(read(&dir, "dep.pkg.rs").contains("pub struct Thing"));
    }

    #[test]
    fn btree_map_makes_the_map_fields_of_a_package_ordered_maps() {
        const MAPS: &str = "syntax = \"proto3\";\npackage maps.pkg;\nmessage Levels { map<string, string> by_name = 1; }\n";
        let (dir, result) = generate(&[("maps.proto", MAPS)], &["maps.proto"], Builder::new());
        result.expect("compile");
        assert!(read(&dir, "maps.pkg.rs").contains("::std::collections::HashMap<"));
        let (dir, result) = generate(
            &[("maps.proto", MAPS)],
            &["maps.proto"],
            Builder::new().btree_map(".maps.pkg"),
        );
        result.expect("compile");
        let types = read(&dir, "maps.pkg.rs");
        assert!(
            types.contains("::prost::alloc::collections::BTreeMap<") && !types.contains("HashMap"),
            "{types}"
        );
        // Its JSON reads into the same type.
        let json = read(&dir, "maps.pkg.serde.rs");
        assert!(json.contains("BTreeMap"), "{json}");
    }

    #[test]
    fn an_extern_message_is_left_to_its_crate_and_the_rest_of_its_package_generated() {
        let (dir, result) = generate(
            &[("dep.proto", DEP), ("mine.proto", MINE)],
            &["mine.proto"],
            Builder::new().extern_path(".dep.pkg.Thing", "::dep_crate::Thing"),
        );
        result.expect("compile");
        let impls = read(&dir, "dep.pkg.aimrt.rs");
        assert!(!impls.contains("prost_message!(Thing,"), "{impls}");
        assert!(
            !impls.contains("Inner"),
            "a message nested in an extern one: {impls}"
        );
        assert!(read(&dir, "my.pkg.rs").contains("::dep_crate::Thing"));
    }

    #[test]
    fn a_malformed_extern_path_is_refused_with_what_would_be_right() {
        for (proto, rust, says) in [
            ("dep.pkg", "::dep_crate::pkg", "with a leading dot"),
            (".", "::dep_crate::pkg", "with a leading dot"),
            (".dep..pkg", "::dep_crate::pkg", "names joined by dots"),
            (".dep.pkg.", "::dep_crate::pkg", "names joined by dots"),
            (".dep-pkg", "::dep_crate::pkg", "names joined by dots"),
            (".dep.pkg", "", "names a module or type"),
            (".dep.pkg", "::dep_crate::", "names a module or type"),
        ] {
            let (_dir, result) = generate(
                &[("dep.proto", DEP), ("mine.proto", MINE)],
                &["mine.proto"],
                Builder::new().extern_path(proto, rust),
            );
            let err = result.expect_err(proto).to_string();
            assert!(
                err.contains(says) && err.contains(&format!("{proto:?}")),
                "extern_path({proto:?}, {rust:?}): {err}"
            );
        }
    }

    #[test]
    fn messages_with_rust_keywords_for_names_are_named_as_prost_names_them() {
        let proto = "syntax = \"proto3\";\npackage kw;\nmessage Type { message Inner { string s = 1; } Inner inner = 1; }\nmessage Self { int32 x = 1; }\n";
        let (dir, result) = generate(&[("kw.proto", proto)], &["kw.proto"], Builder::new());
        result.expect("compile");
        let types = read(&dir, "kw.rs");
        let impls = read(&dir, "kw.aimrt.rs");
        for (rust, full) in [
            ("Type", "kw.Type"),
            ("r#type::Inner", "kw.Type.Inner"),
            ("Self_", "kw.Self"),
        ] {
            assert!(
                impls.contains(&format!("prost_message!({rust}, \"{full}\"")),
                "no impl for {rust}:\n{impls}"
            );
        }
        // The names prost gave them.
        assert!(
            types.contains("pub mod r#type {") && types.contains("pub struct Self_ {"),
            "{types}"
        );
    }

    #[test]
    fn a_file_without_a_package_is_refused_naming_it() {
        let proto = "syntax = \"proto3\";\nmessage Ping { int32 x = 1; }\n";
        let (_dir, result) = generate(&[("np.proto", proto)], &["np.proto"], Builder::new());
        let err = result.expect_err("no package").to_string();
        assert!(
            err.contains("np.proto has no package") && err.contains("package my.pkg;"),
            "{err}"
        );
    }

    #[test]
    fn googles_well_known_types_come_from_plugin_api() {
        let stamped = "syntax = \"proto3\";\npackage my.stamped;\nimport \"google/protobuf/timestamp.proto\";\nimport \"google/protobuf/empty.proto\";\nimport \"google/protobuf/wrappers.proto\";\nmessage Stamped { google.protobuf.Timestamp stamp = 1; google.protobuf.StringValue frame = 2; }\nservice Clock { rpc Now(google.protobuf.Empty) returns (Stamped); }\n";
        let (dir, result) = generate(
            &[("stamped.proto", stamped)],
            &["stamped.proto"],
            Builder::new(),
        );
        result.expect("compile");
        let types = read(&dir, "my.stamped.rs");
        for used in [
            "::aimrt_plugin_api::pbjson_types::Timestamp",
            "::aimrt_plugin_api::pbjson_types::StringValue",
            // prost's own mapping would make it `()`, which is no message.
            "req: &::aimrt_plugin_api::pbjson_types::Empty",
        ] {
            assert!(types.contains(used), "no {used}:\n{types}");
        }
        assert!(!types.contains("prost_types"), "{types}");
        for name in ["google.protobuf.aimrt.rs", "google.protobuf.serde.rs"] {
            assert!(
                !dir.path().join("out").join(name).exists(),
                "{name} was generated"
            );
        }
        assert!(read(&dir, "my.stamped.aimrt.rs").contains("prost_message!(Stamped,"));

        // Given another home, they are taken from there.
        let (dir, result) = generate(
            &[("stamped.proto", stamped)],
            &["stamped.proto"],
            Builder::new().extern_path(".google.protobuf", "::my_wkt"),
        );
        result.expect("compile");
        let types = read(&dir, "my.stamped.rs");
        assert!(
            types.contains("::my_wkt::Timestamp") && !types.contains("pbjson_types"),
            "{types}"
        );
    }

    /// The well-known types' files aimrt-plugin-api implements `Message` for.
    const WELL_KNOWN: [&str; 7] = [
        "google/protobuf/any.proto",
        "google/protobuf/duration.proto",
        "google/protobuf/empty.proto",
        "google/protobuf/field_mask.proto",
        "google/protobuf/struct.proto",
        "google/protobuf/timestamp.proto",
        "google/protobuf/wrappers.proto",
    ];

    /// aimrt-plugin-api keeps the descriptor set of Google's well-known types (their
    /// schema in recordings) as a file, not generated at its build; this is what protox
    /// makes of them. `AIMRT_WRITE_WKT_SET=1` writes it again.
    #[test]
    fn the_well_known_types_descriptor_set_of_plugin_api_is_protoxs() {
        let mut compiler =
            protox::Compiler::with_file_resolver(protox::file::GoogleFileResolver::new());
        compiler.include_imports(true).include_source_info(false);
        compiler
            .open_files(WELL_KNOWN)
            .expect("the well-known types");
        let set = prost::Message::encode_to_vec(&compiler.file_descriptor_set());
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../plugin-api/src/channel/google_protobuf.fds.bin");
        if std::env::var_os("AIMRT_WRITE_WKT_SET").is_some() {
            std::fs::write(&path, &set).expect("write the set");
        }
        let kept = std::fs::read(&path).unwrap_or_default();
        assert!(
            kept == set,
            "{} ({} bytes) is not protox's set of the well-known types ({} bytes): run this test with AIMRT_WRITE_WKT_SET=1",
            path.display(),
            kept.len(),
            set.len()
        );
    }
}
