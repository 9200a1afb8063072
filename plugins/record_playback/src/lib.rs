//! `record_playback_plugin`: records channels to MCAP in AimRT's bag layout
//! (`aimrtbag_YYYYMMDD_hhmmss/` with `metadata.yaml` and `.mcap` files), configured with
//! AimRT's options. This version records in `imd` mode; `signal` mode, playback and the
//! control service are not built yet and are refused with a line that says so.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: record_playback_plugin
//!         path: ./target/debug/libaimrt_record_playback_plugin.so
//!         options:
//!           type_support_pkgs: [{path: ./target/debug/libexample_pb_ts.so}]
//!           timer_executor: storage_executor
//!           record_actions:
//!             - name: my_imd_record
//!               options:
//!                 bag_path: ./bag
//!                 mode: imd
//!                 executor: record_thread
//!                 topic_meta_list:
//!                   - {topic_name: test_topic, msg_type: pb:aimrt.protocols.example.ExampleEventMsg}
//! ```
#![deny(unsafe_code)]

mod bag;
mod options;
mod record;

use std::collections::HashSet;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::ffi::formats_of;
use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Plugin, PluginOptions, Registrar};

use crate::options::Options;
use crate::record::{Recorder, Topic};

struct RecordPlaybackPlugin {
    core: Option<CoreRef>,
    timer_executor: String,
    actions: Vec<(Arc<Recorder>, String)>,
    timer_run: Arc<AtomicBool>,
}

/// The plugin, as `libaimrt_record_playback_plugin.so` exports it.
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(RecordPlaybackPlugin {
        core: None,
        timer_executor: String::new(),
        actions: Vec::new(),
        timer_run: Arc::new(AtomicBool::new(false)),
    })
}

