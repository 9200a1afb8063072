//! The levels a library's `tracing` lets through: the most verbose of its loggers, so a
//! call site below every logger's level (a dependency's `trace!` on a hot path) is
//! skipped without asking the runtime. Its own process: the levels are process-wide.

use std::sync::mpsc::{channel, Sender};
use std::time::Duration;

use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_runtime::{Runtime, RuntimeOptions};
use tracing::level_filters::LevelFilter;

/// Reports the level filter `tracing` applies while it initializes, and logs a debug line.
struct Probe(Sender<LevelFilter>);

impl Module for Probe {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Probe")
    }
    fn initialize(&mut self, _: CoreRef) -> Result<(), Error> {
        tracing::debug!("probe debug line");
        let _ = self.0.send(LevelFilter::current());
        Ok(())
    }
}

/// Runs a runtime whose core logs at `core` and whose module at `module`, logging to
/// `log`; returns the filter the module saw.
fn run(core: &str, module: &str, log: &std::path::Path) -> LevelFilter {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    std::fs::write(
        &path,
        format!(
            "aimrt:\n  log:\n    core_lvl: {core}\n    backends:\n      - type: rotate_file\n        options:\n          path: {}\n          filename: {}\n  module:\n    modules:\n      - name: Probe\n        log_lvl: {module}\n",
            log.parent().unwrap().display(),
            log.file_name().unwrap().to_string_lossy()
        ),
    )
    .unwrap();
    let (tx, rx) = channel();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_millis(50)),
        ..Default::default()
    });
    runtime.register_module(Box::new(Probe(tx)));
    runtime.run().unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap()
}

#[test]
fn call_sites_below_every_loggers_level_are_skipped_and_a_more_verbose_logger_opens_them() {
    let dir = tempfile::tempdir().unwrap();
    let quiet = dir.path().join("quiet.log");
    // Every logger at Warn: debug and info call sites are off for `tracing` itself.
    assert_eq!(run("Warn", "Warn", &quiet), LevelFilter::WARN);
    let text = std::fs::read_to_string(&quiet).unwrap_or_default();
    assert!(!text.contains("probe debug line"), "{text}");
    // A module at Debug: its debug lines pass again.
    let verbose = dir.path().join("verbose.log");
    assert_eq!(run("Warn", "Debug", &verbose), LevelFilter::DEBUG);
    let text = std::fs::read_to_string(&verbose).unwrap();
    assert!(text.contains("probe debug line"), "{text}");
}
