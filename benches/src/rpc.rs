//! Scenario 8: module RPC round trips through the real runtime — `local` within one
//! library (the objects pass), `local` across libraries (another type-support table:
//! encode once + decode once each way, as a second `.so`) and `http` over loopback
//! (net_plugin as client and server of itself, protobuf bodies) — each with the baseline
//! the targets name, measured in the same run:
//!
//! - local: a cross-thread round trip over crossbeam channels carrying the encoded request
//!   and response (postcard, as the across-library call encodes them);
//! - http: a raw hyper client/server pair on one tokio runtime of the same size, doing the
//!   same POST (the same headers, meta and protobuf bodies both ways), its calls issued from a thread outside
//!   tokio with the same window as ours (a module's calls come from its own threads);
//!   the same pair driven from inside tokio is printed for reference;
//! - grpc (grpc_plugin as client and server of itself, HTTP/2): our own http case, same
//!   calls, same run, to tell the two backends apart.

use std::sync::{mpsc, Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use aimrt_plugin_api::rpc::RpcClient;
use aimrt_plugin_api::{
    CoreRef, Error, Module, ModuleInfo, Plugin, PluginOptions, Registrar, RpcContext,
};
use aimrt_protocols::example::{GetFooDataReq, GetFooDataRsp};
use aimrt_runtime::{Runtime, RuntimeOptions};

use crate::stats::{paired, percentile, process_cpu, summary, Summary};

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
struct Blob {
    id: u64,
    #[serde(with = "serde_bytes")]
    data: Vec<u8>,
}
aimrt_plugin_api::serde_message!(Blob, "bench.Blob");

/// The same message type as another library would have it.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
struct ForeignBlob {
    id: u64,
    #[serde(with = "serde_bytes")]
    data: Vec<u8>,
}
aimrt_plugin_api::serde_message!(ForeignBlob, "bench.Blob");

/// The request payload of the local cases (and the size of the HTTP request's text).
const PAYLOAD: usize = 64;

/// One measured case.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct Case {
    pub(crate) case: &'static str,
    /// One call in flight: round-trip latency, µs.
    pub(crate) p50_us: f64,
    pub(crate) p99_us: f64,
    /// Calls per second with `window` calls in flight.
    pub(crate) calls_per_s: f64,
    /// CPU time of the whole process per call in that run, µs (all threads: on a
    /// saturated machine, calls/s follows it).
    pub(crate) cpu_us_per_call: f64,
    pub(crate) window: usize,
    /// The baseline's figures, same method, same run.
    pub(crate) baseline: &'static str,
    pub(crate) base_p50_us: f64,
    pub(crate) base_p99_us: f64,
    pub(crate) base_calls_per_s: f64,
    pub(crate) base_cpu_us_per_call: f64,
    /// Round by round: p50 ÷ the baseline's p50, and calls/s ÷ the baseline's calls/s.
    pub(crate) p50_ratio: Summary,
    pub(crate) rate_ratio: Summary,
    /// Rounds measured (after a discarded warm-up round).
    pub(crate) rounds: usize,
    /// Calls that did not end OK (must be 0).
    pub(crate) failed: u64,
}

type Clients = (
    RpcClient<Blob, Blob>,
    RpcClient<Blob, Blob>,
    RpcClient<GetFooDataReq, GetFooDataRsp>,
    RpcClient<GetFooDataReq, GetFooDataRsp>,
);

/// The function the grpc case calls (the same service as the http case's, under a name
/// the config routes to `grpc`).
const GRPC_FUNC: &str = "pb:/bench.Grpc/GetFooData";

struct Bench {
    out: mpsc::Sender<Clients>,
    clients: Option<Clients>,
}

impl Module for Bench {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("RpcBench")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let rpc = core.rpc()?;
        rpc.serve_sync("serde:/bench/Same", |_: &RpcContext, r: &Blob| {
            Ok(Blob {
                id: r.id,
                data: r.data.clone(),
            })
        })?;
        rpc.serve_sync("serde:/bench/Foreign", |_: &RpcContext, r: &ForeignBlob| {
            Ok(ForeignBlob {
                id: r.id,
                data: r.data.clone(),
            })
        })?;
        rpc.serve_sync(
            "pb:/aimrt.protocols.example.ExampleService/GetFooData",
            |_: &RpcContext, r: &GetFooDataReq| Ok(echo(r)),
        )?;
        rpc.serve_sync(GRPC_FUNC, |_: &RpcContext, r: &GetFooDataReq| Ok(echo(r)))?;
        self.clients = Some((
            rpc.client("serde:/bench/Same")?,
            rpc.client("serde:/bench/Foreign")?,
            rpc.client("pb:/aimrt.protocols.example.ExampleService/GetFooData")?,
            rpc.client(GRPC_FUNC)?,
        ));
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        if let Some(c) = self.clients.take() {
            let _ = self.out.send(c);
        }
        Ok(())
    }
}

