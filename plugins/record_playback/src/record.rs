//! One record action: every accepted message of its topics, encoded in the topic's
//! serialization type, goes through a bounded queue to its `executor`, which writes it to
//! the current MCAP file of the action's bag folder.
//!
//! - `imd` records from start to shutdown into one bag folder made at initialize.
//! - `signal` keeps the last `max_preparation_duration_s` of messages in memory and records
//!   only between `StartRecord` and `StopRecord` (or the end of `record_duration_s`, 0 =
//!   until stopped), each time into a new bag folder that begins with the kept messages
//!   of the asked preparation window.
//!
//! - Publishers never wait: a full queue drops the message, counts it and says so (at most
//!   once a second).
//! - The current chunk is closed after `msg_write_interval` messages and every
//!   `msg_write_interval_time` ms (on `timer_executor`). A process killed mid-recording
//!   leaves a file that is readable up to the last closed chunk.
//! - A file is closed and the next one opened when its estimated size reaches
//!   `max_bag_size_m`; beyond `max_bag_num` files the oldest is deleted.

use std::collections::{BTreeMap, VecDeque};
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant, SystemTime};

use aimrt_plugin_api::channel::Context;
use aimrt_plugin_api::ffi::{schema_of, RawMessage, TypeSupportVtable};
use aimrt_plugin_api::{ExecutorRef, RateLimit};

use crate::bag::{self, FileEntry, McapFile, TopicEntry};
use crate::options::{Compression, RecordOptions};

/// Messages the write queue of an action holds at most.
pub(crate) const QUEUE_CAPACITY: usize = 100_000;
/// Bytes of messages the write queue of an action holds at most, and a `signal` action's
/// preparation window: 100 000 camera images would be hundreds of GiB, and a disk that
/// falls behind must cost messages (counted), not the process (killed for its memory).
pub(crate) const QUEUE_BYTES: usize = 1 << 30;

/// Messages held in memory with their bytes counted: the write queue, and a `signal`
/// action's preparation window.
#[derive(Default)]
struct Held {
    entries: VecDeque<Entry>,
    bytes: usize,
}

impl Held {
    fn push(&mut self, e: Entry) {
        self.bytes += e.data.len();
        self.entries.push_back(e);
    }

    fn pop(&mut self) -> Option<Entry> {
        let e = self.entries.pop_front()?;
        self.bytes -= e.data.len();
        Some(e)
    }

    /// Everything held, leaving it empty.
    fn take(&mut self) -> VecDeque<Entry> {
        self.bytes = 0;
        std::mem::take(&mut self.entries)
    }

    /// Why a message of `bytes` does not fit under `max_messages` and `max_bytes`, if it
    /// does not. An empty queue takes a message of any size.
    fn full(&self, bytes: usize, max_messages: usize, max_bytes: usize) -> Option<String> {
        if self.entries.len() >= max_messages {
            Some(format!("{max_messages} messages"))
        } else if !self.entries.is_empty() && self.bytes + bytes > max_bytes {
            Some(format!(
                "{max_bytes} bytes: {} are waiting, and this one has {bytes}",
                self.bytes
            ))
        } else {
            None
        }
    }

    /// Keeps `e` in a preparation window of `window` ns and at most `max_bytes`: lets go
    /// of the messages older than `window` before `e`, then of the oldest while the rest
    /// is over `max_bytes` (always keeping `e`). Returns how many went for the bytes.
    fn keep_window(&mut self, e: Entry, window: u64, max_bytes: usize) -> u64 {
        let oldest = e.log_time.saturating_sub(window);
        self.push(e);
        while self.entries.front().is_some_and(|e| e.log_time < oldest) {
            self.pop();
        }
        let mut early = 0;
        while self.bytes > max_bytes && self.entries.len() > 1 {
            self.pop();
            early += 1;
        }
        early
    }
}

/// A recorded topic.
pub(crate) struct Topic {
    pub(crate) name: String,
    pub(crate) msg_type: String,
    pub(crate) ts: &'static TypeSupportVtable,
    pub(crate) serialization_type: String,
    /// `sample_freq` in Hz as `f64` bits: messages sooner than `1/f` after the last kept
    /// one are skipped (0: none).
    pub(crate) sample_freq: AtomicU64,
    pub(crate) enabled: AtomicBool,
    pub(crate) cache_last_msg: bool,
}

/// One message on its way to the file.
#[derive(Clone)]
struct Entry {
    topic: usize,
    sequence: u32,
    log_time: u64,
    publish_time: u64,
    data: Arc<[u8]>,
}

/// Counters logged at shutdown.
#[derive(Default)]
struct Stats {
    written: AtomicU64,
    dropped_full: AtomicU64,
    failed: AtomicU64,
    skipped_sample: AtomicU64,
    /// Let go of from a preparation window before `max_preparation_duration_s` because
    /// the window held [`QUEUE_BYTES`].
    window_early: AtomicU64,
}

