//! RPC filters a plugin registers, in process: every way a filter can stop a call (hold
//! it, fail, panic, answer it) is answered exactly once with its status, a failure after
//! passing a call on changes nothing, a server filter's context reaches the service and
//! its observer hears each answer once, and names already taken are refused.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::rpc_modules::{f, req, show, Req, Rsp};
use aimrt_plugin_api::rpc::{CallFilterSide, CallNext, FilterCall};
use aimrt_plugin_api::{
    CoreRef, Error, Module, ModuleInfo, Plugin, PluginOptions, Registrar, RpcContext, RpcStatus,
};
use aimrt_runtime::{Runtime, RuntimeOptions};

/// Client filters that stop calls in each way, a server filter that tags and listens, and
/// the refusals of names taken.
struct StopFilters {
    heard: Arc<AtomicUsize>,
    refusals: mpsc::Sender<String>,
}

impl Plugin for StopFilters {
    fn name(&self) -> &str {
        "stop_filters"
    }
    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _: &PluginOptions,
    ) -> Result<(), Error> {
        let client = CallFilterSide::Client;
        registrar
            .register_rpc_filter("hold", client, |_: &FilterCall<'_>, _: CallNext<'_>| Ok(()))?;
        registrar.register_rpc_filter("fail", client, |_: &FilterCall<'_>, _: CallNext<'_>| {
            Err("not today".to_owned())
        })?;
        registrar.register_rpc_filter(
            "boom",
            client,
            |_: &FilterCall<'_>, _: CallNext<'_>| -> Result<(), String> {
                panic!("a filter panics")
            },
        )?;
        registrar.register_rpc_filter(
            "late",
            client,
            |_: &FilterCall<'_>, next: CallNext<'_>| {
                next.pass()?;
                Err("failed after passing on".to_owned())
            },
        )?;
        registrar.register_rpc_filter(
            "answer",
            client,
            |_: &FilterCall<'_>, next: CallNext<'_>| {
                next.answer(RpcStatus::CLI_INVALID_CONTEXT, "no")
            },
        )?;
        let heard = self.heard.clone();
        registrar.register_rpc_filter(
            "tag",
            CallFilterSide::Server,
            move |call: &FilterCall<'_>, next: CallNext<'_>| {
                assert_eq!(call.module(), "Caller");
                let mut ctx = next.context();
                ctx.set_meta("tagged", "yes");
                let heard = heard.clone();
                next.on_reply(move |reply| {
                    assert!(reply.status().is_ok());
                    heard.fetch_add(1, Ordering::SeqCst);
                })
                .pass_with(&ctx)
            },
        )?;
        let pass = |_: &FilterCall<'_>, next: CallNext<'_>| next.pass();
        for (name, side) in [("hold", client), ("time_cost", CallFilterSide::Server)] {
            let err = registrar.register_rpc_filter(name, side, pass).unwrap_err();
            self.refusals.send(err.to_string()).unwrap();
        }
        // The same name on the other side is another filter.
        registrar.register_rpc_filter("hold", CallFilterSide::Server, pass)?;
        Ok(())
    }
}

const METHODS: [&str; 6] = ["Hold", "Fail", "Boom", "Late", "Answer", "Tagged"];

/// Serves every method (echoing `tagged`) and calls each once from a thread at start.
struct Caller {
    results: Arc<Mutex<Vec<(String, String)>>>,
    clients: Vec<(String, aimrt_plugin_api::rpc::RpcClient<Req, Rsp>)>,
}

impl Module for Caller {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Caller")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let rpc = core.rpc()?;
        for m in METHODS {
            rpc.serve_sync(&f(m), |ctx: &RpcContext, req: &Req| {
                let tagged = ctx.meta("tagged").unwrap_or("no");
                Ok(Rsp {
                    text: format!("{} tagged {tagged}", req.text),
                })
            })?;
            self.clients
                .push((m.to_owned(), rpc.client::<Req, Rsp>(&f(m))?));
        }
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let clients = std::mem::take(&mut self.clients);
        let results = self.results.clone();
        std::thread::spawn(move || {
            for (m, client) in clients {
                let r = client.call(&mut RpcContext::client(), req("x"));
                results.lock().unwrap().push((m, show(&r)));
            }
        });
        Ok(())
    }
}

#[test]
fn every_way_a_filter_stops_a_call_is_answered_once_with_its_status() {
    let cfg = "aimrt:\n  rpc:\n    backends:\n      - type: local\n    clients_options:\n      - func_name: \".*/Hold\"\n        enable_backends: [local]\n        enable_filters: [hold]\n      - func_name: \".*/Fail\"\n        enable_backends: [local]\n        enable_filters: [fail]\n      - func_name: \".*/Boom\"\n        enable_backends: [local]\n        enable_filters: [boom]\n      - func_name: \".*/Late\"\n        enable_backends: [local]\n        enable_filters: [late]\n      - func_name: \".*/Answer\"\n        enable_backends: [local]\n        enable_filters: [answer]\n      - func_name: \".*\"\n        enable_backends: [local]\n    servers_options:\n      - func_name: \".*/Tagged\"\n        enable_backends: [local]\n        enable_filters: [tag]\n      - func_name: \".*\"\n        enable_backends: [local]\n";
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    std::fs::write(&path, cfg).unwrap();
    let heard = Arc::new(AtomicUsize::new(0));
    let (refusals_tx, refusals_rx) = mpsc::channel();
    let results = Arc::new(Mutex::new(Vec::new()));
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_secs(1)),
        ..Default::default()
    });
    runtime.builtin_plugin(Box::new(StopFilters {
        heard: heard.clone(),
        refusals: refusals_tx,
    }));
    runtime.register_module(Box::new(Caller {
        results: results.clone(),
        clients: Vec::new(),
    }));
    runtime.run().unwrap();

    let refusals: Vec<String> = refusals_rx.try_iter().collect();
    assert_eq!(refusals.len(), 2, "{refusals:?}");
    assert!(
        refusals[0].contains("rpc client filter 'hold' is already registered by 'stop_filters'"),
        "{}",
        refusals[0]
    );
    assert!(
        refusals[1].contains("'time_cost' is built into the runtime"),
        "{}",
        refusals[1]
    );

    let results = results.lock().unwrap().clone();
    let expected = [
        ("Hold", "err: 2000"),
        ("Fail", "err: 2000"),
        ("Boom", "err: 2000"),
        ("Late", "ok: x tagged no"),
        ("Answer", "err: 2003"),
        ("Tagged", "ok: x tagged yes"),
    ];
    let expected: Vec<(String, String)> = expected
        .iter()
        .map(|(m, r)| (m.to_string(), r.to_string()))
        .collect();
    assert_eq!(results, expected);
    assert_eq!(heard.load(Ordering::SeqCst), 1);
}
