//! `topic_logger_plugin` (`libaimrt_topic_logger_plugin.so`): the log backend type
//! `topic_logger`, which publishes log lines on a channel topic as AimRT's
//! `aimrt.protocols.topic_logger.LogData`, so that another process (an `echo_plugin`, a
//! recorder, a log viewer) reads them over any channel backend.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: topic_logger_plugin
//!         path: ./target/debug/libaimrt_topic_logger_plugin.so
//!   log:
//!     backends:
//!       - type: topic_logger
//!         options:
//!           topic_name: log_topic              # required
//!           timer_executor_name: timer_executor # required; must support timers
//!           interval_ms: 100                   # optional: how often a LogData goes out
//!           max_msg_size: 4096                 # optional: longer messages are cut (bytes)
//!           module_filter: "(.*)"              # read by the runtime, as for console
//! ```
//!
//! Every `interval_ms` the lines logged since the last publish go out as one `LogData`,
//! in the order they were logged; nothing is published while no line waits (the timer
//! stops, as AimRT's). Lines logged before the modules have started are held and
//! published at the first interval after. Several `topic_logger` entries may publish on
//! different topics (or the same one) with different `module_filter`s.
#![deny(unsafe_code)]

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, UNIX_EPOCH};

use aimrt_plugin_api::channel::Publisher;
use aimrt_plugin_api::{
    create_timer, BackendOptions, CoreRef, Error, LogBackend, LogEntry, Plugin, PluginOptions,
    RateLimit, Registrar, Timer,
};
use aimrt_protocols::topic_logger::{LogData, SingleLogData};
use serde::{Deserialize, Serialize};

/// Lines one backend holds at most while they wait to be published; beyond, a line is
/// refused and the runtime counts it as lost (the timer executor is not keeping up).
pub const MAX_QUEUED_LINES: usize = 100_000;

/// The options of one `topic_logger` entry (AimRT's, checked strictly).
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct TopicLoggerOptions {
    /// The topic the lines are published on.
    topic_name: String,
    /// The executor the publishing timer runs on (`timer_name` in AimRT's first example).
    #[serde(alias = "timer_name")]
    timer_executor_name: String,
    /// How often the waiting lines are published, in milliseconds.
    #[serde(default = "default_interval_ms")]
    interval_ms: u32,
    /// The most bytes of a line's message published; a longer one is cut at a character
    /// boundary. Absent: no limit (AimRT's `SIZE_MAX`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    max_msg_size: Option<u64>,
}

fn default_interval_ms() -> u32 {
    100
}

/// The plugin's own options: none (AimRT's has none either).
#[derive(Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct NoOptions {}

/// `message` cut to at most `max` bytes, at a character boundary.
fn cut(message: &str, max: usize) -> &str {
    if message.len() <= max {
        return message;
    }
    let mut end = max;
    while !message.is_char_boundary(end) {
        end -= 1;
    }
    &message[..end]
}

/// One line as AimRT's `SingleLogData`.
fn single(entry: &LogEntry<'_>, max_msg_size: usize) -> SingleLogData {
    let time_point = entry
        .time
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    SingleLogData {
        module_name: entry.module.to_owned(),
        thread_id: u64::try_from(entry.thread_id).unwrap_or(0),
        time_point,
        // AimRT's numbers: Trace 0 … Fatal 5, Off 6.
        level: entry.level as i32,
        line: entry.source_line,
        file_name: entry.file.to_owned(),
        function_name: entry.function.to_owned(),
        message: cut(entry.message, max_msg_size).to_owned(),
    }
}

/// The lines waiting, and the timer's state.
#[derive(Debug, Default)]
struct Queue {
    lines: Vec<SingleLogData>,
    /// Publishing may start (the modules have started) and has not stopped.
    running: bool,
    /// A timer run is scheduled.
    armed: bool,
}

/// What one `topic_logger` entry publishes, shared by its backend (the log thread) and
/// its timer (the timer executor).
struct Outbox {
    topic: String,
    executor: String,
    interval: Duration,
    /// Where the entry is in the config, for errors.
    location: String,
    publisher: Publisher<LogData>,
    queue: Mutex<Queue>,
    timer: OnceLock<Timer>,
    published_lines: AtomicU64,
    published_msgs: AtomicU64,
    lost_lines: AtomicU64,
    warn: RateLimit,
}

