//! Scenario 9 (issue 19): net_plugin's channel backends between two processes over
//! loopback — `tcp`, `udp` and `http`, at 64 B and 1 KiB — through the real runtime on
//! both sides, each beside a raw baseline of its own kind carrying the same bytes between
//! the same two processes in the same run:
//!
//! - tcp: AimRT's frames over one raw tokio stream, counted by a raw reader;
//! - udp: the same datagrams from a raw send loop, counted by a raw receiver;
//! - http: the same POSTs from a raw hyper client to a raw hyper server.
//!
//! The receiving process is this binary again (`aimrt-bench --net-peer SPEC`): a runtime
//! with net_plugin's listeners and a subscriber per case, or the raw receivers. It reports
//! what it counted (and the latest message's latency, from the send time the message
//! carries on `CLOCK_MONOTONIC`, which both processes share) in UDP datagrams to the
//! harness, from a thread that looks every 50 µs; the raw receivers report the same way.
//! Each round runs every case and its baseline back to back (which goes first alternates)
//! behind the quiet gate; the first round warms up and is discarded; the verdict is the
//! median of the per-round ratios. Throughput is messages a second from the first send
//! until the peer has counted them all (UDP: what arrived); latency is publish to
//! callback with one message in flight.

use std::io::{BufRead, Write};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::Publisher;
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_protocols::example::ExampleEventMsg;
use aimrt_runtime::{Runtime, RuntimeOptions};

use crate::rpc::LinkedPlugin;
use crate::stats::{alternate, percentile, quiet_gate};

/// `CLOCK_MONOTONIC` in ns: the same clock in both processes.
fn now_ns() -> u64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
        .map(|t| t.tv_sec() as u64 * 1_000_000_000 + t.tv_nsec() as u64)
        .unwrap_or(0)
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

/// One case over the measured rounds.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct Case {
    pub(crate) backend: &'static str,
    pub(crate) size: usize,
    /// Messages sent and delivered over the measured rounds.
    pub(crate) sent: u64,
    pub(crate) delivered: u64,
    /// msgs/s of ours and of the raw baseline, round by round.
    pub(crate) ours: Vec<f64>,
    pub(crate) raw: Vec<f64>,
    pub(crate) p50_us: f64,
    pub(crate) p99_us: f64,
}

const BACKENDS: [&str; 3] = ["tcp", "udp", "http"];
const SIZES: [usize; 2] = [64, 1024];

/// The harness's side: publishers, handed out at start.
struct Publish {
    out: mpsc::Sender<Vec<Publisher<ExampleEventMsg>>>,
    publishers: Vec<Publisher<ExampleEventMsg>>,
}

/// The peer's side: a counting subscriber per case; says `ready` once started.
struct Subscribe {
    counters: Vec<Arc<Counter>>,
}

fn topic(backend: &str, size: usize) -> String {
    format!("/bench/{backend}/{size}")
}

fn cases() -> impl Iterator<Item = (&'static str, usize)> {
    BACKENDS
        .into_iter()
        .flat_map(|b| SIZES.into_iter().map(move |s| (b, s)))
}

impl Module for Publish {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("NetBenchPublisher")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let ch = core.channel()?;
        for (b, size) in cases() {
            self.publishers.push(ch.publisher(&topic(b, size))?);
        }
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let _ = self.out.send(std::mem::take(&mut self.publishers));
        Ok(())
    }
}

impl Module for Subscribe {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("NetBenchSubscriber")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let ch = core.channel()?;
        for ((b, size), c) in cases().zip(&self.counters) {
            let c = c.clone();
            ch.subscriber(&topic(b, size))
                .subscribe_msg(move |m: Arc<ExampleEventMsg>| c.hit(sent_at(&m)))?;
        }
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        println!("ready");
        let _ = std::io::stdout().flush();
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

/// Listening ports (http, tcp, udp).
#[derive(Clone, Copy)]
struct Ports {
    http: u16,
    tcp: u16,
    udp: u16,
}

impl Ports {
    fn free() -> Result<Ports, String> {
        Ok(Ports {
            http: free_port(false)?,
            tcp: free_port(false)?,
            udp: free_port(true)?,
        })
    }

