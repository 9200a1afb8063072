//! proxy_plugin: AimRT's three-process example (`config/proxy_plugin*.yaml`: an http
//! publisher, the proxy from http to zenoh, a zenoh subscriber), each test on its own ports
//! and zenoh `limit_domain`; the one-process example (`config/proxy_plugin_local.yaml`);
//! and the start-up errors of its executor.

use std::time::Duration;

use aimrt_e2e::{
    aimrt_example, aimrt_zenoh_example, assert_failure, free_port, repo_config, run_main,
    with_port, Running, ZenohPeers,
};

const WAIT: Duration = Duration::from_secs(30);

/// `(num, aimrt-pub_seq, line)` of each "Receive new pb event" line among `lines`.
fn received(lines: &[(std::time::Instant, String)]) -> Vec<(u64, u64, String)> {
    lines
        .iter()
        .map(|(_, l)| {
            let num = l
                .rsplit_once(r#""num":"#)
                .and_then(|(_, n)| n.trim_end_matches('}').parse().ok())
                .unwrap_or_else(|| panic!("no num in {l}"));
            let seq = l
                .split_once(r#"{"aimrt-pub_seq":""#)
                .and_then(|(_, s)| s.split('"').next()?.parse().ok())
                .unwrap_or_else(|| panic!("no aimrt-pub_seq in {l}"));
            (num, seq, l.clone())
        })
        .collect()
}

/// The proxy's closing line for action `name`, as numbers: received, forwarded, failed,
/// refused, dropped at shutdown.
fn summary(text: &str, name: &str) -> [u64; 5] {
    let prefix = format!("proxy action '{name}': ");
    let line = text
        .lines()
        .filter_map(|l| l.split_once(&prefix).map(|(_, rest)| rest))
        .find(|rest| rest.contains(" messages received, "))
        .unwrap_or_else(|| panic!("no summary of '{name}' in:\n{text}"));
    let n: Vec<u64> = line
        .split(", ")
        .map(|part| {
            part.split(' ')
                .next()
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("{line}"))
        })
        .collect();
    n.try_into().unwrap_or_else(|_| panic!("{line}"))
}

#[test]
fn aimrts_example_forwards_from_http_to_zenoh_with_the_contexts_own_keys() {
    let peers = ZenohPeers::new("proxy_http_zenoh");
    let port = free_port(false);
    let mut sub = Running::start_env(
        &aimrt_zenoh_example(
            "proxy_plugin_zenoh_sub",
            "examples_plugins_proxy_plugin_zenoh_sub_cfg.yaml",
        ),
        &peers.env("b"),
    );
    sub.wait_for("Module manager start completed.", WAIT);
    let proxy_cfg = with_port(
        &aimrt_zenoh_example("proxy_plugin", "examples_plugins_proxy_plugin_cfg.yaml"),
        port,
    );
    let mut proxy = Running::start_env(&proxy_cfg, &peers.env("a"));
    proxy.wait_for("Module manager start completed.", WAIT);
    let pub_cfg = with_port(
        &aimrt_example(
            "proxy_plugin_http_pub",
            "examples_plugins_proxy_plugin_http_pub_cfg.yaml",
        )
        .replace("listen_port: 50081", "listen_port: 0")
        .replace(
            "  channel_frq: 0.5",
            "  channel_frq: 20\n  context_meta:\n    my-key: my-val",
        ),
        port,
    );
    let mut publisher = Running::start(&pub_cfg);
    sub.wait_for("Receive new pb event", WAIT);
    let mut got = sub.collect_for(Duration::from_secs(1), "Receive new pb event");
    while got.len() < 5 {
        got.push(sub.wait_for("Receive new pb event", WAIT));
    }
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(proxy.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));

    let got = received(&got);
    for w in got.windows(2) {
        // In order, none lost; the proxy's topic has its own sequence.
        assert_eq!(w[1].0, w[0].0 + 1, "{}\n{}", w[0].2, w[1].2);
        assert_eq!(w[1].1, w[0].1 + 1, "{}\n{}", w[0].2, w[1].2);
    }
    for kv in [
        r#"{"my-key":"my-val"}"#,
        r#"{"aimrt-backend":"zenoh"}"#,
        r#"{"aimrt-serialization_type":"pb"}"#,
    ] {
        assert!(got[0].2.contains(kv), "{kv} not in {}", got[0].2);
    }
    let [received, forwarded, failed, refused, dropped] = summary(&proxy.text(), "my_proxy");
    assert!(received >= got.len() as u64, "{}", proxy.text());
    assert_eq!((failed, refused, dropped), (0, 0, 0), "{}", proxy.text());
    assert_eq!(forwarded, received, "{}", proxy.text());
}

