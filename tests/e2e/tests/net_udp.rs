//! net_plugin's `udp` channel backend between processes: AimRT's pub/sub and benchmark
//! example configs (ports changed to free ones), 10 000 datagrams in AimRT's layout from a
//! raw socket, `aimrt-to_addr` redirecting, and garbage on the port.

use std::net::UdpSocket;
use std::time::Duration;

use aimrt_e2e::{net_example, Running};

const WAIT: Duration = Duration::from_secs(30);

fn sub_config(port: u16) -> String {
    net_example("pb_chn_udp_sub", port)
}

fn pub_config(port: u16) -> String {
    net_example("pb_chn_udp_pub", port)
}

fn start_sub(port: u16) -> Running {
    let mut sub = Running::start(&sub_config(port));
    sub.wait_for("udp channel listening on", WAIT);
    sub.wait_for("Module manager start completed.", WAIT);
    sub
}

#[test]
fn aimrts_example_pair_exchanges_messages() {
    aimrt_e2e::net_example_pair_exchanges_messages("udp");
}

/// AimRT's layout of `ExampleEventMsg { msg: "count: <n>", num: <n> }` on `test_topic`.
fn datagram(n: u32) -> Vec<u8> {
    let uri = b"/channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg";
    let text = format!("count: {n}");
    let mut payload = vec![0x0a, text.len() as u8];
    payload.extend_from_slice(text.as_bytes());
    payload.push(0x10);
    let mut v = n;
    loop {
        let b = (v & 0x7f) as u8;
        v >>= 7;
        if v == 0 {
            payload.push(b);
            break;
        }
        payload.push(b | 0x80);
    }
    let mut out = vec![uri.len() as u8];
    out.extend_from_slice(uri);
    out.extend_from_slice(&[2, b'p', b'b', 1, 1, 0, b'k', 1, 0, b'v']);
    out.extend_from_slice(&payload);
    out
}

