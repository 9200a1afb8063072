//! Modules the in-process RPC tests share: a server with one function per way a call can
//! end, and the request and response types.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use aimrt_plugin_api::co::block_on;
use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall, BackendReply, Reply, RpcClient, RpcRef};
use aimrt_plugin_api::{
    BackendOptions, CoreRef, Error, Module, ModuleInfo, Plugin, PluginOptions, Registrar,
    RpcBackend, RpcContext, RpcStatus, ServiceHost,
};
use aimrt_runtime::{Runtime, RuntimeOptions};

/// What each check of the scenario gave, by name.
pub type Results = Arc<Mutex<BTreeMap<String, String>>>;

/// A request.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Req {
    /// The text.
    pub text: String,
}

/// A response.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Rsp {
    /// The text.
    pub text: String,
}
aimrt_plugin_api::serde_message!(Req, "test.Req");
aimrt_plugin_api::serde_message!(Rsp, "test.Rsp");

/// The full name of a test method.
pub fn f(method: &str) -> String {
    format!("serde:/test.Svc/{method}")
}

/// Serves every test method.
pub struct Server {
    /// The address of the last request `Echo` saw (same library: the caller's own object).
    pub seen: Arc<AtomicUsize>,
    /// Replies `Never` keeps and never sends.
    pub kept: Arc<Mutex<Vec<Reply<Rsp>>>>,
}

impl Module for Server {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Server")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let rpc = core.rpc()?;
        let seen = self.seen.clone();
        rpc.serve_then(&f("Echo"), move |ctx, req: Arc<Req>, reply| {
            seen.store(Arc::as_ptr(&req) as usize, Ordering::SeqCst);
            let backend = ctx.meta("aimrt-backend").unwrap_or("").to_owned();
            let from = ctx.meta("aimrt-from_module").unwrap_or("").to_owned();
            reply.send(Ok(Rsp {
                text: format!("echo {} via {backend} from {from}", req.text),
            }))
        })?;
        // Answers from another thread after 300 ms.
        rpc.serve_then(&f("Slow"), |_, req: Arc<Req>, reply: Reply<Rsp>| {
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(300));
                reply.send(Ok(Rsp {
                    text: req.text.clone(),
                }))
            });
        })?;
        // Runs on the caller's thread for 300 ms.
        rpc.serve_sync(&f("SlowInline"), |_: &RpcContext, req: &Req| {
            std::thread::sleep(Duration::from_millis(300));
            Ok(Rsp {
                text: req.text.clone(),
            })
        })?;
        rpc.serve_sync(
            &f("Panic"),
            |_: &RpcContext, _: &Req| -> Result<Rsp, RpcStatus> { panic!("the handler gave up") },
        )?;
        rpc.serve_sync(
            &f("Status"),
            |_: &RpcContext, _: &Req| -> Result<Rsp, RpcStatus> {
                Err(RpcStatus::SVR_NOT_IMPLEMENTED)
            },
        )?;
        rpc.serve_then(&f("Drop"), |_, _: Arc<Req>, reply: Reply<Rsp>| drop(reply))?;
        let kept = self.kept.clone();
        rpc.serve_then(&f("Never"), move |_, _: Arc<Req>, reply| {
            kept.lock().unwrap().push(reply)
        })?;
        rpc.serve_async(&f("Async"), |_, req: Arc<Req>| async move {
            Ok(Rsp {
                text: format!("async {}", req.text),
            })
        })?;
        let refusing = core.executor("refusing")?;
        rpc.serve_async_on(&refusing, &f("Refused"), |_, req: Arc<Req>| async move {
            Ok(Rsp {
                text: req.text.clone(),
            })
        })?;
        let serial = core.executor("serial")?;
        rpc.serve_async_on(&serial, &f("OnSerial"), |_, req: Arc<Req>| async move {
            Ok(Rsp {
                text: format!("serial {}", req.text),
            })
        })?;
        // Peek answers what it sees of two keys; Chain calls Peek with a context made from
        // its own: only the key a plugin passes goes along.
        rpc.serve_sync(&f("Peek"), |ctx: &RpcContext, _: &Req| {
            Ok(Rsp {
                text: format!(
                    "{}|{}",
                    ctx.meta("trace-id").unwrap_or(""),
                    ctx.meta("other").unwrap_or("")
                ),
            })
        })?;
        let peek = rpc.client::<Req, Rsp>(&f("Peek"))?;
        rpc.serve_then(
            &f("Chain"),
            move |ctx: RpcContext, req: Arc<Req>, reply: Reply<Rsp>| {
                let mut call_ctx = peek.new_context_from(&ctx);
                // The format is not a passed key: keep the caller's (json over HTTP).
                if let Some(f) = ctx.serialization_type() {
                    call_ctx.set_serialization_type(f);
                }
                peek.call_then(call_ctx, req, move |_, r| {
                    reply.send(r.map(|rsp| Rsp {
                        text: rsp.text.clone(),
                    }))
                });
            },
        )?;
        // Twice by the same module: refused.
        let again = rpc.serve_sync(&f("Echo"), |_: &RpcContext, req: &Req| {
            Ok(Rsp {
                text: req.text.clone(),
            })
        });
        assert!(
            again.unwrap_err().to_string().contains("registered twice"),
            "a second registration is refused"
        );
        Ok(())
    }
}

