//! Scenario 5: what the C ABI costs. The standard executors are loaded from their shared
//! library (`libaimrt_std_executors_plugin.so`) by the runtime, exactly as `aimrt_main`
//! loads a plugin, and compared with the same executors linked into this binary.
//!
//! Both sides are built once and reused by every round, so neither has warmer queues.

use std::path::PathBuf;
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::Duration;

use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};
use aimrt_runtime::{Runtime, RuntimeOptions, ShutdownHandle};

use crate::pools::{self, Target};

/// The executors under test, one of each kind on each side.
pub(crate) struct Sides {
    /// `simple_thread` (single worker), linked and from the `.so`.
    pub(crate) simple: [ExecutorRef; 2],
    /// `asio_thread` with 2 threads, linked and from the `.so`.
    pub(crate) asio2: [ExecutorRef; 2],
    linked: Vec<Target>,
    runtime: ShutdownHandle,
    thread: JoinHandle<Result<(), aimrt_runtime::Error>>,
}

/// Hands the executors the runtime built from the `.so` to the harness.
struct Probe(mpsc::Sender<(ExecutorRef, ExecutorRef)>);

impl Module for Probe {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("AbiProbe")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let got = (core.executor("so_simple")?, core.executor("so_asio2")?);
        let _ = self.0.send(got);
        Ok(())
    }
}

/// The plugin library next to this binary (`target/release/`).
fn plugin_path() -> Result<PathBuf, String> {
    let exe = std::env::current_exe().map_err(|e| format!("cannot find this binary: {e}"))?;
    let so = exe
        .parent()
        .map(|d| d.join("libaimrt_std_executors_plugin.so"))
        .ok_or("this binary has no directory")?;
    if so.exists() {
        Ok(so)
    } else {
        Err(format!(
            "{} does not exist; build it with the same profile first: cargo build --release -p aimrt-std-executors-so",
            so.display()
        ))
    }
}

impl Sides {
    /// Starts a runtime that loads the plugin library and builds the `.so` side.
    pub(crate) fn start() -> Result<Sides, String> {
        let so = plugin_path()?;
        let cfg = format!(
            r#"aimrt:
  log:
    core_lvl: Warn
    backends:
      - type: console
  plugin:
    plugins:
      - name: std_executors
        path: {}
  executor:
    executors:
      - name: so_simple
        type: simple_thread
        options:
          queue_threshold: 4294967295
      - name: so_asio2
        type: asio_thread
        options:
          thread_num: 2
"#,
            so.display()
        );
        let path =
            std::env::temp_dir().join(format!("aimrt-bench-abi-{}.yaml", std::process::id()));
        std::fs::write(&path, cfg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        let (tx, rx) = mpsc::channel();
        let mut runtime = Runtime::new(RuntimeOptions {
            cfg_file_path: Some(path.clone()),
            ..Default::default()
        });
        runtime.register_module(Box::new(Probe(tx)));
        let handle = runtime.shutdown_handle();
        let thread = std::thread::spawn(move || runtime.run());
        let got = rx.recv_timeout(Duration::from_secs(30));
        let _ = std::fs::remove_file(&path);
        let (so_simple, so_asio2) = match got {
            Ok(g) => g,
            Err(_) => {
                handle.request();
                return Err(match thread.join() {
                    Ok(Err(e)) => format!("the runtime failed: {e}"),
                    _ => "the runtime did not build the executors within 30 s".to_owned(),
                });
            }
        };
        let linked = vec![pools::simple_thread(), pools::asio_thread2()];
        let first = |t: &Target| t.executor().expect("an executor target");
        Ok(Sides {
            simple: [first(&linked[0]), so_simple],
            asio2: [first(&linked[1]), so_asio2],
            linked,
            runtime: handle,
            thread,
        })
    }

    /// Stops both sides, counting what the `.so` executors refused.
    pub(crate) fn stop(self) {
        for e in [self.simple[1], self.asio2[1]] {
            pools::REFUSED.fetch_add(e.stats().refused, std::sync::atomic::Ordering::Relaxed);
        }
        for t in self.linked {
            t.stop();
        }
        self.runtime.request();
        if let Ok(Err(e)) = self.thread.join() {
            eprintln!("aimrt-bench: the runtime of the ABI scenario failed: {e}");
        }
    }
}

/// An executor reused across rounds, as a target that does not shut it down.
pub(crate) fn shared(e: ExecutorRef) -> Target {
    Target::Executor(e, Vec::new())
}
