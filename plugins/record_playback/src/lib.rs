//! `record_playback_plugin`: records channels to MCAP in AimRT's bag layout
//! (`aimrtbag_YYYYMMDD_hhmmss/` with `metadata.yaml` and `.mcap` files) and plays bags
//! back, configured with AimRT's options, in `imd` mode (from start) or `signal` mode
//! (controlled by the `RecordPlaybackService` calls, over any RPC backend).
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
mod playback;
mod record;
mod service;

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::ffi::formats_of;
use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Plugin, PluginOptions, Registrar};

use crate::options::{Options, PlaybackOptions};
use crate::playback::{Pace, PlayTopic, Player, PlayerSetup};
use crate::record::{Recorder, Topic};
use crate::service::Actions;

pub use crate::playback::{KEY_RECORD_LOG_TIME, KEY_RECORD_PUB_SEQ, KEY_RECORD_PUB_TS};

struct RecordPlaybackPlugin {
    core: Option<CoreRef>,
    timer_executor: String,
    actions: Arc<Actions>,
    /// The executor name of each action, by action name.
    executors: Vec<(String, String)>,
    timer_run: Arc<AtomicBool>,
}

/// The plugin, as `libaimrt_record_playback_plugin.so` exports it.
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(RecordPlaybackPlugin {
        core: None,
        timer_executor: String::new(),
        actions: Arc::default(),
        executors: Vec::new(),
        timer_run: Arc::new(AtomicBool::new(false)),
    })
}

/// `imd` → false, `signal` → true (any case).
fn signal_mode(mode: &str) -> Result<bool, String> {
    match mode.to_ascii_lowercase().as_str() {
        "imd" => Ok(false),
        "signal" => Ok(true),
        other => Err(format!("mode '{other}' is not imd or signal")),
    }
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
        let o: Options = registrar.read_options(options)?;
        let bad = |message: String| options.invalid(message);
        let types = registrar
            .load_type_support_pkgs(&o.type_support_pkgs)
            .map_err(bad)?;
        let core = registrar.core()?;
        let channel = core.channel()?;
        let mut actions = Actions::default();
        for (a, action) in o.record_actions.into_iter().enumerate() {
            let at = |m: String| bad(format!("record_actions[{a}] ('{}'): {m}", action.name));
            if actions.records.contains_key(&action.name) {
                return Err(at("the name is used by another record action".into()));
            }
            let mut opts = action.options;
            let signal = signal_mode(&opts.mode).map_err(&at)?;
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
                    sample_freq: std::sync::atomic::AtomicU64::new(t.sample_freq.to_bits()),
                    enabled: AtomicBool::new(t.record_enabled),
                    cache_last_msg: t.cache_last_msg,
                });
            }
            let executor = opts.executor.clone();
            let subscriptions: Vec<(String, &'static aimrt_plugin_api::ffi::TypeSupportVtable)> =
                topics.iter().map(|t| (t.name.clone(), t.ts)).collect();
            let recorder =
                Recorder::open(action.name.clone(), opts, topics, signal).map_err(&at)?;
            for (i, (topic, ts)) in subscriptions.into_iter().enumerate() {
                let r = recorder.clone();
                channel.subscribe_raw(&topic, ts, move |ctx, msg| {
                    r.accept(i, ctx, msg);
                    Ok(())
                })?;
            }
            self.executors.push((action.name.clone(), executor));
            actions.records.insert(action.name, recorder);
        }
        if !actions.records.is_empty() && o.timer_executor.is_empty() {
            return Err(bad("timer_executor is required when there are record actions: it runs the timed chunk flushes (msg_write_interval_time) and the ends of timed recordings".into()));
        }
        for (a, action) in o.playback_actions.into_iter().enumerate() {
            let at = |m: String| bad(format!("playback_actions[{a}] ('{}'): {m}", action.name));
            if actions.players.contains_key(&action.name)
                || actions.records.contains_key(&action.name)
            {
                return Err(at("the name is used by another action".into()));
            }
            let player = open_player(&action.name, action.options, &types, channel).map_err(&at)?;
            self.executors.push((action.name.clone(), player.1));
            actions.players.insert(action.name, player.0);
        }
        let service = if o.service_name.is_empty() {
            service::SERVICE
        } else {
            o.service_name.as_str()
        };
        self.actions = Arc::new(actions);
        service::register(registrar, service, &self.actions)?;
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
        let timer = if self.actions.records.is_empty() {
            None
        } else {
            let timer = executor(&self.timer_executor, "timer_executor")?;
            if !timer.supports_timer_schedule() {
                return Err(Error::msg(format!(
                    "record_playback_plugin: Executor {} didn't support TimerSchedule! (timer_executor); use asio_thread or time_wheel",
                    self.timer_executor
                )));
            }
            Some(timer)
        };
        for (action, name) in &self.executors {
            let e = executor(name, &format!("the executor of action '{action}'"))?;
            if let Some(r) = self.actions.records.get(action) {
                if !e.thread_safe() {
                    return Err(Error::msg(format!(
                        "record_playback_plugin: Record executor {name} is not thread safe! (record action '{action}'): its tasks may run at once; use a serial one: simple_thread, asio_thread with thread_num 1, or asio_strand"
                    )));
                }
                if let Some(timer) = timer {
                    r.start(e, timer);
                }
            } else if let Some(p) = self.actions.players.get(action) {
                if !e.supports_timer_schedule() {
                    return Err(Error::msg(format!(
                        "record_playback_plugin: playback executor {name} (playback action '{action}') cannot schedule tasks at a time; use asio_thread, asio_strand or time_wheel"
                    )));
                }
                p.bind(e);
            }
        }
        if let Some(timer) = timer {
            self.timer_run
                .store(true, std::sync::atomic::Ordering::SeqCst);
            for r in self.actions.records.values() {
                let every = Duration::from_millis(r.flush_interval_ms());
                tick(timer, r.clone(), every, self.timer_run.clone());
            }
        }
        Ok(())
    }

    fn post_start(&mut self) {
        for p in self.actions.players.values() {
            p.post_start();
        }
    }

    fn shutdown(&mut self) {
        self.timer_run
            .store(false, std::sync::atomic::Ordering::SeqCst);
        for p in self.actions.players.values() {
            p.stop();
        }
        for r in self.actions.records.values() {
            r.stop();
        }
    }
}