/// The open file and what the folder holds.
struct Files {
    folder: PathBuf,
    day: chrono::NaiveDate,
    current: Option<Open>,
    entries: Vec<FileEntry>,
    /// Bytes written to the current file as estimated (30 + payload per message).
    estimate: u64,
    /// Real size ÷ estimate of the last closed file (1.5 until one closed).
    overhead: f64,
    since_flush: u64,
    last: Vec<Option<Entry>>,
    /// Set while the action has no file it can write (the current one failed, or the
    /// next one did not open): when it tries a new one.
    retry_at: Option<Instant>,
}

/// How long after a file failed, or did not open, the action tries a new one.
const RETRY: Duration = Duration::from_secs(5);

struct Open {
    writer: McapFile,
    path: PathBuf,
    channels: Vec<Option<u16>>,
    /// Why the file failed (a write or a flush, e.g. the disk is full): the `mcap` writer
    /// takes nothing after a failed write, so the file keeps what reached the disk before
    /// and every later message of it is counted as failed.
    failed: Option<String>,
}

/// `CommonRsp` codes of the control service (AimRT's, plus 6 for a topic the action does
/// not record).
pub(crate) mod code {
    pub(crate) const INVALID_ACTION_NAME: u32 = 1;
    pub(crate) const INVALID_ACTION_MODE: u32 = 2;
    pub(crate) const START_RECORD_FAILED: u32 = 3;
    pub(crate) const START_PLAYBACK_FAILED: u32 = 4;
    pub(crate) const STOP_RECORD_FAILED: u32 = 5;
    pub(crate) const INVALID_TOPIC_META: u32 = 6;
}

/// A refused control call: its `CommonRsp` code and message.
pub(crate) type Refusal = (u32, String);

/// The state of a `signal` action.
struct Signal {
    /// `max_preparation_duration_s` in ns.
    window: u64,
    state: Mutex<SignalState>,
}

#[derive(Default)]
struct SignalState {
    /// The kept messages (the last `window` of them) while not recording.
    cache: Held,
    recording: bool,
    /// When the recording ends by itself (ns since the epoch); `None`: when stopped.
    deadline: Option<u64>,
    /// Bumped by every start and stop: a deadline timer of an older recording does nothing.
    session: u64,
}

/// A record action.
/// Queued messages that get the write task posted at once.
const WAKE_BATCH: usize = 256;
/// How long fewer messages wait for their write task at most.
const WRITE_DELAY: Duration = Duration::from_millis(10);

pub(crate) struct Recorder {
    pub(crate) name: String,
    options: RecordOptions,
    signal: Option<Signal>,
    extra_attributes: Mutex<BTreeMap<String, serde_json::Value>>,
    timer: OnceLock<ExecutorRef>,
    topics: Vec<Topic>,
    queue: Mutex<Held>,
    scheduled: AtomicBool,
    accepting: AtomicBool,
    enabled: AtomicBool,
    executor: OnceLock<ExecutorRef>,
    last_kept: Mutex<Vec<Option<Instant>>>,
    files: Mutex<Files>,
    stats: Stats,
    alarm: RateLimit,
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

impl Recorder {
    /// Creates the bag folder, its first MCAP file and `metadata.yaml` (AimRT's imd
    /// action does at initialize).
    /// A `signal` action (`signal` true) makes its folders at `StartRecord`.
    pub(crate) fn open(
        name: String,
        mut options: RecordOptions,
        topics: Vec<Topic>,
        signal: bool,
    ) -> Result<Arc<Recorder>, String> {
        let bag_path = Path::new(&options.bag_path);
        std::fs::create_dir_all(bag_path)
            .map_err(|e| format!("cannot create bag_path '{}': {e}", options.bag_path))?;
        // Made absolute, as AimRT does: StartRecord answers the folder in full.
        if let Ok(full) = std::fs::canonicalize(bag_path) {
            options.bag_path = full.display().to_string();
        }
        let now = chrono::Local::now();
        let n = topics.len();
        let r = Arc::new(Recorder {
            name,
            enabled: AtomicBool::new(options.record_enabled),
            signal: signal.then(|| Signal {
                window: options
                    .max_preparation_duration_s
                    .saturating_mul(1_000_000_000),
                state: Mutex::default(),
            }),
            extra_attributes: Mutex::new(std::mem::take(&mut options.extra_attributes)),
            timer: OnceLock::new(),
            options,
            topics,
            queue: Mutex::default(),
            scheduled: AtomicBool::new(false),
            accepting: AtomicBool::new(false),
            executor: OnceLock::new(),
            last_kept: Mutex::new(vec![None; n]),
            files: Mutex::new(Files {
                folder: PathBuf::new(),
                day: now.date_naive(),
                current: None,
                entries: Vec::new(),
                estimate: 0,
                overhead: 1.5,
                since_flush: 0,
                last: vec![None; n],
                retry_at: None,
            }),
            stats: Stats::default(),
            alarm: RateLimit::from_millis(1000),
        });
        if !signal {
            let mut f = r.files.lock().unwrap_or_else(|e| e.into_inner());
            r.begin_bag(&mut f)?;
        }
        Ok(r)
    }

