//! End-to-end: the channel examples under the real `aimrt_main`, with real pkgs —
//! AimRT's two `pb_chn` configs with only the pkg paths changed (publisher and subscriber
//! in two libraries, then in one), inline delivery with a relay, and an async subscriber
//! in another library receiving JSON; AimRT's channel benchmark configs, and Ctrl-C
//! during a benchmark plan.

use std::time::Duration;

use aimrt_e2e::{example_config, repo_config, run_main_in, Output};

const LIMIT: Duration = Duration::from_secs(60);

/// The text after `marker` on each line that has it.
fn after<'a>(out: &'a Output, marker: &str) -> Vec<&'a str> {
    out.stdout
        .lines()
        .filter_map(|l| l.split_once(marker).map(|(_, rest)| rest))
        .collect()
}

/// Every published message arrived with the same content, and the context says how.
fn check_round_trip(out: &Output, format: &str) {
    let sent = after(out, "]Publish new pb event, data: ");
    let got = after(out, "]Receive new pb event, ctx: ");
    assert!(!sent.is_empty(), "nothing published:\n{}", out.stdout);
    assert_eq!(sent.len(), got.len(), "{}", out.stdout);
    for (i, (s, g)) in sent.iter().zip(&got).enumerate() {
        let (ctx, data) = g.split_once(", data: ").unwrap();
        assert_eq!(data, *s, "message {i}: content changed on the way");
        assert!(ctx.starts_with("Subscriber context, meta: {"), "{ctx}");
        for kv in [
            format!("{{\"aimrt-serialization_type\":\"{format}\"}}"),
            format!("{{\"aimrt-pub_seq\":\"{}\"}}", i + 1),
            "{\"aimrt-backend\":\"local\"}".to_owned(),
        ] {
            assert!(ctx.contains(&kv), "{kv} not in {ctx}");
        }
    }
}

#[test]
fn two_pkgs_exchange_protobuf_bytes() {
    // 0.5 Hz: the first message comes 2 s after start.
    let out = aimrt_e2e::run_for(&example_config("pb_chn"), 3);
    check_round_trip(&out, "pb");
    assert!(
        out.stdout
            .contains("Channel topic 'test_topic': published 1, delivered 1, dropped 0"),
        "{}",
        out.stdout
    );
}

/// The `debug_log` filter in `enable_filters` logs each message as it is published and
/// as it is handed to the subscriber, with the context each side sees and the JSON; the
/// init report names the filter per topic, as AimRT's.
#[test]
fn the_debug_log_filter_logs_each_message_on_both_sides() {
    let cfg = repo_config("pb_chn_debug_log").replace("channel_frq: 0.5", "channel_frq: 10");
    let dir = tempfile::tempdir().unwrap();
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &[
            "--cfg_file_path=./cfg.yaml",
            "--running_duration=1",
            "--dump_init_report=true",
        ],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    let head =
        "msg type: pb:aimrt.protocols.example.ExampleEventMsg, topic name: test_topic, context: ";
    let published = after(
        &out,
        &format!("Channel publish a new msg. {head}Publisher context, meta: "),
    );
    let handled = after(
        &out,
        &format!("Channel subscriber handle a new msg. {head}Subscriber context, meta: "),
    );
    let sent = after(&out, "]Publish new pb event, data: ");
    assert!(!sent.is_empty(), "nothing published:\n{}", out.stdout);
    assert_eq!(published.len(), sent.len(), "{}", out.stdout);
    assert_eq!(
        handled.len(),
        after(&out, "]Receive new pb event, ctx: ").len()
    );
    for (i, line) in published.iter().enumerate() {
        let seq = format!("{{\"aimrt-pub_seq\":\"{}\"}}", i + 1);
        assert!(
            line.starts_with("{{\"aimrt-serialization_type\":\"pb\"}"),
            "{line}"
        );
        assert!(line.contains(&seq), "{seq} not in {line}");
        assert!(
            line.ends_with(&format!(", msg: {}", sent[i])),
            "{line}\n{}",
            sent[i]
        );
        assert!(!line.contains("aimrt-backend"), "{line}");
    }
    for line in &handled {
        assert!(line.contains("{\"aimrt-backend\":\"local\"}"), "{line}");
        assert!(line.contains(", msg: {\"msg\":\"count: "), "{line}");
    }
    let report = std::fs::read_to_string(dir.path().join("init_report.txt")).unwrap();
    for section in ["Channel Pub Filter List", "Channel Sub Filter List"] {
        assert!(report.contains(section), "{section} missing:\n{report}");
    }
    assert!(
        report
            .lines()
            .any(|l| l.contains("test_topic") && l.contains("local") && l.contains("debug_log")),
        "{report}"
    );
}

/// A filter name that is not a filter stops start-up, saying which are.
#[test]
fn an_unknown_channel_filter_is_an_error_naming_the_filters() {
    let cfg = repo_config("pb_chn_debug_log").replacen("[debug_log]", "[debug_lg]", 1);
    let dir = tempfile::tempdir().unwrap();
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml"],
        LIMIT,
    );
    assert_eq!(out.code, Some(255), "{}\n{}", out.stdout, out.stderr);
    let expected = "./cfg.yaml:25:26: enable_filters names 'debug_lg', which is not a filter; did you mean 'debug_log'?; the filters are: debug_log";
    assert!(
        out.stdout.contains(expected),
        "{}\n{}",
        out.stdout,
        out.stderr
    );
}