#[test]
fn ten_thousand_datagrams_arrive_and_garbage_is_counted_not_fatal() {
    let port = aimrt_e2e::free_port(true);
    let mut sub = start_sub(port);
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let target = format!("127.0.0.1:{port}");
    // Garbage first: random bytes, a cut body, a datagram over max_pkg_size (1024), a
    // body for a topic nobody subscribes to.
    for junk in [
        vec![0xffu8; 10],
        datagram(1)[..30].to_vec(),
        vec![0u8; 3000],
        b"\x05/nope\x02pb\x00x".to_vec(),
    ] {
        socket.send_to(&junk, &target).unwrap();
    }
    let n = 10_000u32;
    for i in 1..=n {
        socket.send_to(&datagram(i), &target).unwrap();
        // At most 10 000 a second: the subscriber logs each one.
        if i % 10 == 0 {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    let (_, last) = sub.wait_for(&format!(r#""num":{n}}}"#), WAIT);
    assert!(last.contains(r#"{"k":"v"}"#), "{last}");
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    let received = text.matches("Receive new pb event").count();
    assert_eq!(received, n as usize, "every datagram delivered once");
    assert!(
        text.contains(
            "0 messages sent, 0 refused, 0 lost after publish, 1 received truncated, 2 malformed, 1 for unknown uris"
        ),
        "{}",
        text.lines()
            .filter(|l| l.contains("net_plugin udp"))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

/// A subscriber process that stands still (SIGSTOP) while 30 000 datagrams come: its
/// receive buffer holds some, the kernel drops the rest. Once it goes on and the next
/// datagram comes, it says so while running, and at shutdown every datagram is delivered,
/// dropped and counted by the topic, or dropped by the kernel and counted by the backend.
#[test]
fn datagrams_the_kernel_drops_for_a_stopped_subscriber_are_counted() {
    let port = aimrt_e2e::free_port(true);
    let mut sub = start_sub(port);
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let target = format!("127.0.0.1:{port}");
    sub.signal("STOP");
    let n = 30_000u32;
    for i in 1..=n {
        socket.send_to(&datagram(i), &target).unwrap();
    }
    sub.signal("CONT");
    // Until the subscriber has logged what its buffer held.
    sub.wait_for("Receive new pb event", WAIT);
    let mut delivered = 0;
    loop {
        sub.collect_for(Duration::from_millis(500), "");
        let now = sub.text().matches("Receive new pb event").count();
        if now == delivered {
            break;
        }
        delivered = now;
    }
    assert!(delivered > 0 && delivered < n as usize, "{delivered}");
    // The next datagram brings the kernel's count.
    socket.send_to(&datagram(n + 1), &target).unwrap();
    let (_, warning) = sub.wait_for("datagrams sent to 127.0.0.1:", WAIT);
    assert!(
        warning.contains("before they were read") && warning.contains("receive buffer"),
        "{warning}"
    );
    // Delivered in the receive call that brought the count; the module's line is not
    // ordered with the backend's warning.
    let last = format!(r#""num":{}}}"#, n + 1);
    if !sub.text().contains(&last) {
        sub.wait_for(&last, WAIT);
    }
    assert_eq!(sub.interrupt(WAIT), Some(0));
    let text = sub.text();
    let at_topic = aimrt_e2e::test_topic_received(&text);
    let by_kernel = aimrt_e2e::number_after(&text, "unknown uris, ");
    assert_eq!(
        by_kernel,
        aimrt_e2e::number_after(&warning, "the kernel dropped"),
        "all counted while running"
    );
    assert_eq!(
        at_topic + by_kernel,
        u64::from(n + 1),
        "{at_topic} at the topic\n{}",
        text.lines()
            .filter(|l| l.contains("net_plugin udp"))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

#[test]
fn to_addr_redirects_a_topic_to_another_subscriber() {
    let port = aimrt_e2e::free_port(true);
    let nowhere = aimrt_e2e::free_port(true);
    let mut sub = start_sub(port);
    let cfg = pub_config(nowhere).replace(
        "  channel_frq: 0.5",
        &format!("  channel_frq: 0.5\n  context_meta:\n    aimrt-to_addr: \"http://127.0.0.1:1;udp://127.0.0.1:{port}\""),
    );
    let mut publisher = Running::start(&cfg);
    let (_, line) = sub.wait_for("Receive new pb event", WAIT);
    assert!(
        line.contains(&format!(
            r#"{{"aimrt-to_addr":"http://127.0.0.1:1;udp://127.0.0.1:{port}"}}"#
        )),
        "the key travels, as AimRT's: {line}"
    );
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    assert_eq!(sub.interrupt(WAIT), Some(0));
}

#[derive(serde::Serialize, serde::Deserialize)]
struct Big {
    #[serde(with = "serde_bytes_like")]
    data: Vec<u8>,
}
aimrt_plugin_api::serde_message!(Big, "test.Big");

/// Bytes as one postcard byte string (no per-byte overhead).
mod serde_bytes_like {
    pub(super) fn serialize<S: serde::Serializer>(v: &[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(v)
    }
    pub(super) fn deserialize<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
        let v: Vec<u8> = serde::Deserialize::deserialize(d)?;
        Ok(v)
    }
}

/// Subscribes to `/late` and takes 1 s to start: datagrams that arrive meanwhile must
/// not reach it.
struct SlowStart {
    got: std::sync::Arc<std::sync::atomic::AtomicU64>,
    started: std::sync::Arc<std::sync::atomic::AtomicBool>,
    early: std::sync::Arc<std::sync::atomic::AtomicU64>,
    port: u16,
}

impl aimrt_plugin_api::Module for SlowStart {
    fn info(&self) -> aimrt_plugin_api::ModuleInfo {
        aimrt_plugin_api::ModuleInfo::new("SlowStart")
    }
    fn initialize(
        &mut self,
        core: aimrt_plugin_api::CoreRef,
    ) -> Result<(), aimrt_plugin_api::Error> {
        let (got, started, early) = (self.got.clone(), self.started.clone(), self.early.clone());
        core.channel()?
            .subscriber("/late")
            .subscribe_msg(move |_: std::sync::Arc<Big>| {
                if !started.load(std::sync::atomic::Ordering::SeqCst) {
                    early.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                }
                got.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            })?;
        // A sender that starts now and keeps going past this module's start.
        let port = self.port;
        std::thread::spawn(move || {
            let s = UdpSocket::bind("127.0.0.1:0").unwrap();
            let uri = b"/channel/%2Flate/serde%3Atest.Big";
            let mut d = vec![uri.len() as u8];
            d.extend_from_slice(uri);
            d.extend_from_slice(&[8, b'p', b'o', b's', b't', b'c', b'a', b'r', b'd', 0, 1, 7]);
            for _ in 0..60 {
                let _ = s.send_to(&d, ("127.0.0.1", port));
                std::thread::sleep(Duration::from_millis(50));
            }
        });
        Ok(())
    }
    fn start(&mut self) -> Result<(), aimrt_plugin_api::Error> {
        std::thread::sleep(Duration::from_secs(1));
        self.started
            .store(true, std::sync::atomic::Ordering::SeqCst);
        Ok(())
    }
}

/// Publishes one message too large for a datagram and one that fits, in process.
struct Publisher {
    out: std::sync::mpsc::Sender<String>,
    publisher: Option<aimrt_plugin_api::channel::Publisher<Big>>,
    channel: Option<aimrt_plugin_api::channel::ChannelRef>,
}

impl aimrt_plugin_api::Module for Publisher {
    fn info(&self) -> aimrt_plugin_api::ModuleInfo {
        aimrt_plugin_api::ModuleInfo::new("Big")
    }
    fn initialize(
        &mut self,
        core: aimrt_plugin_api::CoreRef,
    ) -> Result<(), aimrt_plugin_api::Error> {
        let ch = core.channel()?;
        self.publisher = Some(ch.publisher::<Big>("/big")?);
        self.channel = Some(ch);
        Ok(())
    }
    fn start(&mut self) -> Result<(), aimrt_plugin_api::Error> {
        let p = self.publisher.as_ref().unwrap();
        p.publish(Big {
            data: vec![7; 70_000],
        })?;
        p.publish(Big { data: vec![7; 100] })?;
        let stats = self.channel.unwrap().stats("/big").unwrap();
        let _ = self.out.send(format!("{stats:?}"));
        Ok(())
    }
}

#[test]
fn in_process_oversize_is_refused_and_nothing_arrives_before_start() {
    let port = aimrt_e2e::free_port(true);
    let listen = aimrt_e2e::free_port(true);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    std::fs::write(
        &path,
        format!(
            "aimrt:\n  plugin:\n    plugins:\n      - name: net_plugin\n        path: {}\n        options:\n          udp_options: {{listen_ip: 127.0.0.1, listen_port: {listen}}}\n  channel:\n    backends:\n      - type: udp\n        options:\n          pub_topics_options:\n            - topic_name: \"(.*)\"\n              server_url_list: [\"127.0.0.1:{port}\"]\n    pub_topics_options:\n      - topic_name: \"(.*)\"\n        enable_backends: [udp]\n    sub_topics_options:\n      - topic_name: \"(.*)\"\n        enable_backends: [udp]\n",
            aimrt_e2e::lib("libaimrt_net_plugin.so").display()
        ),
    )
    .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let mut runtime = aimrt_runtime::Runtime::new(aimrt_runtime::RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_millis(1500)),
        ..Default::default()
    });
    let got = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let early = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    runtime.register_module(Box::new(SlowStart {
        got: got.clone(),
        started: Default::default(),
        early: early.clone(),
        port: listen,
    }));
    runtime.register_module(Box::new(Publisher {
        out: tx,
        publisher: None,
        channel: None,
    }));
    runtime.run().unwrap();
    let stats = rx.recv_timeout(WAIT).unwrap();
    // Counted once, as refused by the backend; the one that fits went out.
    assert!(
        stats.contains("published: 2") && stats.contains("dropped: [(Other, 1)]"),
        "{stats}"
    );
    // Datagrams came during the subscriber's 1 s start and after it; only the later ones
    // reached it.
    assert!(got.load(std::sync::atomic::Ordering::SeqCst) > 0);
    assert_eq!(early.load(std::sync::atomic::Ordering::SeqCst), 0);
}

#[test]
fn aimrts_channel_benchmark_pair_loses_nothing() {
    aimrt_e2e::net_bench_pair_loses_nothing("udp");
}

/// Nothing listens at the configured address: the kernel says so to the connected socket
/// (the "port unreachable" of a datagram that went out), and refuses the next send. Both
/// messages are counted lost, and the last one's answer is read at shutdown: of 20 or
/// more, none counts as sent (before, every other one did).
#[test]
fn messages_to_an_address_nobody_listens_at_are_counted_lost() {
    let nobody = aimrt_e2e::free_port(true);
    let fast = |cfg: String| cfg.replace("channel_frq: 0.5", "channel_frq: 50");
    let mut publisher = Running::start(&fast(pub_config(nobody)));
    publisher.wait_for("nothing listens at 127.0.0.1:", WAIT);
    let deadline = std::time::Instant::now() + WAIT;
    while publisher.text().matches("Publish new pb event").count() < 20 {
        assert!(
            std::time::Instant::now() < deadline,
            "20 messages published within {WAIT:?}"
        );
        publisher.collect_for(Duration::from_millis(100), "");
    }
    assert_eq!(publisher.interrupt(WAIT), Some(0));
    let text = publisher.text();
    let published = text.matches("Publish new pb event").count();
    let (sent, refused, lost) = aimrt_e2e::net_summary(&text, "udp");
    assert_eq!(refused, 0, "{text}");
    assert!(lost > 0, "{text}");
    assert_eq!((sent + lost) as usize, published, "{text}");
    // The last one's "port unreachable", which no later send heard, is read at shutdown.
    assert_eq!(sent, 0, "{sent} of {published} counted as sent:\n{text}");
    assert_eq!(
        aimrt_e2e::topics_dropped(&text, "lost after publish"),
        lost,
        "the topic's stats count each loss:\n{text}"
    );
}