/// A request with `text`.
pub fn req(text: &str) -> Req {
    Req { text: text.into() }
}

/// `ok: <text>` or `err: <code>`.
pub fn show(r: &Result<Arc<Rsp>, RpcStatus>) -> String {
    match r {
        Ok(rsp) => format!("ok: {}", rsp.text),
        Err(s) => format!("err: {}", s.code()),
    }
}

struct Clients {
    all: BTreeMap<&'static str, RpcClient<Req, Rsp>>,
    serial: aimrt_plugin_api::ExecutorRef,
}

/// Calls everything from a thread of its own once started; records what came back.
struct Client {
    results: Results,
    clients: Option<Clients>,
    rpc: Option<RpcRef>,
    worker: Option<std::thread::JoinHandle<()>>,
    /// Calls made at the end that are still waiting at shutdown.
    in_flight: Arc<Mutex<Vec<RpcStatus>>>,
    seen: Arc<AtomicUsize>,
    /// The serialization type of every call (`None`: the type's default).
    format: Option<String>,
    /// Starts and ends of the filter on Echo's client.
    filter_counts: (Arc<AtomicUsize>, Arc<AtomicUsize>),
}

impl Client {
    fn ctx0(&self) -> RpcContext {
        let mut ctx = RpcContext::client();
        if let Some(f) = &self.format {
            ctx.set_serialization_type(f);
        }
        ctx
    }
}

