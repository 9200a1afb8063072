//! net_plugin's `http` channel backend between processes: AimRT's pub/sub and benchmark
//! example configs (ports changed to free ones), our publisher's request against the one
//! AimRT's sent, curl-style posts, 10 000 messages over one keep-alive connection, and a
//! subscriber whose process stands still (SIGSTOP).

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::Duration;

use aimrt_e2e::{net_example, Running};

const WAIT: Duration = Duration::from_secs(30);

fn sub_config(port: u16) -> String {
    net_example("pb_chn_http_sub", port)
}

fn pub_config(port: u16) -> String {
    net_example("pb_chn_http_pub", port)
}

fn start_sub(port: u16) -> Running {
    let mut sub = Running::start(&sub_config(port));
    sub.wait_for("http server listening on", WAIT);
    sub.wait_for("Module manager start completed.", WAIT);
    sub
}

const PATH: &str = "/channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg";

#[test]
fn aimrts_example_pair_exchanges_messages() {
    aimrt_e2e::net_example_pair_exchanges_messages("http");
}

/// First line, lowercased header names (`aimrt-pub%5Fts` dropped: a time), body.
fn parse(bytes: &[u8]) -> (String, Vec<(String, String)>, Vec<u8>) {
    let end = bytes.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&bytes[..end]).into_owned();
    let mut lines = head.split("\r\n");
    let first = lines.next().unwrap().to_owned();
    let mut headers: Vec<(String, String)> = lines
        .map(|l| {
            let (k, v) = l.split_once(':').unwrap();
            (k.trim().to_ascii_lowercase(), v.trim().to_owned())
        })
        .filter(|(k, _)| k != "aimrt-pub%5fts")
        .collect();
    headers.sort();
    (first, headers, bytes[end + 4..].to_vec())
}

#[test]
fn our_publisher_sends_what_aimrts_publisher_sends() {
    let f = aimrt_e2e::wire_fixture("http_channel_pb.txt");
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let answer = f["listener_response"].clone();
    let captured = std::thread::spawn(move || {
        let (mut s, _) = listener.accept().unwrap();
        s.set_read_timeout(Some(WAIT)).unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        loop {
            let n = s.read(&mut buf).unwrap();
            assert!(n > 0);
            got.extend_from_slice(&buf[..n]);
            if let Some(end) = got.windows(4).position(|w| w == b"\r\n\r\n") {
                let (_, headers, _) = parse(&got);
                let len: usize = headers
                    .iter()
                    .find(|(k, _)| k == "content-length")
                    .map_or(0, |(_, v)| v.parse().unwrap());
                if got.len() >= end + 4 + len {
                    break;
                }
            }
        }
        s.write_all(&answer).unwrap();
        got
    });
    let mut publisher = Running::start(&pub_config(port));
    let sent = captured.join().unwrap();
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    let ours = parse(&sent);
    let aimrts = parse(&f["request_1"]);
    assert_eq!(ours.0, aimrts.0);
    assert_eq!(ours.1, aimrts.1, "the same headers (order aside)");
    assert_eq!(ours.2, aimrts.2);
    assert_eq!(ours.2, f["body_1"]);
}

/// One request on `s` (keep-alive); the status and body of the answer.
fn post(s: &mut TcpStream, path: &str, ct: &str, body: &[u8]) -> (u16, String) {
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {ct}\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    // One write: two small ones would wait for each other (Nagle, delayed ACK).
    let mut request = head.into_bytes();
    request.extend_from_slice(body);
    s.write_all(&request).unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0, "closed");
        got.extend_from_slice(&buf[..n]);
        if let Some(end) = got.windows(4).position(|w| w == b"\r\n\r\n") {
            let text = String::from_utf8_lossy(&got[..end]).to_ascii_lowercase();
            let len: usize = text
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .map_or(0, |v| v.trim().parse().unwrap());
            if got.len() >= end + 4 + len {
                let status = text[9..12].parse().unwrap();
                return (
                    status,
                    String::from_utf8_lossy(&got[end + 4..]).into_owned(),
                );
            }
        }
    }
}

