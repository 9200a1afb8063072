//! Channel filters from a plugin (ABI 1.7): `config/channel_filter_plugin.yaml` with
//! `libexample_filters_plugin.so` — what each filter does to the messages, the order of a
//! chain, the counting of held-back messages, the init report, the errors of names that
//! are not filters of their side — and plugin libraries of ABI 1.6 and 1.7 running on this
//! host.

use std::time::Duration;

use aimrt_e2e::{assert_failure, repo_config, run_main, run_main_in, Output};

const LIMIT: Duration = Duration::from_secs(60);

fn run(cfg: &str, secs: u32) -> Output {
    let out = run_main(
        Some(cfg),
        &[
            "--cfg_file_path=./cfg.yaml",
            &format!("--running_duration={secs}"),
        ],
        LIMIT,
    );
    out.assert_exit(0, "the filter example");
    out
}

/// The text after `marker` on each line that has it.
fn after<'a>(out: &'a Output, marker: &str) -> Vec<&'a str> {
    out.stdout
        .lines()
        .filter_map(|l| l.split_once(marker).map(|(_, rest)| rest))
        .collect()
}

fn example(frq: u32) -> String {
    repo_config("channel_filter_plugin").replace("channel_frq: 2", &format!("channel_frq: {frq}"))
}

#[test]
fn the_example_samples_stamps_logs_and_times_each_message() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_main_in(
        dir.path(),
        Some(&example(20)),
        &[
            "--cfg_file_path=./cfg.yaml",
            "--running_duration=1",
            "--dump_init_report=true",
        ],
        LIMIT,
    );
    out.assert_exit(0, "the filter example");
    let sent = after(&out, "]Publish new pb event, data: ");
    let received = after(&out, "]Receive new pb event, ctx: ");
    assert!(sent.len() >= 4, "{}", out.stdout);
    // `sample` passes the 1st, 3rd, 5th … message on.
    assert_eq!(received.len(), sent.len().div_ceil(2), "{}", out.stdout);
    for (i, line) in received.iter().enumerate() {
        // Stamped after sampling: the trace ids count the messages passed on.
        let stamp = format!("{{\"trace-id\":\"NormalPublisherModule-{}\"}}", i + 1);
        assert!(line.contains(&stamp), "{stamp} not in {line}");
        assert!(line.ends_with(sent[2 * i]), "{line}\n{}", sent[2 * i]);
    }
    // `debug_log` is listed first, so it runs last and sees the stamp.
    let logged = after(&out, "Channel publish a new msg. ");
    assert_eq!(logged.len(), received.len(), "{}", out.stdout);
    assert!(
        logged.iter().all(|l| l.contains("\"trace-id\":")),
        "{logged:?}"
    );
    let timed = after(
        &out,
        "]time_cost: topic 'test_topic', subscriber of module 'NormalSubscriberModule': ",
    );
    assert_eq!(timed.len(), received.len(), "{}", out.stdout);
    let held = sent.len() - received.len();
    assert!(
        out.stdout.contains(&format!(
            "Channel topic 'test_topic': published {}, delivered {}, dropped {held} (filtered: {held})",
            sent.len(),
            received.len()
        )),
        "{}",
        out.stdout
    );
    assert_eq!(
        out.stdout
            .matches("publish filter 'sample' held the message back (reported once;")
            .count(),
        1,
        "{}",
        out.stdout
    );
    let report = std::fs::read_to_string(dir.path().join("init_report.txt")).unwrap();
    for line in [
        "[ debug_log , sample , trace_id ]",
        "[ debug_log , time_cost ]",
    ] {
        assert!(report.contains(line), "{line} missing:\n{report}");
    }
}

#[test]
fn the_filter_listed_last_runs_first() {
    // `debug_log` listed last runs before `trace_id` stamps: it never sees the key, while
    // the subscriber does.
    let cfg = example(20).replace(
        "enable_filters: [debug_log, trace_id, sample]",
        "enable_filters: [trace_id, debug_log]",
    );
    let out = run(&cfg, 1);
    let logged = after(&out, "Channel publish a new msg. ");
    let received = after(&out, "]Receive new pb event, ctx: ");
    assert!(!logged.is_empty(), "{}", out.stdout);
    assert_eq!(logged.len(), received.len(), "{}", out.stdout);
    assert!(logged.iter().all(|l| !l.contains("trace-id")), "{logged:?}");
    assert!(
        received.iter().all(|l| l.contains("trace-id")),
        "{received:?}"
    );
}

