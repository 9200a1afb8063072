//! Modules registered in code (`Runtime::register_module`): lifecycle, executor lookup,
//! `enable`, and name clashes with each other and with pkg modules. One test, because
//! runtimes in one process run one after another.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::lib;
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_runtime::{Runtime, RuntimeOptions};

type Events = Arc<Mutex<Vec<String>>>;

struct Probe {
    name: &'static str,
    events: Events,
}

impl Probe {
    fn boxed(name: &'static str, events: &Events) -> Box<dyn Module> {
        Box::new(Probe {
            name,
            events: events.clone(),
        })
    }
    fn push(&self, what: &str) {
        self.events
            .lock()
            .unwrap()
            .push(format!("{}:{what}", self.name));
    }
}

impl Module for Probe {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new(self.name)
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        self.push("init");
        let w = core.executor("w")?;
        let (tx, rx) = std::sync::mpsc::channel();
        w.execute(move || tx.send(()).unwrap())?;
        rx.recv_timeout(Duration::from_secs(10))
            .expect("the task ran on the plugin's executor");
        self.push("task");
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        self.push("start");
        Ok(())
    }
    fn shutdown(&mut self) {
        self.push("shutdown");
    }
}

fn run(cfg_tail: &str, modules: Vec<Box<dyn Module>>) -> Result<(), aimrt_runtime::Error> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    let cfg = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: std_executors\n        path: {}\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n{cfg_tail}",
        lib("libaimrt_std_executors_plugin.so").display()
    );
    std::fs::write(&path, cfg).unwrap();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_millis(100)),
        ..Default::default()
    });
    for m in modules {
        runtime.register_module(m);
    }
    runtime.run()
}

#[test]
fn modules_registered_in_code() {
    // Lifecycle in registration order, shutdown in reverse; an executor from a loaded plugin.
    let events = Events::default();
    run(
        "",
        vec![Probe::boxed("A", &events), Probe::boxed("B", &events)],
    )
    .expect("runs");
    assert_eq!(
        *events.lock().unwrap(),
        [
            "A:init",
            "A:task",
            "B:init",
            "B:task",
            "A:start",
            "B:start",
            "B:shutdown",
            "A:shutdown"
        ]
    );

    // `enable: false` in aimrt.module.modules applies to a module registered in code.
    let events = Events::default();
    run(
        "  module:\n    modules:\n      - name: A\n        enable: false\n",
        vec![Probe::boxed("A", &events), Probe::boxed("B", &events)],
    )
    .expect("runs");
    assert!(
        events.lock().unwrap().iter().all(|e| e.starts_with("B:")),
        "{:?}",
        events.lock().unwrap()
    );

    // Two modules with one name.
    let events = Events::default();
    let err = run(
        "",
        vec![Probe::boxed("A", &events), Probe::boxed("A", &events)],
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("module 'A' (registered in code) failed to register")
            && err.contains("module names must be unique"),
        "{err}"
    );
    assert!(events.lock().unwrap().is_empty());

    // A pkg module with the name of a module registered in code.
    let err = run(
        &format!(
            "  module:\n    pkgs:\n      - path: {}\n",
            lib("libdemo_pkg.so").display()
        ),
        vec![Probe::boxed("DemoModule", &events)],
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("module 'DemoModule' is also registered in code"),
        "{err}"
    );
    assert!(events.lock().unwrap().is_empty());
}