#[test]
fn curl_style_posts_and_ten_thousand_messages_on_one_connection() {
    let port = aimrt_e2e::free_port(false);
    let mut sub = start_sub(port);
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    // The example tool's curl: JSON.
    assert_eq!(
        post(
            &mut s,
            PATH,
            "application/json",
            br#"{"msg":"test msg","num":123}"#
        )
        .0,
        200
    );
    sub.wait_for(r#"data: {"msg":"test msg","num":123}"#, WAIT);
    let (status, body) = post(
        &mut s,
        "/channel/nobody/pb%3Ax",
        "application/protobuf",
        b"",
    );
    assert_eq!(status, 404, "{body}");
    assert!(body.contains("nobody here subscribes"), "{body}");
    // The topic and type sent as typed, not URL-encoded: the answer names the uri.
    let (status, body) = post(&mut s, &PATH.replace("%3A", ":"), "application/json", b"{}");
    assert_eq!(status, 404, "{body}");
    assert!(
        body.contains(&format!(
            "URL-encoded, as AimRT sends them: did you mean '{PATH}'?"
        )),
        "{body}"
    );
    // A near miss gets the closest subscribed uri.
    let (status, body) = post(
        &mut s,
        &PATH.replace("test_topic", "test_topc"),
        "application/json",
        b"{}",
    );
    assert_eq!(status, 404, "{body}");
    assert!(
        body.contains(&format!("; did you mean '{PATH}'?")),
        "{body}"
    );
    // An unread body ends keep-alive: on a connection of its own.
    let mut other = TcpStream::connect(("127.0.0.1", port)).unwrap();
    other.set_read_timeout(Some(WAIT)).unwrap();
    assert_eq!(post(&mut other, PATH, "text/plain", b"x").0, 415);
    for i in 1..=10_000u32 {
        let text = format!("count: {i}");
        let mut pb = vec![0x0a, text.len() as u8];
        pb.extend_from_slice(text.as_bytes());
        pb.push(0x10);
        let mut v = i;
        loop {
            let b = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                pb.push(b);
                break;
            }
            pb.push(b | 0x80);
        }
        assert_eq!(post(&mut s, PATH, "application/protobuf", &pb).0, 200);
    }
    sub.wait_for(r#""num":10000}"#, WAIT);
    assert_eq!(sub.interrupt(WAIT), Some(0));
    assert_eq!(sub.text().matches("Receive new pb event").count(), 10_001);
}

/// A subscriber process that stands still (SIGSTOP) while its publisher publishes 2 500
/// messages of 64 KiB (more than its 1 024 waiting and the sockets hold): the publisher
/// is not held up, every message it cannot send is refused (1 024 requests in flight to
/// the subscriber) or lost after publish and counted, and every one it sent arrives.
#[test]
fn a_stopped_subscriber_never_holds_the_publisher_up_and_every_message_is_accounted_for() {
    let port = aimrt_e2e::free_port(false);
    let mut sub = start_sub(port);
    let mut publisher = Running::start(&aimrt_e2e::fast_big_publisher(&pub_config(port), 500));
    aimrt_e2e::stop_a_subscriber_under_its_publisher(&mut sub, &mut publisher, 2500, false);
    aimrt_e2e::assert_net_accounts_for_every_message(
        &publisher.text(),
        &sub.text(),
        "http channel",
    );
}

#[test]
fn to_addr_redirects_a_topic_to_another_subscriber() {
    let port = aimrt_e2e::free_port(false);
    let nowhere = aimrt_e2e::free_port(false);
    let mut sub = start_sub(port);
    let cfg = pub_config(nowhere).replace(
        "  channel_frq: 0.5",
        &format!("  channel_frq: 0.5\n  context_meta:\n    aimrt-to_addr: \"tcp://127.0.0.1:1;http://127.0.0.1:{port}\""),
    );
    let mut publisher = Running::start(&cfg);
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    assert!(line.contains(r#"{"aimrt-backend":"http"}"#), "{line}");
    // Where the message came from, under AimRT's name.
    assert!(line.contains(r#"{"Remote-Endpoint":"127.0.0.1:"#), "{line}");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
}

#[test]
fn aimrts_channel_benchmark_pair_loses_nothing() {
    aimrt_e2e::net_bench_pair_loses_nothing("http");
}

/// A subscriber that takes connections and never answers: every request the publisher
/// made is still in flight at its shutdown, which waits 2 s for them and then counts each
/// as lost. A refused connection counts each message as lost too.
#[test]
fn requests_unanswered_at_shutdown_and_refused_connections_are_counted_lost() {
    // Publishes 20 messages a second to `port` until the 10th and `wait_also`; the log, and
    // what it published.
    let publish_to = |port: u16, wait_also: &str| {
        let cfg = pub_config(port).replace("channel_frq: 0.5", "channel_frq: 20");
        let mut publisher = Running::start(&cfg);
        publisher.wait_for("loop count : 10 ", WAIT);
        publisher.wait_for(wait_also, WAIT);
        assert_eq!(publisher.interrupt(WAIT), Some(0));
        let text = publisher.text();
        let published = text.matches("Publish new pb event").count();
        let summary = format!(
            "net_plugin http channel: 0 messages sent, 0 refused, {published} lost after publish,"
        );
        assert!(text.contains(&summary), "{summary}\n{text}");
        // The topic's stats count them too.
        assert_eq!(
            aimrt_e2e::topics_dropped(&text, "lost after publish"),
            published as u64,
            "{text}"
        );
        (text, published)
    };
    let silent = TcpListener::bind("127.0.0.1:0").unwrap();
    let (text, published) = publish_to(silent.local_addr().unwrap().port(), "loop count");
    assert!(
        text.contains(&format!("net_plugin http: {published} messages were still queued or in flight at shutdown, 2 s after it began, and are lost")),
        "{text}"
    );
    drop(silent);
    let (text, _) = publish_to(aimrt_e2e::free_port(false), "failed: ");
    assert!(text.contains("; the message is lost"), "{text}");
}

/// AimRT's http benchmark publisher with one plan of 100 messages of 4 MiB to a host
/// that takes connections and never reads them: the requests in flight stop at 256 MiB of
/// bodies, not at 1 024 requests (which would have held 400 MiB, and up to 16 GiB at the
/// body limit, each for its 5 s deadline); the rest is refused, counted and said.
#[test]
fn messages_in_flight_to_a_host_that_never_answers_hold_at_most_256_mib() {
    let silent = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = silent.local_addr().unwrap().port();
    let cfg = aimrt_e2e::one_bench_plan(
        &net_example("pb_chn_http_benchmark_pub", port),
        4 << 20,
        100,
    );
    let text = Running::start(&cfg).bench_output(Duration::from_secs(120));
    // 256 MiB hold the signals' small bodies and 63 messages of 4 MiB (64 would be over):
    // the other 37 are refused as they are published.
    assert!(
        text.contains("Benchmark plan 0: sent 100 of 100 messages, 0 refused by the channel, 37 dropped after publish"),
        "{text}"
    );
    assert!(
        text.contains("1024 requests or 256 MiB of messages are already in flight to 127.0.0.1:"),
        "{text}"
    );
    drop(silent);
}

/// A subscriber's error answer is quoted in the publisher's warning (a 404 says which uri
/// was meant), and an answer that never ends is read only up to 64 KiB: the loss is said
/// at once, not after the 5 s deadline.
#[test]
fn a_subscribers_error_answer_is_quoted_and_read_only_in_part() {
    let port = aimrt_e2e::free_port(false);
    let mut sub = start_sub(port);
    let fast = |cfg: String| cfg.replace("channel_frq: 0.5", "channel_frq: 20");
    let cfg = fast(pub_config(port)).replace("topic_name: test_topic", "topic_name: test_topik");
    let mut publisher = Running::start(&cfg);
    let (_, line) = publisher.wait_for("got 404 Not Found", WAIT);
    assert!(
        line.contains("did you mean '/channel/test_topic/")
            && line.contains("Channel topic 'test_topik': net_plugin http: http channel publish to ")
            && line.ends_with("; the message is lost (reported at most once a second; every such message is counted in the topic's stats: lost after publish)"),
        "{line}"
    );
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));

    // A "subscriber" that answers 500 with a body that never ends.
    let endless = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = endless.local_addr().unwrap().port();
    std::thread::spawn(move || {
        let Ok((mut s, _)) = endless.accept() else {
            return;
        };
        let mut head = [0u8; 4096];
        let _ = s.read(&mut head);
        let _ = s
            .write_all(b"HTTP/1.1 500 Internal Server Error\r\ntransfer-encoding: chunked\r\n\r\n");
        let chunk = format!("1000\r\n{}\r\n", "x".repeat(0x1000));
        while s.write_all(chunk.as_bytes()).is_ok() {}
    });
    let mut publisher = Running::start(&fast(pub_config(port)));
    let (_, line) = publisher.wait_for("500 Internal Server Error", WAIT);
    assert!(
        line.contains(r#"500 Internal Server Error ("xxxx"#),
        "{line}"
    );
    assert!(!publisher.text().contains("no answer within 5 s"));
    assert_eq!(publisher.interrupt(WAIT), Some(0));
}

/// AimRT's robot messages from `libaimrt_msgs_pb_ts.so`, echoed: an `ImuState` posted as
/// JSON by a foreign publisher (AimRT's http channel) reaches echo_plugin, which prints it
/// with its unknown covariance as `"NaN"`, the value read back.
#[test]
fn echo_prints_an_imu_state_posted_over_http_from_the_robot_messages_package() {
    let port = aimrt_e2e::free_port(false);
    let cfg = format!(
        "aimrt:
  plugin:
    plugins:
      - name: net_plugin
        path: ${{AIMRT_LIB_DIR:-./target/debug}}/libaimrt_net_plugin.so
        options:
          http_options: {{listen_ip: 127.0.0.1, listen_port: {port}}}
      - name: echo_plugin
        path: ${{AIMRT_LIB_DIR:-./target/debug}}/libaimrt_echo_plugin.so
        options:
          type_support_pkgs:
            - path: ${{AIMRT_LIB_DIR:-./target/debug}}/libaimrt_msgs_pb_ts.so
          topic_meta_list:
            - topic_name: imu
              msg_type: pb:aimrt.protocols.sensor.ImuState
  log:
    backends: [{{type: console}}]
  channel:
    backends: [{{type: http}}]
    sub_topics_options:
      - {{topic_name: \"(.*)\", enable_backends: [http]}}
"
    );
    let mut sub = Running::start(&cfg);
    let (_, loaded) = sub.wait_for("loaded type support pkg", WAIT);
    for name in [
        "pb:aimrt.protocols.sensor.ImuState",
        "pb:aimrt.protocols.common.Header",
    ] {
        assert!(loaded.contains(name), "{loaded}");
    }
    sub.wait_for("Module manager start completed.", WAIT);
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    let body = br#"{"header":{"time_stamp":"7","frame_id":"imu","sequence_num":"1"},"orientation_covariance":["NaN",0.5]}"#;
    let (status, answer) = post(
        &mut s,
        "/channel/imu/pb%3Aaimrt.protocols.sensor.ImuState",
        "application/json",
        body,
    );
    assert_eq!(status, 200, "{answer}");
    sub.wait_for(r#""frame_id": "imu""#, WAIT);
    sub.wait_for(r#""NaN""#, WAIT);
    assert_eq!(sub.interrupt(WAIT), Some(0));
}