    /// Makes a new bag folder and opens its first file.
    fn begin_bag(&self, f: &mut Files) -> Result<(), String> {
        let now = chrono::Local::now();
        let parent = Path::new(&self.options.bag_path);
        let stamp = bag::stamp_name(now);
        let (folder, ()) = bag::create_fresh(parent, &stamp, "", |p| std::fs::create_dir(p))
            .map_err(|e| format!("cannot create a bag folder in {}: {e}", parent.display()))?;
        f.folder = folder;
        f.entries.clear();
        f.day = now.date_naive();
        self.open_file(f)?;
        self.copy_extra_files(&f.folder);
        Ok(())
    }

    /// Writes what is queued, closes the file and rewrites `metadata.yaml`.
    fn end_bag(&self, f: &mut Files) {
        let batch = self.queue.lock().unwrap_or_else(|e| e.into_inner()).take();
        for e in batch {
            self.write(f, e);
        }
        if f.current.is_some() {
            self.close_file(f);
            self.write_metadata(f);
        }
        // No file is wanted until the next bag.
        f.retry_at = None;
    }

    /// `storage_policy.msg_write_interval_time` in ms.
    pub(crate) fn flush_interval_ms(&self) -> u64 {
        self.options.storage_policy.msg_write_interval_time
    }

    /// Records are accepted from now on; writes run on `executor`, deadlines and timed
    /// flushes on `timer`.
    pub(crate) fn start(&self, executor: ExecutorRef, timer: ExecutorRef) {
        let _ = self.executor.set(executor);
        let _ = self.timer.set(timer);
        self.accepting.store(true, Ordering::SeqCst);
    }

    /// `StartRecord`: a new bag folder that begins with the kept messages of the last
    /// `preparation_s` seconds (at most `max_preparation_duration_s`) and records until
    /// `StopRecord`, or for `record_s` seconds (0: until stopped; AimRT stops at the first
    /// message, its issue #427). Returns the folder.
    pub(crate) fn start_record(
        self: &Arc<Self>,
        preparation_s: u64,
        record_s: u64,
    ) -> Result<String, Refusal> {
        let Some(sig) = &self.signal else {
            return Err((
                code::INVALID_ACTION_MODE,
                format!("record action '{}' is imd: it records from start to shutdown; StartRecord and StopRecord control signal actions", self.name),
            ));
        };
        let now = now_ns();
        let mut s = sig.state.lock().unwrap_or_else(|e| e.into_inner());
        let mut f = self.files.lock().unwrap_or_else(|e| e.into_inner());
        if s.recording {
            if s.deadline.is_none_or(|d| now < d) {
                return Err((
                    code::START_RECORD_FAILED,
                    format!("record action '{}' is recording into {} already; stop it first (StopRecord)", self.name, f.folder.display()),
                ));
            }
            // Its duration is over and its timer has not run yet.
            self.end_bag(&mut f);
        }
        self.begin_bag(&mut f)
            .map_err(|e| (code::START_RECORD_FAILED, e))?;
        let from = now.saturating_sub(preparation_s.saturating_mul(1_000_000_000).min(sig.window));
        let mut queue = self.queue.lock().unwrap_or_else(|e| e.into_inner());
        for e in s.cache.take() {
            if e.log_time >= from {
                queue.push(e);
            }
        }
        drop(queue);
        s.recording = true;
        s.session += 1;
        s.deadline =
            (record_s > 0).then(|| now.saturating_add(record_s.saturating_mul(1_000_000_000)));
        let folder = f.folder.display().to_string();
        drop(f);
        if let (Some(deadline), Some(timer)) = (s.deadline, self.timer.get()) {
            let me = self.clone();
            let session = s.session;
            let at = SystemTime::UNIX_EPOCH + Duration::from_nanos(deadline);
            let _ = timer.execute_at(at, move || {
                let _ = me.stop_record_of(Some(session));
            });
        }
        drop(s);
        tracing::info!(
            "record action '{}': start recording into {folder}",
            self.name
        );
        self.schedule();
        Ok(folder)
    }

    /// `StopRecord`: ends the recording, writing what is queued and closing its file.
    pub(crate) fn stop_record(&self) -> Result<(), Refusal> {
        self.stop_record_of(None)
    }

    /// Stops the recording (of `session` only, when given: a deadline timer).
    fn stop_record_of(&self, session: Option<u64>) -> Result<(), Refusal> {
        let Some(sig) = &self.signal else {
            return Err((
                code::INVALID_ACTION_MODE,
                format!("record action '{}' is imd: it records until shutdown; StopRecord controls signal actions", self.name),
            ));
        };
        let mut s = sig.state.lock().unwrap_or_else(|e| e.into_inner());
        if !s.recording || session.is_some_and(|n| n != s.session) {
            return Err((
                code::STOP_RECORD_FAILED,
                format!("record action '{}' is not recording", self.name),
            ));
        }
        s.recording = false;
        s.deadline = None;
        s.session += 1;
        let mut f = self.files.lock().unwrap_or_else(|e| e.into_inner());
        self.end_bag(&mut f);
        tracing::info!(
            "record action '{}': stop recording into {}",
            self.name,
            f.folder.display()
        );
        Ok(())
    }