    /// net_plugin's options listening on these ports.
    fn net_options(self) -> String {
        format!(
            "{{\"thread_num\": 2, \"http_options\": {{\"listen_ip\": \"127.0.0.1\", \"listen_port\": {}}}, \"tcp_options\": {{\"listen_ip\": \"127.0.0.1\", \"listen_port\": {}}}, \"udp_options\": {{\"listen_ip\": \"127.0.0.1\", \"listen_port\": {}, \"max_pkg_size\": 2048}}}}",
            self.http, self.tcp, self.udp
        )
    }
}

/// A runtime with net_plugin and `module`, whose channel sends every case's topic to
/// `to` (the peer's ports) and receives them on its own listeners.
fn start_runtime(
    own: Ports,
    to: Ports,
    module: Box<dyn Module>,
) -> Result<
    (
        aimrt_runtime::ShutdownHandle,
        std::thread::JoinHandle<Result<(), String>>,
    ),
    String,
> {
    let mut channel = String::new();
    let mut topics = String::new();
    for (b, port) in [("tcp", to.tcp), ("udp", to.udp), ("http", to.http)] {
        channel.push_str(&format!("      - type: {b}\n        options:\n          pub_topics_options:\n            - topic_name: \"/bench/{b}/.*\"\n              server_url_list: [\"127.0.0.1:{port}\"]\n"));
        topics.push_str(&format!(
            "      - topic_name: \"/bench/{b}/.*\"\n        enable_backends: [{b}]\n"
        ));
    }
    let cfg = format!(
        "aimrt:\n  log:\n    core_lvl: Warn\n    backends:\n      - type: console\n  channel:\n    backends:\n{channel}    pub_topics_options:\n{topics}    sub_topics_options:\n{topics}"
    );
    let path = std::env::temp_dir().join(format!(
        "aimrt-bench-net-{}-{}.yaml",
        std::process::id(),
        own.tcp
    ));
    std::fs::write(&path, cfg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path.clone()),
        ..Default::default()
    });
    runtime.builtin_plugin(Box::new(LinkedPlugin::net(own.net_options())));
    runtime.register_module(module);
    let handle = runtime.shutdown_handle();
    let thread = std::thread::spawn(move || {
        let r = runtime.run().map_err(|e| e.to_string());
        let _ = std::fs::remove_file(&path);
        r
    });
    Ok((handle, thread))
}

