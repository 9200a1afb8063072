//! Module RPC over the `local` backend, in process: every call style, every way a call can
//! end (response, service status, panic, dropped reply, deadline, unknown function, used
//! context, refusing executor, blocking where it could never be answered, before start,
//! shutdown with calls in flight), 1 000 concurrent calls, and the zero-copy same-library
//! path. One test, because runtimes in one process run one after another.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use aimrt_e2e::lib;
use aimrt_plugin_api::co::block_on;
use aimrt_plugin_api::rpc::{Reply, RpcClient, RpcRef};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo, RpcContext, RpcStatus};
use aimrt_runtime::{Runtime, RuntimeOptions};

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Req {
    text: String,
}
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Rsp {
    text: String,
}
aimrt_plugin_api::serde_message!(Req, "test.Req");
aimrt_plugin_api::serde_message!(Rsp, "test.Rsp");

fn f(method: &str) -> String {
    format!("serde:/test.Svc/{method}")
}

type Results = Arc<Mutex<BTreeMap<String, String>>>;

/// Serves every test method.
struct Server {
    /// The address of the last request `Echo` saw (same library: the caller's own object).
    seen: Arc<AtomicUsize>,
    /// Replies `Never` keeps and never sends.
    kept: Arc<Mutex<Vec<Reply<Rsp>>>>,
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
        rpc.serve_sync(&f("Panic"), |_: &RpcContext, _: &Req| -> Result<Rsp, RpcStatus> {
            panic!("the handler gave up")
        })?;
        rpc.serve_sync(&f("Status"), |_: &RpcContext, _: &Req| -> Result<Rsp, RpcStatus> {
            Err(RpcStatus::SVR_NOT_IMPLEMENTED)
        })?;
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
}

fn req(text: &str) -> Req {
    Req { text: text.into() }
}

