//! Scenario 9: net_plugin's channel backends over loopback — `tcp`, `udp` and `http`, at
//! 64 B and 1 KiB — through the real runtime (one process publishing to its own
//! listeners: ports, sockets and wire format as between two processes), each beside a raw
//! baseline of its own kind carrying the same bytes in the same run:
//!
//! - tcp: AimRT's frames over one raw tokio stream, counted by a raw reader;
//! - udp: the same datagrams from a raw send loop, counted by a raw receiver;
//! - http: the same POSTs from a raw hyper client to a raw hyper server.
//!
//! Throughput is messages a second from the first send to the last receipt (UDP counts
//! what arrived); latency is publish to callback with one message in flight.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc, OnceLock};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::Publisher;
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_protocols::example::ExampleEventMsg;
use aimrt_runtime::{Runtime, RuntimeOptions};

use crate::rpc::NetPlugin;
use crate::stats::percentile;

fn now_ns() -> u64 {
    static START: OnceLock<Instant> = OnceLock::new();
    START.get_or_init(Instant::now).elapsed().as_nanos() as u64
}

/// A message of `size` bytes of text whose first 20 carry the send time.
fn message(size: usize) -> ExampleEventMsg {
    let mut msg = format!("{:020}", now_ns());
    msg.push_str(&"x".repeat(size.saturating_sub(20)));
    ExampleEventMsg { msg, num: 1 }
}

fn sent_at(msg: &ExampleEventMsg) -> u64 {
    msg.msg.get(..20).and_then(|t| t.parse().ok()).unwrap_or(0)
}

#[derive(Default)]
struct Counter {
    received: AtomicU64,
    last_latency_ns: AtomicU64,
}

impl Counter {
    fn hit(&self, sent: u64) {
        self.last_latency_ns
            .store(now_ns().saturating_sub(sent), Ordering::Relaxed);
        self.received.fetch_add(1, Ordering::Release);
    }
}

fn wait_for(c: &Counter, n: u64, patience: Duration) -> bool {
    let deadline = Instant::now() + patience;
    while c.received.load(Ordering::Acquire) < n {
        if Instant::now() > deadline {
            return false;
        }
        std::thread::sleep(Duration::from_micros(50));
    }
    true
}

/// One measured case.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct Case {
    pub(crate) backend: &'static str,
    pub(crate) size: usize,
    pub(crate) msgs_per_s: f64,
    pub(crate) delivered: u64,
    pub(crate) sent: u64,
    pub(crate) p50_us: f64,
    pub(crate) p99_us: f64,
    pub(crate) base_msgs_per_s: f64,
}

const BACKENDS: [&str; 3] = ["tcp", "udp", "http"];
const SIZES: [usize; 2] = [64, 1024];

struct Bench {
    counters: Vec<Arc<Counter>>,
    out: mpsc::Sender<Vec<Publisher<ExampleEventMsg>>>,
    publishers: Vec<Publisher<ExampleEventMsg>>,
}

fn topic(backend: &str, size: usize) -> String {
    format!("/bench/{backend}/{size}")
}

impl Module for Bench {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("NetBench")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let ch = core.channel()?;
        let mut i = 0;
        for b in BACKENDS {
            for size in SIZES {
                let c = self.counters[i].clone();
                i += 1;
                ch.subscriber(&topic(b, size))
                    .subscribe_msg(move |m: Arc<ExampleEventMsg>| c.hit(sent_at(&m)))?;
                self.publishers.push(ch.publisher(&topic(b, size))?);
            }
        }
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let _ = self.out.send(std::mem::take(&mut self.publishers));
        Ok(())
    }
}

