//! A backend's answer after its call's deadline is a timeout, also while the runtime's
//! deadline thread is busy elsewhere: the caller gets `TIMEOUT`, never the late answer,
//! and the shutdown line counts the call as timed out and its answer as late. Without it,
//! the outcome and the counts depended on which thread got there first (http's own timer
//! fires a moment after the deadline).

use std::sync::{mpsc, Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::rpc_modules::{f, req, run_with_slow_backend, show, Req, Rsp};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo, RpcContext};

/// What the two calls gave, and the thread `Busy`'s timeout answer ran on.
#[derive(Debug, Default)]
struct Seen {
    busy: String,
    busy_thread: String,
    late: String,
}

/// Calls `Busy` (50 ms) and `Late` (100 ms) at start. `Busy`'s timeout answer runs on the
/// deadline thread (no `timeout_executor`) and holds it until `Late` is answered, so
/// `Late`'s deadline passes unwatched and its answer comes 200 ms after it.
struct Caller {
    seen: Arc<Mutex<Seen>>,
    clients: Option<[aimrt_plugin_api::RpcClient<Req, Rsp>; 2]>,
}

impl Module for Caller {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Caller")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let rpc = core.rpc()?;
        self.clients = Some([rpc.client(&f("Busy"))?, rpc.client(&f("Late"))?]);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let [busy, late] = self.clients.take().expect("initialized");
        let ctx = |ms| {
            let mut ctx = RpcContext::client();
            ctx.set_timeout(Some(Duration::from_millis(ms)));
            ctx
        };
        let (late_tx, late_rx) = mpsc::channel();
        let seen = self.seen.clone();
        busy.call_then(ctx(50), req("busy"), move |_, r| {
            let late = late_rx
                .recv_timeout(Duration::from_secs(5))
                .unwrap_or_else(|_| "no answer in 5 s".to_owned());
            let mut s = seen.lock().unwrap();
            s.busy = show(&r);
            s.busy_thread = std::thread::current().name().unwrap_or("").to_owned();
            s.late = late;
        });
        late.call_then(ctx(100), req("late"), move |_, r| {
            let _ = late_tx.send(show(&r));
        });
        Ok(())
    }
}

#[test]
fn a_backends_answer_after_the_deadline_is_a_timeout_whoever_comes_first() {
    let seen = Arc::new(Mutex::new(Seen::default()));
    let log = run_with_slow_backend(
        Duration::from_millis(1500),
        Caller {
            seen: seen.clone(),
            clients: None,
        },
    );

    let seen = seen.lock().unwrap();
    assert_eq!(seen.busy, "err: 2", "{seen:?}");
    assert!(
        seen.busy_thread.contains("deadline"),
        "Busy's timeout ran on the deadline thread: {seen:?}"
    );
    assert_eq!(
        seen.late, "err: 2",
        "an answer after the deadline: {seen:?}"
    );
    assert!(
        log.contains("Module RPC: 2 calls, 2 answered with an error status (2 timed out), 2 late answers dropped"),
        "{log}"
    );
}