impl Plugin for RecordPlaybackPlugin {
    fn name(&self) -> &str {
        "record_playback_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: Options = options.get()?;
        let bad = |message: String| options.invalid(message);
        if !o.playback_actions.is_empty() {
            return Err(bad("playback_actions: playback is not built yet in this version of record_playback_plugin (docs/record-playback.md); remove them to record".into()));
        }
        if !o.service_name.is_empty() {
            tracing::warn!("record_playback_plugin: service_name is accepted, but the control service is not served yet in this version");
        }
        let types = registrar
            .load_type_support_pkgs(&o.type_support_pkgs)
            .map_err(bad)?;
        let core = registrar.core()?;
        let channel = core.channel()?;
        let mut names = HashSet::new();
        for (a, action) in o.record_actions.into_iter().enumerate() {
            let at = |m: String| bad(format!("record_actions[{a}] ('{}'): {m}", action.name));
            if !names.insert(action.name.clone()) {
                return Err(at("the name is used by another record action".into()));
            }
            let mut opts = action.options;
            match opts.mode.to_ascii_lowercase().as_str() {
                "imd" => {}
                "signal" => return Err(at("mode signal is not built yet in this version (docs/record-playback.md); use imd".into())),
                other => return Err(at(format!("mode '{other}' is not imd or signal"))),
            }
            if opts.bag_path.is_empty() {
                return Err(at("bag_path is empty; give the folder bags go into".into()));
            }
            opts.storage_policy.resolve().map_err(&at)?;
            let mut topics = Vec::new();
            let mut pairs = HashSet::new();
            for (j, t) in opts.topic_meta_list.iter().enumerate() {
                let tat = |m: String| at(format!("topic_meta_list[{j}]: {m}"));
                let ts = types.get(&t.msg_type).map_err(&tat)?;
                let formats = formats_of(ts);
                let ser = t
                    .serialization_type
                    .clone()
                    .or_else(|| formats.first().cloned())
                    .unwrap_or_default();
                if !formats.contains(&ser) {
                    return Err(tat(format!(
                        "serialization_type '{ser}' is not a format of '{}'; it has: {}",
                        t.msg_type,
                        formats.join(", ")
                    )));
                }
                if !(t.sample_freq.is_finite() && t.sample_freq >= 0.0) {
                    return Err(tat(format!(
                        "sample_freq {} must be 0 (every message) or a positive rate in Hz",
                        t.sample_freq
                    )));
                }
                if !pairs.insert((t.topic_name.clone(), t.msg_type.clone())) {
                    return Err(tat(format!(
                        "topic '{}' with type '{}' is listed twice",
                        t.topic_name, t.msg_type
                    )));
                }
                topics.push(Topic {
                    name: t.topic_name.clone(),
                    msg_type: t.msg_type.clone(),
                    ts,
                    serialization_type: ser,
                    min_gap: (t.sample_freq > 0.0)
                        .then(|| Duration::from_secs_f64(1.0 / t.sample_freq)),
                    enabled: AtomicBool::new(t.record_enabled),
                    cache_last_msg: t.cache_last_msg,
                });
            }
            let executor = opts.executor.clone();
            let subscriptions: Vec<(String, &'static aimrt_plugin_api::ffi::TypeSupportVtable)> =
                topics.iter().map(|t| (t.name.clone(), t.ts)).collect();
            let recorder = Recorder::open(action.name.clone(), opts, topics).map_err(&at)?;
            for (i, (topic, ts)) in subscriptions.into_iter().enumerate() {
                let r = recorder.clone();
                channel.subscribe_raw(&topic, ts, move |ctx, msg| {
                    r.accept(i, ctx, msg);
                    Ok(())
                })?;
            }
            self.actions.push((recorder, executor));
        }
        if !self.actions.is_empty() && o.timer_executor.is_empty() {
            return Err(bad("timer_executor is required when there are record actions: it runs the timed chunk flushes (msg_write_interval_time)".into()));
        }
        self.timer_executor = o.timer_executor;
        self.core = Some(core);
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(core) = self.core else {
            return Ok(());
        };
        let executor = |name: &str, what: &str| -> Result<ExecutorRef, Error> {
            core.executor(name).map_err(|_| {
                Error::msg(format!(
                    "record_playback_plugin: {what} '{name}' is not an executor of aimrt.executor.executors"
                ))
            })
        };
        for (r, name) in &self.actions {
            let e = executor(name, &format!("the executor of record action '{}'", r.name))?;
            if !e.thread_safe() {
                return Err(Error::msg(format!(
                    "record_playback_plugin: Record executor {name} is not thread safe! (record action '{}'): its tasks may run at once; use a serial one: simple_thread, asio_thread with thread_num 1, or asio_strand",
                    r.name
                )));
            }
            r.start(e);
        }
        if !self.actions.is_empty() {
            let timer = executor(&self.timer_executor, "timer_executor")?;
            if !timer.supports_timer_schedule() {
                return Err(Error::msg(format!(
                    "record_playback_plugin: Executor {} didn't support TimerSchedule! (timer_executor); use asio_thread or time_wheel",
                    self.timer_executor
                )));
            }
            self.timer_run
                .store(true, std::sync::atomic::Ordering::SeqCst);
            for (r, _) in &self.actions {
                let every = Duration::from_millis(r.flush_interval_ms());
                tick(timer, r.clone(), every, self.timer_run.clone());
            }
        }
        Ok(())
    }

    fn shutdown(&mut self) {
        self.timer_run
            .store(false, std::sync::atomic::Ordering::SeqCst);
        for (r, _) in &self.actions {
            r.stop();
        }
    }
}

/// Closes `r`'s chunk every `every` on `timer` while `run` holds.
fn tick(timer: ExecutorRef, r: Arc<Recorder>, every: Duration, run: Arc<AtomicBool>) {
    let _ = timer.execute_after(every, move || {
        if run.load(std::sync::atomic::Ordering::SeqCst) {
            r.flush_tick();
            tick(timer, r, every, run);
        }
    });
}