fn free_port(udp: bool) -> Result<u16, String> {
    let port = if udp {
        std::net::UdpSocket::bind("127.0.0.1:0").and_then(|s| s.local_addr())
    } else {
        std::net::TcpListener::bind("127.0.0.1:0").and_then(|s| s.local_addr())
    };
    port.map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

pub(crate) fn run(quick: bool) -> Result<Vec<Case>, String> {
    let (ph, pt, pu) = (free_port(false)?, free_port(false)?, free_port(true)?);
    let mut channel = String::new();
    let mut pubs = String::new();
    for (b, port) in [("tcp", pt), ("udp", pu), ("http", ph)] {
        channel.push_str(&format!("      - type: {b}\n        options:\n          pub_topics_options:\n            - topic_name: \"/bench/{b}/.*\"\n              server_url_list: [\"127.0.0.1:{port}\"]\n"));
        pubs.push_str(&format!(
            "      - topic_name: \"/bench/{b}/.*\"\n        enable_backends: [{b}]\n"
        ));
    }
    let cfg = format!(
        "aimrt:\n  log:\n    core_lvl: Warn\n    backends:\n      - type: console\n  channel:\n    backends:\n{channel}    pub_topics_options:\n{pubs}    sub_topics_options:\n{pubs}"
    );
    let path = std::env::temp_dir().join(format!("aimrt-bench-net-{}.yaml", std::process::id()));
    std::fs::write(&path, cfg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    let counters: Vec<Arc<Counter>> = (0..6).map(|_| Arc::default()).collect();
    let (tx, rx) = mpsc::channel();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path.clone()),
        ..Default::default()
    });
    runtime.builtin_plugin(Box::new(NetPlugin::new(format!(
        "{{\"thread_num\": 2, \"http_options\": {{\"listen_ip\": \"127.0.0.1\", \"listen_port\": {ph}}}, \"tcp_options\": {{\"listen_ip\": \"127.0.0.1\", \"listen_port\": {pt}}}, \"udp_options\": {{\"listen_ip\": \"127.0.0.1\", \"listen_port\": {pu}, \"max_pkg_size\": 2048}}}}"
    ))));
    runtime.register_module(Box::new(Bench {
        counters: counters.clone(),
        out: tx,
        publishers: Vec::new(),
    }));
    let handle = runtime.shutdown_handle();
    let thread = std::thread::spawn(move || runtime.run());
    let got = rx.recv_timeout(Duration::from_secs(30));
    let _ = std::fs::remove_file(&path);
    let Ok(publishers) = got else {
        handle.request();
        return Err(match thread.join() {
            Ok(Err(e)) => format!("the runtime failed: {e}"),
            _ => "the runtime did not start within 30 s".to_owned(),
        });
    };
    let (n, samples) = if quick {
        (5_000u64, 300)
    } else {
        (20_000u64, 1_000)
    };
    let mut cases = Vec::new();
    let mut i = 0;
    for backend in BACKENDS {
        for size in SIZES {
            let (p, c) = (&publishers[i], &counters[i]);
            i += 1;
            // Throughput: n messages, never more than 256 ahead of the receiver (the
            // sustained rate; a burst beyond the backends' bounded queues is refused by
            // design).
            let base = c.received.load(Ordering::Acquire);
            let t0 = Instant::now();
            for k in 0..n {
                p.publish(message(size)).map_err(|e| e.to_string())?;
                if k % 128 == 127 {
                    // Let the receiver (and http's bounded requests) keep up.
                    wait_for(c, base + k + 1 - 128, Duration::from_secs(1));
                }
            }
            let complete = wait_for(c, base + n, Duration::from_secs(30));
            let delivered = c.received.load(Ordering::Acquire) - base;
            let rate = delivered as f64 / t0.elapsed().as_secs_f64();
            if !complete && backend != "udp" {
                handle.request();
                return Err(format!("{backend} {size} B: {delivered} of {n} arrived"));
            }
            // Latency: one in flight.
            let mut lat = Vec::with_capacity(samples);
            for _ in 0..samples {
                let before = c.received.load(Ordering::Acquire);
                p.publish(message(size)).map_err(|e| e.to_string())?;
                if wait_for(c, before + 1, Duration::from_secs(5)) {
                    lat.push(c.last_latency_ns.load(Ordering::Relaxed) as f64 / 1e3);
                }
            }
            lat.sort_by(f64::total_cmp);
            eprintln!("net: {backend} {size} B done");
            cases.push(Case {
                backend,
                size,
                msgs_per_s: rate,
                delivered,
                sent: n,
                p50_us: percentile(&lat, 50.0),
                p99_us: percentile(&lat, 99.0),
                base_msgs_per_s: 0.0,
            });
        }
    }
    handle.request();
    eprintln!("net: stopping the runtime");
    match thread.join() {
        Ok(Ok(())) => {}
        Ok(Err(e)) => return Err(format!("the runtime failed: {e}")),
        Err(_) => return Err("the runtime thread panicked".into()),
    }
    for c in &mut cases {
        eprintln!("net: raw {} {} B", c.backend, c.size);
        c.base_msgs_per_s = match c.backend {
            "tcp" => raw_tcp(c.size, n)?,
            "udp" => raw_udp(c.size, n)?,
            _ => raw_http(c.size, n)?,
        };
    }
    Ok(cases)
}

