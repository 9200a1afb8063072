//! mqtt_plugin between processes through a broker on loopback (the plugin's test broker,
//! `aimrt_mqtt::test_broker`, one per test on a free port): AimRT's example configs
//! (`config/mqtt_*`) as two `aimrt_main` processes; 10 000 messages in order; RPC in every
//! call style; a server that stops or dies mid-call; the broker dropping every connection;
//! malformed payloads from a foreign publisher; a subscriber that stops under traffic;
//! bad options; TLS (`ssl://`) with and without client certificates, and brokers that
//! must not be trusted.

use std::time::Duration;

use aimrt_e2e::{repo_config, run_main, Running};
use aimrt_mqtt::test_broker::{Broker, TlsFiles};

const WAIT: Duration = Duration::from_secs(30);

const TOPIC_EVENT: &str = "/channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg";

/// `cfg` with every `broker_addr` made `addr`: no port of the example configs is kept.
fn with_broker(cfg: &str, addr: &str) -> String {
    cfg.lines()
        .map(|l| {
            let indent = &l[..l.len() - l.trim_start().len()];
            if l.trim_start().starts_with("broker_addr:") {
                format!("{indent}broker_addr: {addr}\n")
            } else {
                format!("{l}\n")
            }
        })
        .collect()
}

/// `config/mqtt_<name>.yaml` against `broker`.
fn start(name: &str, broker: &Broker, edit: impl FnOnce(String) -> String) -> Running {
    let cfg = with_broker(
        &edit(repo_config(&format!("mqtt_{name}"))),
        &format!("tcp://{}", broker.addr()),
    );
    let mut running = Running::start(&cfg);
    running.wait_for("Module manager start completed.", WAIT);
    running
}

fn same(cfg: String) -> String {
    cfg
}

fn publishing_at(hz: u32) -> impl FnOnce(String) -> String {
    move |cfg| {
        let out = cfg.replace("channel_frq: 0.5", &format!("channel_frq: {hz}"));
        assert_ne!(out, cfg);
        out
    }
}

#[test]
fn aimrts_channel_example_pair_exchanges_messages_with_their_context() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut sub = start("pb_chn_sub", &broker, same);
    let mut publisher = start("pb_chn_pub", &broker, |cfg| {
        publishing_at(10)(cfg).replace(
            "  channel_frq: 10",
            "  channel_frq: 10\n  context_meta:\n    my-key: my-val",
        )
    });
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    aimrt_e2e::assert_first_event_carries_context(&line, "mqtt");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    assert!(
        text.contains(&format!(
            "Register mqtt handle for channel, uri '{TOPIC_EVENT}'"
        )),
        "{text}"
    );
    assert!(
        text.contains("mqtt_plugin: connected to the mqtt broker"),
        "{text}"
    );
    // The shutdown line: what was received, nothing malformed.
    assert!(text.contains(" 0 malformed received"), "{text}");
}

#[test]
fn ten_thousand_messages_arrive_in_order_and_every_one_is_accounted_for() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut sub = start("pb_chn_sub", &broker, same);
    let mut publisher = start("pb_chn_pub", &broker, publishing_at(2000));
    sub.wait_for(r#""num":10000}"#, Duration::from_secs(120));
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let published =
        aimrt_e2e::number_after(&publisher.text(), "Channel topic 'test_topic': published ");
    let seen = aimrt_e2e::received_seqs(&sub.text());
    assert!(seen.len() >= 10_000, "{} messages", seen.len());
    for (i, s) in seen.iter().enumerate() {
        assert_eq!(*s, i as u64 + 1, "message {i} has pub_seq {s}");
    }
    // Every message published was handed to the broker (QoS 2 by default) and arrived.
    let text = sub.text();
    let line = text
        .lines()
        .find(|l| l.contains("Channel topic 'test_topic': "))
        .unwrap_or_else(|| panic!("no topic line in\n{text}"));
    assert!(
        line.contains(&format!("delivered {published}, dropped 0")),
        "published {published}; subscriber: {line}"
    );
    assert!(
        publisher.text().contains(" 0 refused,"),
        "{}",
        publisher.text()
    );
}

