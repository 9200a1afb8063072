//! The runtime as a library, in this process: it does not link std_executors, so
//! `simple_thread` exists only when the plugin is loaded from its shared library.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::lib;
use aimrt_plugin_api::{
    CoreRef, Error, ExecuteError, Executor, ExecutorRef, Module, ModuleInfo, Plugin, PluginOptions,
    Registrar, Task,
};
use aimrt_runtime::{Runtime, RuntimeOptions};

fn run(cfg: &str) -> Result<(), aimrt_runtime::Error> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    std::fs::write(&path, cfg).unwrap();
    Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_millis(200)),
        ..Default::default()
    })
    .run()
}

#[test]
fn std_executors_load_from_their_shared_library() {
    let so = lib("libaimrt_std_executors_plugin.so");
    let with_plugin = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: std_executors\n        path: {}\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n",
        so.display()
    );
    run(&with_plugin).expect("simple_thread from the .so");

    let without =
        "aimrt:\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n";
    let err = run(without).unwrap_err().to_string();
    assert!(
        err.contains("unknown executor type 'simple_thread'"),
        "{err}"
    );
}

/// An executor that runs each task at once and says when it is freed.
struct Inline {
    freed: Arc<AtomicBool>,
}

impl Drop for Inline {
    fn drop(&mut self) {
        self.freed.store(true, Ordering::SeqCst);
    }
}

impl Executor for Inline {
    fn type_name(&self) -> &str {
        "inline_probe"
    }
    fn name(&self) -> &str {
        "p"
    }
    fn thread_safe(&self) -> bool {
        false
    }
    fn is_in_current_executor(&self) -> bool {
        false
    }
    fn execute(&self, task: Task) -> Result<(), ExecuteError> {
        task.run("p");
        Ok(())
    }
    fn shutdown(&self) {}
}

/// Registers `inline_probe`, whose executors set `freed` when dropped.
struct InlinePlugin {
    freed: Arc<AtomicBool>,
}

impl Plugin for InlinePlugin {
    fn name(&self) -> &str {
        "inline_probe_plugin"
    }
    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        _options: &PluginOptions,
    ) -> Result<(), Error> {
        let freed = self.freed.clone();
        registrar.register_executor_type("inline_probe", &[], move |_| {
            Ok(Arc::new(Inline {
                freed: freed.clone(),
            }))
        })
    }
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
struct Note(u64);
aimrt_plugin_api::serde_message!(Note, "test.Note");

/// What [`Keeper`] keeps for after the runtime's end.
#[derive(Default)]
struct Kept {
    executors: Vec<ExecutorRef>,
    core: Option<CoreRef>,
    publisher: Option<aimrt_plugin_api::channel::Publisher<Note>>,
}

/// Keeps the handles of executors `w` and `p`, its core and a publisher.
struct Keeper {
    kept: Arc<Mutex<Kept>>,
}

impl Module for Keeper {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Keeper")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let w = core.executor("w")?;
        w.execute(|| {})?;
        let mut kept = self.kept.lock().unwrap();
        kept.executors = vec![w, core.executor("p")?];
        kept.publisher = Some(core.channel()?.publisher::<Note>("/kept")?);
        kept.core = Some(core);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        Ok(())
    }
    fn shutdown(&mut self) {}
}

/// A handle kept past the runtime's end (a thread the module did not join, an app that
/// holds one after `run`) reaches a shut-down executor, never freed memory: the runtime
/// never frees an executor. Before, it freed them after shutdown, and such a call read
/// freed memory (AddressSanitizer: heap-use-after-free in `stats`). A kept core and
/// publisher are refused too (under AddressSanitizer none of it reads freed memory:
/// docs/fuzzing.md).
#[test]
fn an_executor_handle_kept_past_the_runtimes_end_is_refused_not_dangling() {
    let freed = Arc::new(AtomicBool::new(false));
    let kept = Arc::new(Mutex::new(Kept::default()));
    let cfg = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: std_executors\n        path: {}\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n      - name: p\n        type: inline_probe\n  channel:\n    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \"/kept\"\n        enable_backends: [local]\n",
        lib("libaimrt_std_executors_plugin.so").display()
    );
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_yaml: Some(cfg),
        running_duration: Some(Duration::from_millis(50)),
        ..Default::default()
    });
    runtime.builtin_plugin(Box::new(InlinePlugin {
        freed: freed.clone(),
    }));
    runtime.register_module(Box::new(Keeper { kept: kept.clone() }));
    runtime.run().expect("the run");

    assert!(
        !freed.load(Ordering::SeqCst),
        "the runtime freed an executor a module may still hold"
    );
    let kept = kept.lock().unwrap();
    let (w, p) = (kept.executors[0], kept.executors[1]);
    assert_eq!((w.name(), w.type_name()), ("w", "simple_thread"));
    assert_eq!(p.name(), "p");
    let err = w.execute(|| {}).unwrap_err().to_string();
    assert!(err.contains("the executor is shut down"), "{err}");
    let stats = w.stats();
    assert_eq!((stats.run, stats.refused), (1, 1), "{stats:?}");

    let core = kept.core.expect("the kept core");
    let again = core.executor("w").expect("w through the kept core");
    assert!(again.execute(|| {}).is_err());
    let publisher = kept.publisher.as_ref().expect("the kept publisher");
    let err = publisher.publish(Note(1)).unwrap_err().to_string();
    assert!(err.contains("after the channel shut down"), "{err}");
}