fn echo(r: &GetFooDataReq) -> GetFooDataRsp {
    GetFooDataRsp {
        msg: r.msg.clone(),
        ..Default::default()
    }
}

/// A transport plugin linked in, with options given in code.
pub(crate) struct LinkedPlugin {
    name: &'static str,
    inner: Box<dyn Plugin>,
    options: String,
}

impl LinkedPlugin {
    /// net_plugin with `options` (JSON).
    pub(crate) fn net(options: String) -> LinkedPlugin {
        LinkedPlugin {
            name: "net_plugin",
            inner: aimrt_net::plugin(),
            options,
        }
    }

    /// grpc_plugin with `options` (JSON).
    pub(crate) fn grpc(options: String) -> LinkedPlugin {
        LinkedPlugin {
            name: "grpc_plugin",
            inner: aimrt_grpc::plugin(),
            options,
        }
    }
}

impl Plugin for LinkedPlugin {
    fn name(&self) -> &str {
        self.name
    }
    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _: &PluginOptions,
    ) -> Result<(), Error> {
        let owner = format!("plugin '{}'", self.name);
        let options = PluginOptions::from_json(&owner, &self.options, "bench");
        self.inner.initialize(registrar, &options)
    }
    fn start(&mut self) -> Result<(), Error> {
        self.inner.start()
    }
    fn shutdown(&mut self) {
        self.inner.shutdown()
    }
}

/// HTTP threads on each side, as net_plugin's `thread_num`.
const HTTP_THREADS: usize = 2;