#[test]
fn the_one_process_example_forwards_every_message_in_order() {
    let cfg = repo_config("proxy_plugin_local").replace("channel_frq: 2", "channel_frq: 50");
    let mut run = Running::start(&cfg);
    run.wait_for("Receive new pb event", WAIT);
    let mut got = run.collect_for(Duration::from_millis(500), "Receive new pb event");
    while got.len() < 10 {
        got.push(run.wait_for("Receive new pb event", WAIT));
    }
    assert_eq!(run.interrupt(WAIT), Some(0));
    let got = received(&got);
    for w in got.windows(2) {
        assert_eq!(w[1].0, w[0].0 + 1, "{}\n{}", w[0].2, w[1].2);
        assert_eq!(w[1].1, w[0].1 + 1, "{}\n{}", w[0].2, w[1].2);
    }
    assert!(got[0].2.contains(r#"{"my-key":"my-val"}"#), "{}", got[0].2);
    // The proxy's own context: its sequence is the forwarded topic's, and no key of the
    // received context's `aimrt-` ones is repeated.
    assert_eq!(got[0].2.matches("aimrt-pub_seq").count(), 1, "{}", got[0].2);
    assert_eq!(got[0].2.matches("aimrt-backend").count(), 1, "{}", got[0].2);
    let text = run.text();
    let [received, forwarded, failed, refused, _] = summary(&text, "local_proxy");
    assert!(received >= 10, "{text}");
    assert_eq!((failed, refused), (0, 0), "{text}");
    assert!(forwarded <= received, "{text}");
}

#[test]
fn an_executor_that_is_unknown_or_not_thread_safe_stops_the_start() {
    let base = repo_config("proxy_plugin_local");
    let cases = [
        (
            base.replace(
                "executor: proxy_plugin_executor",
                "executor: no_such_executor",
            ),
            vec![
                "proxy_plugin",
                "the executor 'no_such_executor' of proxy action 'local_proxy' is not an executor of aimrt.executor.executors",
            ],
        ),
        (
            base.replace(
                "executor: proxy_plugin_executor",
                "executor: work_thread_pool",
            ),
            vec![
                "Proxy executor work_thread_pool is not thread safe! (proxy action 'local_proxy')",
                "simple_thread",
            ],
        ),
        (
            base.replace(
                "msg_type: pb:aimrt.protocols.example.ExampleEventMsg",
                "msg_type: pb:aimrt.protocols.example.ExampleEventMs",
            ),
            vec![
                "proxy_actions[0] ('local_proxy'): topic_meta_list[0].msg_type",
                "pb:aimrt.protocols.example.ExampleEventMs",
            ],
        ),
    ];
    for (cfg, expected) in cases {
        let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], WAIT);
        assert_failure(&out, &expected);
    }
}

#[test]
fn messages_the_executor_refuses_are_counted_by_the_proxy_and_the_topic() {
    let cfg = repo_config("proxy_plugin_local")
        .replace("channel_frq: 2", "channel_frq: 20")
        .replace(
            "        type: simple_thread\n",
            "        type: simple_thread\n        options:\n          queue_threshold: 0\n",
        );
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        WAIT,
    );
    out.assert_exit(0, "refusing proxy");
    let [received, forwarded, failed, refused, dropped] = summary(&out.stdout, "local_proxy");
    assert!(received > 0, "{}", out.stdout);
    assert_eq!(
        (forwarded, failed, refused, dropped),
        (0, 0, received, 0),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout.contains(&format!(
            "Channel topic 'test_topic_in': published {received}, delivered 0, dropped {received} (subscriber failed: {received})"
        )),
        "{}",
        out.stdout
    );
    assert!(
        out.stdout
            .contains("the subscriber of module 'proxy_plugin' failed: proxy action 'local_proxy': the message is not forwarded"),
        "{}",
        out.stdout
    );
    assert!(
        !out.stdout.contains("Receive new pb event"),
        "{}",
        out.stdout
    );
}

#[test]
fn the_dumped_config_has_the_proxys_options_as_it_reads_them_and_loads_again() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("cfg.yaml");
    std::fs::write(&cfg, repo_config("proxy_plugin_local")).unwrap();
    let dump = |from: &std::path::Path, to: &std::path::Path| {
        let out = aimrt_e2e::run_main_in(
            dir.path(),
            None,
            &[
                &format!("--cfg_file_path={}", from.display()),
                "--running_duration=1",
                "--dump_cfg_file",
                &format!("--dump_cfg_file_path={}", to.display()),
            ],
            WAIT,
        );
        out.assert_exit(0, "dump");
        std::fs::read_to_string(to).unwrap()
    };
    let first = dump(&cfg, &dir.path().join("dump.yaml"));
    // The plugin's options with what the file leaves out filled in (its unused top-level
    // `executor`), as the plugin reported them (AimRT's UpdatePluginOptionsNode).
    let proxy = first
        .split("- name: proxy_plugin\n")
        .nth(1)
        .and_then(|rest| rest.split("  main_thread:").next())
        .unwrap_or_else(|| panic!("{first}"));
    for expected in [
        "      options:\n        executor: \"\"\n        proxy_actions:\n",
        "            executor: proxy_plugin_executor\n",
        "              sub_topic_name: test_topic_in\n",
        "libexample_pb_ts.so\n",
    ] {
        assert!(proxy.contains(expected), "{expected:?} missing:\n{first}");
    }
    let again = dump(
        &dir.path().join("dump.yaml"),
        &dir.path().join("again.yaml"),
    );
    assert_eq!(again, first);
}
