//! echo_plugin (ABI 1.3: type support packages, plugins subscribing by type name): AimRT's
//! example config as is, each echo type, and the configs it refuses.

use std::time::Duration;

use aimrt_e2e::{aimrt_example, assert_failure, run_main, Output};

const LIMIT: Duration = Duration::from_secs(60);

fn example() -> String {
    aimrt_example("echo_plugin_pb", "examples_plugins_echo_plugin_pb_cfg.yaml")
        .replace("channel_frq: 0.5", "channel_frq: 10")
}

/// Runs `cfg` for 3 s: about 30 messages at 10 Hz, and at least 5 also when start-up is
/// slow on a loaded machine (with 1 s, a CI run that started slowly published 1).
fn run(cfg: &str) -> Output {
    let out = run_main(
        Some(cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=3"],
        LIMIT,
    );
    assert!(!out.stdout.contains("panicked at"), "{}", out.stdout);
    out
}

#[test]
fn aimrts_example_prints_every_message_as_json() {
    let out = run(&example());
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    assert!(
        out.stdout.contains("loaded type support pkg")
            && out
                .stdout
                .contains("pb:aimrt.protocols.example.ExampleEventMsg"),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout
            .contains("---\n{\n   \"msg\": \"count: 1\",\n   \"num\": 1\n}\n---"),
        "{}",
        out.stdout
    );
    let published = out.stdout.matches("Publish new pb event").count();
    let echoed = out.stdout.matches("\n---\n{").count();
    assert!(published >= 5, "{published} published");
    // Every message published while the plugin subscribed is echoed once (the last one
    // may be published as the run stops).
    assert!(
        echoed == published || echoed + 1 == published,
        "{published} published, {echoed} echoed"
    );
}

#[test]
fn yaml_and_the_types_own_formats_are_printed_too() {
    let out = run(&example().replace("echo_type: json", "echo_type: yaml"));
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    assert!(
        out.stdout.contains("---\nmsg: 'count: 1'\nnum: 1\n---")
            || out.stdout.contains("---\nmsg: \"count: 1\"\nnum: 1\n---"),
        "{}",
        out.stdout
    );
    let out = run(&example().replace("echo_type: json", "echo_type: pb"));
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    // ExampleEventMsg{msg: "count: 1", num: 1} in protobuf.
    assert!(
        out.stdout.contains("---\n0a08636f756e743a20311001\n---"),
        "{}",
        out.stdout
    );
}

#[test]
fn bad_echo_configs_are_refused_with_what_would_be_right() {
    let cases = [
        (
            example().replace(
                "pb:aimrt.protocols.example.ExampleEventMsg",
                "pb:aimrt.protocols.example.NoSuchMsg",
            ),
            vec![
                "topic_meta_list[0].msg_type 'pb:aimrt.protocols.example.NoSuchMsg' is in no type support pkg",
                "loaded: pb:aimrt.protocols.example.ExampleEventMsg",
            ],
        ),
        (
            example().replace(
                "pb:aimrt.protocols.example.ExampleEventMsg",
                "pb:aimrt.protocols.example.ExampleEventMg",
            ),
            vec![
                "is in no type support pkg; did you mean 'pb:aimrt.protocols.example.ExampleEventMsg'?",
            ],
        ),
        (
            example().replace("libexample_pb_ts.so", "libno_such_ts.so"),
            vec!["type_support_pkgs[0].path", "cannot open the library"],
        ),
        (
            example().replace(
                "path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_pb_ts.so",
                "path: ${AIMRT_LIB_DIR:-./target/debug}/libpb_chn_sub_pkg.so",
            ),
            vec!["offers no message types", "export_type_support!"],
        ),
        (
            example().replace("echo_type: json", "echo_type: xml"),
            vec!["echo_type 'xml' is not a format of", "pb, json"],
        ),
        (
            example().replace(
                "              echo_type: json",
                "              echo_type: json\n            - topic_name: test_topic\n              msg_type: pb:aimrt.protocols.example.ExampleEventMsg",
            ),
            vec!["topic_meta_list[1]: topic 'test_topic' with type", "listed twice"],
        ),
        (
            example().replace("topic_meta_list:", "topic_metas:"),
            vec!["topic_metas"],
        ),
    ];
    for (cfg, expected) in &cases {
        let out = run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        assert_failure(&out, expected);
    }
}