/// The bytes our backends send for a message of `size`: AimRT's body.
fn body(size: usize) -> Vec<u8> {
    use prost::Message as _;
    aimrt_net::wire::Body {
        uri: aimrt_net::wire::channel_uri(
            "/bench/raw",
            "pb:aimrt.protocols.example.ExampleEventMsg",
        ),
        serialization_type: "pb".into(),
        meta: vec![
            ("aimrt-serialization_type".into(), "pb".into()),
            ("aimrt-pub_seq".into(), "1".into()),
            ("aimrt-pub_ts".into(), "1795386628205071149".into()),
        ],
        payload: message(size).encode_to_vec(),
    }
    .encode()
    .unwrap_or_default()
}

/// Frames over one raw tokio stream; msgs/s until the reader has them all.
fn raw_tcp(size: usize, n: u64) -> Result<f64, String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    let frame = aimrt_net::wire::tcp_frame(&body(size));
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| e.to_string())?;
        let addr = listener.local_addr().map_err(|e| e.to_string())?;
        let reader = tokio::spawn(async move {
            let (mut s, _) = listener.accept().await.ok()?;
            let mut buf = Vec::new();
            let mut chunk = vec![0u8; 64 << 10];
            let mut got = 0u64;
            while got < n {
                let k = s.read(&mut chunk).await.ok()?;
                if k == 0 {
                    return None;
                }
                buf.extend_from_slice(&chunk[..k]);
                got += aimrt_net::wire::split_frames(&mut buf, 16 << 20)
                    .ok()?
                    .len() as u64;
            }
            Some(())
        });
        let mut s = tokio::net::TcpStream::connect(addr)
            .await
            .map_err(|e| e.to_string())?;
        let _ = s.set_nodelay(true);
        let t0 = Instant::now();
        for _ in 0..n {
            s.write_all(&frame).await.map_err(|e| e.to_string())?;
        }
        reader.await.ok().flatten().ok_or("the raw reader failed")?;
        Ok(n as f64 / t0.elapsed().as_secs_f64())
    })
}