fn free_port() -> Result<u16, String> {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

/// Latencies of `samples` blocking calls, sorted (µs); failed calls counted.
fn latencies<Req, Rsp>(
    c: &RpcClient<Req, Rsp>,
    samples: usize,
    ctx: &dyn Fn() -> RpcContext,
    req: &dyn Fn(u64) -> Req,
    failed: &mut u64,
) -> Vec<f64>
where
    Req: aimrt_plugin_api::channel::Message,
    Rsp: aimrt_plugin_api::channel::Message,
{
    let mut lat = Vec::with_capacity(samples);
    for i in 0..samples {
        let t = Instant::now();
        let r = c.call(&mut ctx(), req(i as u64));
        lat.push(t.elapsed().as_secs_f64() * 1e6);
        if r.is_err() {
            *failed += 1;
        }
    }
    lat.sort_by(f64::total_cmp);
    lat
}

/// Calls per second with up to `window` calls in flight (callbacks), `n` calls in all, and
/// the process's CPU µs per call. The
/// issuing thread refills when half the window is free, so it wakes once per
/// `window / 2` answers instead of once per answer (the baseline issues from inside
/// tokio and never wakes a thread of its own).
fn rate<Req, Rsp>(
    c: &RpcClient<Req, Rsp>,
    n: usize,
    window: usize,
    ctx: &dyn Fn() -> RpcContext,
    req: &dyn Fn(u64) -> Req,
    failed: &mut u64,
) -> (f64, f64)
where
    Req: aimrt_plugin_api::channel::Message,
    Rsp: aimrt_plugin_api::channel::Message,
{
    struct Window {
        state: Mutex<(usize, u64)>,
        cv: Condvar,
    }
    let w = Arc::new(Window {
        state: Mutex::new((0, 0)),
        cv: Condvar::new(),
    });
    let (t, cpu) = (Instant::now(), process_cpu());
    for i in 0..n {
        {
            let mut s = w.state.lock().unwrap();
            if s.0 >= window {
                while s.0 > window / 2 {
                    s = w.cv.wait(s).unwrap();
                }
            }
            s.0 += 1;
        }
        let w2 = w.clone();
        c.call_then(ctx(), req(i as u64), move |_, r| {
            let mut s = w2.state.lock().unwrap();
            s.0 -= 1;
            if r.is_err() {
                s.1 += 1;
            }
            if s.0 == window / 2 || s.0 == 0 {
                w2.cv.notify_one();
            }
        });
    }
    let mut s = w.state.lock().unwrap();
    while s.0 > 0 {
        s = w.cv.wait(s).unwrap();
    }
    *failed += s.1;
    per_call(n, t, cpu)
}

/// `(calls/s, CPU µs per call)` of `n` calls that began at `t` with the process at `cpu`.
fn per_call(n: usize, t: Instant, cpu: f64) -> (f64, f64) {
    (
        n as f64 / t.elapsed().as_secs_f64(),
        (process_cpu() - cpu) * 1e6 / n as f64,
    )
}

/// The crossbeam baseline: encoded request to another thread, decoded, answered, the
/// encoded response back and decoded. `(sorted latencies µs, calls/s with `window` in
/// flight)`.
fn crossbeam_baseline(samples: usize, n: usize, window: usize) -> (Vec<f64>, (f64, f64)) {
    let (to_server, requests) = crossbeam_channel::unbounded::<Vec<u8>>();
    let (to_client, responses) = crossbeam_channel::unbounded::<Vec<u8>>();
    let server = std::thread::spawn(move || {
        while let Ok(bytes) = requests.recv() {
            let Ok(req) = postcard::from_bytes::<ForeignBlob>(&bytes) else {
                break;
            };
            let rsp = ForeignBlob {
                id: req.id,
                data: req.data.clone(),
            };
            if to_client
                .send(postcard::to_allocvec(&rsp).unwrap_or_default())
                .is_err()
            {
                break;
            }
        }
    });
    let data = vec![0xA5u8; PAYLOAD];
    let send = |i: u64| {
        let req = Blob {
            id: i,
            data: data.clone(),
        };
        to_server
            .send(postcard::to_allocvec(&req).unwrap_or_default())
            .expect("the baseline server runs");
    };
    let recv = || {
        let bytes = responses.recv().expect("the baseline server answers");
        postcard::from_bytes::<Blob>(&bytes).expect("a response")
    };
    let mut lat = Vec::with_capacity(samples);
    for i in 0..samples {
        let t = Instant::now();
        send(i as u64);
        std::hint::black_box(recv());
        lat.push(t.elapsed().as_secs_f64() * 1e6);
    }
    lat.sort_by(f64::total_cmp);
    let (t, cpu) = (Instant::now(), process_cpu());
    let mut in_flight = 0;
    for i in 0..n {
        if in_flight == window {
            std::hint::black_box(recv());
            in_flight -= 1;
        }
        send(i as u64);
        in_flight += 1;
    }
    for _ in 0..in_flight {
        std::hint::black_box(recv());
    }
    let r = per_call(n, t, cpu);
    drop(to_server);
    let _ = server.join();
    (lat, r)
}

type HyperClient = hyper_util::client::legacy::Client<
    hyper_util::client::legacy::connect::HttpConnector,
    http_body_util::Full<bytes::Bytes>,
>;

/// The raw hyper baseline: one tokio runtime of `HTTP_THREADS` workers runs a hyper server
/// answering the POST (decode GetFooDataReq, encode the echo) and a pooled hyper client.
struct HyperPair {
    rt: tokio::runtime::Runtime,
    client: HyperClient,
    url: hyper::Uri,
}

/// One baseline call: the same POST as net_plugin's client sends (AimRT's headers and
/// meta), its response decoded.
async fn hyper_call(client: HyperClient, url: hyper::Uri, i: u64) {
    use bytes::Bytes;
    use http_body_util::{BodyExt, Full};
    use prost::Message as _;
    let req = GetFooDataReq {
        msg: format!("{:0>width$}", i, width = PAYLOAD),
    };
    let request = hyper::Request::post(url)
        .header(hyper::header::HOST, "127.0.0.1")
        .header(hyper::header::USER_AGENT, "aimrt")
        .header("Timeout", "10")
        .header(hyper::header::CONTENT_TYPE, "application/protobuf")
        .header(
            "aimrt-function%5Fname",
            "pb%3A%2Faimrt%2Eprotocols%2Eexample%2EExampleService%2FGetFooData",
        )
        .header("aimrt-request%5Fid", i.to_string())
        .header("aimrt-serialization%5Ftype", "pb")
        .header("aimrt-backend", "http")
        .body(Full::new(Bytes::from(req.encode_to_vec())))
        .expect("a request");
    let rsp = client
        .request(request)
        .await
        .expect("the baseline server answers");
    let body = rsp.into_body().collect().await.expect("a body").to_bytes();
    std::hint::black_box(GetFooDataRsp::decode(body).expect("a response"));
}

impl HyperPair {
    fn start() -> Result<HyperPair, String> {
        use bytes::Bytes;
        use http_body_util::{BodyExt, Full};
        use hyper_util::rt::{TokioExecutor, TokioIo};
        use prost::Message as _;

        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(HTTP_THREADS)
            .enable_all()
            .build()
            .map_err(|e| e.to_string())?;
        let listener = rt
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .map_err(|e| e.to_string())?;
        let addr = listener.local_addr().map_err(|e| e.to_string())?;
        rt.spawn(async move {
            loop {
                let Ok((stream, _)) = listener.accept().await else {
                    return;
                };
                let _ = stream.set_nodelay(true);
                tokio::spawn(async move {
                    let service = hyper::service::service_fn(
                        |req: hyper::Request<hyper::body::Incoming>| async move {
                            let body = req.into_body().collect().await?.to_bytes();
                            let r = GetFooDataReq::decode(body).unwrap_or_default();
                            let mut rsp = hyper::Response::new(Full::new(Bytes::from(
                                echo(&r).encode_to_vec(),
                            )));
                            // The same answer as net_plugin's server sends.
                            let h = rsp.headers_mut();
                            h.insert(
                                hyper::header::CONTENT_TYPE,
                                hyper::header::HeaderValue::from_static("application/protobuf"),
                            );
                            h.insert(
                                hyper::header::ACCESS_CONTROL_ALLOW_ORIGIN,
                                hyper::header::HeaderValue::from_static("*"),
                            );
                            h.insert(
                                "aimrt-rs-status",
                                hyper::header::HeaderValue::from_static("0"),
                            );
                            Ok::<_, hyper::Error>(rsp)
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
        let client =
            hyper_util::client::legacy::Client::builder(TokioExecutor::new()).build(connector);
        let url = format!("http://{addr}/rpc/aimrt.protocols.example.ExampleService/GetFooData")
            .parse()
            .map_err(|e| format!("{e}"))?;
        Ok(HyperPair { rt, client, url })
    }

    /// Latencies of `samples` calls one at a time, sorted (µs).
    fn latencies(&self, samples: usize) -> Vec<f64> {
        let mut lat = Vec::with_capacity(samples);
        for i in 0..samples {
            let t = Instant::now();
            self.rt
                .block_on(hyper_call(self.client.clone(), self.url.clone(), i as u64));
            lat.push(t.elapsed().as_secs_f64() * 1e6);
        }
        lat.sort_by(f64::total_cmp);
        lat
    }

    /// `(calls/s, CPU µs per call)` of `n` calls issued from this thread, as a module
    /// issues its calls, with the same window logic as [`rate`] (the target's baseline).
    fn issued(&self, n: usize, window: usize) -> (f64, f64) {
        struct Window {
            state: Mutex<usize>,
            cv: Condvar,
        }
        let w = Arc::new(Window {
            state: Mutex::new(0),
            cv: Condvar::new(),
        });
        let (t, cpu) = (Instant::now(), process_cpu());
        for i in 0..n {
            {
                let mut s = w.state.lock().unwrap();
                if *s >= window {
                    while *s > window / 2 {
                        s = w.cv.wait(s).unwrap();
                    }
                }
                *s += 1;
            }
            let (client, url, w2) = (self.client.clone(), self.url.clone(), w.clone());
            self.rt.spawn(async move {
                hyper_call(client, url, i as u64).await;
                let mut s = w2.state.lock().unwrap();
                *s -= 1;
                if *s == window / 2 || *s == 0 {
                    w2.cv.notify_one();
                }
            });
        }
        let mut s = w.state.lock().unwrap();
        while *s > 0 {
            s = w.cv.wait(s).unwrap();
        }
        per_call(n, t, cpu)
    }

    /// Calls/s issued from `window` tasks inside tokio: raw hyper at its best, for
    /// reference.
    fn inside(&self, n: usize, window: usize) -> f64 {
        let t = Instant::now();
        self.rt.block_on(async {
            let per = n / window;
            let mut tasks = Vec::new();
            for w in 0..window {
                let (client, url) = (self.client.clone(), self.url.clone());
                tasks.push(tokio::spawn(async move {
                    for i in 0..per {
                        hyper_call(client.clone(), url.clone(), (w * per + i) as u64).await;
                    }
                }));
            }
            for t in tasks {
                let _ = t.await;
            }
        });
        (n / window * window) as f64 / t.elapsed().as_secs_f64()
    }
}

pub(crate) fn run(scale: crate::stats::Scale) -> Result<Vec<Case>, String> {
    let quick = scale.quick;
    let port = free_port()?;
    let grpc_port = free_port()?;
    let cfg = format!(
        "aimrt:\n  log:\n    core_lvl: Warn\n    backends:\n      - type: console\n  rpc:\n    backends:\n      - type: local\n      - type: http\n        options:\n          clients_options:\n            - func_name: \"(.*)\"\n              server_url: http://127.0.0.1:{port}\n      - type: grpc\n        options:\n          clients_options:\n            - func_name: \"(.*)\"\n              server_url: http://127.0.0.1:{grpc_port}\n    clients_options:\n      - func_name: \"pb:/bench.Grpc/.*\"\n        enable_backends: [grpc]\n      - func_name: \"pb:.*\"\n        enable_backends: [http]\n      - func_name: \".*\"\n        enable_backends: [local]\n    servers_options:\n      - func_name: \"pb:/bench.Grpc/.*\"\n        enable_backends: [grpc]\n      - func_name: \".*\"\n        enable_backends: [local, http]\n"
    );
    let path = std::env::temp_dir().join(format!("aimrt-bench-rpc-{}.yaml", std::process::id()));
    std::fs::write(&path, cfg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    let (tx, rx) = mpsc::channel();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path.clone()),
        ..Default::default()
    });
    runtime.builtin_plugin(Box::new(LinkedPlugin::net(format!(
        "{{\"thread_num\": {HTTP_THREADS}, \"http_options\": {{\"listen_ip\": \"127.0.0.1\", \"listen_port\": {port}}}}}"
    ))));
    runtime.builtin_plugin(Box::new(LinkedPlugin::grpc(format!(
        "{{\"thread_num\": {HTTP_THREADS}, \"listen_ip\": \"127.0.0.1\", \"listen_port\": {grpc_port}}}"
    ))));
    runtime.register_module(Box::new(Bench {
        out: tx,
        clients: None,
    }));
    let handle = runtime.shutdown_handle();
    let thread = std::thread::spawn(move || runtime.run());
    let got = rx.recv_timeout(Duration::from_secs(30));
    let _ = std::fs::remove_file(&path);
    let Ok((same, foreign, http, grpc)) = got else {
        handle.request();
        return Err(match thread.join() {
            Ok(Err(e)) => format!("the runtime failed: {e}"),
            _ => "the runtime did not start within 30 s".to_owned(),
        });
    };
    let (samples, n, http_n) = if quick {
        (2_000, 20_000, 4_000)
    } else {
        (10_000, 100_000, 20_000)
    };
    let rounds = scale.rounds(3, 5);
    let window = 32;
    let data = vec![0xA5u8; PAYLOAD];
    let blob = |i: u64| Blob {
        id: i,
        data: data.clone(),
    };
    let ctx = RpcContext::client;
    let text = |i: u64| GetFooDataReq {
        msg: format!("{:0>width$}", i, width = PAYLOAD),
    };
    let http_ctx = || {
        let mut c = RpcContext::client();
        c.set_timeout(Some(Duration::from_secs(10)));
        c
    };
    let hyper = match HyperPair::start() {
        Ok(h) => h,
        Err(e) => {
            handle.request();
            let _ = thread.join();
            return Err(format!("the hyper baseline did not start: {e}"));
        }
    };
    // Rounds interleave each case with its baseline (BENCHMARKING.md); round 0 warms up
    // and is discarded.
    let mut figures: [Vec<Round>; 4] = Default::default();
    let mut failed = [0u64; 4];
    for round in 0..=rounds {
        let load = crate::stats::quiet_gate(Duration::from_secs(if quick { 3 } else { 30 }));
        eprintln!("rpc: round {round}, foreign load {load:.2} core");
        let (base_lat, base_rate) = crossbeam_baseline(samples, n, window);
        let mut measured = Vec::new();
        for (i, client) in [&same, &foreign].into_iter().enumerate() {
            let mut f = 0;
            let lat = latencies(client, samples, &ctx, &blob, &mut f);
            let (r, cpu) = rate(client, n, window, &ctx, &blob, &mut f);
            failed[i] += f;
            measured.push(Round::new(&lat, (r, cpu), &base_lat, base_rate));
        }
        let mut f = 0;
        let lat = latencies(&http, samples / 2, &http_ctx, &text, &mut f);
        let (r, cpu) = rate(&http, http_n, window, &http_ctx, &text, &mut f);
        failed[2] += f;
        let base_lat = hyper.latencies(samples / 2);
        let base_rate = hyper.issued(http_n, window);
        measured.push(Round::new(&lat, (r, cpu), &base_lat, base_rate));
        // grpc beside our own http, measured just before in this round.
        let mut f = 0;
        let glat = latencies(&grpc, samples / 2, &http_ctx, &text, &mut f);
        let grate = rate(&grpc, http_n, window, &http_ctx, &text, &mut f);
        failed[3] += f;
        measured.push(Round::new(&glat, grate, &lat, (r, cpu)));
        if round > 0 {
            for (all, m) in figures.iter_mut().zip(measured) {
                all.push(m);
            }
        }
    }
    let inside = hyper.inside(http_n, window);
    let hyper_lat = hyper.latencies(samples / 2);
    drop(hyper);
    handle.request();
    let joined = thread.join();
    eprintln!("rpc: done");
    let names = [
        ("local, same library", "crossbeam round trip, encoded"),
        ("local, across libraries", "crossbeam round trip, encoded"),
        (
            "http, loopback (pb)",
            "raw hyper client/server, issued from a thread",
        ),
        (
            "grpc, loopback (pb)",
            "our http backend, same calls and run",
        ),
    ];
    let mut cases: Vec<Case> = names
        .iter()
        .zip(&figures)
        .zip(failed)
        .map(|(((case, baseline), rounds), failed)| {
            Case::of(case, baseline, rounds, window, failed)
        })
        .collect();
    cases.push(Case {
        case: "(reference) raw hyper issued inside tokio",
        p50_us: percentile(&hyper_lat, 50.0),
        p99_us: percentile(&hyper_lat, 99.0),
        calls_per_s: inside,
        cpu_us_per_call: f64::NAN,
        window,
        baseline: "—",
        base_p50_us: f64::NAN,
        base_p99_us: f64::NAN,
        base_calls_per_s: f64::NAN,
        base_cpu_us_per_call: f64::NAN,
        p50_ratio: Summary::none(),
        rate_ratio: Summary::none(),
        rounds: 1,
        failed: 0,
    });
    match joined {
        Ok(Ok(())) => Ok(cases),
        Ok(Err(e)) => Err(format!("the runtime failed: {e}")),
        Err(_) => Err("the runtime thread panicked".into()),
    }
}

/// One round of one case beside its baseline.
struct Round {
    p50: f64,
    p99: f64,
    rate: f64,
    cpu: f64,
    base_p50: f64,
    base_p99: f64,
    base_rate: f64,
    base_cpu: f64,
}

impl Round {
    fn new(
        lat: &[f64],
        (rate, cpu): (f64, f64),
        base_lat: &[f64],
        (base_rate, base_cpu): (f64, f64),
    ) -> Round {
        Round {
            p50: percentile(lat, 50.0),
            p99: percentile(lat, 99.0),
            rate,
            cpu,
            base_p50: percentile(base_lat, 50.0),
            base_p99: percentile(base_lat, 99.0),
            base_rate,
            base_cpu,
        }
    }
}

impl Case {
    /// Medians over `rounds`, and the paired ratios round by round.
    fn of(
        case: &'static str,
        baseline: &'static str,
        rounds: &[Round],
        window: usize,
        failed: u64,
    ) -> Case {
        let med = |f: fn(&Round) -> f64| summary(&rounds.iter().map(f).collect::<Vec<_>>()).median;
        let col = |f: fn(&Round) -> f64| rounds.iter().map(f).collect::<Vec<_>>();
        Case {
            case,
            p50_us: med(|r| r.p50),
            p99_us: med(|r| r.p99),
            calls_per_s: med(|r| r.rate),
            cpu_us_per_call: med(|r| r.cpu),
            window,
            baseline,
            base_p50_us: med(|r| r.base_p50),
            base_p99_us: med(|r| r.base_p99),
            base_calls_per_s: med(|r| r.base_rate),
            base_cpu_us_per_call: med(|r| r.base_cpu),
            p50_ratio: paired(&col(|r| r.p50), &col(|r| r.base_p50)),
            rate_ratio: paired(&col(|r| r.rate), &col(|r| r.base_rate)),
            rounds: rounds.len(),
            failed,
        }
    }
}