impl Module for Client {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Client")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let rpc = core.rpc()?;
        let mut all = BTreeMap::new();
        for m in [
            "Echo",
            "Slow",
            "SlowInline",
            "Panic",
            "Status",
            "Drop",
            "Never",
            "Async",
            "Refused",
            "OnSerial",
            "Missing",
            "Chain",
        ] {
            all.insert(m, rpc.client::<Req, Rsp>(&f(m))?);
        }
        // A module filter on Echo's client: every start has exactly one end, in every style.
        let (starts, ends) = (self.filter_counts.0.clone(), self.filter_counts.1.clone());
        if let Some(echo) = all.get_mut("Echo") {
            echo.add_filter(aimrt_plugin_api::rpc::filter(move |_, _| {
                starts.fetch_add(1, Ordering::SeqCst);
                let ends = ends.clone();
                Box::new(move |_, _| {
                    ends.fetch_add(1, Ordering::SeqCst);
                })
            }));
        }
        assert!(
            rpc.client::<Req, Rsp>(&f("Echo")).is_err(),
            "twice: refused"
        );
        // Before start: answered at once, no hang.
        let ctx0 = self.ctx0();
        let early = all["Echo"].call(&mut ctx0.clone(), req("early"));
        self.results
            .lock()
            .unwrap()
            .insert("before start".into(), show(&early));
        self.rpc = Some(rpc);
        self.clients = Some(Clients {
            all,
            serial: core.executor("serial")?,
        });
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let late = self
            .rpc
            .unwrap()
            .client::<Req, Rsp>(&f("Echo"))
            .map(|_| ())
            .unwrap_err()
            .to_string();
        let Clients { all, serial } = self.clients.take().unwrap();
        let results = self.results.clone();
        let in_flight = self.in_flight.clone();
        let seen = self.seen.clone();
        results
            .lock()
            .unwrap()
            .insert("register in start".into(), late);
        let ctx0 = self.ctx0();
        let filter_counts = self.filter_counts.clone();
        self.worker = Some(std::thread::spawn(move || {
            let put = |k: &str, v: String| {
                results.lock().unwrap().insert(k.into(), v);
            };
            let c = |m: &str| all[m].clone();
            // Blocking, with the zero-copy check.
            let sent = Arc::new(req("hi"));
            let ptr = Arc::as_ptr(&sent) as usize;
            put("sync", show(&c("Echo").call(&mut ctx0.clone(), sent)));
            put(
                "same object",
                (seen.load(Ordering::SeqCst) == ptr).to_string(),
            );
            // Future.
            let echo = c("Echo");
            let mut ctx = ctx0.clone();
            put(
                "future",
                show(&block_on(echo.call_async(&mut ctx, req("f")))),
            );
            put(
                "function name in ctx",
                ctx.meta("aimrt-function_name").unwrap_or("").into(),
            );
            // Used context.
            put("used ctx", show(&echo.call(&mut ctx, req("again"))));
            // Callback.
            let (tx, rx) = mpsc::channel();
            echo.call_then(ctx0.clone(), req("cb"), move |_, r| {
                tx.send(show(&r)).unwrap()
            });
            put(
                "callback",
                rx.recv_timeout(Duration::from_secs(10)).unwrap(),
            );
            // Timeout: the deadline thread answers.
            let mut ctx = ctx0.clone();
            ctx.set_timeout(Some(Duration::from_millis(100)));
            let begin = Instant::now();
            put("slow", show(&c("Slow").call(&mut ctx, req("s"))));
            put(
                "slow took < 250 ms",
                (begin.elapsed() < Duration::from_millis(250)).to_string(),
            );
            // Inline: the caller's thread runs the handler, then sees the timeout.
            let mut ctx = ctx0.clone();
            ctx.set_timeout(Some(Duration::from_millis(100)));
            put(
                "slow inline",
                show(&c("SlowInline").call(&mut ctx, req("s"))),
            );
            for m in ["Panic", "Status", "Drop", "Missing", "Async", "Refused"] {
                put(m, show(&c(m).call(&mut ctx0.clone(), req(m))));
            }
            // Blocking on the serial executor the service runs on: refused at once.
            let on_serial = c("OnSerial");
            let (tx, rx) = mpsc::channel();
            serial
                .execute({
                    // Locally refused at once; over HTTP the service waits for this
                    // thread: the deadline ends the call.
                    let mut ctx = ctx0.clone();
                    ctx.set_timeout(Some(Duration::from_secs(1)));
                    move || {
                        let begin = Instant::now();
                        let r = on_serial.call(&mut ctx, req("x"));
                        tx.send((show(&r), begin.elapsed())).unwrap();
                    }
                })
                .unwrap();
            let (r, took) = rx.recv_timeout(Duration::from_secs(10)).unwrap();
            put("blocking on the service's serial executor", r);
            put(
                "refused at once",
                (took < Duration::from_millis(50)).to_string(),
            );
            put(
                "OnSerial from elsewhere",
                show(&c("OnSerial").call(&mut ctx0.clone(), req("y"))),
            );
            // A key a plugin passes goes along a chain of calls; another does not.
            let mut chained = ctx0.clone();
            chained.set_meta("trace-id", "abc");
            chained.set_meta("other", "x");
            put("chain", show(&c("Chain").call(&mut chained, req("c"))));
            // 1 000 concurrent calls, all answered.
            let (tx, rx) = mpsc::channel();
            for i in 0..1000 {
                let tx = tx.clone();
                echo.call_then(ctx0.clone(), req(&i.to_string()), move |_, r| {
                    let _ = tx.send(r.is_ok());
                });
            }
            let ok = (0..1000)
                .filter(|_| rx.recv_timeout(Duration::from_secs(20)).unwrap())
                .count();
            put("concurrent ok", ok.to_string());
            // 100 calls that will still wait at shutdown.
            for _ in 0..100 {
                let mut ctx = ctx0.clone();
                ctx.set_timeout(Some(Duration::from_secs(60)));
                let in_flight = in_flight.clone();
                c("Never").call_then(ctx, req("n"), move |_, r| {
                    in_flight
                        .lock()
                        .unwrap()
                        .push(r.err().unwrap_or(RpcStatus::OK))
                });
            }
            let (starts, ends) = (&filter_counts.0, &filter_counts.1);
            put(
                "filter starts = ends",
                format!(
                    "{} {}",
                    starts.load(Ordering::SeqCst) == ends.load(Ordering::SeqCst),
                    starts.load(Ordering::SeqCst) > 1000
                ),
            );
            put("done", "true".into());
        }));
        Ok(())
    }
    fn shutdown(&mut self) {
        if let Some(w) = self.worker.take() {
            w.join().unwrap();
        }
    }
}