/// A raw send loop to a raw receiver (same pacing and receive buffer as ours); msgs/s of
/// what arrived.
fn raw_udp(size: usize, n: u64) -> Result<f64, String> {
    let sock = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::DGRAM, None)
        .map_err(|e| e.to_string())?;
    let _ = sock.set_recv_buffer_size(4 << 20);
    let any: std::net::SocketAddr = "127.0.0.1:0".parse().map_err(|e| format!("{e}"))?;
    sock.bind(&any.into()).map_err(|e| e.to_string())?;
    let rx: std::net::UdpSocket = sock.into();
    let addr = rx.local_addr().map_err(|e| e.to_string())?;
    rx.set_read_timeout(Some(Duration::from_millis(100)))
        .map_err(|e| e.to_string())?;
    let got = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (counted, stopped) = (got.clone(), stop.clone());
    let reader = std::thread::spawn(move || {
        let mut buf = vec![0u8; 2049];
        while !stopped.load(Ordering::Acquire) {
            if rx.recv_from(&mut buf).is_ok() {
                counted.fetch_add(1, Ordering::Release);
            }
        }
    });
    let tx = std::net::UdpSocket::bind("127.0.0.1:0").map_err(|e| e.to_string())?;
    let d = body(size);
    let t0 = Instant::now();
    for k in 0..n {
        let _ = tx.send_to(&d, addr);
        if k % 128 == 127 {
            let deadline = Instant::now() + Duration::from_secs(1);
            while got.load(Ordering::Acquire) + 128 < k + 1 && Instant::now() < deadline {
                std::thread::sleep(Duration::from_micros(50));
            }
        }
    }
    let deadline = Instant::now() + Duration::from_secs(2);
    while got.load(Ordering::Acquire) < n && Instant::now() < deadline {
        std::thread::sleep(Duration::from_micros(50));
    }
    let rate = got.load(Ordering::Acquire) as f64 / t0.elapsed().as_secs_f64();
    stop.store(true, Ordering::Release);
    let _ = reader.join();
    Ok(rate)
}

/// The same POSTs from a raw hyper client (256 in flight) to a raw hyper
/// server answering 200.
fn raw_http(size: usize, n: u64) -> Result<f64, String> {
    use bytes::Bytes;
    use http_body_util::{BodyExt, Full};
    use hyper_util::rt::{TokioExecutor, TokioIo};
    use prost::Message as _;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    let payload = Bytes::from(message(size).encode_to_vec());
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| e.to_string())?;
        let addr = listener.local_addr().map_err(|e| e.to_string())?;
        tokio::spawn(async move {
            while let Ok((stream, _)) = listener.accept().await {
                let _ = stream.set_nodelay(true);
                tokio::spawn(async move {
                    let service = hyper::service::service_fn(
                        |req: hyper::Request<hyper::body::Incoming>| async move {
                            let _ = req.into_body().collect().await?;
                            Ok::<_, hyper::Error>(hyper::Response::new(Full::new(Bytes::new())))
                        },
                    );
                    let _ = hyper::server::conn::http1::Builder::new()
                        .serve_connection(TokioIo::new(stream), service)
                        .await;
                });
            }
        });
        let mut connector = hyper_util::client::legacy::connect::HttpConnector::new();
        connector.set_nodelay(true);
        let client: hyper_util::client::legacy::Client<_, Full<Bytes>> =
            hyper_util::client::legacy::Client::builder(TokioExecutor::new()).build(connector);
        let url = format!(
            "http://{addr}/channel/%2Fbench%2Fraw/pb%3Aaimrt.protocols.example.ExampleEventMsg"
        );
        let slots = Arc::new(tokio::sync::Semaphore::new(256));
        let t0 = Instant::now();
        let mut tasks = Vec::with_capacity(n as usize);
        for _ in 0..n {
            let permit = slots
                .clone()
                .acquire_owned()
                .await
                .map_err(|e| e.to_string())?;
            let request = hyper::Request::post(url.as_str())
                .header(hyper::header::USER_AGENT, "aimrt")
                .header(hyper::header::CONTENT_TYPE, "application/protobuf")
                .header("aimrt-serialization%5Ftype", "pb")
                .header("aimrt-pub%5Fseq", "1")
                .header("aimrt-pub%5Fts", "1795386628205071149")
                .body(Full::new(payload.clone()))
                .map_err(|e| e.to_string())?;
            let client = client.clone();
            tasks.push(tokio::spawn(async move {
                let _permit = permit;
                client.request(request).await.is_ok()
            }));
        }
        for t in tasks {
            let _ = t.await;
        }
        Ok(n as f64 / t0.elapsed().as_secs_f64())
    })
}
