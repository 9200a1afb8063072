//! zenoh_plugin between processes on loopback: AimRT's example configs (`config/zenoh_*`)
//! as pairs of `aimrt_main` processes, each test on its own ports and `limit_domain`
//! ([`ZenohPeers`]); malformed payloads and a server that never answers from a raw zenoh
//! peer (`aimrt_zenoh_probe`); a subscriber and a server whose processes stand still
//! (SIGSTOP); 1 MiB messages with and without shared memory.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use aimrt_e2e::{zenoh_example, Running, ZenohLink, ZenohPeers};

const WAIT: Duration = Duration::from_secs(30);
const KEY_EVENT: &str = "channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg";
const KEY_FOO: &str = "aimrt_rpc/%2Faimrt.protocols.example.ExampleService%2FGetFooData";

fn start(cfg: &str, peers: &ZenohPeers, side: &str) -> Running {
    let mut p = Running::start_env(cfg, &peers.env(side));
    p.wait_for("Module manager start completed.", WAIT);
    p
}

/// A raw zenoh peer on side `side` of `peers`.
fn probe(peers: &ZenohPeers, side: &str, args: &[&str]) -> Running {
    let native = peers.native(side).display().to_string();
    let mut all = vec![args[0], native.as_str()];
    all.extend_from_slice(&args[1..]);
    Running::start_program_env(&aimrt_e2e::binary("aimrt_zenoh_probe"), &all, "", &[])
}

fn fast_pub(frq: u32) -> String {
    zenoh_example("pb_chn_pub").replace("channel_frq: 0.5", &format!("channel_frq: {frq}"))
}

fn stat(text: &str, prefix: &str) -> String {
    text.lines()
        .find_map(|l| l.split_once(prefix).map(|(_, rest)| rest.to_owned()))
        .unwrap_or_else(|| panic!("no line with '{prefix}' in\n{text}"))
}

#[test]
fn aimrts_channel_example_pair_exchanges_messages_with_their_context() {
    let peers = ZenohPeers::new("chn_pair");
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let cfg = fast_pub(10).replace(
        "  channel_frq: 10",
        "  channel_frq: 10\n  context_meta:\n    my-key: my-val",
    );
    let mut publisher = start(&cfg, &peers, "a");
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    aimrt_e2e::assert_first_event_carries_context(&line, "zenoh");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    assert!(
        sub.text().contains(&format!(
            "Register subscribe type to zenoh channel, url: {KEY_EVENT}/{}",
            peers.domain
        )),
        "{}",
        sub.text()
    );
    assert!(sub.text().contains("close session"), "{}", sub.text());
    // Started first, the subscriber found nobody at its connect endpoint.
    assert!(
        sub.text().contains("Scouting delay elapsed before start conditions are met: no peer answered at connect.endpoints within scouting.delay; the session opens now and goes on connecting in the background"),
        "{}",
        sub.text()
    );
}

