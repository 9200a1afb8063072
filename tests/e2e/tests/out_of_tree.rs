//! The journeys of docs/writing-modules.md, docs/writing-plugins.md and docs/app_mode.md
//! as a user outside this workspace takes them: crates of their own made of the pages'
//! `Cargo.toml`, code and config, built by cargo against this repository's crates by
//! path, and run by this repository's `aimrt_main` (or as the app itself). The pages' text
//! is the tests' input, so the pages cannot drift from what works.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The fenced blocks of `text` whose fence names `lang`, in order.
fn blocks(text: &str, lang: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut current: Option<String> = None;
    for line in text.lines() {
        match (&mut current, line.trim_start().strip_prefix("```")) {
            (None, Some(fence)) if fence.trim() == lang => current = Some(String::new()),
            (Some(_), Some(_)) => out.extend(current.take()),
            (Some(block), None) => {
                block.push_str(line);
                block.push('\n');
            }
            (None, _) => {}
        }
    }
    out
}

/// The first block of `text` whose fence names `lang`; fails the test naming `what`.
fn first_block(text: &str, lang: &str, what: &str) -> String {
    blocks(text, lang)
        .into_iter()
        .next()
        .unwrap_or_else(|| panic!("no ```{lang} block: {what}"))
}

/// A crate of `files` (path, text) in a new folder, with the workspace's `Cargo.lock` (so
/// that nothing new is fetched) and a `./target` kept between runs; built by cargo,
/// offline. `/path/to/aimrt-rs` in the files is this repository.
fn build_crate(files: &[(&str, &str)]) -> tempfile::TempDir {
    let repo = root().canonicalize().expect("the repository");
    let dir = tempfile::tempdir().expect("tempdir");
    for (path, text) in files {
        let path = dir.path().join(path);
        std::fs::create_dir_all(path.parent().expect("a folder")).expect("folders");
        let text = text.replace("/path/to/aimrt-rs", &repo.display().to_string());
        std::fs::write(path, text).expect("write");
    }
    std::fs::copy(repo.join("Cargo.lock"), dir.path().join("Cargo.lock")).expect("Cargo.lock");
    let shared = aimrt_e2e::target_root().join("out-of-tree");
    std::fs::create_dir_all(&shared).expect("target/out-of-tree");
    std::os::unix::fs::symlink(&shared, dir.path().join("target")).expect("./target");
    let mut build = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    build
        .args(["build", "--offline"])
        .env_remove("CARGO_TARGET_DIR")
        .env_remove("CARGO_BUILD_TARGET_DIR");
    let out = aimrt_e2e::run_in(build, dir.path(), Duration::from_secs(600));
    out.assert_exit(0, "cargo build of the page's crate");
    dir
}

fn page() -> String {
    read_page("writing-modules.md")
}

fn read_page(name: &str) -> String {
    std::fs::read_to_string(root().join("docs").join(name)).expect("page")
}

/// The part of `page` from `heading` to the next heading of its level.
fn section<'a>(page: &'a str, heading: &str) -> &'a str {
    let (_, rest) = page.split_once(heading).expect("the section");
    rest.split("\n## ").next().unwrap_or(rest)
}

#[test]
fn the_pages_module_outside_this_workspace_builds_and_runs() {
    let page = page();
    let outside = section(&page, "## A module outside this workspace");
    let module = first_block(&page, "rust", "the module");
    let manifest = first_block(outside, "toml", "Cargo.toml");
    let config = first_block(outside, "yaml", "hello.yaml");
    assert!(
        manifest.contains("/path/to/aimrt-rs/plugin-api") && module.contains("HelloModule"),
        "the page changed its example:\n{manifest}\n{module}"
    );
    let dir = build_crate(&[
        ("Cargo.toml", &manifest),
        ("src/lib.rs", &module),
        ("hello.yaml", &config),
    ]);
    let out = aimrt_e2e::run_main_in(
        dir.path(),
        None,
        &["--cfg_file_path=hello.yaml", "--running_duration=1"],
        Duration::from_secs(30),
    );
    out.assert_exit(0, "the page's module runs");
    for said in ["][HelloModule][", "initialized", "hello from a task"] {
        assert!(out.stdout.contains(said), "no '{said}':\n{}", out.stdout);
    }
}

/// A recipe of the page's section on `.proto` files: the crate `name` made of the
/// section's `Cargo.toml` lines with the `extra` dependencies, and the `build.rs` and
/// `lib.rs` blocks of `text` (the section or one of its subsections).
struct Recipe {
    manifest: String,
    build_rs: String,
    lib_rs: String,
}