#[test]
fn one_pkg_shares_the_message() {
    let out = aimrt_e2e::run_for(&example_config("pb_chn_single_pkg"), 3);
    check_round_trip(&out, "pb");
}

#[test]
fn inline_relay_carries_user_keys_downstream() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_main_in(
        dir.path(),
        Some(&repo_config("pb_chn_inline")),
        &[
            "--cfg_file_path=./cfg.yaml",
            "--running_duration=2",
            "--dump_init_report=true",
        ],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    // The initialization report lists the channel backends and who publishes and
    // subscribes what, as AimRT's.
    let report = std::fs::read_to_string(dir.path().join("init_report.txt")).unwrap();
    let row = |topic: &str, module: &str| {
        format!("|  {topic:<13}  |  pb:aimrt.protocols.example.ExampleEventMsg  |  {module}")
    };
    for needle in [
        "]. Channel Backend List\n[ local ]".to_owned(),
        "]. Channel Pub Topic Info".to_owned(),
        row("test_topic", "NormalPublisherModule"),
        row("relayed_topic", "RelayModule"),
        "]. Channel Sub Topic Info".to_owned(),
        row("relayed_topic", "NormalSubscriberModule"),
    ] {
        assert!(report.contains(&needle), "{needle:?} not in:\n{report}");
    }
    let sent = after(&out, "]Publish new pb event, data: ");
    let relayed = after(&out, "]Relay pb event, upstream seq: ");
    let got = after(&out, "]Receive new pb event, ctx: ");
    assert!(sent.len() >= 3, "{}", out.stdout);
    assert_eq!(relayed.len(), sent.len(), "{}", out.stdout);
    assert_eq!(got.len(), sent.len(), "{}", out.stdout);
    for (i, g) in got.iter().enumerate() {
        let (ctx, data) = g.split_once(", data: ").unwrap();
        assert_eq!(data, sent[i]);
        assert!(ctx.contains("{\"trace_id\":\"demo-42\"}"), "{ctx}");
        assert!(
            ctx.contains(&format!("{{\"aimrt-pub_seq\":\"{}\"}}", i + 1)),
            "{ctx}"
        );
    }
    // Inline: the relay and the final subscriber run on the publisher's thread, so each
    // message's three lines come in order before the next one is published.
    let order: Vec<char> = out
        .stdout
        .lines()
        .filter_map(|l| {
            if l.contains("]Publish new pb event") {
                Some('p')
            } else if l.contains("]Relay pb event") {
                Some('r')
            } else if l.contains("]Receive new pb event") {
                Some('s')
            } else {
                None
            }
        })
        .collect();
    let expected: String = "prs".repeat(sent.len());
    assert_eq!(order.iter().collect::<String>(), expected);
}

#[test]
fn async_subscriber_in_another_library_gets_json() {
    let out = aimrt_e2e::run_for(&repo_config("pb_chn_async"), 2);
    let sent = after(&out, "]Publish new pb event, data: ");
    let handled = after(&out, "]Async handled pb event, seq: ");
    assert!(sent.len() >= 3, "{}", out.stdout);
    // The last one may still be in flight at shutdown.
    assert!(handled.len() + 1 >= sent.len(), "{}", out.stdout);
    for (i, h) in handled.iter().enumerate() {
        assert_eq!(*h, format!("{}, data: {}", i + 1, sent[i]));
    }
}

/// AimRT's channel benchmark configs (two pkgs, then one; both at once) with the plans
/// cut short: every plan's report says every message arrived once, at the announced size.
#[test]
fn aimrts_channel_benchmark_runs_every_plan_without_loss() {
    let mut runs: Vec<_> = ["pb_chn_benchmark", "pb_chn_benchmark_single_pkg"]
        .into_iter()
        .map(|name| {
            let cfg = aimrt_e2e::shorter_bench_plans(&example_config(name), 10);
            (name, aimrt_e2e::Running::start(&cfg))
        })
        .collect();
    for (name, p) in &mut runs {
        aimrt_e2e::assert_bench_plans_arrive_whole(p, 3, LIMIT);
        p.wait_for("Bench completed.", LIMIT);
        assert_eq!(p.interrupt(LIMIT), Some(0), "{name}");
        let text = p.text();
        assert!(!text.contains("panicked:"), "{name}:\n{text}");
        for (plan, sent) in [2000, 100, 500].into_iter().enumerate() {
            assert!(
                text.contains(&format!(
                    "Benchmark plan {plan}: sent {sent} of {sent} messages, 0 refused by the channel, 0 dropped after publish (counted in the topics' stats)."
                )),
                "{name}, plan {plan}:\n{text}"
            );
        }
    }
}

/// Ctrl-C during a plan ends the benchmark at once: the senders and the plan loop wake
/// up from their waits (without that, the plan would run on for about 5 s more).
#[test]
fn ctrl_c_during_a_benchmark_plan_exits_at_once() {
    let mut p = aimrt_e2e::Running::start(&example_config("pb_chn_benchmark"));
    p.wait_for("Publish benchmark start signal", LIMIT);
    std::thread::sleep(Duration::from_millis(1500));
    let asked = std::time::Instant::now();
    assert_eq!(p.interrupt(LIMIT), Some(0));
    assert!(
        asked.elapsed() < Duration::from_secs(4),
        "took {:?}:\n{}",
        asked.elapsed(),
        p.text()
    );
    let text = p.text();
    assert!(text.contains("Bench stopped."), "{text}");
    assert!(!text.contains("did not end within"), "{text}");
}