    /// `UpdateMetadata`: adds `pairs` to `extra_attributes` (each value read as YAML when it
    /// is, else kept as a string) and rewrites `metadata.yaml` of the current bag.
    pub(crate) fn update_metadata(&self, pairs: &std::collections::HashMap<String, String>) {
        {
            let mut extra = self
                .extra_attributes
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            for (k, v) in pairs {
                if k.is_empty() {
                    tracing::warn!(
                        "record action '{}': UpdateMetadata: an empty key is skipped",
                        self.name
                    );
                    continue;
                }
                let value = serde_saphyr::from_str::<serde_json::Value>(v)
                    .unwrap_or_else(|_| serde_json::Value::String(v.clone()));
                extra.insert(k.clone(), value);
            }
        }
        let f = self.files.lock().unwrap_or_else(|e| e.into_inner());
        if !f.folder.as_os_str().is_empty() {
            self.write_metadata(&f);
        }
    }

    /// Whether the action records at all (`record_enabled`).
    pub(crate) fn enabled(&self) -> bool {
        self.enabled.load(Ordering::Relaxed)
    }

    /// The topics: (name, type, enabled, sample_freq).
    pub(crate) fn topic_status(&self) -> Vec<(String, String, bool, f64)> {
        self.topics
            .iter()
            .map(|t| {
                (
                    t.name.clone(),
                    t.msg_type.clone(),
                    t.enabled.load(Ordering::Relaxed),
                    f64::from_bits(t.sample_freq.load(Ordering::Relaxed)),
                )
            })
            .collect()
    }

    /// `UpdateRecordAction`: sets the master switch and, per `(topic, type)`, the topic's
    /// switch and `sample_freq` (unchanged when `None`). Every pair must be one this
    /// action records and every rate ≥ 0, else nothing changes.
    pub(crate) fn update(
        &self,
        enabled: Option<bool>,
        topics: &[(String, String, bool, Option<f64>)],
    ) -> Result<(), Refusal> {
        let mut found = Vec::new();
        for (name, ty, on, freq) in topics {
            let Some(t) = self
                .topics
                .iter()
                .find(|t| &t.name == name && &t.msg_type == ty)
            else {
                return Err((
                    code::INVALID_TOPIC_META,
                    format!("record action '{}' does not record topic '{name}' of type '{ty}'; its topics: {}", self.name,
                        self.topics.iter().map(|t| format!("{} ({})", t.name, t.msg_type)).collect::<Vec<_>>().join(", ")),
                ));
            };
            if freq.is_some_and(|f| !(f.is_finite() && f >= 0.0)) {
                return Err((
                    code::INVALID_TOPIC_META,
                    format!("sample_freq of topic '{name}' must be 0 (every message) or a positive rate in Hz"),
                ));
            }
            found.push((t, *on, *freq));
        }
        for (t, on, freq) in found {
            t.enabled.store(on, Ordering::Relaxed);
            if let Some(f) = freq {
                t.sample_freq.store(f.to_bits(), Ordering::Relaxed);
            }
        }
        if let Some(on) = enabled {
            self.enabled.store(on, Ordering::Relaxed);
        }
        Ok(())
    }

    fn warn(&self, what: std::fmt::Arguments<'_>) {
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(
                "record action '{}': {what} ({held} more such lines held back since the last)",
                self.name
            );
        }
    }