/// Reads a playback action's bag and registers its topics for publishing; returns the
/// player and its executor's name.
fn open_player(
    name: &str,
    o: PlaybackOptions,
    types: &aimrt_plugin_api::TypeSupports,
    channel: aimrt_plugin_api::channel::ChannelRef,
) -> Result<(Arc<Player>, String), String> {
    let signal = signal_mode(&o.mode)?;
    if !(o.rate.is_finite() && o.rate > 0.0) {
        return Err(format!(
            "rate {} must be a positive factor (1: as recorded, 10: ten times as fast); for no waiting at all set as_fast_as_possible: true",
            o.rate
        ));
    }
    let folder = Path::new(&o.bag_path);
    let info = bag::read_metadata(folder).map_err(|e| format!("bag_path: {e}"))?;
    if info.version != 1 {
        return Err(format!(
            "bag_path: Version inconsistency: {} has version {}, and this plugin reads version 1",
            folder.join("metadata.yaml").display(),
            info.version
        ));
    }
    // Which recorded topics to play: all, or those listed.
    let mut chosen = Vec::new();
    if o.topic_meta_list.is_empty() {
        chosen.extend(info.topics.iter());
    } else {
        // The first recorded topic of each name and type, found without a walk of the
        // bag's topics for each listed one.
        let mut recorded = HashMap::new();
        for r in &info.topics {
            recorded
                .entry((r.topic_name.as_str(), r.msg_type.as_str()))
                .or_insert(r);
        }
        for (j, t) in o.topic_meta_list.iter().enumerate() {
            match recorded.get(&(t.topic_name.as_str(), t.msg_type.as_str())) {
                Some(r) => chosen.push(*r),
                None => tracing::warn!(
                    "playback action '{name}': topic_meta_list[{j}] ('{}', '{}') is not in the bag; its topics: {}",
                    t.topic_name,
                    t.msg_type,
                    info.topics
                        .iter()
                        .map(|r| format!("{} ({})", r.topic_name, r.msg_type))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            }
        }
    }
    let mut topics: Vec<PlayTopic> = Vec::new();
    let mut names = HashSet::new();
    for r in chosen {
        if !names.insert(r.topic_name.as_str()) {
            return Err(format!(
                "topic '{}' is recorded with two types; list the one to play in topic_meta_list",
                r.topic_name
            ));
        }
        let ts = types
            .get(&r.msg_type)
            .map_err(|e| format!("recorded topic '{}': {e}", r.topic_name))?;
        if !formats_of(ts).contains(&r.serialization_type) {
            return Err(format!(
                "recorded topic '{}' is in {}, which type '{}' of the loaded packages does not read; it reads: {}",
                r.topic_name,
                r.serialization_type,
                r.msg_type,
                formats_of(ts).join(", ")
            ));
        }
        channel
            .register_publish_raw(&r.topic_name, ts)
            .map_err(|e| e.to_string())?;
        topics.push(PlayTopic {
            name: r.topic_name.clone(),
            ts,
            serialization_type: r.serialization_type.clone(),
        });
    }
    let mut files = Vec::new();
    for f in &info.files {
        let p = folder.join(&f.path);
        if p.is_file() {
            files.push((p, f.start_timestamp));
        } else {
            tracing::warn!("playback action '{name}': {} is listed in metadata.yaml but missing; it is skipped", p.display());
        }
    }
    if files.is_empty() {
        return Err(format!(
            "bag_path: none of the files metadata.yaml lists is in {}",
            folder.display()
        ));
    }
    let pace = if o.as_fast_as_possible {
        Pace::AsFastAsPossible
    } else {
        Pace::Rate(o.rate)
    };
    let player = Player::new(PlayerSetup {
        name: name.to_owned(),
        signal,
        files,
        topics,
        skip_s: o.skip_duration_s,
        play_s: o.play_duration_s,
        pace,
        channel,
    });
    Ok((player, o.executor))
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

/// For the fuzz targets in `fuzz/`; not a stable API.
#[doc(hidden)]
pub mod __fuzz {
    /// Reads `bytes` as one MCAP file of a bag that plays topic `test_topic` (the record
    /// examples' topic), as playback does: to its end or its first damage outside a chunk,
    /// passing over damaged chunks. Returns how many messages it read. Panics only where
    /// the reader breaks its own promises: a message of another topic, or one larger than
    /// the record limit.
    pub fn read_mcap(bytes: &[u8]) -> usize {
        let back = crate::bag::read_bytes(bytes, &[("test_topic".to_owned(), 0)].into());
        let limit = crate::bag::RECORD_LIMIT.max(bytes.len() as u64);
        for m in &back.messages {
            assert_eq!(m.topic, 0, "a message of a topic not played");
            assert!(m.data.len() as u64 <= limit, "{} bytes", m.data.len());
        }
        back.messages.len()
    }
}
