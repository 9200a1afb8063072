//! One playback action: republishes the messages of one bag folder on their topics, at the
//! recorded pace (or `rate` times it, or as fast as possible), on the action's executor.
//!
//! Messages are published by one chain of tasks, so they keep their recorded order on any
//! executor: a task publishes every message that is due, then schedules itself at the
//! next message's time (`execute_at` on the executor's clock, so a `time_manipulator`
//! executor scales playback too). A message is due at `t0 + (log_time - start) / rate`,
//! where `t0` is when playback started and `start` the first file's start plus
//! `skip_duration_s`: a gap before the first message is kept, as AimRT keeps it.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, SystemTime};

use aimrt_plugin_api::channel::{ChannelRef, Context, ContextKind};
use aimrt_plugin_api::ffi::{RawMessage, TypeSupportVtable};
use aimrt_plugin_api::{ExecutorRef, RateLimit};

use crate::bag::{BagReader, Recorded};

/// Messages one task publishes at most before it yields the executor.
const BATCH: usize = 1000;

/// Context meta keys that carry what the recording says of a played message (the
/// runtime gives every publication a fresh `aimrt-pub_seq` and `aimrt-pub_ts`).
pub const KEY_RECORD_PUB_TS: &str = "aimrt-record_pub_ts";
/// The recorded `aimrt-pub_seq`.
pub const KEY_RECORD_PUB_SEQ: &str = "aimrt-record_pub_seq";
/// When the recorder received it (ns since the Unix epoch).
pub const KEY_RECORD_LOG_TIME: &str = "aimrt-record_log_time";

/// A played topic.
pub(crate) struct PlayTopic {
    pub(crate) name: String,
    pub(crate) ts: &'static TypeSupportVtable,
    pub(crate) serialization_type: String,
}

/// How fast a playback runs.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Pace {
    /// The recorded gaps divided by this factor (1 = as recorded).
    Rate(f64),
    /// No waiting between messages.
    AsFastAsPossible,
}

/// A playback action.
pub(crate) struct Player {
    pub(crate) name: String,
    pub(crate) signal: bool,
    files: Vec<(PathBuf, u64)>,
    topics: Vec<PlayTopic>,
    skip_s: u64,
    play_s: u64,
    pace: Pace,
    channel: ChannelRef,
    executor: OnceLock<ExecutorRef>,
    /// Bumped by every start and stop: a task of an older run ends itself.
    generation: AtomicU64,
    playing: AtomicBool,
    run: Mutex<Option<Run>>,
    published: AtomicU64,
    failed: AtomicU64,
    alarm: RateLimit,
}

struct Run {
    generation: u64,
    reader: BagReader,
    start: u64,
    t0: SystemTime,
    pending: Option<Recorded>,
}

/// What `Player::new` needs.
pub(crate) struct PlayerSetup {
    pub(crate) name: String,
    pub(crate) signal: bool,
    pub(crate) files: Vec<(PathBuf, u64)>,
    pub(crate) topics: Vec<PlayTopic>,
    pub(crate) skip_s: u64,
    pub(crate) play_s: u64,
    pub(crate) pace: Pace,
    pub(crate) channel: ChannelRef,
}

impl Player {
    pub(crate) fn new(s: PlayerSetup) -> Arc<Player> {
        Arc::new(Player {
            name: s.name,
            signal: s.signal,
            files: s.files,
            topics: s.topics,
            skip_s: s.skip_s,
            play_s: s.play_s,
            pace: s.pace,
            channel: s.channel,
            executor: OnceLock::new(),
            generation: AtomicU64::new(0),
            playing: AtomicBool::new(false),
            run: Mutex::new(None),
            published: AtomicU64::new(0),
            failed: AtomicU64::new(0),
            alarm: RateLimit::from_millis(1000),
        })
    }

    /// Binds the executor (at start).
    pub(crate) fn bind(&self, executor: ExecutorRef) {
        let _ = self.executor.set(executor);
    }

    /// An imd action begins playing (once everything has started, as AimRT's does at
    /// kPostStart: channels carry a plugin's messages from then on).
    pub(crate) fn post_start(self: &Arc<Self>) {
        if !self.signal {
            if let Err(e) = self.play(self.skip_s, self.play_s) {
                tracing::warn!("playback action '{}': {e}", self.name);
            }
        }
    }

    /// Starts playing from `skip_s` seconds after the bag's start for `play_s` seconds (0:
    /// to the end). Every start reads the bag from its beginning (AimRT's signal playback
    /// resumes where the last one stopped, or plays nothing after a complete one).
    /// `Err` when one is playing already.
    pub(crate) fn play(self: &Arc<Self>, skip_s: u64, play_s: u64) -> Result<(), String> {
        let Some(exec) = self.executor.get().copied() else {
            return Err("the plugin has not started yet".into());
        };
        let mut run = self.run.lock().unwrap_or_else(|e| e.into_inner());
        if self.playing.swap(true, Ordering::SeqCst) {
            return Err(
                "a playback of this action is running; stop it first (StopPlayback)".into(),
            );
        }
        let first = self.files.first().map_or(0, |f| f.1);
        let start = first.saturating_add(skip_s.saturating_mul(1_000_000_000));
        let stop = (play_s > 0).then(|| start.saturating_add(play_s.saturating_mul(1_000_000_000)));
        let topics: HashMap<String, usize> = self
            .topics
            .iter()
            .enumerate()
            .map(|(i, t)| (t.name.clone(), i))
            .collect();
        let generation = self.generation.fetch_add(1, Ordering::SeqCst) + 1;
        *run = Some(Run {
            generation,
            reader: BagReader::new(&self.files, topics, start, stop),
            start,
            t0: exec.now(),
            pending: None,
        });
        drop(run);
        tracing::info!(
            "playback action '{}': start playback (skip {skip_s} s, play {}, {})",
            self.name,
            if play_s == 0 {
                "all".to_string()
            } else {
                format!("{play_s} s")
            },
            match self.pace {
                Pace::Rate(r) => format!("rate {r}"),
                Pace::AsFastAsPossible => "as fast as possible".into(),
            }
        );
        self.post(exec, generation, None);
        Ok(())
    }