    /// A message delivered to the action's subscription of topic `i`.
    pub(crate) fn accept(self: &Arc<Self>, i: usize, ctx: &Context, msg: RawMessage) {
        if !self.accepting.load(Ordering::Acquire) {
            if self.executor.get().is_some() {
                // Stopped: the file is closed. A backend that still delivers after the
                // plugin shut down (its executor was late) loses the message here.
                self.stats.failed.fetch_add(1, Ordering::Relaxed);
                self.warn(format_args!(
                    "a message of '{}' arrived after the action stopped and is not recorded",
                    self.topics[i].name
                ));
            }
            return;
        }
        if !self.enabled.load(Ordering::Relaxed) || !self.topics[i].enabled.load(Ordering::Relaxed)
        {
            return;
        }
        let t = &self.topics[i];
        let freq = f64::from_bits(t.sample_freq.load(Ordering::Relaxed));
        if freq > 0.0 {
            let gap = Duration::from_secs_f64(1.0 / freq);
            let now = Instant::now();
            let mut last = self.last_kept.lock().unwrap_or_else(|e| e.into_inner());
            if last[i].is_some_and(|l| now.duration_since(l) < gap) {
                self.stats.skipped_sample.fetch_add(1, Ordering::Relaxed);
                return;
            }
            last[i] = Some(now);
        }
        let data = match msg.encode(&t.serialization_type) {
            Ok(d) => d,
            Err(e) => {
                self.stats.failed.fetch_add(1, Ordering::Relaxed);
                self.warn(format_args!(
                    "a message of '{}' cannot be encoded as {}: {e}",
                    t.name, t.serialization_type
                ));
                return;
            }
        };
        let num = |k: &str| ctx.get(k).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
        let entry = Entry {
            topic: i,
            sequence: num("aimrt-pub_seq") as u32,
            log_time: now_ns(),
            publish_time: num("aimrt-pub_ts"),
            data: data.into(),
        };
        if let Some(sig) = &self.signal {
            let mut s = sig.state.lock().unwrap_or_else(|e| e.into_inner());
            if !(s.recording && s.deadline.is_none_or(|d| entry.log_time < d)) {
                // Kept for a later StartRecord: the last `window` of messages.
                let early = s.cache.keep_window(entry, sig.window, QUEUE_BYTES);
                drop(s);
                if early > 0 {
                    self.stats.window_early.fetch_add(early, Ordering::Relaxed);
                    self.warn(format_args!(
                        "the preparation window holds {QUEUE_BYTES} bytes of messages, less than max_preparation_duration_s ({} s): its oldest are let go early",
                        self.options.max_preparation_duration_s
                    ));
                }
                return;
            }
            // Queued while the state is held, so a stop never leaves it behind.
            let queued = self.enqueue(entry);
            drop(s);
            self.schedule_soon(queued);
            return;
        }
        let queued = self.enqueue(entry);
        self.schedule_soon(queued);
    }

    /// Queues `entry` for the file, unless the queue is full (counted, said). Returns the
    /// messages queued now (0: dropped).
    fn enqueue(&self, entry: Entry) -> usize {
        let mut q = self.queue.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(why) = q.full(entry.data.len(), QUEUE_CAPACITY, QUEUE_BYTES) {
            drop(q);
            self.stats.dropped_full.fetch_add(1, Ordering::Relaxed);
            self.warn(format_args!(
                "the write queue is full ({why}): a message of '{}' is dropped; the disk or the executor cannot keep up",
                self.topics[entry.topic].name
            ));
            return 0;
        }
        q.push(entry);
        q.entries.len()
    }

    /// Gets the queue written without waking the executor for every message: at once when
    /// [`WAKE_BATCH`] are queued, else [`WRITE_DELAY`] after the first one (a timer on
    /// `timer_executor`). At 100 000 messages a second that is one wake-up of the write
    /// thread per 256 messages instead of one per message.
    fn schedule_soon(self: &Arc<Self>, queued: usize) {
        if queued >= WAKE_BATCH {
            self.schedule();
        } else if queued == 1 {
            let Some(timer) = self.timer.get() else {
                self.schedule();
                return;
            };
            let me = self.clone();
            if timer
                .execute_after(WRITE_DELAY, move || me.schedule())
                .is_err()
            {
                self.schedule();
            }
        }
    }

    /// Posts a drain task to the executor unless one is pending.
    fn schedule(self: &Arc<Self>) {
        if self.scheduled.swap(true, Ordering::AcqRel) {
            return;
        }
        let Some(exec) = self.executor.get() else {
            self.scheduled.store(false, Ordering::Release);
            return;
        };
        let me = self.clone();
        if exec.execute(move || me.drain(false, true)).is_err() {
            self.scheduled.store(false, Ordering::Release);
            self.warn(format_args!(
                "executor '{}' refused the write task; the messages wait for the next one",
                exec.name()
            ));
        }
    }

    /// Writes what is queued, in queue order: batches are taken while the file is held,
    /// so two drain tasks on a pool never interleave. `flush` closes the current chunk
    /// afterwards; `scheduled` says this task is the one [`schedule`](Self::schedule)
    /// posted.
    fn drain(self: &Arc<Self>, flush: bool, scheduled: bool) {
        {
            let mut f = self.files.lock().unwrap_or_else(|e| e.into_inner());
            loop {
                let batch = self.queue.lock().unwrap_or_else(|e| e.into_inner()).take();
                if batch.is_empty() {
                    break;
                }
                for e in batch {
                    self.write(&mut f, e);
                }
            }
            if flush {
                self.flush(&mut f);
            }
        }
        if scheduled {
            self.scheduled.store(false, Ordering::Release);
            // A message queued after the last take needs a task of its own.
            if !self
                .queue
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .entries
                .is_empty()
            {
                self.schedule();
            }
        }
    }

    /// Closes the current chunk (the timer's task).
    pub(crate) fn flush_tick(self: &Arc<Self>) {
        let Some(exec) = self.executor.get() else {
            return;
        };
        let me = self.clone();
        let _ = exec.execute(move || me.drain(true, false));
    }