/// A subscriber that shuts down while messages still come: its connection outlives the
/// channel backend, and what it brings after is counted, so every message the plugin
/// received is delivered, dropped or counted as received after the channel shut down.
#[test]
fn a_subscriber_shutting_down_under_traffic_accounts_for_every_message_it_received() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut sub = start("pb_chn_sub", &broker, same);
    let mut publisher = start("pb_chn_pub", &broker, publishing_at(10_000));
    sub.wait_for(r#""num":1000}"#, Duration::from_secs(60));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    let text = sub.text();
    let number = |prefix| aimrt_e2e::number_after(&text, prefix);
    let received = number("mqtt_plugin: 0 payloads sent, 0 refused, ");
    let after = number("malformed received, ");
    let delivered = number("Channel topic 'test_topic': published 0, delivered ");
    let dropped = number(&format!("published 0, delivered {delivered}, dropped "));
    assert!(received >= 1000, "{received} received");
    assert_eq!(
        received,
        delivered + dropped + after,
        "received {received}: delivered {delivered}, dropped {dropped}, after the channel shut down {after}"
    );
}

#[test]
fn both_sides_connect_again_when_the_broker_drops_them() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut sub = start("pb_chn_sub", &broker, |cfg| {
        cfg.replace(
            "max_pkg_size_k: 1024",
            "max_pkg_size_k: 1024\n          reconnect_interval_ms: 100",
        )
    });
    let mut publisher = start("pb_chn_pub", &broker, |cfg| {
        publishing_at(20)(cfg).replace(
            "max_pkg_size_k: 1024",
            "max_pkg_size_k: 1024\n          reconnect_interval_ms: 100",
        )
    });
    sub.wait_for(r#""num":3}"#, WAIT);
    broker.drop_connections();
    sub.wait_for("mqtt_plugin: lost the connection to the mqtt broker", WAIT);
    // Subscribed again on the new connection: later messages arrive.
    let (_, line) = sub.wait_for(r#""num":100}"#, WAIT);
    assert!(line.contains("Receive new pb event"), "{line}");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    assert!(text.contains(" 2 connections made to the broker"), "{text}");
}

/// The numbers (`"num":N`) of the example subscriber's messages, in the order received.
fn nums_received(text: &str) -> Vec<u64> {
    text.lines()
        .filter(|l| l.contains("Receive new pb event"))
        .map(|l| aimrt_e2e::number_after(l, r#""num":"#))
        .collect()
}

/// A connection that loses what it carries, then breaks: the channel messages the broker
/// never acknowledged go out again on the next connection, ahead of the newer ones, so
/// the subscriber gets every message. Before, rumqttc's clean session dropped them
/// without a word, and the shutdown line still counted them as sent.
#[test]
fn channel_messages_a_lost_connection_took_are_sent_again_on_the_next() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let reconnect = |ms: u32| {
        move |cfg: String| {
            cfg.replace(
                "max_pkg_size_k: 1024",
                &format!("max_pkg_size_k: 1024\n          reconnect_interval_ms: {ms}"),
            )
        }
    };
    // The subscriber connects again long before the publisher, so nothing the publisher
    // sends again finds the broker without its subscription.
    let mut sub = start("pb_chn_sub", &broker, reconnect(100));
    let mut publisher = start("pb_chn_pub", &broker, |cfg| {
        reconnect(2000)(publishing_at(100)(cfg))
    });
    sub.wait_for(r#""num":20}"#, WAIT);
    broker.swallow_publishes(true);
    // The example logs this line before it publishes message 120. The connections are
    // dropped while the broker still swallows: a message the broker acknowledged and
    // forwarded just before the drop could be lost on its way to the subscriber (its
    // subscription is QoS 0), and the publisher, rightly, would not send it again.
    publisher.wait_for("loop count : 120 ", WAIT);
    broker.drop_connections();
    let (_, line) = publisher.wait_for("mqtt_plugin: lost the connection", WAIT);
    // Long before the publisher connects again (2 s).
    broker.swallow_publishes(false);
    let kept = aimrt_e2e::number_after(&line, "connecting again every 2000 ms; ");
    assert!(kept >= 90, "{line}");
    sub.wait_for(r#""num":300}"#, WAIT);
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let nums = nums_received(&sub.text());
    let last = *nums.iter().max().unwrap();
    let missing: Vec<u64> = (1..=last).filter(|n| !nums.contains(n)).collect();
    assert!(missing.is_empty(), "missing {missing:?} of 1..={last}");
    let text = publisher.text();
    assert_eq!(
        aimrt_e2e::number_after(&text, " answers for unknown request ids, "),
        kept,
        "sent again: {text}"
    );
}

#[test]
fn malformed_payloads_from_a_foreign_publisher_are_counted_and_never_stop_the_subscriber() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut sub = start("pb_chn_sub", &broker, same);
    let good = {
        let mut p = Vec::new();
        aimrt_wire::payload::put_channel_header(&mut p, "pb", [("forged", "yes")]).unwrap();
        // ExampleEventMsg{msg: "hi", num: 7}
        p.extend_from_slice(&[0x0a, 0x02, b'h', b'i', 0x10, 0x07]);
        p
    };
    let bad: Vec<Vec<u8>> = vec![
        vec![],
        vec![200],                              // a type longer than the payload
        b"\x02pb\x05".to_vec(),                 // 5 meta pairs, none there
        b"\x02pb\x01\xff\xff".to_vec(),         // a key longer than the payload
        b"\x04nope\x00body".to_vec(),           // an unknown serialization type
        b"\x02pb\x00\xff\xff\xff\xff".to_vec(), // a message protobuf cannot read
        good[..good.len() - 3].to_vec(),        // cut inside the message
    ];
    for b in &bad {
        broker.inject(TOPIC_EVENT, b);
    }
    broker.inject(TOPIC_EVENT, &good);
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    assert!(line.contains(r#"{"forged":"yes"}"#), "{line}");
    assert!(line.ends_with(r#"data: {"msg":"hi","num":7}"#), "{line}");
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    // Four are not AimRT's layout; three are, with a message the subscriber cannot
    // decode (reported as drops); one arrives.
    assert!(text.contains(" 8 received, 4 malformed received"), "{text}");
    assert_eq!(
        aimrt_e2e::topics_dropped(&text, "decode failed"),
        3,
        "{text}"
    );
}

/// The RPC example config with the client id named after the client module, so the
/// four call styles run at once as four distinct clients of the broker, calling every
/// 2 s as the helper expects.
fn rpc_client(cfg: &str) -> String {
    let out = cfg
        .replace(
            "client_id: example_pb_rpc_client",
            "client_id: NormalRpcCoClientModule",
        )
        .replace("rpc_frq: 1", "rpc_frq: 0.5");
    assert_ne!(out, cfg);
    out
}

#[test]
fn aimrts_rpc_example_pair_calls_in_every_style() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut server = start("pb_rpc_server", &broker, same);
    let cfg = with_broker(
        &rpc_client(&repo_config("mqtt_pb_rpc_client")),
        &format!("tcp://{}", broker.addr()),
    );
    aimrt_e2e::every_client_style_calls(&cfg, aimrt_e2e::RPC_EXAMPLE_RSP);
    let (_, line) = server.wait_for("Server handle new rpc call. context: ", WAIT);
    for kv in [
        r#"{"aimrt-function_name":"pb:/aimrt.protocols.example.ExampleService/GetFooData"}"#,
        r#"{"aimrt-serialization_type":"pb"}"#,
        r#"{"aimrt-backend":"mqtt"}"#,
        r#"{"aimrt-from_mqtt_client":"NormalRpc"#,
    ] {
        assert!(line.contains(kv), "{kv} not in {line}");
    }
    assert_eq!(server.interrupt(WAIT), Some(0));
    // The services ran on callback_executor_name's executor.
    let served = aimrt_e2e::number_after(
        &server.text(),
        "executor 'mqtt_callback' shut down: submitted ",
    );
    assert!(served >= 4, "{}", server.text());
}

#[test]
fn a_stopped_server_is_timed_out_and_answers_again_once_it_goes_on() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut server = start("pb_rpc_server", &broker, same);
    let mut client = start("pb_rpc_client", &broker, |c| {
        c.replace("rpc_frq: 1", "rpc_frq: 5")
    });
    client.wait_for(aimrt_e2e::RPC_EXAMPLE_RSP, WAIT);
    let text = aimrt_e2e::stop_a_server_under_its_client(&mut server, &mut client);
    // The answer the stopped server sent late reached its call's record and was dropped
    // by the runtime (the call had been answered TIMEOUT), not taken for another call.
    assert!(!text.contains(" 0 late answers dropped"), "{text}");
}

#[test]
fn a_server_that_dies_mid_call_leaves_its_client_a_timeout_and_a_call_to_another_server_by_id_is_answered(
) {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let server = start("pb_rpc_server", &broker, same);
    let mut client = start("pb_rpc_client", &broker, |c| {
        c.replace("rpc_frq: 1", "rpc_frq: 5")
    });
    client.wait_for(aimrt_e2e::RPC_EXAMPLE_RSP, WAIT);
    server.signal("KILL");
    let (_, line) = client.wait_for("Client get rpc error ret", WAIT);
    assert!(line.contains("code 2, msg: Timeout"), "{line}");
    assert_eq!(client.interrupt(WAIT), Some(0));

    // A client naming its server (server_mqtt_id) reaches that one; one naming a server
    // that is not there gets timeouts.
    let _second = start("pb_rpc_server", &broker, |c| {
        c.replace("client_id: example_pb_rpc_server", "client_id: server_b")
    });
    let by_id = |id: &str| {
        let id = id.to_owned();
        move |c: String| {
            c.replace(
                "            - func_name: \"(.*)\"\n              qos: 0",
                &format!("            - func_name: \"(.*)\"\n              qos: 0\n              server_mqtt_id: {id}"),
            )
        }
    };
    let mut to_b = start("pb_rpc_client", &broker, by_id("server_b"));
    to_b.wait_for(aimrt_e2e::RPC_EXAMPLE_RSP, WAIT);
    assert_eq!(to_b.interrupt(WAIT), Some(0));
    let mut to_nobody = start("pb_rpc_client", &broker, by_id("server_x"));
    let (_, line) = to_nobody.wait_for("Client get rpc error ret", WAIT);
    assert!(line.contains("code 2, msg: Timeout"), "{line}");
    assert_eq!(to_nobody.interrupt(WAIT), Some(0));
}

#[test]
fn bad_options_stop_start_up_with_a_message_naming_them() {
    // A broker of the test's own: a case that gets as far as connecting reaches it, not
    // whatever listens on the examples' port.
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let ours = format!("tcp://{}", broker.addr());
    let port = broker.addr().port();
    let ssl = format!("ssl://127.0.0.1:{port}");
    let bare = format!("127.0.0.1:{port}");
    let wss = format!("wss://127.0.0.1:{port}");
    let cases: [(&str, &str, &str); 6] = [
        (&ours, &ssl, "is a TLS broker: set truststore"),
        (&ours, &wss, "MQTT over websocket (wss://) is not supported"),
        (&ours, &bare, "has no scheme: write tcp://host:port"),
        (
            "client_id: example_pb_rpc_server",
            "client_id: \"\"",
            "client_id is empty",
        ),
        (
            "qos: 0",
            "qos: 3",
            "servers_options[0].qos is 3: MQTT's QoS is 0, 1 or 2",
        ),
        (
            "callback_executor_name: mqtt_callback",
            "callback_executor_name: nowhere",
            "callback_executor_name 'nowhere' is not an executor",
        ),
    ];
    for (from, to, expected) in cases {
        let cfg = with_broker(&repo_config("mqtt_pb_rpc_server"), &ours).replace(from, to);
        assert!(cfg.contains(to), "{from} not in the config");
        let out = run_main(
            Some(&cfg),
            &["--cfg_file_path=./cfg.yaml"],
            Duration::from_secs(30),
        );
        aimrt_e2e::assert_failure(&out, &[expected, "cfg.yaml:"]);
    }
}

#[test]
fn a_message_over_max_pkg_size_k_is_refused_to_its_publisher_and_counted() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut sub = start("pb_chn_sub", &broker, same);
    let mut publisher = start("pb_chn_pub", &broker, |cfg| {
        aimrt_e2e::fast_big_publisher(&cfg, 20)
            .replace("max_pkg_size_k: 1024", "max_pkg_size_k: 63")
    });
    publisher.wait_for(
        "Mqtt publish failed, pkg is too large, limit 64512 bytes",
        WAIT,
    );
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = publisher.text();
    let refused = aimrt_e2e::number_after(&text, "mqtt_plugin: 0 payloads sent, ");
    assert!(refused > 0, "{text}");
    assert!(
        !sub.text().contains("Receive new pb event"),
        "{}",
        sub.text()
    );
}

/// How many calls a server's log says it handled.
fn served(server: &Running) -> usize {
    server.text().matches("Server handle new rpc call").count()
}

#[test]
fn servers_of_a_function_take_turns_unless_allow_share_is_off() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let server = |id: &'static str, share: bool| {
        start("pb_rpc_server", &broker, move |c| {
            c.replace(
                "client_id: example_pb_rpc_server",
                &format!("client_id: {id}"),
            )
            .replace(
                "qos: 0",
                &format!("qos: 0\n              allow_share: {share}"),
            )
        })
    };
    let mut a = server("server_a", true);
    let mut b = server("server_b", true);
    let mut own = server("server_own", false);
    let mut client = start("pb_rpc_client", &broker, |c| {
        c.replace("rpc_frq: 1", "rpc_frq: 20")
    });
    client.wait_for("echo hello world foo, count 20\"", WAIT);
    assert_eq!(client.interrupt(WAIT), Some(0));
    for s in [&mut a, &mut b, &mut own] {
        assert_eq!(s.interrupt(WAIT), Some(0));
    }
    assert!(
        served(&a) >= 5 && served(&b) >= 5,
        "a {}, b {}",
        served(&a),
        served(&b)
    );
    assert_eq!(served(&own), 0, "{}", own.text());
    assert!(
        !client.text().contains("Client get rpc error ret"),
        "{}",
        client.text()
    );
}

#[test]
fn a_broker_that_comes_up_after_the_processes_is_connected_to_and_carries_their_messages() {
    // A free port, with nothing listening on it yet.
    let port = aimrt_e2e::free_port(false);
    let env = [(
        "AIMRT_MQTT_BROKER".to_owned(),
        format!("tcp://127.0.0.1:{port}"),
    )];
    let fast_reconnect = |cfg: String| {
        cfg.replace(
            "max_pkg_size_k: 1024",
            "max_pkg_size_k: 1024\n          reconnect_interval_ms: 100",
        )
    };
    let mut sub = Running::start_env(&fast_reconnect(repo_config("mqtt_pb_chn_sub")), &env);
    sub.wait_for("mqtt_plugin: failed to connect to the mqtt broker", WAIT);
    // Start-up goes on after its wait, and says so.
    sub.wait_for("not connected to the mqtt broker", WAIT);
    sub.wait_for("Module manager start completed.", WAIT);
    let mut publisher = Running::start_env(
        &fast_reconnect(publishing_at(10)(repo_config("mqtt_pb_chn_pub"))),
        &env,
    );
    publisher.wait_for("Module manager start completed.", WAIT);
    let _broker = Broker::start(&format!("127.0.0.1:{port}")).unwrap();
    sub.wait_for("mqtt_plugin: connected to the mqtt broker", WAIT);
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    assert!(line.contains(r#"{"aimrt-backend":"mqtt"}"#), "{line}");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
}

/// AimRT's channel benchmark pair (QoS 0, 1000 messages a second on up to four topics),
/// plans shortened: every plan arrives whole through the broker.
#[test]
fn the_channel_benchmark_pair_loses_nothing() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut sub = start("pb_chn_benchmark_sub", &broker, same);
    let mut publisher = start("pb_chn_benchmark_pub", &broker, |c| {
        aimrt_e2e::shorter_bench_plans(&c, 10)
    });
    aimrt_e2e::assert_bench_plans_arrive_whole(&mut sub, 3, Duration::from_secs(60));
    publisher.wait_for("Bench completed.", WAIT);
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
}

/// AimRT's RPC benchmark client's two plans (shortened) against the example server,
/// every call answered OK.
#[test]
fn the_benchmark_client_calls_through_the_broker_without_error() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let mut server = start("pb_rpc_server", &broker, same);
    let mut client = start("pb_rpc_benchmark_client", &broker, |c| {
        aimrt_e2e::shorter_bench_plans(&c, 20)
    });
    let rates = aimrt_e2e::rpc_bench_error_rates(&mut client, 2, Duration::from_secs(60));
    assert_eq!(rates, ["0 %", "0 %"], "{}", client.text());
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
}

/// Two processes with the same client_id take the connection from each other (MQTT allows
/// one per id): the plugin says so, naming the id, instead of only logging lost
/// connections.
#[test]
fn two_processes_with_one_client_id_are_told_apart_from_a_flaky_broker() {
    let broker = Broker::start("127.0.0.1:0").unwrap();
    let fast = |cfg: String| {
        cfg.replace(
            "max_pkg_size_k: 1024",
            "max_pkg_size_k: 1024\n          reconnect_interval_ms: 100",
        )
    };
    let mut a = start("pb_chn_sub", &broker, fast);
    let mut b = start("pb_chn_sub", &broker, fast);
    let said = "another client with client_id 'example_pb_chn_subscriber' is probably connected";
    let deadline = std::time::Instant::now() + WAIT;
    let mut found = false;
    while !found && std::time::Instant::now() < deadline {
        let step = Duration::from_millis(200);
        found = !a.collect_for(step, said).is_empty() || !b.collect_for(step, said).is_empty();
    }
    assert!(found, "{}\n---\n{}", a.text(), b.text());
    assert_eq!(a.interrupt(WAIT), Some(0));
    assert_eq!(b.interrupt(WAIT), Some(0));
}

/// A TLS test broker on a free port; with `client_ca`, it requires client certificates.
fn tls_broker(client_ca: bool) -> Broker {
    let files = TlsFiles {
        cert: aimrt_e2e::tls_file("broker.pem"),
        key: aimrt_e2e::tls_file("broker.key"),
        client_ca: if client_ca {
            aimrt_e2e::tls_file("ca.pem")
        } else {
            String::new()
        },
    };
    Broker::start_tls("127.0.0.1:0", &files).unwrap()
}

/// `config/mqtt_pb_chn_ssl_<side>.yaml` against `broker`, edited by `edit`, with the test
/// certificates' folder; not waited for.
fn start_ssl(side: &str, broker: &Broker, edit: impl FnOnce(String) -> String) -> Running {
    start_ssl_at(side, broker.addr(), edit)
}

/// [`start_ssl`] against whatever listens at `addr`.
fn start_ssl_at(
    side: &str,
    addr: std::net::SocketAddr,
    edit: impl FnOnce(String) -> String,
) -> Running {
    let cfg = with_broker(
        &edit(repo_config(&format!("mqtt_pb_chn_ssl_{side}"))),
        &format!("ssl://{addr}"),
    );
    Running::start_env(
        &cfg,
        &[("AIMRT_MQTT_TLS_DIR".to_owned(), aimrt_e2e::tls_file(""))],
    )
}

/// Stops `running`, which must end well, its shutdown line saying it never connected.
fn ends_never_connected(mut running: Running) {
    assert_eq!(running.interrupt(WAIT), Some(0));
    let text = running.text();
    assert!(text.contains(" 0 connections made to the broker"), "{text}");
}

#[test]
fn the_ssl_example_pair_talks_through_a_tls_broker_that_requires_client_certificates() {
    let broker = tls_broker(true);
    let mut sub = start_ssl("sub", &broker, same);
    sub.wait_for("Module manager start completed.", WAIT);
    let mut publisher = start_ssl("pub", &broker, publishing_at(10));
    let (_, line) = sub.wait_for(r#""num":3}"#, WAIT);
    assert!(line.contains(r#"{"aimrt-backend":"mqtt"}"#), "{line}");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    assert!(
        text.contains("mqtt_plugin: connected to the mqtt broker ssl://"),
        "{text}"
    );
    assert!(!text.contains("failed to connect"), "{text}");
    assert!(broker.forwarded() >= 3, "{}", broker.forwarded());
}

#[test]
fn a_broker_the_truststore_does_not_vouch_for_is_never_connected_to_and_says_why() {
    // The broker's certificate is signed by the test CA; the client trusts another.
    let broker = tls_broker(false);
    let mut publisher = start_ssl("pub", &broker, |cfg| {
        publishing_at(10)(cfg).replace("/ca.pem", "/other_ca.pem")
    });
    let (_, line) = publisher.wait_for("mqtt_plugin: failed to connect to the mqtt broker", WAIT);
    assert!(line.contains("UnknownIssuer"), "{line}");
    assert!(
        line.contains("must be signed by a CA of truststore and name the host of broker_addr"),
        "{line}"
    );
    // Start-up goes on after its wait, and nothing reaches the broker.
    publisher.wait_for("Module manager start completed.", WAIT);
    std::thread::sleep(Duration::from_millis(500));
    ends_never_connected(publisher);
}

#[test]
fn a_client_without_a_certificate_is_refused_by_a_broker_that_requires_one_and_one_with_it_is_not()
{
    let broker = tls_broker(true);
    let without = |cfg: String| {
        cfg.lines()
            .filter(|l| !l.contains("client_cert:") && !l.contains("client_key:"))
            .map(|l| format!("{l}\n"))
            .collect::<String>()
    };
    let mut sub = start_ssl("sub", &broker, without);
    let (_, line) = sub.wait_for("mqtt_plugin: failed to connect to the mqtt broker", WAIT);
    assert!(
        line.contains(
            "the broker wants a client certificate it trusts: set client_cert and client_key"
        ),
        "{line}"
    );
    sub.wait_for("Module manager start completed.", WAIT);
    ends_never_connected(sub);
    // The same broker takes the example's client certificate.
    let mut with = start_ssl("sub", &broker, same);
    with.wait_for("mqtt_plugin: connected to the mqtt broker", WAIT);
    assert_eq!(with.interrupt(WAIT), Some(0));
}

#[test]
fn tls_files_that_cannot_serve_stop_start_up_naming_the_option_and_the_file() {
    let broker = tls_broker(false);
    let missing = aimrt_e2e::tls_file("missing.pem");
    for (from, to, expected) in [
        (
            "/ca.pem",
            "/missing.pem",
            format!("truststore '{missing}' cannot be read"),
        ),
        ("/ca.pem", "/ca.key", "holds no certificate".to_owned()),
        (
            "/client.key",
            "/broker.key",
            "do not go together".to_owned(),
        ),
        (
            "max_pkg_size_k: 1024",
            "max_pkg_size_k: 1024\n          client_key_password: secret",
            "encrypted private keys are not supported".to_owned(),
        ),
    ] {
        let cfg = with_broker(
            &repo_config("mqtt_pb_chn_ssl_pub"),
            &format!("ssl://{}", broker.addr()),
        )
        .replace(
            "${AIMRT_MQTT_TLS_DIR:-./tests/tls}/",
            &aimrt_e2e::tls_file(""),
        )
        .replace(from, to);
        assert!(cfg.contains(to), "{from} not in the config");
        let out = run_main(
            Some(&cfg),
            &["--cfg_file_path=./cfg.yaml"],
            Duration::from_secs(30),
        );
        aimrt_e2e::assert_failure(&out, &[&expected, "cfg.yaml:"]);
    }
}

#[test]
fn a_tls_broker_that_never_answers_the_handshake_is_a_failed_connect_and_nothing_waits_on_it() {
    // The kernel takes the connection; nothing ever reads it or answers.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let mut publisher = start_ssl_at("pub", silent.local_addr().unwrap(), same);
    // Start-up goes on after its wait; the connect gives up after rumqttc's 5 s.
    publisher.wait_for("Module manager start completed.", WAIT);
    let (_, line) = publisher.wait_for("mqtt_plugin: failed to connect to the mqtt broker", WAIT);
    assert!(line.to_lowercase().contains("timeout"), "{line}");
    ends_never_connected(publisher);
}
