//! net_plugin's `tcp` channel backend between processes: AimRT's pub/sub and benchmark
//! example configs (ports changed to free ones), 10 000 frames from a raw connection,
//! garbage and 500 stalled connections beside a working one, 4 400 stalled connections
//! (beyond the limit) before a working one, a subscriber restarted under a publisher,
//! one whose process stands still (SIGSTOP), and frames of 8 MiB.

use std::io::Write;
use std::net::TcpStream;
use std::time::Duration;

use aimrt_e2e::{net_example, Running};

const WAIT: Duration = Duration::from_secs(30);

fn sub_config(port: u16) -> String {
    net_example("pb_chn_tcp_sub", port)
}

fn pub_config(port: u16) -> String {
    net_example("pb_chn_tcp_pub", port)
}

fn start_sub(cfg: &str) -> Running {
    let mut sub = Running::start(cfg);
    sub.wait_for("tcp channel listening on", WAIT);
    sub.wait_for("Module manager start completed.", WAIT);
    sub
}

#[test]
fn aimrts_example_pair_exchanges_messages() {
    aimrt_e2e::net_example_pair_exchanges_messages("tcp");
}

/// AimRT's frame of `ExampleEventMsg { msg: "count: <n>", num: <n> }` on `test_topic`.
fn frame(n: u32) -> Vec<u8> {
    let uri = b"/channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg";
    let text = format!("count: {n}");
    let mut body = vec![uri.len() as u8];
    body.extend_from_slice(uri);
    body.extend_from_slice(&[2, b'p', b'b', 0, 0x0a, text.len() as u8]);
    body.extend_from_slice(text.as_bytes());
    body.push(0x10);
    let mut v = n;
    loop {
        let b = (v & 0x7f) as u8;
        v >>= 7;
        if v == 0 {
            body.push(b);
            break;
        }
        body.push(b | 0x80);
    }
    let mut out = b"YT".to_vec();
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

#[test]
fn ten_thousand_frames_arrive_beside_garbage_and_stalled_connections() {
    let port = aimrt_e2e::free_port(false);
    let mut sub = start_sub(&sub_config(port));
    let addr = format!("127.0.0.1:{port}");
    // Connections that stall (connect, send nothing) and ones that send garbage (a bad
    // magic; an absurd length).
    let idle: Vec<TcpStream> = (0..500)
        .map(|_| TcpStream::connect(&addr).unwrap())
        .collect();
    // Half a frame, then the connection closes: that message is counted received
    // truncated (the first warning, so the limiter lets it through).
    let mut half = TcpStream::connect(&addr).unwrap();
    half.write_all(&frame(1)[..20]).unwrap();
    drop(half);
    sub.wait_for(
        "ended in the middle of a frame: its 20 bytes so far are dropped",
        WAIT,
    );
    for junk in [b"GET / HTTP/1.1\r\n\r\n".to_vec(), {
        let mut j = b"YT".to_vec();
        j.extend_from_slice(&u32::MAX.to_le_bytes());
        j
    }] {
        let mut s = TcpStream::connect(&addr).unwrap();
        s.write_all(&junk).unwrap();
    }
    // 10 000 frames on one connection, written in odd-sized pieces, a heartbeat between.
    let mut stream = Vec::new();
    for i in 1..=10_000u32 {
        stream.extend(frame(i));
        if i == 5000 {
            stream.extend_from_slice(b"YT\0\0\0\0");
        }
    }
    let mut s = TcpStream::connect(&addr).unwrap();
    for piece in stream.chunks(997) {
        s.write_all(piece).unwrap();
    }
    sub.wait_for(r#""num":10000}"#, WAIT);
    drop((idle, s));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    assert_eq!(text.matches("Receive new pb event").count(), 10_000);
    assert!(
        text.contains("net_plugin tcp: 0 messages sent, 0 refused, 0 lost after publish, 1 received truncated, 2 malformed, 0 for unknown uris"),
        "{}",
        text.lines().filter(|l| l.contains("net_plugin tcp")).collect::<Vec<_>>().join("\n")
    );
}

/// A subscriber stopped and started again under a publisher: nothing the publisher wrote
/// is lost with the closed connection (it sees the close while idle and waits for the new
/// one), and what is still queued for the absent subscriber at the publisher's shutdown is
/// counted: every published message is sent or counted lost, and every sent one arrived
/// (a stopping subscriber reads its connection until the publisher leaves it).
#[test]
fn a_restarted_subscriber_gets_messages_again_and_the_publisher_never_blocks() {
    let port = aimrt_e2e::free_port(false);
    let fast = |cfg: String| cfg.replace("channel_frq: 0.5", "channel_frq: 20");
    let mut sub = start_sub(&sub_config(port));
    let mut publisher = Running::start(&fast(pub_config(port)));
    sub.wait_for("Receive new pb event", WAIT);
    assert_eq!(sub.interrupt(WAIT), Some(0));
    // The publisher goes on while nobody listens (its frames queue, then are refused).
    publisher.wait_for("loop count : 40 ", WAIT);
    let mut again = start_sub(&sub_config(port));
    let (_, line) = again.wait_for("Receive new pb event", WAIT);
    assert!(line.contains(r#"{"aimrt-backend":"tcp"}"#), "{line}");
    assert_eq!(again.interrupt(WAIT), Some(0));
    // Frames queue for the absent subscriber until the publisher stops. The publisher
    // sees the subscriber go as an end of stream ("closed the connection") or, when
    // frames were still unread in its socket, as a reset ("broke: ..."); either way it
    // reconnects.
    publisher.wait_for("; reconnecting", WAIT);
    let stops = publisher.text().matches("Publish new pb event").count();
    publisher.wait_for(&format!("loop count : {} ", stops + 5), WAIT);
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    let text = publisher.text();
    assert!(
        text.contains("; reconnecting") || text.contains("cannot connect"),
        "{text}"
    );
    let published = aimrt_e2e::number_after(&text, "Channel topic 'test_topic': published");
    let (sent, refused, lost) = aimrt_e2e::net_summary(&text, "tcp");
    assert_eq!(refused, 0, "{text}");
    assert!(lost > 0, "frames waited for the absent subscriber:\n{text}");
    assert_eq!(published, sent + lost, "{text}");
    assert_eq!(
        aimrt_e2e::topics_dropped(&text, "lost after publish"),
        lost,
        "the topic's stats count each loss:\n{text}"
    );
    assert!(
        text.contains(&format!(
            "{lost} messages queued for 127.0.0.1:{port} are lost"
        )),
        "{text}"
    );
    // What reached a subscriber: delivered, or dropped there and counted (a frame that
    // arrived while it was shutting down).
    let received: u64 = [sub.text(), again.text()]
        .iter()
        .map(|t| aimrt_e2e::test_topic_received(t))
        .sum();
    // A stopping subscriber ends its side of the connection and reads until the
    // publisher, seeing that, closes its own: no frame is left unread in its socket.
    assert_eq!(
        received, sent,
        "every frame written arrived: sent {sent}, received {received}"
    );
}

/// A subscriber process that stands still (SIGSTOP) while its publisher publishes 2 500
/// messages of 64 KiB (more than its 1 024 waiting and the sockets hold): the publisher
/// is not held up, every message it cannot send is refused or lost after publish and
/// counted, and every one it sent arrives.
#[test]
fn a_stopped_subscriber_never_holds_the_publisher_up_and_every_message_is_accounted_for() {
    let port = aimrt_e2e::free_port(false);
    let mut sub = start_sub(&sub_config(port));
    let mut publisher = Running::start(&aimrt_e2e::fast_big_publisher(&pub_config(port), 500));
    aimrt_e2e::stop_a_subscriber_under_its_publisher(&mut sub, &mut publisher, 2500, true);
    aimrt_e2e::assert_net_accounts_for_every_message(&publisher.text(), &sub.text(), "tcp");
}

#[test]
fn to_addr_redirects_a_topic_to_another_subscriber() {
    let port = aimrt_e2e::free_port(false);
    let nowhere = aimrt_e2e::free_port(false);
    let mut sub = start_sub(&sub_config(port));
    let cfg = pub_config(nowhere).replace(
        "  channel_frq: 0.5",
        &format!("  channel_frq: 0.5\n  context_meta:\n    aimrt-to_addr: \"udp://127.0.0.1:1;tcp://127.0.0.1:{port}\""),
    );
    let mut publisher = Running::start(&cfg);
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    assert!(line.contains(r#"{"aimrt-backend":"tcp"}"#), "{line}");
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
}

#[test]
fn thousands_of_stalled_connections_beyond_the_limit_never_keep_a_working_one_out() {
    // 4 096 connections are served at most (`tcp.rs`); this opens 4 400 that never send.
    const STALLED: usize = 4_400;
    let (_, now) = aimrt_runtime::raise_open_file_limit().expect("raise the open-file limit");
    assert!(
        now as usize > STALLED + 200,
        "this test needs {} open files and the hard limit allows {now}",
        STALLED + 200
    );
    let port = aimrt_e2e::free_port(false);
    let mut sub = start_sub(&sub_config(port));
    let addr = format!("127.0.0.1:{port}");
    let mut idle = Vec::with_capacity(STALLED);
    for _ in 0..STALLED {
        idle.push(TcpStream::connect(&addr).unwrap());
    }
    // Some of the stalled ones were closed to take the later ones in.
    sub.wait_for(
        "connections are open: the one silent longest is closed",
        WAIT,
    );
    // A working peer connecting last is served at once.
    let mut s = TcpStream::connect(&addr).unwrap();
    for i in 1..=100u32 {
        s.write_all(&frame(i)).unwrap();
    }
    sub.wait_for(r#""num":100}"#, WAIT);
    drop((idle, s));
    assert_eq!(sub.interrupt(WAIT), Some(0));
    assert_eq!(sub.text().matches("Receive new pb event").count(), 100);
}

#[test]
fn aimrts_channel_benchmark_pair_loses_nothing() {
    aimrt_e2e::net_bench_pair_loses_nothing("tcp");
}

/// A loopback port held, bound but not listening, so every connect to it is refused; it
/// stays so while the socket is held.
fn held_port() -> (socket2::Socket, u16) {
    use socket2::{Domain, Socket, Type};
    let held = Socket::new(Domain::IPV4, Type::STREAM, None).unwrap();
    held.bind(&std::net::SocketAddr::from(([127, 0, 0, 1], 0)).into())
        .unwrap();
    let port = held.local_addr().unwrap().as_socket().unwrap().port();
    (held, port)
}

/// AimRT's tcp benchmark publisher whose subscriber never comes (its port is held, bound
/// but not listening, so every connect is refused): the send queue fills, publishing goes
/// on without blocking, and each plan's line says how many messages the channel dropped
/// after `publish` returned; the refusals are logged at most once a second.
#[test]
fn a_benchmark_publisher_without_its_subscriber_says_what_the_channel_dropped() {
    let (held, port) = held_port();
    let cfg = aimrt_e2e::shorter_bench_plans(&net_example("pb_chn_tcp_benchmark_pub", port), 10);
    let text = Running::start(&cfg).bench_output(Duration::from_secs(60));
    // The queue to the peer holds 1 024 frames: the 10 WarmUp signals, plan 0's Begin,
    // then plan 0's first messages. Everything after waits for a peer that never comes.
    let line = |plan: u32, sent: u32, dropped: u32| {
        format!("Benchmark plan {plan}: sent {sent} of {sent} messages, 0 refused by the channel, {dropped} dropped after publish (counted in the topics' stats).")
    };
    for (plan, sent, dropped) in [(0, 2000, 2000 - (1024 - 11)), (1, 100, 100), (2, 500, 500)] {
        assert!(
            text.contains(&line(plan, sent, dropped)),
            "plan {plan}:\n{text}"
        );
    }
    // The frames still queued at shutdown are counted, at once (no wait for the peer).
    assert!(
        text.contains(&format!("1024 messages queued for 127.0.0.1:{port} are lost: it cannot be reached and the backend is shutting down"))
            && text.contains(" refused, 1024 lost after publish,"),
        "{text}"
    );
    // Each is counted in its topic's stats (signals and messages alike).
    assert_eq!(
        aimrt_e2e::topics_dropped(&text, "lost after publish"),
        1024,
        "{text}"
    );
    assert!(
        text.contains("channel backend 'tcp' failed to publish: the send queue to 127.0.0.1:")
            && text.contains("(reported at most once a second; every such message is counted in the topic's stats: other)"),
        "{text}"
    );
    drop(held);
}

/// The same publisher with one plan of 200 messages of 4 MiB: the queue to the absent
/// peer stops at 256 MiB, not at its 1 024 frames (which would have held 800 MiB, and up to
/// 10 GiB at the frame limit); the rest is refused, counted and said.
#[test]
fn the_send_queue_to_an_absent_peer_holds_at_most_256_mib() {
    let (held, port) = held_port();
    let cfg =
        aimrt_e2e::one_bench_plan(&net_example("pb_chn_tcp_benchmark_pub", port), 4 << 20, 200);
    let text = Running::start(&cfg).bench_output(Duration::from_secs(120));
    // 256 MiB hold 63 messages of 4 MiB with their frames' headers (64 would be over):
    // the other 137 are refused as they are published.
    assert!(
        text.contains("Benchmark plan 0: sent 200 of 200 messages, 0 refused by the channel, 137 dropped after publish"),
        "{text}"
    );
    // At shutdown the 63 and the 12 signals (10 WarmUp, Begin, End) are counted lost.
    assert!(
        text.contains(&format!("75 messages queued for 127.0.0.1:{port} are lost: it cannot be reached and the backend is shutting down")),
        "{text}"
    );
    assert!(
        text.contains("the send queue to 127.0.0.1:")
            && text
                .contains("is full (1024 messages or 256 MiB wait for a slow or unreachable peer)"),
        "{text}"
    );
    drop(held);
}

/// AimRT's tcp benchmark pair with one plan of 40 messages of 8 MiB: each frame arrives
/// whole and none is refused as it arrives (the receiving connection's buffer grows to the
/// frame whose header it holds, within the server's 256 MiB budget).
#[test]
fn large_frames_arrive_whole_within_the_servers_receiving_budget() {
    let wait = Duration::from_secs(120);
    let port = aimrt_e2e::free_port(false);
    let mut sub = start_sub(&net_example("pb_chn_tcp_benchmark_sub", port));
    let cfg =
        aimrt_e2e::one_bench_plan(&net_example("pb_chn_tcp_benchmark_pub", port), 8 << 20, 40)
            // 160 MiB a second: within the publisher's queue of 256 MiB on a debug build.
            .replace("channel_frq: 1000", "channel_frq: 20");
    let mut publisher = Running::start(&cfg);
    aimrt_e2e::assert_bench_plans_arrive_whole(&mut sub, 1, wait);
    publisher.wait_for("Bench completed.", wait);
    assert_eq!(publisher.interrupt(wait), Some(0));
    assert_eq!(sub.interrupt(wait), Some(0));
    let text = sub.text();
    assert!(
        text.contains(" 0 received truncated, 0 malformed,")
            && !text.contains("refused as they arrived"),
        "{text}"
    );
}

/// A process that the system refuses threads (its address space limited with `ulimit -v`,
/// so thread stacks do not fit) stops start-up with one line that says so, at every
/// limit: never a hang, a panic or an abort. tokio panics when it cannot spawn a worker
/// and, when that was not its first, waits forever for those it started: the subscriber
/// hung at about 43 MB here before net_plugin built its runtimes on a helper thread. The
/// limit rises from 30 MB in 1 MB steps until the subscriber runs.
#[test]
fn a_process_refused_threads_says_so_and_never_hangs() {
    let refusals =
        aimrt_e2e::refusals_until_it_runs(&sub_config(0), "-v", (30..=400).map(|mb| mb * 1024));
    let threads: Vec<_> = refusals
        .iter()
        .filter(|(_, line)| line.contains("cannot start the TCP threads"))
        .collect();
    assert!(
        !threads.is_empty(),
        "no limit stopped the TCP threads: {refusals:#?}"
    );
    for (limit, line) in threads {
        assert!(
            line.contains("(`ulimit -u`), or is out of memory"),
            "ulimit -v {limit}:\n{line}"
        );
    }
}