    fn flush(&self, f: &mut Files) {
        let unflushed = f.since_flush;
        if let Some(open) = f.current.as_mut() {
            if open.failed.is_none() {
                if let Err(e) = open.writer.flush() {
                    self.file_failed(open, &e, unflushed);
                }
            }
        }
        self.note_failure(f);
        f.since_flush = 0;
    }

    /// A current file that failed has the action try a new one [`RETRY`] later.
    fn note_failure(&self, f: &mut Files) {
        let failed = f.current.as_ref().is_some_and(|o| o.failed.is_some());
        if failed && f.retry_at.is_none() {
            f.retry_at = Some(Instant::now() + RETRY);
        }
    }

    /// Says once, whatever the rate limit, that `open` failed and what follows from it;
    /// `unflushed` messages were written to it since its last flush.
    fn file_failed(&self, open: &mut Open, e: &mcap::McapError, unflushed: u64) {
        let why = with_causes(e);
        tracing::warn!(
            "record action '{}': writing {} failed: {why}. The file keeps what reached the disk \
             before (up to the {unflushed} messages written since its last flush may be missing, \
             though counted as written); the messages after it are counted as failed until \
             the action opens a new file, which it tries every {} s",
            self.name,
            open.path.display(),
            RETRY.as_secs()
        );
        open.failed = Some(why);
    }

    fn write(&self, f: &mut Files, e: Entry) {
        if f.retry_at.is_some_and(|at| Instant::now() >= at) {
            f.retry_at = None;
            self.rotate(f);
        }
        let policy = &self.options.storage_policy;
        let max = policy.max_bag_size_m.saturating_mul(1 << 20);
        // Without a file (the next one did not open) only the retry above opens one.
        if f.current.is_some() && f.estimate > 0 && (f.estimate as f64 * f.overhead) >= max as f64 {
            self.rotate(f);
        }
        if self.topics[e.topic].cache_last_msg {
            f.last[e.topic] = Some(e.clone());
        }
        let unwritable = match &f.current {
            None => Some("no file is open".to_owned()),
            Some(open) => open
                .failed
                .as_ref()
                .map(|why| format!("{} failed: {why}", open.path.display())),
        };
        if let Some(why) = unwritable {
            self.stats.failed.fetch_add(1, Ordering::Relaxed);
            self.warn(format_args!("a message is not recorded: {why}"));
            return;
        }
        let written = self.put(f, &e);
        self.note_failure(f);
        match written {
            Ok(()) => {
                self.stats.written.fetch_add(1, Ordering::Relaxed);
                f.estimate += 30 + e.data.len() as u64;
                f.since_flush += 1;
                if f.since_flush > policy.msg_write_interval {
                    self.flush(f);
                }
            }
            Err(why) => {
                self.stats.failed.fetch_add(1, Ordering::Relaxed);
                self.warn(format_args!("Failed to write record to mcap file: {why}"));
            }
        }
    }