/// A plugin that passes `trace-id` from server to client contexts.
struct PassTraceId;

impl aimrt_plugin_api::Plugin for PassTraceId {
    fn name(&self) -> &str {
        "pass_trace_id"
    }
    fn initialize(
        &mut self,
        registrar: &mut aimrt_plugin_api::Registrar<'_>,
        _: &aimrt_plugin_api::PluginOptions,
    ) -> Result<(), Error> {
        registrar.add_passed_context_meta_keys(&["trace-id"])
    }
}

/// What [`run_scenario`] saw.
#[derive(Debug)]
pub struct Scenario {
    /// Each check's outcome, by name.
    pub results: BTreeMap<String, String>,
    /// The answers of the 100 calls still in flight at shutdown.
    pub in_flight: Vec<RpcStatus>,
    /// How long `run` took after the scenario's 3 s.
    pub shutdown_took: Duration,
}

/// The outcome every backend that carries calls between processes (`http`, `grpc`) must
/// give the scenario, the runtime being client and server of itself through `backend`:
/// each way a call ends reaches the caller as the same status (AimRT's code crosses the
/// wire), the request is a copy, the deadline holds across the wire, 1 000 concurrent
/// calls succeed, and the 100 calls in flight at shutdown are answered "not ready".
pub fn assert_carried_between_processes(s: &Scenario, backend: &str) {
    let r = &s.results;
    let get = |k: &str| r.get(k).map(String::as_str).unwrap_or("<missing>");
    assert_eq!(get("done"), "true", "{r:#?}");
    assert_eq!(get("before start"), "err: 2011");
    assert_eq!(get("sync"), format!("ok: echo hi via {backend} from "));
    assert_eq!(
        get("same object"),
        "false",
        "over {backend} the request is a copy"
    );
    assert_eq!(get("future"), format!("ok: echo f via {backend} from "));
    assert_eq!(get("used ctx"), "err: 2003");
    assert_eq!(get("callback"), format!("ok: echo cb via {backend} from "));
    assert_eq!(get("slow"), "err: 2");
    assert_eq!(get("slow took < 250 ms"), "true");
    assert_eq!(get("slow inline"), "err: 2");
    assert_eq!(get("Panic"), "err: 1008", "the code crosses {backend}");
    assert_eq!(get("Status"), "err: 1002");
    assert_eq!(get("Drop"), "err: 1008");
    assert_eq!(get("Missing"), "err: 1003");
    assert_eq!(get("Async"), "ok: async Async");
    assert_eq!(get("Refused"), "err: 1009");
    // The service runs on the serial executor the caller blocks: the deadline ends it.
    assert_eq!(get("blocking on the service's serial executor"), "err: 2");
    assert_eq!(get("OnSerial from elsewhere"), "ok: serial y");
    assert_eq!(get("concurrent ok"), "1000");
    assert_eq!(get("filter starts = ends"), "true true");
    assert_eq!(get("chain"), "ok: abc|", "only the passed key goes along");
    assert_eq!(s.in_flight.len(), 100);
    assert!(
        s.in_flight.iter().all(|st| *st == RpcStatus::CLI_NOT_READY),
        "{:?}",
        s.in_flight
    );
    assert!(
        s.shutdown_took < Duration::from_secs(10),
        "shutdown took {:?}",
        s.shutdown_took
    );
}