    /// Stops the running playback; `false` when none runs. Nothing more is published
    /// once this returns, except a message being published at this moment.
    pub(crate) fn stop(&self) -> bool {
        let mut run = self.run.lock().unwrap_or_else(|e| e.into_inner());
        self.generation.fetch_add(1, Ordering::SeqCst);
        *run = None;
        let was = self.playing.swap(false, Ordering::SeqCst);
        if was {
            tracing::info!("playback action '{}': Stop playback (stopped)", self.name);
        }
        was
    }

    fn post(self: &Arc<Self>, exec: ExecutorRef, generation: u64, at: Option<SystemTime>) {
        let me = self.clone();
        let task = move || me.step(generation);
        let posted = match at {
            Some(at) => exec.execute_at(at, task),
            None => exec.execute(task),
        };
        if posted.is_err() {
            tracing::warn!(
                "playback action '{}': executor '{}' refused the playback task; playback stops",
                self.name,
                exec.name()
            );
            self.finish(generation);
        }
    }

    fn finish(&self, generation: u64) {
        let mut run = self.run.lock().unwrap_or_else(|e| e.into_inner());
        if self.generation.load(Ordering::SeqCst) == generation {
            *run = None;
            self.playing.store(false, Ordering::SeqCst);
            tracing::info!(
                "playback action '{}': Stop playback ({} messages published, {} failed)",
                self.name,
                self.published.load(Ordering::Relaxed),
                self.failed.load(Ordering::Relaxed)
            );
        }
    }

    /// Publishes what is due, then schedules the next message.
    fn step(self: &Arc<Self>, generation: u64) {
        let Some(exec) = self.executor.get().copied() else {
            return;
        };
        // The run is taken out while publishing, so a subscriber may call StopPlayback.
        let mut run = {
            let mut slot = self.run.lock().unwrap_or_else(|e| e.into_inner());
            match slot.take() {
                Some(r) if r.generation == generation => r,
                other => {
                    *slot = other;
                    return;
                }
            }
        };
        for _ in 0..BATCH {
            if self.generation.load(Ordering::SeqCst) != generation {
                return;
            }
            let Some(m) = run.pending.take().or_else(|| run.reader.next()) else {
                // The end of the bag, or past play_duration_s.
                let bag_start = self.files.first().map_or(0, |f| f.1);
                if let Some(why) = run.reader.why_nothing(bag_start) {
                    tracing::warn!("playback action '{}': nothing played: {why}", self.name);
                }
                self.finish(generation);
                return;
            };
            if let Pace::Rate(rate) = self.pace {
                let offset = m.log_time.saturating_sub(run.start) as f64 / rate;
                let due = run.t0 + Duration::from_nanos(offset as u64);
                if due > exec.now() {
                    run.pending = Some(m);
                    if self.put_back(run) {
                        self.post(exec, generation, Some(due));
                    }
                    return;
                }
            }
            self.publish(&m);
        }
        if self.put_back(run) {
            self.post(exec, generation, None);
        }
    }

    /// Puts `run` back unless it was stopped meanwhile.
    fn put_back(&self, run: Run) -> bool {
        let mut slot = self.run.lock().unwrap_or_else(|e| e.into_inner());
        if self.generation.load(Ordering::SeqCst) == run.generation {
            *slot = Some(run);
            true
        } else {
            false
        }
    }

    /// Publishes `m` with what the recording says of it; a failure is counted and said.
    fn publish(&self, m: &Recorded) {
        let t = &self.topics[m.topic];
        let result = RawMessage::decode(t.ts, &t.serialization_type, &m.data).and_then(|msg| {
            let mut ctx = Context::new(ContextKind::Publish);
            ctx.set_serialization_type(&t.serialization_type);
            ctx.set(KEY_RECORD_PUB_TS, &m.publish_time.to_string());
            ctx.set(KEY_RECORD_PUB_SEQ, &m.sequence.to_string());
            ctx.set(KEY_RECORD_LOG_TIME, &m.log_time.to_string());
            self.channel
                .publish_raw(&t.name, &ctx, msg)
                .map_err(|e| e.to_string())
        });
        match result {
            Ok(()) => {
                self.published.fetch_add(1, Ordering::Relaxed);
            }
            Err(e) => self.failed(m, &e),
        }
    }

    fn failed(&self, m: &Recorded, why: &str) {
        self.failed.fetch_add(1, Ordering::Relaxed);
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(
                "playback action '{}': a message of '{}' is not played: {why} ({held} more such lines held back)",
                self.name,
                self.topics[m.topic].name
            );
        }
    }
}