/// What a peer counted, as its reports arrive: one counter per case (aimrt peer) or per
/// raw kind (tcp, udp, http).
struct Reports {
    counters: Vec<Arc<Counter>>,
    port: u16,
    stop: Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Reports {
    fn listen(n: usize) -> Result<Reports, String> {
        let sock = std::net::UdpSocket::bind("127.0.0.1:0").map_err(|e| e.to_string())?;
        let port = sock.local_addr().map_err(|e| e.to_string())?.port();
        sock.set_read_timeout(Some(Duration::from_millis(50)))
            .map_err(|e| e.to_string())?;
        let counters: Vec<Arc<Counter>> = (0..n).map(|_| Arc::default()).collect();
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (cs, st) = (counters.clone(), stop.clone());
        let thread = std::thread::spawn(move || {
            let mut buf = [0u8; 128];
            while !st.load(Ordering::Acquire) {
                let Ok(k) = sock.recv(&mut buf) else { continue };
                let text = String::from_utf8_lossy(&buf[..k]);
                let mut it = text.split(' ').map(|x| x.trim().parse::<u64>().ok());
                if let (Some(Some(i)), Some(Some(count)), Some(Some(lat))) =
                    (it.next(), it.next(), it.next())
                {
                    if let Some(c) = cs.get(i as usize) {
                        c.last_latency_ns.store(lat, Ordering::Relaxed);
                        c.received.fetch_max(count, Ordering::Release);
                    }
                }
            }
        });
        Ok(Reports {
            counters,
            port,
            stop,
            thread: Some(thread),
        })
    }
}

impl Drop for Reports {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The peer process; killed when dropped (a failed run leaves none behind).
struct Peer(Child);

impl Peer {
    /// Starts `aimrt-bench --net-peer SPEC` and waits (at most 30 s) for its `ready`.
    fn start(spec: &serde_json::Value) -> Result<Peer, String> {
        let exe = std::env::current_exe().map_err(|e| e.to_string())?;
        let mut child = Command::new(exe)
            .arg("--net-peer")
            .arg(spec.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .map_err(|e| format!("cannot start the peer process: {e}"))?;
        let stdout = child.stdout.take().ok_or("the peer has no stdout")?;
        let peer = Peer(child);
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if line.trim() == "ready" {
                    let _ = tx.send(());
                }
            }
        });
        rx.recv_timeout(Duration::from_secs(30))
            .map_err(|_| "the peer process did not get ready within 30 s".to_owned())?;
        Ok(peer)
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        // Closing its stdin asks it to stop; the kill makes sure.
        drop(self.0.stdin.take());
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

pub(crate) fn run(scale: crate::stats::Scale) -> Result<Vec<Case>, String> {
    let (own, to, raw) = (Ports::free()?, Ports::free()?, Ports::free()?);
    let reports = Reports::listen(6)?;
    let raw_reports = Reports::listen(3)?;
    let _peer = Peer::start(&serde_json::json!({
        "kind": "aimrt", "report": reports.port,
        "http": to.http, "tcp": to.tcp, "udp": to.udp
    }))?;
    let _raw_peer = Peer::start(&serde_json::json!({
        "kind": "raw", "report": raw_reports.port,
        "http": raw.http, "tcp": raw.tcp, "udp": raw.udp
    }))?;
    let (tx, rx) = mpsc::channel();
    let (handle, thread) = start_runtime(
        own,
        to,
        Box::new(Publish {
            out: tx,
            publishers: Vec::new(),
        }),
    )?;
    let measured = match rx.recv_timeout(Duration::from_secs(30)) {
        Ok(publishers) => measure(scale, &publishers, &reports, &raw_reports, raw),
        Err(_) => Err("the runtime did not start within 30 s".to_owned()),
    };
    handle.request();
    eprintln!("net: stopping the runtime");
    match thread.join() {
        Ok(Ok(())) => measured,
        Ok(Err(e)) => Err(format!("the runtime failed: {e}")),
        Err(_) => Err("the runtime thread panicked".into()),
    }
}

/// The rounds: in each, every case runs ours and its raw baseline back to back (which
/// goes first alternates); round 0 warms up and is discarded. Then each case's latency.
fn measure(
    scale: crate::stats::Scale,
    publishers: &[Publisher<ExampleEventMsg>],
    reports: &Reports,
    raw_reports: &Reports,
    raw: Ports,
) -> Result<Vec<Case>, String> {
    let quick = scale.quick;
    let rounds = scale.rounds(3, 5);
    let (n, samples) = if quick {
        (10_000u64, 300)
    } else {
        (50_000u64, 1_000)
    };
    let mut out: Vec<Case> = cases()
        .map(|(backend, size)| Case {
            backend,
            size,
            sent: 0,
            delivered: 0,
            ours: Vec::new(),
            raw: Vec::new(),
            p50_us: f64::NAN,
            p99_us: f64::NAN,
        })
        .collect();
    for round in 0..=rounds {
        let load = quiet_gate(Duration::from_secs(if quick { 3 } else { 30 }));
        eprintln!("net: round {round} of {rounds} (0 warms up), foreign load {load:.2} core");
        for (i, c) in out.iter_mut().enumerate() {
            let (p, counter) = (&publishers[i], &reports.counters[i]);
            let (backend, size) = (c.backend, c.size);
            // One message for the whole measurement: the raw loops send bytes made once,
            // so ours does not build a message per send either.
            let msg = Arc::new(message(size));
            let ours = || -> Result<(f64, u64), String> {
                paced(counter, n, |_| {
                    p.publish(msg.clone()).map_err(|e| e.to_string())
                })
            };
            let base = || -> Result<f64, String> {
                match backend {
                    "tcp" => raw_tcp(size, n, raw.tcp, &raw_reports.counters[0]),
                    "udp" => raw_udp(size, n, raw.udp, &raw_reports.counters[1]),
                    _ => raw_http(size, n, raw.http),
                }
            };
            let ((rate, delivered), base_rate) = alternate(round, ours, base)?;
            if delivered < n && backend != "udp" {
                return Err(format!("{backend} {size} B: {delivered} of {n} arrived"));
            }
            if round > 0 {
                c.ours.push(rate);
                c.raw.push(base_rate);
                c.sent += n;
                c.delivered += delivered;
            }
        }
    }
    // Latency: one in flight, each message stamped when it is made.
    for (i, c) in out.iter_mut().enumerate() {
        let (p, counter) = (&publishers[i], &reports.counters[i]);
        let mut lat = Vec::with_capacity(samples);
        for _ in 0..samples {
            let before = counter.received.load(Ordering::Acquire);
            p.publish(message(c.size)).map_err(|e| e.to_string())?;
            if wait_for(counter, before + 1, Duration::from_secs(5)) {
                lat.push(counter.last_latency_ns.load(Ordering::Relaxed) as f64 / 1e3);
            }
        }
        lat.sort_by(f64::total_cmp);
        c.p50_us = percentile(&lat, 50.0);
        c.p99_us = percentile(&lat, 99.0);
    }
    Ok(out)
}

/// Sends `n` messages with `send`, never more than 256 ahead of what the peer counted on
/// `c` (the sustained rate: a burst beyond the backends' bounded queues is refused by
/// design), and waits (at most 30 s) for the peer to count them all. (msgs/s, arrived).
fn paced(
    c: &Counter,
    n: u64,
    mut send: impl FnMut(u64) -> Result<(), String>,
) -> Result<(f64, u64), String> {
    let base = c.received.load(Ordering::Acquire);
    let t0 = Instant::now();
    for k in 0..n {
        send(k)?;
        if k % 128 == 127 {
            wait_for(c, base + k + 1 - 128, Duration::from_secs(1));
        }
    }
    wait_for(c, base + n, Duration::from_secs(30));
    let arrived = c.received.load(Ordering::Acquire) - base;
    Ok((arrived as f64 / t0.elapsed().as_secs_f64(), arrived))
}

/// The peer process's main (`--net-peer SPEC`): receives until its stdin closes.
pub(crate) fn peer(spec: &str) -> Result<(), String> {
    let spec: serde_json::Value =
        serde_json::from_str(spec).map_err(|e| format!("--net-peer: {e}"))?;
    let port = |k: &str| -> Result<u16, String> {
        spec[k]
            .as_u64()
            .and_then(|p| u16::try_from(p).ok())
            .ok_or(format!("--net-peer: '{k}' is not a port"))
    };
    let ports = Ports {
        http: port("http")?,
        tcp: port("tcp")?,
        udp: port("udp")?,
    };
    let report = port("report")?;
    let aimrt = spec["kind"] == "aimrt";
    let counters: Vec<Arc<Counter>> = (0..if aimrt { 6 } else { 3 })
        .map(|_| Arc::default())
        .collect();
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let reporter = {
        let (cs, st) = (counters.clone(), stop.clone());
        std::thread::spawn(move || report_loop(&cs, report, &st))
    };
    let stopped = if aimrt {
        let (handle, thread) = start_runtime(
            ports,
            Ports::free()?,
            Box::new(Subscribe {
                counters: counters.clone(),
            }),
        )?;
        wait_for_stdin_eof();
        handle.request();
        thread
            .join()
            .unwrap_or_else(|_| Err("the runtime thread panicked".into()))
    } else {
        raw_peer(ports, &counters)
    };
    stop.store(true, Ordering::Release);
    let _ = reporter.join();
    stopped
}

/// Blocks until the harness closes this process's stdin (or is gone).
fn wait_for_stdin_eof() {
    let _ = std::io::copy(&mut std::io::stdin().lock(), &mut std::io::sink());
}

/// Every 50 µs, sends `index count latency_ns` for each counter that moved. After 50 ms
/// without a move it looks every 2 ms, so an idle peer (while the other kind is measured)
/// does not load the machine.
fn report_loop(counters: &[Arc<Counter>], port: u16, stop: &std::sync::atomic::AtomicBool) {
    let Ok(sock) = std::net::UdpSocket::bind("127.0.0.1:0") else {
        return;
    };
    let mut sent = vec![0u64; counters.len()];
    let mut last_move = Instant::now();
    while !stop.load(Ordering::Acquire) {
        for (i, c) in counters.iter().enumerate() {
            let count = c.received.load(Ordering::Acquire);
            if count != sent[i] {
                sent[i] = count;
                last_move = Instant::now();
                let lat = c.last_latency_ns.load(Ordering::Relaxed);
                let _ = sock.send_to(format!("{i} {count} {lat}").as_bytes(), ("127.0.0.1", port));
            }
        }
        let idle = last_move.elapsed() > Duration::from_millis(50);
        std::thread::sleep(Duration::from_micros(if idle { 2_000 } else { 50 }));
    }
}

/// The raw receivers: a tokio reader of frames on `ports.tcp` (counter 0), a UDP receiver
/// with a 4 MiB buffer on `ports.udp` (counter 1), a hyper server answering 200 on
/// `ports.http` (counter 2).
fn raw_peer(ports: Ports, counters: &[Arc<Counter>]) -> Result<(), String> {
    use bytes::Bytes;
    use http_body_util::{BodyExt, Full};
    use hyper_util::rt::TokioIo;
    use tokio::io::AsyncReadExt;
    let sock = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::DGRAM, None)
        .map_err(|e| e.to_string())?;
    let _ = sock.set_recv_buffer_size(4 << 20);
    let at: std::net::SocketAddr = ([127, 0, 0, 1], ports.udp).into();
    sock.bind(&at.into()).map_err(|e| e.to_string())?;
    let udp: std::net::UdpSocket = sock.into();
    udp.set_read_timeout(Some(Duration::from_millis(100)))
        .map_err(|e| e.to_string())?;
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let udp_thread = {
        let (c, st) = (counters[1].clone(), stop.clone());
        std::thread::spawn(move || {
            let mut buf = vec![0u8; 2049];
            while !st.load(Ordering::Acquire) {
                if udp.recv_from(&mut buf).is_ok() {
                    c.received.fetch_add(1, Ordering::Release);
                }
            }
        })
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    let (tcp_count, http_count) = (counters[0].clone(), counters[2].clone());
    rt.block_on(async move {
        let tcp = tokio::net::TcpListener::bind(("127.0.0.1", ports.tcp))
            .await
            .map_err(|e| e.to_string())?;
        let http = tokio::net::TcpListener::bind(("127.0.0.1", ports.http))
            .await
            .map_err(|e| e.to_string())?;
        tokio::spawn(async move {
            while let Ok((mut s, _)) = tcp.accept().await {
                let c = tcp_count.clone();
                tokio::spawn(async move {
                    let mut buf = Vec::new();
                    let mut chunk = vec![0u8; 64 << 10];
                    loop {
                        let Ok(k) = s.read(&mut chunk).await else {
                            return;
                        };
                        if k == 0 {
                            return;
                        }
                        buf.extend_from_slice(&chunk[..k]);
                        let Ok(frames) = aimrt_net::wire::split_frames(&mut buf, 16 << 20) else {
                            return;
                        };
                        c.received.fetch_add(frames.len() as u64, Ordering::Release);
                    }
                });
            }
        });
        tokio::spawn(async move {
            while let Ok((stream, _)) = http.accept().await {
                let _ = stream.set_nodelay(true);
                let c = http_count.clone();
                tokio::spawn(async move {
                    let service = hyper::service::service_fn(
                        move |req: hyper::Request<hyper::body::Incoming>| {
                            let c = c.clone();
                            async move {
                                let _ = req.into_body().collect().await?;
                                c.received.fetch_add(1, Ordering::Release);
                                Ok::<_, hyper::Error>(hyper::Response::new(Full::new(Bytes::new())))
                            }
                        },
                    );
                    let _ = hyper::server::conn::http1::Builder::new()
                        .serve_connection(TokioIo::new(stream), service)
                        .await;
                });
            }
        });
        println!("ready");
        let _ = std::io::stdout().flush();
        tokio::task::spawn_blocking(wait_for_stdin_eof)
            .await
            .map_err(|e| e.to_string())
    })?;
    stop.store(true, Ordering::Release);
    let _ = udp_thread.join();
    rt.shutdown_background();
    Ok(())
}

/// The bytes our backends send for a message of `size`: AimRT's body.
fn body(size: usize) -> Vec<u8> {
    use prost::Message as _;
    let uri =
        aimrt_net::wire::channel_uri("/bench/raw", "pb:aimrt.protocols.example.ExampleEventMsg");
    let payload = message(size).encode_to_vec();
    let body = aimrt_net::wire::Body {
        uri: &uri,
        serialization_type: "pb",
        meta: vec![
            ("aimrt-serialization_type", "pb"),
            ("aimrt-pub_seq", "1"),
            ("aimrt-pub_ts", "1795386628205071149"),
        ]
        .into(),
        payload: &payload,
    };
    body.encode().unwrap_or_default()
}

/// Frames over one raw blocking stream to the peer's raw reader, paced as ours.
fn raw_tcp(size: usize, n: u64, port: u16, c: &Counter) -> Result<f64, String> {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).map_err(|e| e.to_string())?;
    let _ = s.set_nodelay(true);
    let frame = aimrt_net::wire::tcp_frame(&body(size));
    let (rate, arrived) = paced(c, n, |_| s.write_all(&frame).map_err(|e| e.to_string()))?;
    if arrived < n {
        return Err(format!("raw tcp: {arrived} of {n} arrived"));
    }
    Ok(rate)
}

/// A raw send loop to the peer's raw receiver, paced as ours; msgs/s of what arrived.
fn raw_udp(size: usize, n: u64, port: u16, c: &Counter) -> Result<f64, String> {
    let tx = std::net::UdpSocket::bind("127.0.0.1:0").map_err(|e| e.to_string())?;
    let d = body(size);
    let to: std::net::SocketAddr = ([127, 0, 0, 1], port).into();
    let (rate, _) = paced(c, n, |_| {
        let _ = tx.send_to(&d, to);
        Ok(())
    })?;
    Ok(rate)
}

/// The same POSTs from a raw hyper client (256 in flight) to the peer's raw hyper server.
fn raw_http(size: usize, n: u64, port: u16) -> Result<f64, String> {
    use bytes::Bytes;
    use http_body_util::Full;
    use hyper_util::rt::TokioExecutor;
    use prost::Message as _;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    let payload = Bytes::from(message(size).encode_to_vec());
    rt.block_on(async move {
        let mut connector = hyper_util::client::legacy::connect::HttpConnector::new();
        connector.set_nodelay(true);
        let client: hyper_util::client::legacy::Client<_, Full<Bytes>> =
            hyper_util::client::legacy::Client::builder(TokioExecutor::new()).build(connector);
        let url = format!(
            "http://127.0.0.1:{port}/channel/%2Fbench%2Fraw/pb%3Aaimrt.protocols.example.ExampleEventMsg"
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
        let mut ok = 0u64;
        for t in tasks {
            ok += u64::from(t.await.unwrap_or(false));
        }
        if ok < n {
            return Err(format!("raw http: {ok} of {n} requests answered"));
        }
        Ok(n as f64 / t0.elapsed().as_secs_f64())
    })
}