/// Runs [`Server`] and the scenario's client in one runtime for 3 s, with `cfg` (which
/// must declare the executors `refusing` (queue_threshold 0) and `serial`), every call in
/// `format` (`None`: the types' default, postcard).
pub fn run_scenario(cfg: &str, format: Option<&str>) -> Scenario {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    std::fs::write(&path, cfg).unwrap();
    let results = Results::default();
    let seen = Arc::new(AtomicUsize::new(0));
    let kept = Arc::new(Mutex::new(Vec::new()));
    let in_flight = Arc::new(Mutex::new(Vec::new()));
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_secs(3)),
        ..Default::default()
    });
    runtime.builtin_plugin(Box::new(PassTraceId));
    runtime.register_module(Box::new(Server {
        seen: seen.clone(),
        kept: kept.clone(),
    }));
    runtime.register_module(Box::new(Client {
        results: results.clone(),
        clients: None,
        rpc: None,
        worker: None,
        in_flight: in_flight.clone(),
        seen,
        format: format.map(str::to_owned),
        filter_counts: Default::default(),
    }));
    let begin = Instant::now();
    runtime.run().unwrap();
    let shutdown_took = begin.elapsed().saturating_sub(Duration::from_secs(3));
    let answered = in_flight.lock().unwrap().clone();
    // The replies the service still holds answer nobody: late answers are dropped.
    kept.lock().unwrap().clear();
    assert_eq!(in_flight.lock().unwrap().len(), answered.len());
    let results = results.lock().unwrap().clone();
    Scenario {
        results,
        in_flight: answered,
        shutdown_took,
    }
}

/// An RPC backend of type `slow` for the deadline tests: answers each call with its
/// request (a `Req` reads as a `Rsp`), from a thread of its own: `Busy` after 600 ms,
/// everything else after 300 ms; `Expired` with `TIMEOUT`, as a backend whose own timer
/// gives the call up.
pub struct SlowBackend;

impl RpcBackend for SlowBackend {
    fn type_name(&self) -> &str {
        "slow"
    }
    fn init(&self, _: &BackendOptions, _: ServiceHost) -> Result<(), Error> {
        Ok(())
    }
    fn start(&self) -> Result<(), Error> {
        Ok(())
    }
    fn shutdown(&self) {}
    fn invoke(&self, call: BackendCall, reply: BackendReply) {
        let after = if call.func == f("Busy") { 600 } else { 300 };
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(after));
            reply.send(if call.func == f("Expired") {
                BackendAnswer::fail(RpcStatus::TIMEOUT, "the backend's own timer")
            } else {
                BackendAnswer::ok(call.body)
            });
        });
    }
}

/// Registers [`SlowBackend`] (type `slow`).
pub struct SlowBackendPlugin;

impl Plugin for SlowBackendPlugin {
    fn name(&self) -> &str {
        "slow_backend"
    }
    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _: &PluginOptions,
    ) -> Result<(), Error> {
        registrar.register_rpc_backend(SlowBackend)
    }
}

/// Runs `module` in this process for `running` with [`SlowBackend`] as the backend of every
/// client function (see [`crate::run_in_process`]); returns the log.
pub fn run_with_slow_backend(running: Duration, module: impl Module + 'static) -> String {
    crate::run_in_process(
        "  rpc:\n    backends:\n      - type: slow\n    clients_options:\n      - func_name: \".*\"\n        enable_backends: [slow]\n",
        running,
        |runtime| {
            runtime.builtin_plugin(Box::new(SlowBackendPlugin));
            runtime.register_module(Box::new(module));
        },
    )
}