    fn put(&self, f: &mut Files, e: &Entry) -> Result<(), String> {
        let unflushed = f.since_flush;
        let Some(open) = f.current.as_mut() else {
            return Err("no file is open".into());
        };
        let channel = match open.channels[e.topic] {
            Some(c) => c,
            None => {
                let c = self.add_channel(open, e.topic)?;
                open.channels[e.topic] = Some(c);
                c
            }
        };
        let written = open.writer.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: channel,
                sequence: e.sequence,
                log_time: e.log_time,
                publish_time: e.publish_time,
            },
            &e.data,
        );
        written.map_err(|err| {
            self.file_failed(open, &err, unflushed);
            format!("{}: {}", open.path.display(), with_causes(&err))
        })
    }

    /// The schema and channel of topic `i` in `open`.
    fn add_channel(&self, open: &mut Open, i: usize) -> Result<u16, String> {
        let t = &self.topics[i];
        let schema = schema_of(t.ts);
        let (message_encoding, schema) = match (t.serialization_type.as_str(), schema) {
            ("pb", Some(s @ ("protobuf", _, _))) => ("protobuf", Some(s)),
            ("pb", _) => ("protobuf", None),
            ("json", Some(s @ ("jsonschema", _, _))) => ("json", Some(s)),
            ("json", _) => ("json", None),
            (other, s) => (other, s),
        };
        let schema_id = match schema {
            Some((encoding, name, data)) => open
                .writer
                .add_schema(name, encoding, data)
                .map_err(|e| format!("cannot add the schema of '{}': {e}", t.msg_type))?,
            None => 0,
        };
        open.writer
            .add_channel(schema_id, &t.name, message_encoding, &BTreeMap::new())
            .map_err(|e| format!("cannot add the channel of '{}': {e}", t.name))
    }

    fn open_file(&self, f: &mut Files) -> Result<(), String> {
        let policy = &self.options.storage_policy;
        let now = chrono::Local::now();
        if policy.new_folder_daily && now.date_naive() != f.day && !f.entries.is_empty() {
            let parent = Path::new(&self.options.bag_path);
            let stamp = bag::stamp_name(now);
            let (folder, ()) = bag::create_fresh(parent, &stamp, "", |p| std::fs::create_dir(p))
                .map_err(|e| format!("cannot create a bag folder in {}: {e}", parent.display()))?;
            f.folder = folder;
            f.entries.clear();
        }
        f.day = now.date_naive();
        // The folder again if it was deleted from outside while recording; its files went
        // with it, and its metadata lists only the files from now on.
        if !f.folder.is_dir() {
            std::fs::create_dir_all(&f.folder)
                .map_err(|e| format!("cannot create {}: {e}", f.folder.display()))?;
            f.entries.clear();
        }
        let (path, file) =
            bag::create_fresh(&f.folder, &bag::stamp_name(now), ".mcap", bag::new_file)
                .map_err(|e| format!("cannot create a file in {}: {e}", f.folder.display()))?;
        let compression = match policy.compression {
            Compression::None => None,
            Compression::Lz4 => Some(mcap::Compression::Lz4),
            Compression::Zstd => Some(mcap::Compression::Zstd),
        };
        // The header is written to the disk at once: a file that cannot take it (a full
        // disk) is removed before anything counts on it, and no older file is deleted
        // for it (max_bag_num).
        let writer = mcap::WriteOptions::new()
            .profile("aimrtbag")
            .library(concat!("aimrt-rs ", env!("CARGO_PKG_VERSION")))
            .compression(compression)
            .compression_level(policy.level)
            .compression_threads(0)
            .create(BufWriter::new(file))
            .and_then(|mut w| w.flush().map(|()| w))
            .map_err(|e| {
                let _ = std::fs::remove_file(&path);
                format!("cannot start {}: {}", path.display(), with_causes(&e))
            })?;
        tracing::info!("Open new mcap file to record: {}", path.display());
        let start = now_ns();
        f.entries.push(FileEntry {
            path: path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            start_timestamp: start,
        });
        f.retry_at = None;
        f.current = Some(Open {
            failed: None,
            writer,
            path,
            channels: vec![None; self.topics.len()],
        });
        f.estimate = 0;
        f.since_flush = 0;
        // The last message of a `cache_last_msg` topic starts every new file.
        let cached: Vec<Entry> = f.last.iter().flatten().cloned().collect();
        for mut e in cached {
            e.log_time = start;
            let _ = self.put(f, &e);
        }
        if policy.max_bag_num > 0 {
            while f.entries.len() as u64 > policy.max_bag_num {
                let old = f.entries.remove(0);
                let _ = std::fs::remove_file(f.folder.join(&old.path));
            }
        }
        self.write_metadata(f);
        Ok(())
    }

    fn close_file(&self, f: &mut Files) {
        if let Some(mut open) = f.current.take() {
            // A failed file was reported when it failed; finishing it fails again.
            if open.failed.is_none() {
                if let Err(e) = open.writer.finish() {
                    tracing::warn!(
                        "record action '{}': closing {} failed: {}",
                        self.name,
                        open.path.display(),
                        with_causes(&e)
                    );
                }
            }
            drop(open.writer);
            if let Ok(m) = std::fs::metadata(&open.path) {
                if f.estimate > 0 {
                    f.overhead = (m.len() as f64 / f.estimate as f64).max(0.1);
                }
            }
        }
    }

    fn rotate(&self, f: &mut Files) {
        self.close_file(f);
        if let Err(e) = self.open_file(f) {
            // Not rate limited: a try every RETRY at most.
            tracing::warn!(
                "record action '{}': cannot open the next file: {e}; the messages are counted as failed until a new file opens, tried every {} s",
                self.name,
                RETRY.as_secs()
            );
            f.retry_at = Some(Instant::now() + RETRY);
        }
    }

    fn write_metadata(&self, f: &Files) {
        let topics: Vec<TopicEntry> = self
            .topics
            .iter()
            .enumerate()
            .map(|(id, t)| TopicEntry {
                id,
                topic_name: t.name.clone(),
                msg_type: t.msg_type.clone(),
                serialization_type: t.serialization_type.clone(),
            })
            .collect();
        if let Err(e) = bag::write_metadata(
            &f.folder,
            &self
                .extra_attributes
                .lock()
                .unwrap_or_else(|e| e.into_inner()),
            &topics,
            &f.entries,
        ) {
            // Not rate limited: it happens when a file opens or closes, and a flood of
            // failed messages (a full disk) must not hide it.
            tracing::warn!(
                "record action '{}': {} is not written: {e}",
                self.name,
                f.folder.join("metadata.yaml").display()
            );
        }
    }

    /// Copies `extra_file_path` entries into `<bag>/extra_file/` (a missing one is a
    /// warning).
    fn copy_extra_files(&self, bag: &Path) {
        if self.options.extra_file_path.is_empty() {
            return;
        }
        let folder = bag.join("extra_file");
        if let Err(e) = std::fs::create_dir_all(&folder) {
            tracing::warn!(
                "record action '{}': cannot create {}: {e}",
                self.name,
                folder.display()
            );
            return;
        }
        for p in &self.options.extra_file_path {
            let src = Path::new(p);
            let Some(name) = src.file_name() else {
                continue;
            };
            let result = if src.is_dir() {
                copy_dir(src, &folder.join(name))
            } else {
                std::fs::copy(src, folder.join(name)).map(|_| ())
            };
            if let Err(e) = result {
                tracing::warn!(
                    "record action '{}': extra_file_path '{p}' is not copied: {e}",
                    self.name
                );
            }
        }
    }

    /// Stops accepting, writes what is queued and closes the file (shutdown).
    pub(crate) fn stop(self: &Arc<Self>) {
        self.accepting.store(false, Ordering::SeqCst);
        if let Some(sig) = &self.signal {
            let mut s = sig.state.lock().unwrap_or_else(|e| e.into_inner());
            s.recording = false;
            s.session += 1;
            s.cache.take();
        }
        let mut f = self.files.lock().unwrap_or_else(|e| e.into_inner());
        self.end_bag(&mut f);
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let early = if self.signal.is_some() {
            format!(
                ", {} let go early from the preparation window ({QUEUE_BYTES} bytes full)",
                g(&self.stats.window_early)
            )
        } else {
            String::new()
        };
        // A signal action that was never started has made no bag folder.
        let into = if f.folder.as_os_str().is_empty() {
            "no bag folder (StartRecord never came)".to_owned()
        } else {
            f.folder.display().to_string()
        };
        tracing::info!(
            "record action '{}': {} messages written to {into}, {} dropped (write queue full), {} failed, {} skipped by sample_freq{early}",
            self.name,
            g(&self.stats.written),
            g(&self.stats.dropped_full),
            g(&self.stats.failed),
            g(&self.stats.skipped_sample)
        );
    }
}

