//! A module's own calls through a plugin backend still go out while it shuts down, as in
//! AimRT (whose RPC backends stop after the modules): a module that tells a remote
//! service it is leaving, in its `shutdown`, gets that service's answer, not
//! `CLI_NOT_READY`. Calls still waiting when the modules have shut down are answered
//! `CLI_NOT_READY`.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::rpc_modules::{f, req, run_with_slow_backend, show, Req, Rsp};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo, RpcClient, RpcContext};

/// Calls `Echo` through the `slow` backend (answered after 300 ms) in its `shutdown`,
/// once blocking and once with a callback that is still waiting when `shutdown` returns.
struct CallsInShutdown {
    seen: Arc<Mutex<Vec<String>>>,
    client: Option<RpcClient<Req, Rsp>>,
}

impl Module for CallsInShutdown {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("CallsInShutdown")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        self.client = Some(core.rpc()?.client(&f("Echo"))?);
        Ok(())
    }
    fn shutdown(&mut self) {
        let client = self.client.take().expect("initialized");
        let mut ctx = RpcContext::client();
        ctx.set_timeout(Some(Duration::from_secs(2)));
        let blocking = show(&client.call(&mut ctx, req("bye")));
        self.seen
            .lock()
            .unwrap()
            .push(format!("blocking {blocking}"));
        let mut ctx = RpcContext::client();
        ctx.set_timeout(Some(Duration::from_secs(2)));
        let seen = self.seen.clone();
        client.call_then(ctx, req("later"), move |_, r| {
            seen.lock().unwrap().push(format!("waiting {}", show(&r)));
        });
    }
}

#[test]
fn a_module_calls_through_a_backend_in_its_shutdown() {
    let seen = Arc::new(Mutex::new(Vec::new()));
    let log = run_with_slow_backend(
        Duration::from_millis(300),
        CallsInShutdown {
            seen: seen.clone(),
            client: None,
        },
    );

    assert_eq!(
        *seen.lock().unwrap(),
        ["blocking ok: bye", "waiting err: 2011"],
        "{log}"
    );
    assert!(
        log.contains("Module RPC: 2 calls, 1 answered with an error status (0 timed out), 0 late answers dropped"),
        "{log}"
    );
}