impl Outbox {
    fn queue(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Schedules the timer's next run (one interval from now).
    fn arm(&self) {
        let Some(timer) = self.timer.get() else {
            return;
        };
        if timer.reset().is_err() {
            // The executor refused the run (it is shutting down): the lines stay queued
            // and are counted at shutdown; the next line tries again.
            self.queue().armed = false;
        }
    }

    /// Holds `line` for the next publish; refused when too many wait.
    fn push(&self, line: SingleLogData) -> Result<(), String> {
        let arm = {
            let mut q = self.queue();
            if q.lines.len() >= MAX_QUEUED_LINES {
                return Err(format!(
                    "topic_logger on topic '{}': {MAX_QUEUED_LINES} lines wait to be published; the timer executor '{}' is not keeping up",
                    self.topic, self.executor
                ));
            }
            q.lines.push(line);
            let arm = q.running && !q.armed;
            q.armed |= arm;
            arm
        };
        if arm {
            self.arm();
        }
        Ok(())
    }

    /// A timer run: publishes the waiting lines as one `LogData`, or stops the timer when
    /// none wait.
    fn tick(&self, timer: &Timer) {
        let lines = {
            let mut q = self.queue();
            if q.lines.is_empty() || !q.running {
                // Cancelled under the lock: a line pushed after this re-arms the timer.
                q.armed = false;
                timer.cancel();
                return;
            }
            std::mem::take(&mut q.lines)
        };
        let n = lines.len() as u64;
        match self.publisher.publish(LogData { logs: lines }) {
            Ok(()) => {
                self.published_lines.fetch_add(n, Ordering::Relaxed);
                self.published_msgs.fetch_add(1, Ordering::Relaxed);
            }
            Err(e) => {
                let lost = self.lost_lines.fetch_add(n, Ordering::Relaxed) + n;
                if let Some(held) = self.warn.admit() {
                    tracing::warn!(
                        "topic_logger on topic '{}': {n} log lines were not published ({lost} in all; {held} such warnings held back): {e}",
                        self.topic
                    );
                }
            }
        }
    }
}

/// The backend the runtime writes to: one per `topic_logger` entry.
struct TopicLogger {
    outbox: Arc<Outbox>,
    max_msg_size: usize,
}

impl LogBackend for TopicLogger {
    fn write(&mut self, entry: &LogEntry<'_>) -> Result<(), String> {
        self.outbox.push(single(entry, self.max_msg_size))
    }
}

/// The plugin: its core (for the publishers) and every entry's outbox.
#[derive(Default)]
struct Shared {
    core: OnceLock<CoreRef>,
    outboxes: Mutex<Vec<Arc<Outbox>>>,
    /// One publisher per topic: entries on the same topic share it.
    publishers: Mutex<BTreeMap<String, Publisher<LogData>>>,
}

impl Shared {
    fn outboxes(&self) -> Vec<Arc<Outbox>> {
        self.outboxes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The backend of one `topic_logger` entry (the runtime calls this once plugins are
    /// loaded, before the channel is configured, so the publisher is registered in time).
    fn backend(&self, options: &BackendOptions) -> Result<TopicLogger, Error> {
        let o: TopicLoggerOptions = options.read()?;
        if o.topic_name.is_empty() {
            return Err(
                options.invalid("topic_name is empty; name the topic the lines are published on")
            );
        }
        if o.timer_executor_name.is_empty() {
            return Err(options.invalid(
                "timer_executor_name is empty; name an executor that supports timers (e.g. one of type asio_thread)",
            ));
        }
        if o.interval_ms == 0 {
            return Err(options.invalid("interval_ms is 0; give the publishing interval in milliseconds, at least 1 (default 100)"));
        }
        if o.max_msg_size == Some(0) {
            return Err(options.invalid(
                "max_msg_size is 0: every message would be empty; give at least 1 byte, or leave it out for no limit",
            ));
        }
        let Some(core) = self.core.get() else {
            return Err(options.invalid("topic_logger_plugin has not been initialized"));
        };
        let publisher = {
            let mut publishers = self.publishers.lock().unwrap_or_else(|e| e.into_inner());
            match publishers.get(&o.topic_name) {
                Some(p) => p.clone(),
                None => {
                    let p = core
                        .channel()?
                        .publisher::<LogData>(&o.topic_name)
                        .map_err(|e| {
                            options
                                .invalid(format!("cannot publish on topic '{}': {e}", o.topic_name))
                        })?;
                    publishers.insert(o.topic_name.clone(), p.clone());
                    p
                }
            }
        };
        let outbox = Arc::new(Outbox {
            topic: o.topic_name,
            executor: o.timer_executor_name,
            interval: Duration::from_millis(u64::from(o.interval_ms)),
            location: options.location().to_owned(),
            publisher,
            queue: Mutex::new(Queue::default()),
            timer: OnceLock::new(),
            published_lines: AtomicU64::new(0),
            published_msgs: AtomicU64::new(0),
            lost_lines: AtomicU64::new(0),
            warn: RateLimit::from_millis(1000),
        });
        self.outboxes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(outbox.clone());
        Ok(TopicLogger {
            outbox,
            max_msg_size: o
                .max_msg_size
                .map_or(usize::MAX, |m| usize::try_from(m).unwrap_or(usize::MAX)),
        })
    }
}

struct TopicLoggerPlugin {
    shared: Arc<Shared>,
}

impl Plugin for TopicLoggerPlugin {
    fn name(&self) -> &str {
        "topic_logger_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let _: NoOptions = registrar.read_options(options)?;
        let core = registrar.core()?;
        let _ = self.shared.core.set(core);
        let shared = self.shared.clone();
        registrar
            .register_log_backend_type("topic_logger", move |o: &BackendOptions| shared.backend(o))
    }

    /// Makes each entry's timer on its executor (the executors exist from here on); an
    /// executor that does not exist or has no timers stops start-up.
    fn start(&mut self) -> Result<(), Error> {
        let Some(core) = self.shared.core.get() else {
            return Ok(());
        };
        for outbox in self.shared.outboxes() {
            let fail = |why: String| Error::Options {
                what: format!(
                    "options of log backend 'topic_logger' at {}",
                    outbox.location
                ),
                message: why,
            };
            let executor = core
                .executor(&outbox.executor)
                .map_err(|e| fail(format!("timer_executor_name: {e}")))?;
            let ticking = Arc::downgrade(&outbox);
            let timer = create_timer(
                executor,
                outbox.interval,
                move |t: &Timer| {
                    if let Some(o) = ticking.upgrade() {
                        o.tick(t);
                    }
                },
                false,
            )
            .map_err(|e| {
                fail(format!(
                    "timer_executor_name '{}' cannot run the publishing timer ({e}); name an executor that supports timers (e.g. one of type asio_thread)",
                    outbox.executor
                ))
            })?;
            let _ = outbox.timer.set(timer);
        }
        Ok(())
    }

    /// Publishing starts once the modules have started (AimRT's kPostStartChannel): the
    /// lines held so far go out one interval later.
    fn post_start(&mut self) {
        for outbox in self.shared.outboxes() {
            let arm = {
                let mut q = outbox.queue();
                q.running = true;
                let arm = !q.lines.is_empty() && !q.armed;
                q.armed |= arm;
                arm
            };
            if arm {
                outbox.arm();
            }
        }
    }

    /// Stops the timers (the channel has shut down) and says what was published and what
    /// was not.
    fn shutdown(&mut self) {
        for outbox in self.shared.outboxes() {
            let unpublished = {
                let mut q = outbox.queue();
                q.running = false;
                q.armed = false;
                std::mem::take(&mut q.lines).len()
            };
            if let Some(timer) = outbox.timer.get() {
                timer.cancel();
            }
            let lost = outbox.lost_lines.load(Ordering::Relaxed);
            tracing::info!(
                "topic_logger on topic '{}': {} lines published in {} messages; {lost} lost to failed publishes; {unpublished} logged since the last publish were not published (the channel has shut down)",
                outbox.topic,
                outbox.published_lines.load(Ordering::Relaxed),
                outbox.published_msgs.load(Ordering::Relaxed),
            );
        }
    }
}

fn plugin() -> Box<dyn Plugin> {
    Box::new(TopicLoggerPlugin {
        shared: Arc::new(Shared::default()),
    })
}

aimrt_plugin_api::export_plugin!(plugin);

#[cfg(test)]
mod tests {
    use super::*;
    use aimrt_plugin_api::LogLevel;

    #[test]
    fn a_long_message_is_cut_at_a_character_boundary() {
        assert_eq!(cut("hello", 10), "hello");
        assert_eq!(cut("hello", 5), "hello");
        assert_eq!(cut("hello", 3), "hel");
        // 'é' is two bytes: a cut inside it keeps the character out.
        assert_eq!(cut("aé", 2), "a");
        assert_eq!(cut("aé", 3), "aé");
        assert_eq!(cut("日本", 5), "日");
    }

    #[test]
    fn a_line_becomes_aimrts_single_log_data() {
        let mut entry = LogEntry::new(LogLevel::Warn, "[x] ignored formatted line");
        entry.time = UNIX_EPOCH + Duration::from_nanos(1_700_000_000_123_456_789);
        entry.thread_id = 4242;
        entry.module = "LoggerModule";
        entry.file = "src/lib.rs";
        entry.source_line = 17;
        entry.function = "logger::start";
        entry.message = "low battery: 12%";
        let s = single(&entry, 11);
        assert_eq!(s.module_name, "LoggerModule");
        assert_eq!(s.thread_id, 4242);
        assert_eq!(s.time_point, 1_700_000_000_123_456_789);
        assert_eq!(s.level, 3, "AimRT's Warn");
        assert_eq!(s.line, 17);
        assert_eq!(s.file_name, "src/lib.rs");
        assert_eq!(s.function_name, "logger::start");
        assert_eq!(
            s.message, "low battery",
            "cut to max_msg_size, the message alone"
        );
        entry.thread_id = -1;
        assert_eq!(single(&entry, usize::MAX).thread_id, 0, "unknown");
    }

    #[test]
    fn levels_have_aimrts_numbers() {
        use aimrt_protocols::topic_logger::LogLevel as Pb;
        for (ours, theirs) in [
            (LogLevel::Trace, Pb::Trace),
            (LogLevel::Debug, Pb::Debug),
            (LogLevel::Info, Pb::Info),
            (LogLevel::Warn, Pb::Warn),
            (LogLevel::Error, Pb::Error),
            (LogLevel::Fatal, Pb::Fatal),
            (LogLevel::Off, Pb::Off),
        ] {
            assert_eq!(ours as i32, theirs as i32, "{ours:?}");
        }
    }

    #[test]
    fn options_are_aimrts_with_strict_checks() {
        let shared = Shared::default();
        let read = |json: &str| {
            shared
                .backend(&BackendOptions::from_json(
                    "log backend 'topic_logger'",
                    json,
                    "cfg.yaml:7:9",
                ))
                .err()
                .map(|e| e.to_string())
        };
        let missing = read(r#"{"timer_executor_name": "t"}"#).unwrap();
        assert!(missing.contains("topic_name"), "{missing}");
        let unknown =
            read(r#"{"topic_name": "l", "timer_executor_name": "t", "intervl_ms": 5}"#).unwrap();
        assert!(
            unknown.contains("intervl_ms") && unknown.contains("interval_ms"),
            "{unknown}"
        );
        let zero =
            read(r#"{"topic_name": "l", "timer_executor_name": "t", "interval_ms": 0}"#).unwrap();
        assert!(
            zero.contains("interval_ms is 0") && zero.contains("cfg.yaml:7:9"),
            "{zero}"
        );
        let empty = read(r#"{"topic_name": "", "timer_executor_name": "t"}"#).unwrap();
        assert!(empty.contains("topic_name is empty"), "{empty}");
        let size =
            read(r#"{"topic_name": "l", "timer_executor_name": "t", "max_msg_size": 0}"#).unwrap();
        assert!(size.contains("max_msg_size is 0"), "{size}");
        // AimRT's first example names the executor `timer_name`: read as the same key.
        let alias = read(r#"{"topic_name": "l", "timer_name": "t"}"#).unwrap();
        assert!(
            alias.contains("not been initialized"),
            "the options were read: {alias}"
        );
    }
}