fn recipe(page: &str, text: &str, name: &str, extra: &str) -> Recipe {
    let section = section(page, "## RPC services and clients from `.proto` files");
    let deps = first_block(section, "toml", "the Cargo.toml lines");
    let rust = blocks(text, "rust");
    let block = |first: &str| {
        rust.iter()
            .find(|b| b.starts_with(first))
            .unwrap_or_else(|| panic!("no block starting {first}"))
            .clone()
    };
    let manifest = format!(
        "[package]\nname = \"{name}\"\nversion = \"0.1.0\"\nedition = \"2021\"\n\n[lib]\ncrate-type = [\"cdylib\", \"rlib\"]\n\n{}",
        deps.trim_start_matches("# Cargo.toml\n")
    )
    .replacen("[dependencies]\n", &format!("[dependencies]\n{extra}"), 1);
    Recipe {
        manifest,
        build_rs: block("// build.rs"),
        lib_rs: block("// lib.rs"),
    }
}

/// The page's recipe for code from `.proto` files (its `Cargo.toml` lines, `build.rs` and
/// `lib.rs`) builds, with a service of the user's own: the versions it names are the ones
/// the generated code needs.
#[test]
fn the_pages_recipe_for_proto_files_builds() {
    let page = page();
    let text = section(&page, "## RPC services and clients from `.proto` files");
    // serde_json only to look at the JSON below.
    let r = recipe(&page, text, "my_service_pkg", "serde_json = \"1\"\n");
    assert!(
        r.build_rs.contains("proto/my_service.proto") && r.lib_rs.contains("\"my.pkg\""),
        "the page changed its recipe:\n{}\n{}",
        r.build_rs,
        r.lib_rs
    );
    // Messages named by Rust keywords too (their impls name them as prost does).
    let proto = "syntax = \"proto3\";\npackage my.pkg;\nmessage HelloReq { string name = 1; }\nmessage HelloRsp { string text = 1; int64 count = 2; }\nservice Greeter { rpc Hello(HelloReq) returns (HelloRsp); }\nmessage Type { message Inner { string s = 1; } Inner inner = 1; }\nmessage Self { int32 x = 1; }\n";
    // The generated service and client are there, with the messages' JSON.
    let use_them = "\npub fn json() -> String {\n    let rsp = my_pkg::HelloRsp { text: \"hi\".into(), count: 1 };\n    serde_json::to_string(&rsp).unwrap_or_default()\n}\n\n#[allow(dead_code)]\nfn names() -> (&'static str, Option<my_pkg::GreeterClient>) {\n    (my_pkg::GREETER_NAME, None)\n}\n";
    build_crate(&[
        ("Cargo.toml", &r.manifest),
        ("build.rs", &r.build_rs),
        ("src/lib.rs", &format!("{}{use_them}", r.lib_rs)),
        ("proto/my_service.proto", proto),
    ]);
}

/// The page's recipe for a `.proto` file that imports another crate's package and Google's
/// well-known types builds, and its message holds those crates' types, not copies
/// generated again: the page's `lib.rs` puts an `aimrt_protocols::example::ExampleFoo` and
/// a `pbjson_types::Timestamp` into the generated message, whose JSON a test of the crate
/// prints; its service takes `google.protobuf.Empty`.
#[test]
fn the_pages_recipe_for_imported_packages_builds() {
    let page = page();
    let (_, sub) = section(&page, "## RPC services and clients from `.proto` files")
        .split_once("### Imported packages")
        .expect("the subsection");
    let proto = first_block(sub, "proto", "the .proto file");
    let more: String = first_block(sub, "toml", "the Cargo.toml line")
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| format!("{l}\n"))
        .collect();
    let Recipe {
        manifest,
        build_rs,
        lib_rs,
    } = recipe(&page, sub, "my_topics_pkg", &more);
    assert!(
        proto.contains("import \"common.proto\"")
            && proto.contains("rpc Latest(google.protobuf.Empty)")
            && build_rs.contains(".extern_path(\".aimrt.protocols.example\"")
            && lib_rs.contains("aimrt_protocols::example::ExampleFoo")
            && lib_rs.contains("pbjson_types::Timestamp"),
        "the page changed its recipe:\n{proto}\n{build_rs}\n{lib_rs}"
    );
    // The JSON of the page's message, and the service's generated names.
    let print = "\n#[test]\nfn prints_json() {\n    use aimrt_plugin_api::channel::Message;\n    let foo = aimrt_protocols::example::ExampleFoo { code: 7, data: \"x\".into() };\n    let m = stamped(Timestamp { seconds: 1, nanos: 0 }, foo);\n    let json = m.encode(\"json\").expect(\"json\");\n    println!(\"JSON {} {}\", String::from_utf8_lossy(&json), my_topics::FOO_LOG_NAME);\n    let _: Option<my_topics::FooLogClient> = None;\n}\n";
    let dir = build_crate(&[
        ("Cargo.toml", &manifest),
        ("build.rs", &build_rs),
        ("src/lib.rs", &format!("{lib_rs}{print}")),
        ("proto/my_topics.proto", proto.as_str()),
    ]);
    let mut test = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    test.args(["test", "--offline", "--lib", "--", "--nocapture"])
        .env_remove("CARGO_TARGET_DIR")
        .env_remove("CARGO_BUILD_TARGET_DIR");
    let out = aimrt_e2e::run_in(test, dir.path(), Duration::from_secs(600));
    out.assert_exit(0, "the crate's test");
    assert!(
        out.stdout.contains(
            r#"JSON {"stamp":"1970-01-01T00:00:01Z","foo":{"code":7,"data":"x"}} my.topics.FooLog"#
        ),
        "{}",
        out.stdout
    );
}