fn show(r: &Result<Arc<Rsp>, RpcStatus>) -> String {
    match r {
        Ok(rsp) => format!("ok: {}", rsp.text),
        Err(s) => format!("err: {}", s.code()),
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
            "Echo", "Slow", "SlowInline", "Panic", "Status", "Drop", "Never", "Async", "Refused", "OnSerial",
            "Missing",
        ] {
            all.insert(m, rpc.client::<Req, Rsp>(&f(m))?);
        }
        assert!(rpc.client::<Req, Rsp>(&f("Echo")).is_err(), "twice: refused");
        // Before start: answered at once, no hang.
        let early = all["Echo"].call(&mut RpcContext::client(), req("early"));
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
        results.lock().unwrap().insert("register in start".into(), late);
        self.worker = Some(std::thread::spawn(move || {
            let put = |k: &str, v: String| {
                results.lock().unwrap().insert(k.into(), v);
            };
            let c = |m: &str| all[m].clone();
            // Blocking, with the zero-copy check.
            let sent = Arc::new(req("hi"));
            let ptr = Arc::as_ptr(&sent) as usize;
            put("sync", show(&c("Echo").call(&mut RpcContext::client(), sent)));
            put("same object", (seen.load(Ordering::SeqCst) == ptr).to_string());
            // Future.
            let echo = c("Echo");
            let mut ctx = RpcContext::client();
            put("future", show(&block_on(echo.call_async(&mut ctx, req("f")))));
            put("function name in ctx", ctx.meta("aimrt-function_name").unwrap_or("").into());
            // Used context.
            put("used ctx", show(&echo.call(&mut ctx, req("again"))));
            // Callback.
            let (tx, rx) = mpsc::channel();
            echo.call_then(RpcContext::client(), req("cb"), move |_, r| {
                tx.send(show(&r)).unwrap()
            });
            put("callback", rx.recv_timeout(Duration::from_secs(10)).unwrap());
            // Timeout: the deadline thread answers.
            let mut ctx = RpcContext::client();
            ctx.set_timeout(Some(Duration::from_millis(100)));
            let begin = Instant::now();
            put("slow", show(&c("Slow").call(&mut ctx, req("s"))));
            put("slow took < 250 ms", (begin.elapsed() < Duration::from_millis(250)).to_string());
            // Inline: the caller's thread runs the handler, then sees the timeout.
            let mut ctx = RpcContext::client();
            ctx.set_timeout(Some(Duration::from_millis(100)));
            put("slow inline", show(&c("SlowInline").call(&mut ctx, req("s"))));
            for m in ["Panic", "Status", "Drop", "Missing", "Async", "Refused"] {
                put(m, show(&c(m).call(&mut RpcContext::client(), req(m))));
            }
            // Blocking on the serial executor the service runs on: refused at once.
            let on_serial = c("OnSerial");
            let (tx, rx) = mpsc::channel();
            serial
                .execute(move || {
                    let begin = Instant::now();
                    let r = on_serial.call(&mut RpcContext::client(), req("x"));
                    tx.send((show(&r), begin.elapsed())).unwrap();
                })
                .unwrap();
            let (r, took) = rx.recv_timeout(Duration::from_secs(10)).unwrap();
            put("blocking on the service's serial executor", r);
            put("refused at once", (took < Duration::from_millis(50)).to_string());
            put(
                "OnSerial from elsewhere",
                show(&c("OnSerial").call(&mut RpcContext::client(), req("y"))),
            );
            // 1 000 concurrent calls, all answered.
            let (tx, rx) = mpsc::channel();
            for i in 0..1000 {
                let tx = tx.clone();
                echo.call_then(RpcContext::client(), req(&i.to_string()), move |_, r| {
                    let _ = tx.send(r.is_ok());
                });
            }
            let ok = (0..1000)
                .filter(|_| rx.recv_timeout(Duration::from_secs(20)).unwrap())
                .count();
            put("concurrent ok", ok.to_string());
            // 100 calls that will still wait at shutdown.
            for _ in 0..100 {
                let mut ctx = RpcContext::client();
                ctx.set_timeout(Some(Duration::from_secs(60)));
                let in_flight = in_flight.clone();
                c("Never").call_then(ctx, req("n"), move |_, r| {
                    in_flight.lock().unwrap().push(r.err().unwrap_or(RpcStatus::OK))
                });
            }
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

#[test]
fn local_calls_end_exactly_once_in_every_way() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    let cfg = format!(
        r#"aimrt:
  plugin:
    plugins:
      - name: std_executors
        path: {}
  executor:
    executors:
      - name: refusing
        type: simple_thread
        options:
          queue_threshold: 0
      - name: serial
        type: simple_thread
  rpc:
    backends:
      - type: local
    clients_options:
      - func_name: "(.*)"
        enable_backends: [local]
    servers_options:
      - func_name: "(.*)"
        enable_backends: [local]
"#,
        lib("libaimrt_std_executors_plugin.so").display()
    );
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
    }));
    runtime.run().unwrap();
    let r = results.lock().unwrap();
    let get = |k: &str| r.get(k).map(String::as_str).unwrap_or("<missing>");
    assert_eq!(get("done"), "true", "{r:#?}");
    assert_eq!(get("before start"), "err: 2011");
    assert!(get("register in start").contains("initialize only"), "{r:#?}");
    assert_eq!(get("sync"), "ok: echo hi via local from Client");
    assert_eq!(get("same object"), "true", "same library: the request is not copied");
    assert_eq!(get("future"), "ok: echo f via local from Client");
    assert_eq!(get("function name in ctx"), "serde:/test.Svc/Echo");
    assert_eq!(get("used ctx"), "err: 2003");
    assert_eq!(get("callback"), "ok: echo cb via local from Client");
    assert_eq!(get("slow"), "err: 2");
    assert_eq!(get("slow took < 250 ms"), "true");
    assert_eq!(get("slow inline"), "err: 2");
    assert_eq!(get("Panic"), "err: 1008");
    assert_eq!(get("Status"), "err: 1002");
    assert_eq!(get("Drop"), "err: 1008");
    assert_eq!(get("Missing"), "err: 1003");
    assert_eq!(get("Async"), "ok: async Async");
    assert_eq!(get("Refused"), "err: 1009");
    assert_eq!(get("blocking on the service's serial executor"), "err: 2002");
    assert_eq!(get("refused at once"), "true");
    assert_eq!(get("OnSerial from elsewhere"), "ok: serial y");
    assert_eq!(get("concurrent ok"), "1000");
    // The 100 calls in flight at shutdown were answered "not ready" before run returned;
    // the replies the service still holds answer nobody.
    let answered = in_flight.lock().unwrap();
    assert_eq!(answered.len(), 100);
    assert!(answered.iter().all(|s| *s == RpcStatus::CLI_NOT_READY), "{answered:?}");
    drop(answered);
    kept.lock().unwrap().clear();
    assert_eq!(in_flight.lock().unwrap().len(), 100, "late answers are dropped");
}