#[test]
fn a_name_that_is_no_filter_of_its_side_is_an_error_listing_those_that_are() {
    let cases = [
        (
            example(2).replace("[debug_log, trace_id, sample]", "[trace_idd]"),
            vec![
                "trace_idd",
                "did you mean 'trace_id'",
                "debug_log, sample, trace_id",
            ],
        ),
        (
            // A publish filter named on the subscribing side.
            example(2).replace("enable_filters: [time_cost]", "enable_filters: [sample]"),
            vec!["sample", "debug_log, time_cost"],
        ),
        (
            example(2).replace("keep_one_in: 2", "keep_one_in: 0"),
            vec!["sample.keep_one_in is 0"],
        ),
    ];
    for (cfg, expected) in cases {
        let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        assert_failure(&out, &expected);
    }
}

#[test]
fn without_the_plugin_its_filters_are_unknown() {
    let cfg = example(2).replace(
        "  plugin:\n    plugins:\n      - name: example_filters\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_filters_plugin.so\n        options:\n          sample:\n            keep_one_in: 2\n",
        "",
    );
    assert!(!cfg.contains("name: example_filters"), "{cfg}");
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(&out, &["trace_id", "debug_log"]);
}

#[test]
fn a_plugin_library_of_abi_1_6_loads_and_runs_on_this_host() {
    let cfg = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: abi_1_6_plugin\n        path: {}\n  log:\n    backends:\n      - type: console\n",
        aimrt_e2e::lib("libfixture_abi_1_6.so").display()
    );
    let out = run(&cfg, 1);
    for line in [
        "]ABI 1.6 plugin initialized",
        "]ABI 1.6 plugin started",
        "]ABI 1.6 plugin shut down",
    ] {
        assert!(out.stdout.contains(line), "no {line:?} in:\n{}", out.stdout);
    }
}

/// A plugin library of ABI 1.7 (`plugins/fixtures/abi_1_7`): its publish filter and its
/// channel backend see every message of the local pub/sub example, beside `local`, on a
/// host whose publications carry 1.8's topic reference after what 1.7 knew.
#[test]
fn a_plugin_library_of_abi_1_7_filters_and_carries_every_message_on_this_host() {
    let cfg = example(20)
        .replace(
            "      - name: example_filters\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_filters_plugin.so\n        options:\n          sample:\n            keep_one_in: 2\n",
            &format!(
                "      - name: abi_1_7_plugin\n        path: {}\n",
                aimrt_e2e::lib("libfixture_abi_1_7.so").display()
            ),
        )
        .replace(
            "      - type: local\n    pub_topics_options:",
            "      - type: local\n      - type: abi_1_7_tally\n    pub_topics_options:",
        )
        .replacen(
            "        enable_backends: [local]\n        enable_filters: [debug_log, trace_id, sample]",
            "        enable_backends: [local, abi_1_7_tally]\n        enable_filters: [abi_1_7_pass]",
            1,
        )
        .replace("        enable_filters: [time_cost]\n", "");
    assert!(
        cfg.contains("enable_filters: [abi_1_7_pass]") && !cfg.contains("name: example_filters"),
        "{cfg}"
    );
    let out = run(&cfg, 1);
    let sent = after(&out, "]Publish new pb event, data: ").len();
    let received = after(&out, "]Receive new pb event, ctx: ").len();
    assert!(sent >= 4, "{}", out.stdout);
    assert_eq!(received, sent, "{}", out.stdout);
    let line = format!(
        "]ABI 1.7 plugin shut down: its filter passed {sent} messages on, its backend was handed {sent}"
    );
    assert!(
        out.stdout.contains("]ABI 1.7 plugin initialized"),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout.contains(&line),
        "no {line:?} in:\n{}",
        out.stdout
    );
}