/// The executor plugin of writing-plugins.md, exported from a `cdylib` as the page says,
/// runs the tasks of writing-modules.md's module: the module's config names an executor
/// of the plugin's type.
#[test]
fn the_plugin_pages_executor_runs_the_module_pages_tasks() {
    let modules = page();
    let outside = section(&modules, "## A module outside this workspace");
    let manifest = first_block(outside, "toml", "Cargo.toml");
    let module = first_block(&modules, "rust", "the module");
    let plugins = read_page("writing-plugins.md");
    let plugin = first_block(&plugins, "rust", "the plugin");
    let export = plugins
        .split('`')
        .find(|s| s.starts_with("aimrt_plugin_api::export_plugin!("))
        .expect("the page's export line")
        .replace("my_crate::", "");
    assert!(
        plugin.contains("\"inline\"") && plugin.contains("inline_plugin"),
        "the page changed its example:\n{plugin}"
    );
    let built = build_crate(&[
        (
            "Cargo.toml",
            &manifest.replace("name = \"hello_pkg\"", "name = \"inline_plugin\""),
        ),
        ("src/lib.rs", &format!("{plugin}\n{export}\n")),
    ]);
    let lib = built.path().join("target/debug/libinline_plugin.so");
    // Its own package name: the first test's `libhello_pkg.so` is rewritten while it runs.
    let run = build_crate(&[
        (
            "Cargo.toml",
            &manifest.replace("name = \"hello_pkg\"", "name = \"tasks_pkg\""),
        ),
        ("src/lib.rs", &module),
    ]);
    let config = format!(
        "aimrt:\n  plugin:\n    plugins: [{{name: inline_plugin, path: {}}}]\n  log: {{backends: [{{type: console}}]}}\n  executor:\n    executors: [{{name: work, type: inline}}]\n  module:\n    pkgs: [{{path: ./target/debug/libtasks_pkg.so}}]\nHelloModule:\n  executor: work\n",
        lib.display()
    );
    let out = aimrt_e2e::run_main_in(
        run.path(),
        Some(&config),
        &["--cfg_file_path=cfg.yaml", "--running_duration=1"],
        Duration::from_secs(30),
    );
    out.assert_exit(0, "the plugin's executor runs the module's task");
    for said in [
        "Load plugin 'inline_plugin'",
        "][HelloModule][",
        "hello from a task",
    ] {
        assert!(out.stdout.contains(said), "no '{said}':\n{}", out.stdout);
    }
}

/// app_mode.md's app, with its `Cargo.toml` and writing-modules.md's module as `MyModule`:
/// it builds, runs the module's task, and stops on Ctrl-C with exit 0.
#[test]
fn the_app_mode_pages_app_builds_runs_and_stops_on_ctrl_c() {
    let app_page = read_page("app_mode.md");
    let writing = section(&app_page, "## Writing an app");
    let main = first_block(writing, "rust", "main");
    let manifest = first_block(writing, "toml", "Cargo.toml");
    let module = first_block(&page(), "rust", "the module")
        .replace("aimrt_plugin_api::export_modules!(HelloModule);", "")
        .replace("pub struct HelloModule", "pub struct MyModule")
        .replace("impl Module for HelloModule", "impl Module for MyModule");
    assert!(main.contains("MyModule::default()"), "{main}");
    let built = build_crate(&[
        ("Cargo.toml", &manifest),
        ("src/main.rs", &format!("{main}\n{module}")),
    ]);
    let program = built.path().join("target/debug/my_app");
    let config = "aimrt:\n  log: {backends: [{type: console}]}\n  executor:\n    executors: [{name: work, type: asio_thread}]\nHelloModule:\n  executor: work\n";
    let mut app = aimrt_e2e::Running::start_program(&program, &[], config);
    app.wait_for("hello from a task", Duration::from_secs(30));
    assert_eq!(
        app.interrupt(Duration::from_secs(30)),
        Some(0),
        "{}",
        app.text()
    );
    assert!(app.text().contains("][HelloModule]["), "{}", app.text());
}