fn copy_dir(src: &Path, dst: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(dst)?;
    for entry in std::fs::read_dir(src)? {
        let entry = entry?;
        let to = dst.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_dir(&entry.path(), &to)?;
        } else {
            std::fs::copy(entry.path(), to)?;
        }
    }
    Ok(())
}

/// An error and its causes, as `what: cause: cause` (the `mcap` crate's I/O error says
/// only "I/O error from writing", its cause which one, e.g. "No space left on device").
fn with_causes(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(log_time: u64, bytes: usize) -> Entry {
        Entry {
            topic: 0,
            sequence: 0,
            log_time,
            publish_time: 0,
            data: vec![0u8; bytes].into(),
        }
    }

    /// The write queue is full at its count of messages or at its bytes, whichever comes
    /// first; an empty queue takes a message of any size; taking it all empties the count.
    #[test]
    fn the_write_queue_is_bounded_by_messages_and_by_bytes() {
        let mut q = Held::default();
        assert_eq!(
            q.full(5000, 3, 1000),
            None,
            "an empty queue takes any message"
        );
        q.push(entry(0, 5000));
        assert_eq!(
            q.full(1, 3, 1000).as_deref(),
            Some("1000 bytes: 5000 are waiting, and this one has 1")
        );
        q.take();
        assert_eq!((q.entries.len(), q.bytes), (0, 0));
        for t in 0..3 {
            assert_eq!(q.full(100, 3, 1000), None);
            q.push(entry(t, 100));
        }
        assert_eq!(q.full(100, 3, 1000).as_deref(), Some("3 messages"));
        assert_eq!(q.pop().map(|e| e.log_time), Some(0));
        assert_eq!(q.bytes, 200);
        assert_eq!(q.full(800, 3, 1000), None);
        assert!(q.full(801, 3, 1000).is_some());
    }

    /// A preparation window lets go of what is older than its duration, and of its oldest
    /// while it holds more than its bytes, counting only those; the newest always stays.
    #[test]
    fn a_preparation_window_is_bounded_by_time_and_by_bytes() {
        let mut w = Held::default();
        for t in 0..10 {
            assert_eq!(w.keep_window(entry(t, 10), 5, 1000), 0);
        }
        // Times 4 to 9: none is older than 9 - 5.
        let times = |w: &Held| w.entries.iter().map(|e| e.log_time).collect::<Vec<_>>();
        assert_eq!(times(&w), [4, 5, 6, 7, 8, 9]);
        assert_eq!(w.bytes, 60);
        // 960 bytes more: 1020 in all, so the two oldest go early.
        assert_eq!(w.keep_window(entry(9, 960), 5, 1000), 2);
        assert_eq!(times(&w), [6, 7, 8, 9, 9]);
        assert_eq!(w.bytes, 1000);
        // A message larger than the window's bytes stays, alone.
        assert_eq!(w.keep_window(entry(10, 2000), 5, 1000), 5);
        assert_eq!(times(&w), [10]);
        assert_eq!(w.bytes, 2000);
    }
}
