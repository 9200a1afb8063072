//! A backend that gives a call up with its own `TIMEOUT` after the call's deadline (its
//! timer fires a moment after the runtime's, or it forgets the call's record) repeats the
//! timeout the runtime has answered already: the shutdown line counts the call as timed
//! out, not that answer as a late one. An answer after the deadline is still counted.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::rpc_modules::{f, req, run_with_slow_backend, show, Req, Rsp};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo, RpcContext};

/// Calls `Expired` and `Late` with 100 ms deadlines at start; the backend answers both
/// after 300 ms, `Expired` with its own `TIMEOUT`.
struct TwoLate {
    seen: Arc<Mutex<Vec<String>>>,
    clients: Option<[aimrt_plugin_api::RpcClient<Req, Rsp>; 2]>,
}

impl Module for TwoLate {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("TwoLate")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let rpc = core.rpc()?;
        self.clients = Some([rpc.client(&f("Expired"))?, rpc.client(&f("Late"))?]);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        for client in self.clients.take().expect("initialized") {
            let mut ctx = RpcContext::client();
            ctx.set_timeout(Some(Duration::from_millis(100)));
            let seen = self.seen.clone();
            client.call_then(ctx, req("x"), move |_, r| {
                seen.lock().unwrap().push(show(&r));
            });
        }
        Ok(())
    }
}

#[test]
fn a_backends_own_timeout_after_the_deadline_is_not_a_late_answer() {
    let seen = Arc::new(Mutex::new(Vec::new()));
    let log = run_with_slow_backend(
        Duration::from_millis(1000),
        TwoLate {
            seen: seen.clone(),
            clients: None,
        },
    );

    assert_eq!(*seen.lock().unwrap(), ["err: 2", "err: 2"]);
    // Both timed out; only `Late`'s answer is a late one.
    assert!(
        log.contains("Module RPC: 2 calls, 2 answered with an error status (2 timed out), 1 late answers dropped"),
        "{log}"
    );
}