/// The example at 20 Hz without its filters plugin, with the channel backend `backend`
/// of the fixture of ABI `1.<minor>` (`plugins/fixtures/abi_1_<minor>`) beside `local`
/// for publishing, and for subscribing too when `subscribe`.
fn with_fixture_backend(minor: u32, backend: &str, subscribe: bool) -> String {
    let mut cfg = example(20)
        .replace(
            "      - name: example_filters\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_filters_plugin.so\n        options:\n          sample:\n            keep_one_in: 2\n",
            &format!(
                "      - name: abi_1_{minor}_plugin\n        path: {}\n",
                aimrt_e2e::lib(&format!("libfixture_abi_1_{minor}.so")).display()
            ),
        )
        .replace(
            "      - type: local\n    pub_topics_options:",
            &format!("      - type: local\n      - type: {backend}\n    pub_topics_options:"),
        )
        .replacen(
            "        enable_backends: [local]\n        enable_filters: [debug_log, trace_id, sample]",
            &format!("        enable_backends: [local, {backend}]"),
            1,
        )
        .replace("        enable_filters: [time_cost]\n", "");
    if subscribe {
        cfg = cfg.replacen(
            "        enable_backends: [local]\n",
            &format!("        enable_backends: [local, {backend}]\n"),
            1,
        );
    }
    let routes = cfg
        .matches(&format!("enable_backends: [local, {backend}]"))
        .count();
    assert!(
        routes == 1 + usize::from(subscribe) && !cfg.contains("name: example_filters"),
        "{cfg}"
    );
    cfg
}

/// A plugin library of ABI 1.8 (`plugins/fixtures/abi_1_8`) on this host of 1.9: its
/// channel backend's losses after publish are counted on the topic, and the dump writes
/// its options as it read them (the default filled in).
#[test]
fn a_plugin_library_of_abi_1_8_reports_losses_and_options_on_this_host() {
    let cfg = with_fixture_backend(8, "abi_1_8_lossy", false);
    let dir = tempfile::tempdir().unwrap();
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &[
            "--cfg_file_path=./cfg.yaml",
            "--running_duration=1",
            "--dump_cfg_file",
            "--dump_cfg_file_path=./dump.yaml",
        ],
        LIMIT,
    );
    out.assert_exit(0, "the ABI 1.8 fixture");
    let sent = after(&out, "]Publish new pb event, data: ").len();
    let received = after(&out, "]Receive new pb event, ctx: ").len();
    assert!(sent >= 4, "{}", out.stdout);
    assert_eq!(received, sent, "{}", out.stdout);
    // One in two (the default) lost: the 1st, 3rd, 5th … message.
    let lost = sent.div_ceil(2);
    for line in [
        format!("]ABI 1.8 plugin shut down: its backend was handed {sent} messages and reported {lost} lost"),
        format!("Channel topic 'test_topic': published {sent}, delivered {sent}, dropped {lost} (lost after publish: {lost})"),
    ] {
        assert!(out.stdout.contains(&line), "no {line:?} in:\n{}", out.stdout);
    }
    let dump = std::fs::read_to_string(dir.path().join("dump.yaml")).unwrap();
    assert!(
        dump.contains("- type: abi_1_8_lossy\n      options:\n        lose_one_in: 2\n"),
        "{dump}"
    );
}

/// A plugin library of ABI 1.12 (`plugins/fixtures/abi_1_12`) on this host of 1.13: its
/// channel backend reports many losses at once on each subscription, and the topic
/// counts them all.
#[test]
fn a_plugin_library_of_abi_1_12_reports_many_drops_at_once_on_this_host() {
    let cfg = with_fixture_backend(12, "abi_1_12_gaps", true);
    let dir = tempfile::tempdir().unwrap();
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    out.assert_exit(0, "the ABI 1.12 fixture");
    let sent = after(&out, "]Publish new pb event, data: ").len();
    let received = after(&out, "]Receive new pb event, ctx: ").len();
    assert!(sent >= 4, "{}", out.stdout);
    assert_eq!(received, sent, "{}", out.stdout);
    let line = format!(
        "Channel topic 'test_topic': published {sent}, delivered {sent}, dropped {lost} (lost after publish: {lost})",
        lost = 2 * sent
    );
    assert!(
        out.stdout.contains(&line),
        "no {line:?} in:\n{}",
        out.stdout
    );
}
