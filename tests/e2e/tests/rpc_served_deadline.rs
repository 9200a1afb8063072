//! A call another process makes through a backend is held to the caller's deadline where
//! the wire carries one (http's `Timeout`), and not cut off where it carries none (zenoh's
//! layout, as AimRT's): the service's context then has no timeout (AimRT's 0) and its
//! answer after 5 s reaches the caller. Before, the runtime gave such a call its own 5 s
//! default, so a service that took longer was answered `TIMEOUT` whatever the caller was
//! willing to wait.

use std::sync::{mpsc, Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use aimrt_e2e::rpc_modules::{f, Req, Rsp};
use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall, BackendReply, Reply};
use aimrt_plugin_api::{
    meta_keys, BackendOptions, CoreRef, Error, Module, ModuleInfo, Plugin, PluginOptions,
    Registrar, RpcBackend, RpcStatus, ServiceHost,
};

/// How long `Long` takes: past the runtime's 5 s default.
const LONG: Duration = Duration::from_millis(5300);

/// What each call the backend brought in got: (label, status code, body, after).
type Answers = Arc<Mutex<Vec<(&'static str, u32, String, Duration)>>>;

/// Brings calls in once the runtime runs, as a transport would from another process: two
/// of `Long`, one without a deadline and one with 300 ms, and one of `Keep` without a
/// deadline.
struct Inbound {
    host: OnceLock<ServiceHost>,
    answers: Answers,
}

impl Inbound {
    fn bring_in(&self, label: &'static str, method: &str, timeout: Option<Duration>) {
        let host = *self.host.get().expect("initialized");
        let method = method.to_owned();
        let answers = self.answers.clone();
        std::thread::spawn(move || {
            let mut call = BackendCall::new(f(&method));
            call.set_meta(meta_keys::SERIALIZATION_TYPE, "json");
            call.body = br#"{"text":"x"}"#.to_vec();
            call.timeout = timeout;
            // Modules start after the backends: until then the runtime answers 1009.
            let tried = Instant::now();
            loop {
                let (tx, rx) = mpsc::channel();
                let sent = Instant::now();
                host.call(&call, move |a| {
                    let _ = tx.send(a);
                });
                let a = rx
                    .recv_timeout(Duration::from_secs(20))
                    .unwrap_or(BackendAnswer::fail(RpcStatus::CLI_UNKNOWN, "none in 20 s"));
                if a.status == RpcStatus::SVR_NOT_READY && tried.elapsed() < Duration::from_secs(5)
                {
                    std::thread::sleep(Duration::from_millis(20));
                    continue;
                }
                let body = String::from_utf8_lossy(&a.body).into_owned();
                answers
                    .lock()
                    .unwrap()
                    .push((label, a.status.code(), body, sent.elapsed()));
                return;
            }
        });
    }
}

impl RpcBackend for Inbound {
    fn type_name(&self) -> &str {
        "inbound"
    }
    fn init(&self, _: &BackendOptions, host: ServiceHost) -> Result<(), Error> {
        let _ = self.host.set(host);
        Ok(())
    }
    fn start(&self) -> Result<(), Error> {
        self.bring_in("no deadline", "Long", None);
        self.bring_in("300 ms", "Long", Some(Duration::from_millis(300)));
        self.bring_in("kept", "Keep", None);
        Ok(())
    }
    fn shutdown(&self) {}
    fn invoke(&self, _: BackendCall, reply: BackendReply) {
        reply.send(BackendAnswer::fail(RpcStatus::CLI_NOT_READY, "serves only"));
    }
}

struct InboundPlugin(Answers);

impl Plugin for InboundPlugin {
    fn name(&self) -> &str {
        "inbound_backend"
    }
    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _: &PluginOptions,
    ) -> Result<(), Error> {
        registrar.register_rpc_backend(Inbound {
            host: OnceLock::new(),
            answers: self.0.clone(),
        })
    }
}

/// Serves `Long`: answers, after [`LONG`], the timeout its context showed; and `Keep`,
/// whose replies it keeps unanswered.
struct Patient(Arc<Mutex<Vec<Reply<Rsp>>>>);

impl Module for Patient {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Patient")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let rpc = core.rpc()?;
        rpc.serve_then(&f("Long"), |ctx, _: Arc<Req>, reply: Reply<Rsp>| {
            let text = format!("{:?}", ctx.timeout());
            std::thread::spawn(move || {
                std::thread::sleep(LONG);
                reply.send(Ok(Rsp { text }));
            });
        })?;
        let kept = self.0.clone();
        rpc.serve_then(&f("Keep"), move |_, _: Arc<Req>, reply: Reply<Rsp>| {
            kept.lock().unwrap().push(reply)
        })
    }
}

#[test]
fn a_call_brought_in_without_a_deadline_is_not_cut_off_and_one_with_a_deadline_is() {
    let answers = Answers::default();
    let kept = Arc::new(Mutex::new(Vec::new()));
    let log = aimrt_e2e::run_in_process(
        "  rpc:\n    backends:\n      - type: inbound\n    servers_options:\n      - func_name: \".*\"\n        enable_backends: [inbound]\n",
        LONG + Duration::from_millis(1500),
        |runtime| {
            runtime.builtin_plugin(Box::new(InboundPlugin(answers.clone())));
            runtime.register_module(Box::new(Patient(kept.clone())));
        },
    );

    // The calls' threads record their answers.
    let waited = Instant::now();
    while answers.lock().unwrap().len() < 3 && waited.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(10));
    }
    let answers = answers.lock().unwrap();
    let of = |label: &str| {
        answers
            .iter()
            .find(|a| a.0 == label)
            .unwrap_or_else(|| panic!("no answer for the {label} call: {answers:?}"))
            .clone()
    };
    let (_, status, body, after) = of("no deadline");
    assert_eq!(
        (status, body.as_str()),
        (0, r#"{"text":"None"}"#),
        "{answers:?}"
    );
    assert!(after >= LONG, "{answers:?}");
    let (_, status, _, after) = of("300 ms");
    assert_eq!(status, RpcStatus::TIMEOUT.code(), "{answers:?}");
    assert!(after < LONG, "{answers:?}");
    // Without a deadline a call is still answered when the runtime shuts down.
    let (_, status, _, _) = of("kept");
    assert_eq!(status, RpcStatus::SVR_NOT_READY.code(), "{answers:?}");
    // (Calls brought in before the modules started were answered 1009 and tried again:
    // the counts of calls and errors include them.)
    assert!(
        log.contains(" (1 timed out), 1 late answers dropped"),
        "{log}"
    );
}
