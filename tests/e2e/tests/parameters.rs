//! Module parameters (ABI 1.6, AimRT's `ParameterHandle`): each module's own store, in
//! every phase; AimRT's parameter example under the real `aimrt_main`; and a module
//! library of ABI 1.5, from before parameters, still loads and runs.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::{repo_config, run_main};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo, ParameterRef};
use aimrt_runtime::{Runtime, RuntimeOptions};

type Seen = Arc<Mutex<Vec<String>>>;

/// Sets `key` to its own name in initialize, reads it (and what else it holds) in start.
struct Holder {
    name: &'static str,
    params: Option<ParameterRef>,
    seen: Seen,
}

impl Module for Holder {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new(self.name)
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let params = core.parameter()?;
        params.set("key", self.name);
        params.set(&format!("only-{}", self.name), "");
        self.params = Some(params);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let p = self.params.expect("initialized");
        let mut seen = self.seen.lock().unwrap();
        seen.push(format!(
            "{}: key={:?} keys={:?}",
            self.name,
            p.get("key"),
            p.keys()
        ));
        seen.push(format!(
            "{}: removed={} again={}",
            self.name,
            p.remove("key"),
            p.remove("key")
        ));
        seen.push(format!(
            "{}: after={:?} missing={:?}",
            self.name,
            p.get("key"),
            p.get("nope")
        ));
        Ok(())
    }
}

#[test]
fn each_module_has_its_own_parameters() {
    let seen = Seen::default();
    let mut runtime = Runtime::new(RuntimeOptions {
        running_duration: Some(Duration::from_millis(50)),
        ..Default::default()
    });
    for name in ["A", "B"] {
        runtime.register_module(Box::new(Holder {
            name,
            params: None,
            seen: seen.clone(),
        }));
    }
    runtime.run().expect("runs");
    assert_eq!(
        *seen.lock().unwrap(),
        [
            "A: key=Some(\"A\") keys=[\"key\", \"only-A\"]",
            "A: removed=true again=false",
            "A: after=None missing=None",
            "B: key=Some(\"B\") keys=[\"key\", \"only-B\"]",
            "B: removed=true again=false",
            "B: after=None missing=None",
        ]
    );
}

#[test]
fn the_parameter_example_sets_and_reads_back() {
    let out = run_main(
        Some(&repo_config("parameter")),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=2"],
        Duration::from_secs(60),
    );
    out.assert_exit(0, "the parameter example");
    let sets = out.stdout.matches("]Set parameter, key: 'key-").count();
    assert!(sets >= 2, "{}", out.stdout);
    for n in 1..=sets {
        for line in [
            format!("]Set parameter, key: 'key-{n}', val: 'val-{n}'"),
            format!("]Get parameter, key: 'key-{n}', val: 'val-{n}'"),
        ] {
            assert!(
                out.stdout.contains(&line),
                "no {line:?} in:\n{}",
                out.stdout
            );
        }
    }
    let held = format!("]Parameters held: {sets}\n");
    assert!(
        out.stdout.contains(&held),
        "no {held:?} in:\n{}",
        out.stdout
    );
    assert!(!out.stdout.contains("aimrt.parameter"), "{}", out.stdout);
}

#[test]
fn a_module_library_of_abi_1_5_loads_and_runs_on_this_host() {
    let cfg = format!(
        "aimrt:\n  log:\n    backends:\n      - type: console\n  module:\n    pkgs:\n      - path: {}\n",
        aimrt_e2e::lib("libfixture_abi_1_5.so").display()
    );
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        Duration::from_secs(60),
    );
    out.assert_exit(0, "the ABI 1.5 library");
    for line in ["]ABI 1.5 module initialized", "]ABI 1.5 module started"] {
        assert!(out.stdout.contains(line), "no {line:?} in:\n{}", out.stdout);
    }
}