#[test]
fn ten_thousand_messages_arrive_in_order_and_every_one_is_accounted_for() {
    let peers = ZenohPeers::new("ten_thousand");
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let mut publisher = start(&fast_pub(2000), &peers, "a");
    sub.wait_for(r#""num":10000}"#, Duration::from_secs(120));
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let published =
        aimrt_e2e::number_after(&publisher.text(), "Channel topic 'test_topic': published ");
    let seen = aimrt_e2e::received_seqs(&sub.text());
    assert!(seen.len() >= 10_000, "{} messages", seen.len());
    // In order, none missing: the subscriber was there before the first publish.
    for (i, s) in seen.iter().enumerate() {
        assert_eq!(*s, i as u64 + 1, "message {i} has pub_seq {s}");
    }
    let line = stat(&sub.text(), "Channel topic 'test_topic': ");
    assert!(
        line.contains(&format!("delivered {published}, dropped 0")),
        "published {published}; subscriber: {line}"
    );
}

#[test]
fn a_late_subscriber_and_a_restarted_publisher_are_heard() {
    let peers = ZenohPeers::new("late_and_restart");
    // The publisher first: its messages go nowhere, and it never blocks.
    let mut publisher = start(&fast_pub(20), &peers, "a");
    publisher.wait_for("loop count : 10 ", WAIT);
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    sub.wait_for("Receive new pb event", WAIT);
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    // What it published before the subscriber came reached no one: said once, counted.
    let text = publisher.text();
    let said: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("zenoh_plugin: no subscriber matches"))
        .collect();
    assert_eq!(said.len(), 1, "{text}");
    assert!(
        said[0].contains(&format!("'{KEY_EVENT}/{}'", peers.domain)),
        "{}",
        said[0]
    );
    let unmatched = aimrt_e2e::number_after(&text, " answers for unknown request ids, ");
    assert!(unmatched >= 10, "{unmatched}");
    // The end of that stretch is said too, after the subscriber's process connected.
    let at = |what: &str| {
        text.find(what)
            .unwrap_or_else(|| panic!("no '{what}' in:\n{text}"))
    };
    let (none, connected, matches) = (
        at("zenoh_plugin: no subscriber matches"),
        at("zenoh_plugin: connected to peer "),
        at(&format!(
            "zenoh_plugin: a subscriber matches '{KEY_EVENT}/{}': its messages reach it from now on",
            peers.domain
        )),
    );
    assert!(none < connected && connected < matches, "{text}");
    // The subscriber's process says when the publisher's went and came back.
    sub.wait_for(" is gone: it closed its session", WAIT);
    let mut again = start(&fast_pub(20), &peers, "a");
    let (_, line) = again.wait_for("Publish new pb event", WAIT);
    assert!(line.contains(r#""num":1}"#), "{line}");
    // The restarted publisher counts from 1 again (the first one was past 10 when the
    // subscriber came).
    sub.wait_for(r#"data: {"msg":"count: 3","num":3}"#, WAIT);
    assert_eq!(again.interrupt(WAIT), Some(0));
    sub.wait_for(" is gone: it closed its session", WAIT);
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    let lines = |what: &str| text.lines().filter(|l| l.contains(what)).count();
    assert_eq!(lines("zenoh_plugin: connected to peer "), 2, "{text}");
    // Gone twice, once a publisher.
    assert_eq!(lines(" is gone: it closed its session"), 2, "{text}");
}

/// AimRT's channel and RPC example pairs over unix sockets (`unixsock-stream/` endpoints):
/// the same messages and answers as over TCP.
#[test]
fn unix_socket_pairs_exchange_messages_and_calls() {
    let peers = ZenohPeers::over("unix_chn", ZenohLink::Unix);
    let native = std::fs::read_to_string(peers.native("a")).unwrap();
    assert!(native.contains("\"unixsock-stream/"), "{native}");
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let mut publisher = start(&fast_pub(10), &peers, "a");
    sub.wait_for(r#"data: {"msg":"count: 3","num":3}"#, WAIT);
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    // The subscriber, up first, tried the publisher's socket before it existed: zenoh's
    // warning at each try is left out, as its TCP link retries without a word.
    for side in [&sub, &publisher] {
        assert!(
            !side.text().contains("UnixSocketStream link bound to"),
            "{}",
            side.text()
        );
    }

    let peers = ZenohPeers::over("unix_rpc", ZenohLink::Unix);
    let (mut server, mut client) = answered_rpc_pair(&peers, "");
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
    assert!(
        !client.text().contains("code 2010"),
        "a call found no server\n{}",
        client.text()
    );
}

#[test]
fn a_process_in_another_limit_domain_hears_nothing() {
    let peers = ZenohPeers::new("domain_a");
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let mut env = peers.env("a");
    env[1].1 = format!("{}/other", peers.domain);
    let mut publisher = Running::start_env(&fast_pub(50), &env);
    publisher.wait_for("loop count : 50 ", WAIT);
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    assert!(
        !sub.text().contains("Receive new pb event"),
        "{}",
        sub.text()
    );
}

const RSP: &str = aimrt_e2e::RPC_EXAMPLE_RSP;

#[test]
fn aimrts_rpc_example_pair_calls_in_every_style() {
    for (server_style, client_style) in [
        ("Co", "Co"),
        ("Sync", "Sync"),
        ("Async", "Async"),
        ("Co", "Future"),
    ] {
        let peers = ZenohPeers::new(&format!("rpc_{client_style}"));
        let server_cfg = zenoh_example("pb_rpc_server").replace(
            "NormalRpcCoServerModule",
            &format!("NormalRpc{server_style}ServerModule"),
        );
        let mut server = start(&server_cfg, &peers, "b");
        let client_cfg = zenoh_example("pb_rpc_client")
            .replace(
                "NormalRpcCoClientModule",
                &format!("NormalRpc{client_style}ClientModule"),
            )
            .replace("rpc_frq: 0.5", "rpc_frq: 5");
        let mut client = start(&client_cfg, &peers, "a");
        client.wait_for(RSP, WAIT);
        assert_eq!(client.interrupt(WAIT), Some(0));
        let (_, line) = server.wait_for("Server handle new rpc call. context: ", WAIT);
        for kv in [
            r#"{"aimrt-function_name":"pb:/aimrt.protocols.example.ExampleService/GetFooData"}"#,
            r#"{"aimrt-serialization_type":"pb"}"#,
            r#"{"aimrt-backend":"zenoh"}"#,
            // As AimRT sets it for every backend: the caller's request id.
            r#"{"aimrt-request_id":"1"},"#,
            r#"{"aimrt-response_id":"1"}"#,
            // zenoh carries no timeout: the service has none (AimRT's 0) and is not cut
            // off at the runtime's 5 s default.
            "Server context, timeout: 0ms, ",
        ] {
            assert!(line.contains(kv), "{client_style}: {kv} not in {line}");
        }
        assert_eq!(server.interrupt(WAIT), Some(0));
        assert!(
            !client.text().contains("code 2,") && !client.text().contains("panicked:"),
            "{client_style}: {}",
            client.text()
        );
    }
}

#[test]
fn a_call_without_a_server_and_a_server_that_dies_mid_call_are_answered_in_time() {
    let peers = ZenohPeers::new("server_dies");
    let client_cfg = zenoh_example("pb_rpc_client").replace("rpc_frq: 0.5", "rpc_frq: 2");
    let mut client = start(&client_cfg, &peers, "a");
    // Nobody serves GetFooData: the call is answered at once, not at its timeout.
    let (_, line) = client.wait_for("Client get rpc error ret", WAIT);
    assert!(line.contains("code 2010"), "{line}");
    // A raw peer that takes requests and never answers, then dies mid-call.
    let req_key = format!("req/{KEY_FOO}/{}", peers.domain);
    let mut mute = probe(&peers, "b", &["listen", &req_key, "1000"]);
    mute.wait_for("sample ", WAIT);
    // A server that never answers: the call ends at its deadline (3 s), with 2. (Calls
    // made before the raw peer was known may still be logged with 2010 before it.)
    let (_, line) = client.wait_for("code 2, msg: Timeout", WAIT);
    assert!(line.contains("Client get rpc error ret"), "{line}");
    // The next call is in flight when the server dies.
    mute.wait_for("sample ", WAIT);
    let killed = Instant::now();
    mute.signal("KILL");
    let (at, line) = client.wait_for("Client get rpc error ret", WAIT);
    assert!(
        line.contains("code 2010") || line.contains("code 2,"),
        "{line}"
    );
    assert!(
        at.duration_since(killed) < Duration::from_secs(3),
        "answered {:?} after the server died; the call's timeout is 3 s",
        at.duration_since(killed)
    );
    assert_eq!(client.interrupt(WAIT), Some(0));
}

/// A subscriber process that stands still (SIGSTOP) while its publisher publishes 800
/// messages of 64 KiB (52 MB) does not hold the publisher up (no 2.5 s gap between two
/// of its loops): with zenoh's `Drop` congestion control a publish waits at most
/// `wait_before_drop` (1 ms; up to 50 ms for a fragmented message), and none at all
/// once zenoh has marked the link congested; what the link cannot take is dropped. When
/// the subscriber goes on, it hears what is published from then on, and nothing arrives
/// twice or out of order.
#[test]
fn a_stopped_subscriber_never_holds_the_publisher_up_and_hears_it_again() {
    let peers = ZenohPeers::new("stopped_sub");
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let cfg = aimrt_e2e::fast_big_publisher(&zenoh_example("pb_chn_pub"), 200);
    let mut publisher = start(&cfg, &peers, "a");
    aimrt_e2e::stop_a_subscriber_under_its_publisher(&mut sub, &mut publisher, 800, true);
    // The stop did congest the link: messages are missing (zenoh drops them without
    // telling the publisher; docs/zenoh.md), and the subscriber counted every one of them
    // from the gaps in the publisher's sequence.
    let text = sub.text();
    let seen = aimrt_e2e::received_seqs(&text);
    let missing = seen.windows(2).map(|w| w[1] - w[0] - 1).sum::<u64>();
    assert!(missing > 0, "nothing was dropped: {seen:?}");
    let lost = aimrt_e2e::number_after(&text, " subscriber matched, ");
    let topic = stat(&text, "Channel topic 'test_topic': published ");
    assert!(
        topic.contains(&format!("dropped {missing} (lost after publish: {lost})")),
        "{missing} missing, {lost} lost; subscriber: {topic}"
    );
}

/// AimRT's RPC example pair `pb_rpc_server<suffix>` (side b) and `pb_rpc_client<suffix>`
/// (side a, calling 5 times a second), once the client has logged an answer.
fn answered_rpc_pair(peers: &ZenohPeers, suffix: &str) -> (Running, Running) {
    let server = start(
        &zenoh_example(&format!("pb_rpc_server{suffix}")),
        peers,
        "b",
    );
    let client_cfg =
        zenoh_example(&format!("pb_rpc_client{suffix}")).replace("rpc_frq: 0.5", "rpc_frq: 5");
    let mut client = start(&client_cfg, peers, "a");
    client.wait_for(RSP, WAIT);
    (server, client)
}

/// A server process whose four modules all serve the example's functions runs each
/// request once: one answer a call, none left over for the client to count as unknown.
#[test]
fn a_function_several_modules_of_a_process_serve_is_served_once_a_call() {
    let peers = ZenohPeers::new("served_by_many");
    let all_servers = zenoh_example("pb_rpc_server")
        .replace("        enable_modules: [NormalRpcCoServerModule]\n", "");
    assert!(!all_servers.contains("enable_modules"), "{all_servers}");
    let mut server = start(&all_servers, &peers, "b");
    let client_cfg = zenoh_example("pb_rpc_client").replace("rpc_frq: 0.5", "rpc_frq: 5");
    let mut client = start(&client_cfg, &peers, "a");
    for _ in 0..3 {
        client.wait_for("Client get rpc ret, status: suc", WAIT);
    }
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
    let (client, server) = (client.text(), server.text());
    let served = server.matches("Server handle new rpc call").count();
    let calls = aimrt_e2e::number_after(&client, "Module RPC: ");
    assert!(
        served >= 3 && served as u64 <= calls,
        "{served} requests served for {calls} calls:\n{server}"
    );
    assert_eq!(
        aimrt_e2e::number_after(&client, " malformed received, "),
        0,
        "answers for unknown request ids:\n{client}"
    );
}

/// A server process that stands still (SIGSTOP): the call in flight ends at its deadline
/// (3 s) with 2, its answer, sent when the server goes on, is counted and dropped, and the
/// calls after it are answered.
#[test]
fn a_stopped_server_is_timed_out_and_its_late_answers_are_counted() {
    let peers = ZenohPeers::new("stopped_server");
    let (mut server, mut client) = answered_rpc_pair(&peers, "");
    let text = aimrt_e2e::stop_a_server_under_its_client(&mut server, &mut client);
    // The timed-out call's answer came after its deadline: the runtime drops it as late
    // while the backend still knows the call (1 s), the backend as unknown after.
    let late = aimrt_e2e::number_after(&text, " timed out), ");
    let unknown = aimrt_e2e::number_after(&text, " malformed received, ");
    assert_eq!(late + unknown, 1, "{text}");
}

#[test]
fn malformed_payloads_from_a_raw_peer_are_counted_and_never_stop_the_subscriber() {
    let peers = ZenohPeers::new("malformed");
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let key = format!("{KEY_EVENT}/{}", peers.domain);
    let mut inject = probe(&peers, "a", &["inject", &key]);
    assert_eq!(inject.wait_exit(WAIT), Some(0), "{}", inject.text());
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    assert!(line.contains(r#"{"probe":"after-garbage"}"#), "{line}");
    assert!(
        line.contains(r#"{"aimrt-backend":"zenoh"}"#) && !line.contains("forged"),
        "{line}"
    );
    assert!(
        line.ends_with(r#"data: {"msg":"after garbage","num":7}"#),
        "{line}"
    );
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    // Six payloads are not AimRT's layout; two are (the unknown serialization type and the
    // bad protobuf): those are dropped by the subscriber's decoder, counted per topic.
    assert!(text.contains("6 malformed received"), "{text}");
    assert!(text.contains("dropped 2"), "{text}");
}

/// The sequence numbers of zenoh's source info that `aimrt_zenoh_probe listen` printed
/// for `n` samples of our example publisher on side a, with `backend_options` for its
/// zenoh channel backend (`None` for those of the example).
fn sequence_numbers_heard(suffix: &str, backend_options: Option<&str>) -> Vec<String> {
    let peers = ZenohPeers::new(&format!("send_sequence{suffix}"));
    let key = format!("{KEY_EVENT}/{}", peers.domain);
    let mut listener = probe(&peers, "b", &["listen", &key, "3"]);
    listener.wait_for("listening on", WAIT);
    let mut cfg = fast_pub(20);
    if let Some(options) = backend_options {
        let with = format!("      - type: zenoh\n        options:\n{options}");
        cfg = cfg.replacen("      - type: zenoh\n", &with, 1);
        assert!(cfg.contains(options), "{cfg}");
    }
    let mut publisher = start(&cfg, &peers, "a");
    assert_eq!(listener.wait_exit(WAIT), Some(0), "{}", listener.text());
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    let text = listener.text();
    text.lines()
        .filter_map(|l| l.strip_prefix("sample "))
        .map(|l| stat(l, "sn=").split(' ').next().unwrap_or("").to_owned())
        .collect()
}

/// Our publisher puts zenoh's source info with a sequence number one up for each message;
/// `send_sequence: false` leaves it out.
#[test]
fn a_publisher_numbers_its_messages_unless_a_topic_says_not_to() {
    let sns: Vec<u32> = sequence_numbers_heard("_on", None)
        .iter()
        .map(|sn| sn.parse().unwrap_or_else(|_| panic!("sn={sn}")))
        .collect();
    assert_eq!(sns.len(), 3);
    assert!(sns.windows(2).all(|w| w[1] == w[0] + 1), "{sns:?}");
    let off = "          pub_topics_options:\n            - topic_name: \"(.*)\"\n              send_sequence: false\n";
    assert_eq!(sequence_numbers_heard("_off", Some(off)), ["none"; 3]);
}

/// Gaps in a publisher's sequence (zenoh's source info, which our publishers send) are
/// counted as messages lost on the way, apart for each publisher; a late message and a
/// publisher's first are no gap.
#[test]
fn gaps_in_a_publishers_sequence_are_counted_as_lost() {
    let peers = ZenohPeers::new("sequence_gaps");
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let key = format!("{KEY_EVENT}/{}", peers.domain);
    // Publisher 0: 5 6 _ _ 9 10 (8 late) _ … _ 20: 2 + 9 lost. Publisher 1: 0 1 _ _ 4: 2.
    let list = "5,6,9,1:0,1:1,10,8,20,1:4";
    let mut put = probe(&peers, "a", &["sequence", &key, list]);
    assert_eq!(put.wait_exit(WAIT), Some(0), "{}", put.text());
    sub.wait_for(r#"{"msg":"sn 4","num":4}"#, WAIT);
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    assert!(
        text.contains("Channel topic 'test_topic': published 0, delivered 9, dropped 13 (lost after publish: 13)"),
        "{text}"
    );
    assert_eq!(
        aimrt_e2e::number_after(&text, " subscriber matched, "),
        13,
        "{text}"
    );
    // Reported as they came, at most once a second.
    assert!(
        text.contains("2 messages for module 'NormalSubscriberModule' were dropped by backend 'zenoh': zenoh dropped them on the way from publisher "),
        "{text}"
    );
}

#[test]
fn a_server_survives_malformed_requests() {
    let peers = ZenohPeers::new("malformed_req");
    let mut server = start(&zenoh_example("pb_rpc_server"), &peers, "b");
    let key = format!("req/{KEY_FOO}/{}", peers.domain);
    let mut inject = probe(&peers, "a", &["inject", &key]);
    assert_eq!(inject.wait_exit(WAIT), Some(0), "{}", inject.text());
    let client_cfg = zenoh_example("pb_rpc_client").replace("rpc_frq: 0.5", "rpc_frq: 5");
    let mut client = start(&client_cfg, &peers, "a");
    client.wait_for(RSP, WAIT);
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
    // All nine are channel payloads, not requests: none is AimRT's request layout.
    assert!(
        server.text().contains("9 malformed received"),
        "{}",
        server.text()
    );
}

fn mib_pub(shm: bool) -> String {
    let name = if shm {
        "pb_chn_pub_with_shm"
    } else {
        "pb_chn_pub"
    };
    let cfg = zenoh_example(name).replace(
        "  channel_frq: 0.5",
        "  channel_frq: 5\n  msg_size: 1048576",
    );
    if shm {
        // AimRT's example pool (10 KiB) cannot hold a 1 MiB message: give it 8 MiB.
        cfg.replace("shm_pool_size: 10240", "shm_pool_size: 8388608")
    } else {
        cfg
    }
}

#[test]
fn one_mib_messages_cross_with_and_without_shared_memory() {
    for shm in [false, true] {
        let peers = ZenohPeers::new(&format!("mib_{shm}"));
        let key = format!("{KEY_EVENT}/{}", peers.domain);
        let mut listener = probe(&peers, "b", &["listen", &key, "4"]);
        listener.wait_for("listening on", WAIT);
        let mut publisher = start(&mib_pub(shm), &peers, "a");
        assert_eq!(listener.wait_exit(WAIT), Some(0));
        // Every sample, not only the first: zenoh's own shared memory for large payloads
        // (off in these native configs) starts after the first few messages.
        let text = listener.text();
        let samples: Vec<&str> = text.lines().filter(|l| l.starts_with("sample ")).collect();
        assert_eq!(samples.len(), 4, "{text}");
        for line in samples {
            let size: usize = line
                .split_whitespace()
                .nth(1)
                .and_then(|n| n.parse().ok())
                .expect("a size");
            assert!(size > 1 << 20, "{line}");
            assert!(line.ends_with(&format!("shm={shm}")), "shm {shm}: {line}");
        }
        assert_eq!(publisher.interrupt(WAIT), Some(0));
        if shm {
            assert!(
                !publisher.text().contains("(0 through shared memory"),
                "{}",
                publisher.text()
            );
        }
        // And an aimrt_main subscriber takes them.
        let peers = ZenohPeers::new(&format!("mib_sub_{shm}"));
        let sub_name = if shm {
            "pb_chn_sub_with_shm"
        } else {
            "pb_chn_sub"
        };
        let mut sub = start(&zenoh_example(sub_name), &peers, "b");
        let mut publisher = start(&mib_pub(shm), &peers, "a");
        // Whichever message arrives first: one published before the two peers have
        // found each other is not delivered (zenoh, like AimRT, keeps no history).
        let (_, line) = sub.wait_for("Receive new pb event", WAIT);
        assert!(
            line.contains(r#"data: {"msg":"<1048576 bytes>","num":"#),
            "{line}"
        );
        if shm {
            stop_removing_the_pools(&mut [&mut publisher, &mut sub], &[8 << 20]);
        } else {
            assert_eq!(publisher.interrupt(WAIT), Some(0));
            assert_eq!(sub.interrupt(WAIT), Some(0));
        }
    }
}

/// Side b's native config with `transport.link.rx.max_message_size` 64 KiB.
fn bound_max_message_size(peers: &ZenohPeers) {
    let native = peers.native("b");
    let text = std::fs::read_to_string(&native).expect("the native config");
    let bounded = text.replacen(
        "transport: {",
        "transport: { link: { rx: { max_message_size: 65536 } },",
        1,
    );
    assert_ne!(bounded, text);
    std::fs::write(&native, bounded).expect("write the native config");
}

/// A subscriber's native config bounds what a peer can make it take in
/// (`transport.link.rx.max_message_size`, 1 GiB by default): zenoh drops larger messages,
/// and the subscriber goes on with the next ones.
#[test]
fn a_subscribers_max_message_size_drops_larger_messages_and_it_goes_on() {
    let peers = ZenohPeers::new("max_message_size");
    bound_max_message_size(&peers);
    let mut sub = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    // Small messages cross before and after: the two are connected throughout.
    let mut small = start(&fast_pub(20), &peers, "a");
    sub.wait_for(r#"{"msg":"count: 2","num":2}"#, WAIT);
    assert_eq!(small.interrupt(WAIT), Some(0));
    let mut big = start(&mib_pub(false), &peers, "a");
    big.wait_for("loop count : 5 ", WAIT);
    assert_eq!(big.interrupt(WAIT), Some(0));
    let sent = stat(&big.text(), "zenoh_plugin: ");
    assert!(!sent.starts_with("0 payloads sent"), "{sent}");
    // A raw peer's message, which nothing before could have sent.
    let key = format!("{KEY_EVENT}/{}", peers.domain);
    let mut inject = probe(&peers, "a", &["inject", &key]);
    assert_eq!(inject.wait_exit(WAIT), Some(0), "{}", inject.text());
    sub.wait_for("after garbage", WAIT);
    assert_eq!(sub.interrupt(WAIT), Some(0));
    assert!(
        !sub.text().contains("<1048576 bytes>"),
        "a 1 MiB message got through: {}",
        sub.text()
    );
}

/// Messages over the subscriber's `max_message_size`, between smaller ones of the same
/// publisher: zenoh drops them without a word, and the subscriber counts them as lost when
/// the publisher's next message arrives.
#[test]
fn messages_over_the_subscribers_max_message_size_are_counted_when_the_next_arrives() {
    let peers = ZenohPeers::new("over_max_counted");
    bound_max_message_size(&peers);
    let mut sub = start(&zenoh_example("pb_chn_benchmark_sub"), &peers, "b");
    let plan = |size: u32, count: u32| {
        format!("    - perf_mode: multi-topic\n      channel_frq: 200\n      msg_size: {size}\n      topic_number: 1\n      msg_count: {count}\n")
    };
    let cfg = zenoh_example("pb_chn_benchmark_pub");
    let (head, _) = cfg.split_once("  bench_plans:\n").expect("bench plans");
    let cfg = format!(
        "{head}  bench_plans:\n{}{}{}",
        plan(512, 20),
        plan(131_072, 5),
        plan(512, 20)
    );
    let mut publisher = start(&cfg, &peers, "a");
    publisher.wait_for("Bench completed.", Duration::from_secs(60));
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    assert_eq!(
        aimrt_e2e::number_after(&text, " subscriber matched, "),
        5,
        "{text}"
    );
}

#[test]
fn a_full_shared_memory_pool_falls_back_to_the_network() {
    let peers = ZenohPeers::new("shm_full");
    let mut sub = start(&zenoh_example("pb_chn_sub_with_shm"), &peers, "b");
    // AimRT's example pool of 10 KiB, and messages of 64 KiB: none fits.
    let cfg = zenoh_example("pb_chn_pub_with_shm")
        .replace("  channel_frq: 0.5", "  channel_frq: 10\n  msg_size: 65536");
    let mut publisher = start(&cfg, &peers, "a");
    sub.wait_for(r#""num":3}"#, WAIT);
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = publisher.text();
    assert!(text.contains("has no room for"), "{text}");
    assert!(text.contains("(0 through shared memory"), "{text}");
}

/// The same side started twice: the second cannot listen on the endpoint, and says so
/// in one line, without zenoh's source paths, with what would be right; zenoh's own
/// warning shows them from the crate's folder on.
#[test]
fn the_same_side_started_twice_is_a_clear_failure() {
    let peers = ZenohPeers::new("twice");
    let mut first = start(&zenoh_example("pb_chn_sub"), &peers, "b");
    let out = aimrt_e2e::run_main(
        Some(&own_sub(&peers)),
        &["--cfg_file_path=./cfg.yaml"],
        WAIT,
    );
    aimrt_e2e::assert_failure(
        &out,
        &[
            "Unable to open zenoh session",
            "Address already in use (os error 98)]",
            "another process listens on that endpoint (this config started twice?)",
        ],
    );
    // zenoh's own warning about the listener shows its source places from the crate on.
    assert!(
        out.stdout.contains("Unable to open listener") && !out.stdout.contains("/registry/src/"),
        "{}",
        out.stdout
    );
    assert_eq!(first.interrupt(WAIT), Some(0));
}

/// Processes in client mode talk through a router (`config/zenoh_router.yaml`: aimrt_main
/// with zenoh_plugin alone, in router mode). A client started before its router says what
/// it waits for and goes on when the router comes. Messages arrive in order and calls are
/// answered. While the router is restarted the publisher says nobody hears it, a call is
/// answered 2010 (no server) at once, and the subscriber counts what was lost meanwhile:
/// delivered + lost = published.
#[test]
fn clients_talk_through_a_router_that_starts_late_and_restarts() {
    let peers = ZenohPeers::routed("router");
    let mut sub = Running::start_env(&zenoh_example("pb_chn_sub"), &peers.env("b"));
    sub.wait_for(
        "zenoh_plugin: start-up waits until this client connects to a router at tcp/127.0.0.1:",
        WAIT,
    );
    let router_cfg = aimrt_e2e::repo_config("zenoh_router");
    let mut router = start(&router_cfg, &peers, "r");
    assert!(
        router.text().contains("open as a router"),
        "{}",
        router.text()
    );
    sub.wait_for("Module manager start completed.", WAIT);
    let mut publisher = start(&fast_pub(20), &peers, "a");
    let mut server = start(&zenoh_example("pb_rpc_server"), &peers, "c");
    let client_cfg = zenoh_example("pb_rpc_client").replace("rpc_frq: 0.5", "rpc_frq: 5");
    let mut client = start(&client_cfg, &peers, "a");
    client.wait_for(RSP, WAIT);
    sub.wait_for(r#""num":5}"#, WAIT);

    // The router goes away: a call finds no server at once. It comes back on its port,
    // and the clients connect again.
    assert_eq!(router.interrupt(WAIT), Some(0));
    client.wait_for("status: fail, code 2010", WAIT);
    let mut router = start(&router_cfg, &peers, "r");
    sub.wait_for("were dropped by backend 'zenoh'", WAIT);
    client.wait_for("Client get rpc ret, status: suc, code 0", WAIT);
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));

    assert_eq!(publisher.interrupt(WAIT), Some(0));
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    assert_eq!(router.interrupt(WAIT), Some(0));
    assert!(
        publisher
            .text()
            .contains("zenoh_plugin: no subscriber matches"),
        "{}",
        publisher.text()
    );
    let published =
        aimrt_e2e::number_after(&publisher.text(), "Channel topic 'test_topic': published ");
    let seen = aimrt_e2e::received_seqs(&sub.text());
    assert!(
        seen.windows(2).all(|w| w[0] < w[1]),
        "out of order: {seen:?}"
    );
    let line = stat(&sub.text(), "Channel topic 'test_topic': published ");
    let delivered = aimrt_e2e::number_after(&line, "delivered ");
    let lost = aimrt_e2e::number_after(&line, "lost after publish: ");
    assert!(lost > 0, "nothing lost while the router was away: {line}");
    assert_eq!(
        delivered + lost,
        published,
        "published {published}; subscriber: {line}"
    );
}

/// Shared memory works between clients of one router on one machine: a 1 MiB message of
/// an `shm_enabled` publisher reaches a raw subscriber through shared memory.
#[test]
fn shared_memory_crosses_a_router() {
    let peers = ZenohPeers::routed("router_shm");
    let mut router = start(&aimrt_e2e::repo_config("zenoh_router"), &peers, "r");
    let key = format!("{KEY_EVENT}/{}", peers.domain);
    let mut listener = probe(&peers, "b", &["listen", &key, "2"]);
    listener.wait_for("listening on", WAIT);
    let mut publisher = start(&mib_pub(true), &peers, "a");
    assert_eq!(listener.wait_exit(WAIT), Some(0), "{}", listener.text());
    let text = listener.text();
    let samples: Vec<&str> = text.lines().filter(|l| l.starts_with("sample ")).collect();
    assert_eq!(samples.len(), 2, "{text}");
    assert!(samples.iter().all(|l| l.ends_with("shm=true")), "{text}");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert!(
        !publisher.text().contains("(0 through shared memory"),
        "{}",
        publisher.text()
    );
    assert_eq!(router.interrupt(WAIT), Some(0));
}

/// A Ctrl-C while a client waits for its router is said at once. It takes effect when the
/// session has opened: no later plugin is loaded, no module initialized, the zenoh plugin
/// is shut down (its session closed) and the process exits 0.
#[test]
fn a_signal_while_a_client_waits_for_its_router_stops_start_up_once_it_opens() {
    let peers = ZenohPeers::routed("signal_waiting");
    let cfg = zenoh_example("pb_chn_sub").replacen(
        "  log:",
        &format!(
            "      - name: abi_1_9_plugin\n        path: {}\n  log:",
            aimrt_e2e::lib("libfixture_abi_1_9.so").display()
        ),
        1,
    );
    let mut sub = Running::start_env(&cfg, &peers.env("b"));
    sub.wait_for(
        "start-up waits until this client connects to a router",
        WAIT,
    );
    sub.signal("INT");
    sub.wait_for("Received shutdown signal during start-up", WAIT);
    let mut router = start(&aimrt_e2e::repo_config("zenoh_router"), &peers, "r");
    assert_eq!(sub.wait_exit(WAIT), Some(0), "{}", sub.text());
    let text = sub.text();
    for present in [
        "open as a client",
        "Shutdown requested: plugin 'abi_1_9_plugin' and the plugins after it are not loaded.",
        "zenoh_plugin: 0 payloads sent",
        "close session",
    ] {
        assert!(text.contains(present), "no '{present}':\n{text}");
    }
    assert!(!text.contains("Init module"), "{text}");
    assert_eq!(router.interrupt(WAIT), Some(0));
}

/// A start-up that fails after zenoh_plugin opened its session (here a module's
/// `initialize` returns an error) still shuts the plugin down: the session closes, its
/// shutdown line is written, and its listen port is free again. In app mode the next
/// `start` in the same process listens on it; before, a plugin that had not started was
/// never shut down, and that start failed with "Address already in use".
#[test]
fn a_start_up_that_fails_after_the_session_opened_closes_it() {
    use aimrt_runtime::{Runtime, RuntimeOptions};
    let peers = ZenohPeers::new("failed_start");
    let plugin = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: zenoh_plugin\n        path: {}\n        options:\n          native_cfg_path: {}\n          limit_domain: {}\n",
        aimrt_e2e::lib("libaimrt_zenoh_plugin.so").display(),
        peers.native("b").display(),
        peers.domain
    );
    let failing = format!(
        "{plugin}  module:\n    pkgs:\n      - path: {}\n        enable_modules: [FailModule]\n",
        aimrt_e2e::lib("libfixture_init_panic.so").display()
    );
    let start = |cfg: &str| {
        Runtime::new(RuntimeOptions {
            cfg_yaml: Some(cfg.to_owned()),
            ..Default::default()
        })
        .start()
    };
    let err = start(&failing).expect_err("FailModule fails").to_string();
    assert!(err.contains("required setting 'speed' is missing"), "{err}");
    match start(&plugin) {
        Ok(app) => app.shutdown(),
        Err(e) => panic!("the session of the failed start still holds its port: {e}"),
    }
    let logged = failing.replace(
        "  module:",
        "  log:\n    backends:\n      - type: console\n  module:",
    );
    let out = aimrt_e2e::run_main(Some(&logged), &["--cfg_file_path=./cfg.yaml"], WAIT);
    aimrt_e2e::assert_failure(&out, &["required setting 'speed' is missing"]);
    assert!(
        out.stdout.contains("zenoh_plugin: 0 payloads sent")
            && out.stdout.contains("close session"),
        "{}",
        out.stdout
    );
}

/// The subscriber of AimRT's channel example, on this test's own ports and domain.
fn own_sub(peers: &ZenohPeers) -> String {
    zenoh_example("pb_chn_sub")
        .replace(
            "${AIMRT_ZENOH_NATIVE_CFG:-./config/zenoh_native_b.json5}",
            &peers.native("b").display().to_string(),
        )
        .replace("${AIMRT_ZENOH_LIMIT_DOMAIN:-}", &peers.domain)
}

/// A process with too few file descriptors for zenoh fails with one line that says so,
/// never a panic or an abort. zenoh panics when one of its thread pools cannot start;
/// inside `zenoh::open` that panic unwound through zenoh's listeners, whose drop panicked
/// again, and the process aborted (`ulimit -n 16`: SIGABRT). The limit rises from 8 until
/// the process runs.
#[test]
fn too_few_file_descriptors_are_a_clear_failure_never_an_abort() {
    let peers = ZenohPeers::new("fd_limit");
    let refusals = aimrt_e2e::refusals_until_it_runs(&own_sub(&peers), "-n", 8..=256);
    let zenoh: Vec<_> = refusals
        .iter()
        .filter(|(_, line)| line.contains("Unable to open zenoh session"))
        .collect();
    assert!(zenoh.len() >= 3, "zenoh refused only {refusals:#?}");
    for (limit, line) in zenoh {
        assert!(
            line.contains("raise the limit (`ulimit -n`)"),
            "ulimit -n {limit}:\n{line}"
        );
    }
    for (limit, line) in &refusals {
        assert!(
            line.contains("Unable to open zenoh session") || line.contains("Too many open files"),
            "ulimit -n {limit}:\n{line}"
        );
    }
}

/// A process that the system refuses threads (`ulimit -v`: thread stacks do not fit) fails
/// with one line, never a hang: tokio, under zenoh's `rx` pool, waited forever for the
/// worker it had started when the system refused the second (at about 64 MB here). The
/// limit rises from 40 MB in 1 MB steps until the process runs.
#[test]
fn a_process_refused_threads_never_hangs_in_zenoh() {
    let peers = ZenohPeers::new("as_limit");
    let refusals =
        aimrt_e2e::refusals_until_it_runs(&own_sub(&peers), "-v", (40..=600).map(|mb| mb * 1024));
    assert!(
        refusals
            .iter()
            .any(|(_, line)| line.contains("zenoh cannot start its thread pool")),
        "no limit stopped zenoh's pools: {refusals:#?}"
    );
}

#[test]
fn bad_zenoh_configs_stop_start_up_with_a_clear_error() {
    let peers = ZenohPeers::new("bad_configs");
    let native = peers.native("a").display().to_string();
    let base = |name: &str| {
        zenoh_example(name)
            .replace(
                "${AIMRT_ZENOH_NATIVE_CFG:-./config/zenoh_native_a.json5}",
                &native,
            )
            .replace("${AIMRT_ZENOH_LIMIT_DOMAIN:-}", &peers.domain)
    };
    let native_line = format!("native_cfg_path: {native}");
    let cases: Vec<(String, Vec<&str>)> = vec![
        (
            base("pb_chn_pub").replace(&native_line, "native_cfg_path: ./no_such.json5"),
            vec![
                "zenoh_plugin",
                "native_cfg_path './no_such.json5' is not a file",
            ],
        ),
        (
            base("pb_chn_pub").replace(&native_line, "native_cfg_path: ./cfg.yaml"),
            vec!["native_cfg_path './cfg.yaml' is not a zenoh config"],
        ),
        (
            base("pb_chn_pub").replace(&peers.domain, "/room1"),
            vec!["limit_domain '/room1' must not start or end with '/'"],
        ),
        (
            base("pb_chn_pub").replace(&peers.domain, "room1//A2"),
            vec!["limit_domain 'room1//A2' does not make valid zenoh keys (as channel/<topic>/<type>/room1//A2): empty chunks are forbidden"],
        ),
        (
            base("pb_chn_pub").replace(&peers.domain, "a*b"),
            vec!["limit_domain 'a*b' does not make valid zenoh keys (as channel/<topic>/<type>/a*b): `*` may only be preceded by `/` or `$`"],
        ),
        (
            base("pb_chn_pub").replace("native_cfg_path:", "native_config_path:"),
            vec!["native_config_path", "native_cfg_path"],
        ),
        (
            base("pb_chn_pub_with_shm").replace(
                "- topic_name: \"(.*)\"\n              shm_enabled",
                "- topic_name: \"(.*\"\n              shm_enabled",
            ),
            vec!["pub_topics_options[0].topic_name '(.*' is not a valid regular expression"],
        ),
        (
            base("pb_chn_pub_with_shm").replace("shm_enabled: true", "shm_enabled: yes please"),
            vec!["shm_enabled"],
        ),
        (
            base("pb_chn_pub_with_shm")
                .replace("shm_enabled: true", "shm_enabled: true\n              send_sequence: 1"),
            vec!["send_sequence"],
        ),
        (
            // A topic's key, not an RPC rule's.
            base("pb_rpc_client_with_shm").replace(
                "shm_enabled: true",
                "shm_enabled: true\n              send_sequence: true",
            ),
            vec!["unknown key 'send_sequence'; expected one of func_name, shm_enabled"],
        ),
        (
            base("pb_rpc_client").replace(
                "timeout_executor: timeout_handle",
                "timeout_executor: timeout_handl",
            ),
            vec!["timeout_executor 'timeout_handl' is not an executor"],
        ),
    ];
    for (cfg, expected) in &cases {
        let out = aimrt_e2e::run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], WAIT);
        aimrt_e2e::assert_failure(&out, expected);
    }
    // A client whose router is not up, with zenoh's default for a client (one try).
    let routed = ZenohPeers::routed("no_router");
    let client = std::fs::read_to_string(routed.native("a")).expect("the client config");
    let once = routed.native("once");
    let cfg = base("pb_chn_pub").replace(&native, &once.display().to_string());
    // The example publisher with `text` as its native config.
    let run_with = |text: String| {
        std::fs::write(&once, text).expect("write");
        aimrt_e2e::run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], WAIT)
    };
    let out = run_with(client.replace(", timeout_ms: -1", ""));
    aimrt_e2e::assert_failure(
        &out,
        &[
            "Unable to open zenoh session",
            "): cannot connect: tcp/127.0.0.1:",
            ": Connection refused (os error 111). Start the process that listens there first (a router, for a client: `config/zenoh_router.yaml` runs one), or have this one wait for it with `connect: { timeout_ms: -1 }` in the native config",
        ],
    );
    // An endpoint no wait can mend, refused before the session opens (also when it would
    // wait without end).
    let port = client
        .split("tcp/127.0.0.1:")
        .nth(1)
        .and_then(|rest| rest.split('"').next())
        .expect("the router's port");
    let out = run_with(client.replace(&format!(":{port}\""), "\""));
    // The error ends with an example endpoint; nothing listens or connects there.
    let said = "connect endpoint 'tcp/127.0.0.1' has no valid port (1 to 65535); write e.g. tcp/127.0.0.1:";
    aimrt_e2e::assert_failure(&out, &[said]);
    let example = out
        .failure_line()
        .and_then(|l| l.split_once(said))
        .map(|(_, port)| port.trim_end().to_owned())
        .unwrap_or_default();
    assert!(
        example.parse::<u16>().is_ok_and(|p| p > 0),
        "the example endpoint's port is not one: {example:?}"
    );
    // A tls/ endpoint (zenoh's TLS link is left out), refused naming why.
    let out = run_with(client.replace("\"tcp/", "\"tls/"));
    aimrt_e2e::assert_failure(
        &out,
        &[
            "uses protocol 'tls', which this build leaves out",
            "zenoh issue #2557",
            "docs/zenoh.md#tls",
        ],
    );
}

/// `aimrt_zenoh_probe call` with a captured request: the answer line.
fn call_with(peers: &ZenohPeers, request: &[u8]) -> String {
    let hex: String = request.iter().map(|b| format!("{b:02x}")).collect();
    let mut call = probe(peers, "a", &["call", &peers.domain, &hex]);
    let (_, line) = call.wait_for("answer status=", WAIT);
    assert_eq!(call.wait_exit(WAIT), Some(0));
    line
}

#[test]
fn our_server_answers_the_requests_aimrts_client_sent() {
    let peers = ZenohPeers::new("aimrt_requests");
    let mut server = start(&zenoh_example("pb_rpc_server"), &peers, "b");
    let captures = aimrt_e2e::wire_fixture("zenoh_rpc_server_rsp.hex");
    let ok = |label: &str, rsp: &str, body_at: usize| {
        let line = call_with(&peers, &captures[label]);
        // AimRT's server answered these bytes (rsp_*: prefix, type, id, status, body).
        let want = &captures[rsp][body_at..];
        let want_hex: String = want.iter().map(|b| format!("{b:02x}")).collect();
        assert!(line.starts_with("answer status=0 "), "{label}: {line}");
        assert!(
            line.ends_with(&format!("body={want_hex}")),
            "{label}: {line}"
        );
    };
    ok("req_replay_of_request_1", "rsp_replay_of_request_1", 15);
    ok(
        "req_min_pb_req_id_12345678",
        "rsp_min_pb_req_id_12345678",
        15,
    );
    ok("req_json", "rsp_json", 17);
    // A body that does not decode: AimRT sends no answer; ours says why.
    let line = call_with(&peers, &captures["req_bad_pb"]);
    assert!(
        line.starts_with("answer status=1007 id=33000000 body="),
        "{line}"
    );
    assert_eq!(server.interrupt(WAIT), Some(0));
}

/// AimRT's zenoh request of `func` (without the domain, which `aimrt_zenoh_probe call`
/// adds): the length, the serialization type, the reply pattern, the id, no meta, `body`.
fn zenoh_request(serialization_type: &str, func: &str, id: [u8; 4], body: &[u8]) -> Vec<u8> {
    let pattern = format!(
        "aimrt_rpc/{}",
        aimrt_wire::url_encode(aimrt_wire::name_without_prefix(func))
    );
    let mut out = vec![0; 4];
    aimrt_wire::put_str8(&mut out, "serialization type", serialization_type).unwrap();
    aimrt_wire::put_str8(&mut out, "reply pattern", &pattern).unwrap();
    out.extend_from_slice(&id);
    aimrt_wire::put_meta(&mut out, std::iter::empty::<(&str, &str)>()).unwrap();
    out.extend_from_slice(body);
    let len = u32::try_from(out.len() - 4).unwrap();
    out[..4].copy_from_slice(&len.to_le_bytes());
    out
}

/// A plugin's own service is served over zenoh as a module's is (AimRT's plugins register
/// theirs through the same handle): log_control_plugin answers AimRT's request, in json.
#[test]
fn a_plugins_service_is_served_over_zenoh() {
    let peers = ZenohPeers::new("plugin_service");
    let plugin = format!(
        "      - name: log_control_plugin\n        path: {}\n  log:\n",
        aimrt_e2e::lib("libaimrt_log_control_plugin.so").display()
    );
    let cfg = zenoh_example("pb_rpc_server").replacen("  log:\n", &plugin, 1);
    assert!(cfg.contains("name: log_control_plugin"), "{cfg}");
    let mut server = start(&cfg, &peers, "b");
    let func = "pb:/aimrt.protocols.log_control_plugin.LogControlService/GetModuleLogLevel";
    let body = br#"{"module_names": ["NormalRpcCoServerModule"]}"#;
    let line = call_with(
        &peers,
        &zenoh_request("json", func, *b"\x01\x02\x03\x04", body),
    );
    let answer =
        br#"{"code":0,"msg":"","module_log_level_map":{"NormalRpcCoServerModule":"Info"}}"#;
    let hex: String = answer.iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(line, format!("answer status=0 id=01020304 body={hex}"));
    assert_eq!(server.interrupt(WAIT), Some(0));
}

/// Stops `processes` (in order) and fails if a shared-memory pool one of them held (a
/// `/dev/shm` file of one of `pool_sizes` bytes, each held while they ran) is still
/// there: a process removes its pool when zenoh_plugin shuts down. Before, every pool
/// stayed until the next zenoh process on the machine started. (zenoh's own smaller
/// files may stay a moment longer; docs/zenoh.md.)
fn stop_removing_the_pools(processes: &mut [&mut Running], pool_sizes: &[u64]) {
    let held: Vec<(PathBuf, u64)> = processes
        .iter()
        .flat_map(|p| aimrt_e2e::zenoh_shm_files(Some(p.pid())))
        .filter_map(|f| Some((f.clone(), std::fs::metadata(&f).ok()?.len())))
        .collect();
    for size in pool_sizes {
        assert!(
            held.iter().any(|(_, len)| len == size),
            "no pool of {size} bytes held: {held:?}"
        );
    }
    for p in processes.iter_mut() {
        assert_eq!(p.interrupt(WAIT), Some(0));
    }
    let left: Vec<&(PathBuf, u64)> = held
        .iter()
        .filter(|(f, len)| pool_sizes.contains(len) && f.exists())
        .collect();
    assert!(left.is_empty(), "pools left in /dev/shm: {left:?}");
}

#[test]
fn rpc_through_shared_memory_carries_the_request_and_the_answer() {
    // AimRT's shm RPC writes a length that leaves the body out, so the server reads an
    // empty request; here the echo must carry the request's text both ways.
    let peers = ZenohPeers::new("rpc_shm");
    let (mut server, mut client) = answered_rpc_pair(&peers, "_with_shm");
    // The client's pool is zenoh_plugin's default, the server's as AimRT's example sets it.
    stop_removing_the_pools(&mut [&mut client, &mut server], &[10 << 20, 10_240_000]);
    for (side, text) in [("client", client.text()), ("server", server.text())] {
        assert!(
            !text.contains("(0 through shared memory"),
            "{side} sent nothing through shared memory:\n{text}"
        );
    }
}

/// The `count N` of each answer a client logged, and whether its echo matched.
fn answers(text: &str) -> Vec<(String, bool)> {
    text.lines()
        .filter(|l| l.contains("Client get rpc ret, status: suc"))
        .map(|l| {
            let echo = l
                .split_once(r#""msg":"echo hello world foo, count "#)
                .and_then(|(_, r)| r.split('"').next())
                .unwrap_or("?")
                .to_owned();
            (echo, true)
        })
        .collect()
}

#[test]
fn an_answer_for_a_request_id_aimrt_would_use_is_not_taken() {
    // AimRT's clients number their requests from 0, so an answer with id 0 on the shared
    // answer key is taken by whichever client has id 0 in flight. Ours start at a random
    // id: the stray answer is counted and dropped, and the call ends at its deadline.
    let peers = ZenohPeers::new("stray_answer");
    let client_cfg = zenoh_example("pb_rpc_client").replace("rpc_frq: 0.5", "rpc_frq: 2");
    let req_key = format!("req/{KEY_FOO}/{}", peers.domain);
    let mut mute = probe(&peers, "b", &["listen", &req_key, "1000"]);
    mute.wait_for("listening on", WAIT);
    let mut client = start(&client_cfg, &peers, "a");
    mute.wait_for("sample ", WAIT);
    // AimRT's captured answer to request 0 ("python echo …"), on this test's answer key.
    let stray = &aimrt_e2e::wire_fixture("zenoh_rpc_req.hex")["python_reply_1"];
    let hex: String = stray.iter().map(|b| format!("{b:02x}")).collect();
    let rsp_key = format!("rsp/{KEY_FOO}/{}", peers.domain);
    let mut put = probe(&peers, "c", &["put", &rsp_key, &hex]);
    assert_eq!(put.wait_exit(WAIT), Some(0), "{}", put.text());
    let (_, line) = client.wait_for("Client get rpc error ret", WAIT);
    assert!(line.contains("code 2, msg: Timeout"), "{line}");
    assert_eq!(client.interrupt(WAIT), Some(0));
    let text = client.text();
    assert!(!text.contains("python echo"), "{text}");
    let line = stat(&text, "payloads sent (");
    assert!(
        line.contains(" 1 answers for unknown request ids,"),
        "{line}"
    );
}

#[test]
fn two_client_processes_sharing_the_answer_key_each_get_their_own_answers() {
    let peers = ZenohPeers::new("two_clients");
    let mut server = start(&zenoh_example("pb_rpc_server"), &peers, "b");
    let client_cfg = zenoh_example("pb_rpc_client").replace("rpc_frq: 0.5", "rpc_frq: 20");
    let mut one = start(&client_cfg, &peers, "a");
    // The second client ("c") listens on its own port and connects to both others.
    let mut two = Running::start_env(&client_cfg, &peers.env("c"));
    two.wait_for("Module manager start completed.", WAIT);
    one.wait_for("count 20\"}", WAIT);
    two.wait_for("count 20\"}", WAIT);
    assert_eq!(one.interrupt(WAIT), Some(0));
    assert_eq!(two.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
    for (name, p) in [("one", &one), ("two", &two)] {
        let text = p.text();
        // Each answer echoes the request this client sent just before it, in order.
        let got = answers(&text);
        assert!(got.len() >= 20, "{name}: {} answers", got.len());
        for (i, (count, _)) in got.iter().enumerate() {
            assert_eq!(
                count,
                &(i + 1).to_string(),
                "{name}: answer {i} is for count {count}"
            );
        }
        // It heard the other client's answers on the shared key too, and dropped them.
        let line = stat(&text, "payloads sent (");
        assert!(
            !line.contains(" 0 answers for unknown request ids"),
            "{name}: {line}"
        );
    }
}

/// AimRT's zenoh channel benchmark pairs, with and without shared memory (both pairs at
/// once), with the plans cut short: every plan arrives whole.
#[test]
fn aimrts_channel_benchmark_pairs_lose_nothing_with_and_without_shared_memory() {
    let runs: Vec<_> = ["", "_with_shm"]
        .into_iter()
        .map(|shm| {
            let peers = ZenohPeers::new(&format!("chn_bench{shm}"));
            let sub = start(
                &zenoh_example(&format!("pb_chn_benchmark_sub{shm}")),
                &peers,
                "b",
            );
            let cfg = aimrt_e2e::shorter_bench_plans(
                &zenoh_example(&format!("pb_chn_benchmark_pub{shm}")),
                10,
            );
            let publisher = start(&cfg, &peers, "a");
            (shm, peers, sub, publisher)
        })
        .collect();
    for (shm, _peers, mut sub, mut publisher) in runs {
        aimrt_e2e::assert_bench_plans_arrive_whole(&mut sub, 3, Duration::from_secs(60));
        publisher.wait_for("Bench completed.", WAIT);
        assert_eq!(publisher.interrupt(WAIT), Some(0), "pub{shm}");
        assert_eq!(sub.interrupt(WAIT), Some(0), "sub{shm}");
        // The parallel plan's four senders share one publisher: their sequence numbers
        // went out in the order of their puts, so no gap was seen.
        let text = sub.text();
        assert_eq!(
            aimrt_e2e::number_after(&text, " published while no subscriber matched, "),
            0,
            "sub{shm}: messages counted lost on the way:\n{text}"
        );
    }
}

/// AimRT's zenoh RPC benchmark client against its server, with and without shared memory
/// (both pairs at once), with the plans cut short: every call of every plan succeeds.
#[test]
fn aimrts_rpc_benchmark_client_calls_without_error_with_and_without_shared_memory() {
    let runs: Vec<_> = ["", "_with_shm"]
        .into_iter()
        .map(|shm| {
            let peers = ZenohPeers::new(&format!("rpc_bench{shm}"));
            let server = start(&zenoh_example(&format!("pb_rpc_server{shm}")), &peers, "b");
            let cfg = aimrt_e2e::shorter_bench_plans(
                &zenoh_example(&format!("pb_rpc_benchmark_client{shm}")),
                20,
            );
            let client = Running::start_env(&cfg, &peers.env("a"));
            (shm, peers, server, client)
        })
        .collect();
    for (shm, _peers, mut server, mut client) in runs {
        let rates = aimrt_e2e::rpc_bench_error_rates(&mut client, 2, WAIT);
        assert_eq!(rates, ["0 %", "0 %"], "{shm}:\n{}", client.text());
        assert_eq!(client.interrupt(WAIT), Some(0), "client{shm}");
        assert_eq!(server.interrupt(WAIT), Some(0), "server{shm}");
    }
}

/// AimRT's RPC proxy example over zenoh: the benchmark client calls
/// `ExampleProxyService` on the proxy, whose calls go on to the server; three processes,
/// every call succeeds.
#[test]
fn aimrts_rpc_benchmark_through_a_proxy_calls_without_error() {
    let peers = ZenohPeers::new("rpc_proxy");
    let mut server = start(&zenoh_example("pb_rpc_server"), &peers, "b");
    let mut proxy = start(&zenoh_example("pb_rpc_proxy_server"), &peers, "c");
    let cfg =
        aimrt_e2e::shorter_bench_plans(&zenoh_example("pb_rpc_benchmark_client_to_proxy"), 20);
    let mut client = Running::start_env(&cfg, &peers.env("a"));
    let rates = aimrt_e2e::rpc_bench_error_rates(&mut client, 2, WAIT);
    assert_eq!(rates, ["0 %", "0 %"], "{}", client.text());
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(proxy.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
}

/// The benchmark client started before any server waits for one, as AimRT's: it warns
/// once a second, and its plans begin only when a call succeeds, so none of them fails.
#[test]
fn an_rpc_benchmark_client_started_first_waits_for_the_server() {
    let peers = ZenohPeers::new("rpc_bench_wait");
    let cfg = aimrt_e2e::shorter_bench_plans(&zenoh_example("pb_rpc_benchmark_client"), 50);
    let mut client = start(&cfg, &peers, "a");
    let (_, line) = client.wait_for("Server is not available!!!", WAIT);
    assert!(line.contains("[Warn]"), "{line}");
    client.wait_for("Server is not available!!!", WAIT);
    let mut server = start(&zenoh_example("pb_rpc_server"), &peers, "b");
    let rates = aimrt_e2e::rpc_bench_error_rates(&mut client, 2, WAIT);
    assert_eq!(rates, ["0 %", "0 %"], "{}", client.text());
    assert_eq!(client.interrupt(WAIT), Some(0));
    assert_eq!(server.interrupt(WAIT), Some(0));
}

#[test]
fn the_probes_ping_names_a_busy_work_value_that_is_not_nanoseconds() {
    let out = std::process::Command::new(aimrt_e2e::binary("aimrt_zenoh_probe"))
        .args("ping unread.json5 a b 64 10 1 0 typed".split(' '))
        .env("AIMRT_PROBE_RECV_SPIN_NS", "1µs")
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{said}");
    assert!(
        said.contains("AIMRT_PROBE_RECV_SPIN_NS: '1µs' is not a count of nanoseconds"),
        "{said}"
    );
}

/// The benchmark's raw baseline (`aimrt-bench --only zenoh`) between two processes: the
/// typed ping counts every echo of the typed pong, and its JSON line has the figures the
/// benchmark reads, `stalls` among them.
#[test]
fn the_raw_baselines_ping_counts_every_echo_of_its_pong() {
    let peers = ZenohPeers::new("raw_baseline");
    let ping_key = format!("bench/ping/{}", peers.domain);
    let pong_key = format!("bench/pong/{}", peers.domain);
    let mut pong = probe(&peers, "b", &["pong", &ping_key, &pong_key, "0", "typed"]);
    pong.wait_for("ready", WAIT);
    let mut ping = probe(
        &peers,
        "a",
        &[
            "ping", &ping_key, &pong_key, "64", "3000", "20", "0", "typed",
        ],
    );
    assert_eq!(ping.wait_exit(WAIT), Some(0), "{}", ping.text());
    let text = ping.text();
    let line = text
        .lines()
        .find(|l| l.starts_with('{'))
        .unwrap_or_else(|| panic!("no JSON line in\n{text}"));
    let v: serde_json::Value = serde_json::from_str(line).expect(line);
    assert_eq!(v["sent"], 3000, "{line}");
    assert_eq!(v["delivered"], 3000, "{line}");
    for figure in ["msgs_per_s", "rtt_p50_us", "rtt_p99_us"] {
        assert!(
            v[figure].as_f64().is_some_and(|x| x > 0.0),
            "{figure}: {line}"
        );
    }
    // A stall is a wait for room in the window: at most one a message sent.
    let stalls = v["stalls"]
        .as_u64()
        .unwrap_or_else(|| panic!("no stalls: {line}"));
    assert!(stalls <= 3000, "{line}");
}
