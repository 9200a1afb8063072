//! `BenchmarkPublisherModule` and `BenchmarkSubscriberModule`: AimRT's channel benchmark.
//!
//! The publisher runs `bench_plans` one after another. Each plan is framed by a
//! `BenchmarkSignal` on `benchmark_signal` (`Begin` with the plan's figures, `End`), and
//! in between sends `BenchmarkMessage`s (`seq`, send time in ns since the Unix epoch,
//! `msg_size` bytes of `data`) on `test_topic_<i>` at `channel_frq` a second per sender.
//! The subscriber records each message's latency (receive time minus send time) and, at
//! `End`, logs AimRT's `Benchmark plan <i> completed, report:` block. Both speak AimRT's
//! `benchmark.proto`, so either side can be AimRT's.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use aimrt_plugin_api::channel::Publisher;
use aimrt_plugin_api::{CoreRef, DynamicLatch, Error, ExecutorRef, Module, ModuleInfo, RateLimit};
use aimrt_protocols::example::{BenchmarkMessage, BenchmarkSignal, BenchmarkStatus};
use serde::Deserialize;

/// The topic of the plans' `Begin`, `End` and `WarmUp` signals.
pub const SIGNAL_TOPIC: &str = "benchmark_signal";

/// The topic of sender (multi-topic) or of every sender (parallel) number `i`.
pub fn test_topic(i: usize) -> String {
    format!("test_topic_{i}")
}

/// The most messages one plan may announce (`send_num × topic_number`): a subscriber keeps
/// 16 bytes for each, so a `Begin` beyond this (160 MB) is refused, not allocated.
pub const MAX_PLAN_MESSAGES: u64 = 10_000_000;

/// The most topics a subscriber takes (`max_topic_number`): each is a subscription.
pub const MAX_TOPICS: u32 = 10_000;

/// The largest `msg_size` a plan may ask for (each sender holds one message).
pub const MAX_MSG_SIZE: u32 = 256 << 20;

/// A signal as one line of JSON, as AimRT's `Pb2CompactJson` prints it.
fn signal_json(signal: &BenchmarkSignal) -> String {
    serde_json::to_string(signal).unwrap_or_else(|e| format!("<not json: {e}>"))
}

/// Nanoseconds since the Unix epoch (AimRT's `GetCurTimestampNs`): the two sides compare
/// clocks, so across machines they must be synchronised.
fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

// ---------------------------------------------------------------------------------------
// Publisher
// ---------------------------------------------------------------------------------------

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
enum PerfMode {
    /// `topic_number` senders, sender `i` on `test_topic_<i>`, `msg_count` messages each.
    #[serde(rename = "multi-topic")]
    MultiTopic,
    /// `parallel_number` senders on `test_topic_0`, `msg_count` messages between them.
    #[serde(rename = "parallel")]
    Parallel,
}

impl PerfMode {
    fn name(self) -> &'static str {
        match self {
            PerfMode::MultiTopic => "multi-topic",
            PerfMode::Parallel => "parallel",
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct PlanConfig {
    perf_mode: PerfMode,
    /// Messages a second per sender.
    channel_frq: u32,
    /// Bytes of `data` in each message.
    msg_size: u32,
    /// Messages per topic.
    msg_count: u32,
    /// Senders of a multi-topic plan (one topic each).
    #[serde(default)]
    topic_number: Option<u32>,
    /// Senders of a parallel plan (all on `test_topic_0`).
    #[serde(default)]
    parallel_number: Option<u32>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PublisherConfig {
    max_topic_number: u32,
    max_parallel_number: u32,
    #[serde(default)]
    bench_plans: Vec<PlanConfig>,
}

/// A plan, checked.
#[derive(Debug, Clone, Copy)]
struct Plan {
    mode: PerfMode,
    frequency: u32,
    msg_size: u32,
    msg_count: u32,
    /// Senders: `topic_number` or `parallel_number`.
    senders: u32,
}

impl Plan {
    fn check(i: usize, p: &PlanConfig, cfg: &PublisherConfig) -> Result<Plan, Error> {
        let bad = |what: String| Error::msg(format!("bench_plans[{i}]: {what}"));
        let (key, number, max_key, max) = match p.perf_mode {
            PerfMode::MultiTopic => (
                "topic_number",
                p.topic_number,
                "max_topic_number",
                cfg.max_topic_number,
            ),
            PerfMode::Parallel => (
                "parallel_number",
                p.parallel_number,
                "max_parallel_number",
                cfg.max_parallel_number,
            ),
        };
        let Some(senders) = number else {
            return Err(bad(format!("a {} plan needs {key}", p.perf_mode.name())));
        };
        if senders == 0 || senders > max {
            return Err(bad(format!(
                "{key} is {senders}; it must be in 1 ..= {max_key} ({max})"
            )));
        }
        if p.channel_frq == 0 {
            return Err(bad(
                "channel_frq is 0; it must be at least 1 message a second".into(),
            ));
        }
        if p.msg_count == 0 {
            return Err(bad("msg_count is 0; it must be at least 1".into()));
        }
        if p.msg_size > MAX_MSG_SIZE {
            return Err(bad(format!(
                "msg_size is {}; at most {MAX_MSG_SIZE} bytes",
                p.msg_size
            )));
        }
        let topics = if p.perf_mode == PerfMode::MultiTopic {
            senders
        } else {
            1
        };
        if u64::from(p.msg_count) * u64::from(topics) > MAX_PLAN_MESSAGES {
            return Err(bad(format!(
                "msg_count × topics is {}; a subscriber records at most {MAX_PLAN_MESSAGES} messages a plan",
                u64::from(p.msg_count) * u64::from(topics)
            )));
        }
        Ok(Plan {
            mode: p.perf_mode,
            frequency: p.channel_frq,
            msg_size: p.msg_size,
            msg_count: p.msg_count,
            senders,
        })
    }

    /// The `Begin` signal of plan `id`.
    fn begin(&self, id: u32) -> BenchmarkSignal {
        let multi = self.mode == PerfMode::MultiTopic;
        BenchmarkSignal {
            status: BenchmarkStatus::Begin.into(),
            bench_plan_id: id,
            mode: self.mode.name().to_owned(),
            topic_number: if multi { self.senders } else { 1 },
            parallel_number: if multi { 1 } else { self.senders },
            send_num: self.msg_count,
            message_size: self.msg_size,
            send_frequency: self.frequency,
        }
    }

    /// The topic index and the `seq` range of sender `s`: in a parallel plan the senders
    /// share `test_topic_0` and split `0..msg_count` (the last takes the remainder).
    fn sender(&self, s: u32) -> (usize, std::ops::Range<u32>) {
        match self.mode {
            PerfMode::MultiTopic => (s as usize, 0..self.msg_count),
            PerfMode::Parallel => {
                let share = self.msg_count / self.senders;
                let end = if s + 1 == self.senders {
                    self.msg_count
                } else {
                    (s + 1) * share
                };
                (0, s * share..end)
            }
        }
    }
}

/// Runs AimRT's channel benchmark plans from `start` (config keys as AimRT's:
/// `max_topic_number`, `max_parallel_number`, `bench_plans[]` with `perf_mode`
/// (`multi-topic` or `parallel`), `channel_frq`, `msg_size`, `msg_count`, and
/// `topic_number` or `parallel_number`). Without a config node it warns and stays idle.
///
/// The plans run on `publish_control_executor`; sender `i` runs on `publish_executor_<i>`
/// (executors `0 .. max(max_topic_number, max_parallel_number)` must exist; give them a
/// thread each, e.g. `simple_thread`: a sender keeps its thread for the whole plan). First
/// 10 `WarmUp` signals 100 ms apart, then per plan: `Begin`, 1 s, the messages, 1 s,
/// `End`, 1 s. After each plan the module logs how many messages the channel refused.
#[derive(Debug, Default)]
pub struct BenchmarkPublisherModule {
    setup: Option<PublisherSetup>,
    running: Option<(DynamicLatch, mpsc::Receiver<()>)>,
}

#[derive(Debug)]
struct PublisherSetup {
    plans: Vec<Plan>,
    control: ExecutorRef,
    senders: Vec<ExecutorRef>,
    signal: Publisher<BenchmarkSignal>,
    topics: Vec<Publisher<BenchmarkMessage>>,
}

impl Module for BenchmarkPublisherModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("BenchmarkPublisherModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        // A pkg loaded whole (no `enable_modules`) brings this module without a config
        // node: it stays idle instead of failing the start-up.
        let node: serde_json::Value = core.config()?;
        if node.as_object().is_some_and(|o| o.is_empty()) {
            tracing::warn!(
                "No config node 'BenchmarkPublisherModule': no plans, nothing is published."
            );
            return Ok(());
        }
        let cfg: PublisherConfig = core.config()?;
        let plans = cfg
            .bench_plans
            .iter()
            .enumerate()
            .map(|(i, p)| Plan::check(i, p, &cfg))
            .collect::<Result<Vec<_>, _>>()?;
        let control = core.executor("publish_control_executor")?;
        let senders = (0..cfg.max_topic_number.max(cfg.max_parallel_number))
            .map(|i| core.executor(&format!("publish_executor_{i}")))
            .collect::<Result<Vec<_>, _>>()?;
        let channel = core.channel()?;
        let signal = channel.publisher::<BenchmarkSignal>(SIGNAL_TOPIC)?;
        let topics = (0..cfg.max_topic_number as usize)
            .map(|i| channel.publisher::<BenchmarkMessage>(&test_topic(i)))
            .collect::<Result<Vec<_>, _>>()?;
        self.setup = Some(PublisherSetup {
            plans,
            control,
            senders,
            signal,
            topics,
        });
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(setup) = self.setup.take() else {
            return Ok(());
        };
        // At 1 while the module runs; `shutdown` counts it down to 0, waking every
        // `stop.wait_timeout` (true: stopped) at once.
        let stop = DynamicLatch::new();
        stop.try_add(1);
        let (done_tx, done) = mpsc::channel();
        let stopping = stop.clone();
        let control = setup.control;
        control.execute(move || {
            main_loop(&setup, &stopping);
            let _ = done_tx.send(());
        })?;
        self.running = Some((stop, done));
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        if let Some((stop, done)) = self.running.take() {
            let _ = stop.count_down(1);
            // Disconnected: the loop ended without a word (its task was dropped unrun).
            if let Err(mpsc::RecvTimeoutError::Timeout) = done.recv_timeout(Duration::from_secs(10))
            {
                tracing::warn!("The benchmark loop did not end within 10 s.");
            }
        }
        tracing::info!("Shutdown succeeded.");
    }
}

fn publish_signal(setup: &PublisherSetup, signal: BenchmarkSignal) {
    if let Err(e) = setup.signal.publish(signal) {
        tracing::error!("Publish of a benchmark signal failed: {e}");
    }
}

fn main_loop(setup: &PublisherSetup, stop: &DynamicLatch) {
    tracing::info!("Start Bench.");
    for _ in 0..10 {
        publish_signal(
            setup,
            BenchmarkSignal {
                status: BenchmarkStatus::WarmUp.into(),
                ..Default::default()
            },
        );
        if stop.wait_timeout(Duration::from_millis(100)) {
            return;
        }
    }
    for (id, plan) in setup.plans.iter().enumerate() {
        if !run_plan(setup, stop, id as u32, *plan) || stop.wait_timeout(Duration::from_secs(1)) {
            tracing::info!("Bench stopped.");
            return;
        }
    }
    tracing::info!("Bench completed.");
}

/// Runs one plan; `false` if the module stopped during it.
fn run_plan(setup: &PublisherSetup, stop: &DynamicLatch, id: u32, plan: Plan) -> bool {
    let begin = plan.begin(id);
    let expected = u64::from(plan.msg_count) * u64::from(begin.topic_number);
    tracing::info!(
        "Publish benchmark start signal, data: {}",
        signal_json(&begin)
    );
    publish_signal(setup, begin);
    if stop.wait_timeout(Duration::from_secs(1)) {
        return false;
    }
    let counts = Arc::new(SendCounts::default());
    // What the channel dropped after `publish` returned (a backend's full queue, no
    // subscriber): counted per topic, read before and after the plan.
    let mut plan_topics: Vec<usize> = (0..plan.senders).map(|s| plan.sender(s).0).collect();
    plan_topics.sort_unstable();
    plan_topics.dedup();
    let dropped = || -> u64 {
        plan_topics
            .iter()
            .filter_map(|&t| setup.topics[t].stats())
            .map(|s| s.dropped_total())
            .sum()
    };
    let dropped_before = dropped();
    let (done_tx, done) = mpsc::channel::<()>();
    for s in 0..plan.senders {
        let (topic, seqs) = plan.sender(s);
        let publisher = setup.topics[topic].clone();
        let (stop, counts, done_tx) = (stop.clone(), counts.clone(), done_tx.clone());
        let task = move || {
            send(&publisher, &stop, plan, seqs, &counts);
            let _ = done_tx.send(());
        };
        if let Err(e) = setup.senders[s as usize].execute(task) {
            tracing::error!("publish_executor_{s} refused sender {s}: {e}");
        }
    }
    drop(done_tx);
    // Each sender holds an end of the channel: this ends when every one has finished, or
    // was refused or dropped unrun by its executor.
    for () in done.iter() {}
    let stopped = stop.wait_timeout(Duration::from_secs(1));
    // After that second: drops that happen after `publish` on another thread are in.
    let dropped_in_plan = dropped().saturating_sub(dropped_before);
    let end = BenchmarkSignal {
        status: BenchmarkStatus::End.into(),
        bench_plan_id: id,
        ..Default::default()
    };
    tracing::info!("Publish benchmark end signal, data: {}", signal_json(&end));
    publish_signal(setup, end);
    tracing::info!(
        "Benchmark plan {id}: sent {} of {expected} messages, {} refused by the channel, {dropped_in_plan} dropped after publish (counted in the topics' stats).",
        counts.sent.load(Ordering::Relaxed),
        counts.refused.load(Ordering::Relaxed)
    );
    !stopped
}

/// What the senders of a plan did.
#[derive(Debug, Default)]
struct SendCounts {
    sent: AtomicU64,
    refused: AtomicU64,
}

/// One sender: messages `seqs` at `plan.frequency` a second, on a fixed schedule (a late
/// message does not push the later ones back).
fn send(
    publisher: &Publisher<BenchmarkMessage>,
    stop: &DynamicLatch,
    plan: Plan,
    seqs: std::ops::Range<u32>,
    counts: &SendCounts,
) {
    let mut msg = Arc::new(BenchmarkMessage {
        seq: 0,
        timestamp: 0,
        data: random_alphanumerics(plan.msg_size as usize),
    });
    let period = Duration::from_nanos(1_000_000_000 / u64::from(plan.frequency));
    let mut due = Instant::now();
    for seq in seqs {
        // The runtime keeps no reference after the publish returns unless a subscriber
        // in this process still holds the message; only then is it copied.
        let m = Arc::make_mut(&mut msg);
        m.seq = seq;
        m.timestamp = now_ns();
        if let Err(e) = publisher.publish(msg.clone()) {
            // Counted and reported after the plan; the first one says why.
            if counts.refused.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!("Publish on '{}' refused: {e}", publisher.topic());
            }
        } else {
            counts.sent.fetch_add(1, Ordering::Relaxed);
        }
        due += period;
        if stop.wait_timeout(due.saturating_duration_since(Instant::now())) {
            return;
        }
    }
}

/// `len` letters and digits from a small xorshift generator, seeded from the clock.
fn random_alphanumerics(len: usize) -> Vec<u8> {
    const CHARS: &[u8] = b"abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789";
    let mut x = now_ns() | 1;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            CHARS[(x % CHARS.len() as u64) as usize]
        })
        .collect()
}

// ---------------------------------------------------------------------------------------
// Subscriber
// ---------------------------------------------------------------------------------------

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SubscriberConfig {
    /// Topics `test_topic_0 ..` subscribed; without it, none (only the signals).
    #[serde(default)]
    max_topic_number: u32,
}

/// Receives AimRT's channel benchmark (config key as AimRT's: `max_topic_number`, the
/// topics `test_topic_0 ..` it subscribes, default 0) and logs a report per plan at its
/// `End`: AimRT's lines (mode, frequency, topic and parallel number, message size and count,
/// sent, received, loss rate, min/max/avg/p90/p99/p999 latency in µs), then what AimRT
/// does not count: messages of the wrong size, with a `seq` outside the plan, received
/// twice, or received before they were sent (clocks apart).
///
/// Unlike AimRT's, a plan with nothing received reports `n/a` latencies (AimRT's reads
/// an empty list), a `Begin` during a plan abandons that plan with a warning and starts
/// the new one, and messages outside a plan are counted and warned about at most once a
/// second, not once each.
#[derive(Debug, Default)]
pub struct BenchmarkSubscriberModule;

impl Module for BenchmarkSubscriberModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("BenchmarkSubscriberModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: SubscriberConfig = core.config()?;
        if cfg.max_topic_number > MAX_TOPICS {
            return Err(Error::msg(format!(
                "max_topic_number is {}; at most {MAX_TOPICS} topics can be subscribed",
                cfg.max_topic_number
            )));
        }
        let state = Arc::new(Receiver {
            max_topics: cfg.max_topic_number,
            current: Mutex::new(None),
            outside: RateLimit::from_millis(1000),
            odd: RateLimit::from_millis(1000),
        });
        let channel = core.channel()?;
        let on_signal = state.clone();
        channel
            .subscriber(SIGNAL_TOPIC)
            .subscribe_msg(move |signal: Arc<BenchmarkSignal>| {
                if let Some(report) = on_signal.signal(&signal) {
                    tracing::info!("{report}");
                }
            })?;
        for i in 0..cfg.max_topic_number as usize {
            let state = state.clone();
            channel.subscriber(&test_topic(i)).subscribe_msg(
                move |msg: Arc<BenchmarkMessage>| state.message(i, &msg, now_ns()),
            )?;
        }
        tracing::info!("Init succeeded.");
        Ok(())
    }
}

/// The subscriber's state, shared by its callbacks (which may run on several threads).
#[derive(Debug)]
struct Receiver {
    max_topics: u32,
    /// The plan between its `Begin` and its `End`.
    current: Mutex<Option<Recording>>,
    /// Warnings for messages outside a plan.
    outside: RateLimit,
    /// Warnings for odd messages inside a plan.
    odd: RateLimit,
}

/// One plan being received.
#[derive(Debug)]
struct Recording {
    begin: BenchmarkSignal,
    /// Per topic, per `seq`: (send ns, receive ns); receive 0 = not received.
    records: Vec<Vec<(u64, u64)>>,
    wrong_size: u64,
    bad_seq: u64,
    duplicates: u64,
    before_sent: u64,
}

impl Receiver {
    fn lock(&self) -> std::sync::MutexGuard<'_, Option<Recording>> {
        self.current.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Handles a signal; the report of the plan an `End` completes.
    fn signal(&self, signal: &BenchmarkSignal) -> Option<String> {
        tracing::info!("Receive new signal data: {}", signal_json(signal));
        match BenchmarkStatus::try_from(signal.status) {
            Ok(BenchmarkStatus::Begin) => self.begin(signal),
            Ok(BenchmarkStatus::End) => match self.lock().take() {
                Some(rec) => {
                    tracing::info!(
                        "Benchmark plan {} completed, evaluate...",
                        rec.begin.bench_plan_id
                    );
                    return Some(rec.report());
                }
                None => tracing::warn!(
                    "End of benchmark plan {} without its Begin: nothing to report.",
                    signal.bench_plan_id
                ),
            },
            Ok(BenchmarkStatus::WarmUp) => {}
            Err(_) => tracing::warn!(
                "Benchmark signal with unknown status {}: ignored.",
                signal.status
            ),
        }
        None
    }

    fn begin(&self, signal: &BenchmarkSignal) {
        let topics = signal.topic_number;
        let announced = u64::from(signal.send_num) * u64::from(topics);
        let refusal = if topics == 0 || topics > self.max_topics {
            Some(format!(
                "its topic number {topics} must be in 1 ..= max_topic_number ({})",
                self.max_topics
            ))
        } else if announced > MAX_PLAN_MESSAGES {
            Some(format!(
                "it announces {announced} messages, more than the {MAX_PLAN_MESSAGES} a plan may have"
            ))
        } else {
            None
        };
        let mut current = self.lock();
        if let Some(old) = current.take() {
            tracing::warn!(
                "Benchmark plan {} abandoned without its End: plan {} began.",
                old.begin.bench_plan_id,
                signal.bench_plan_id
            );
        }
        if let Some(why) = refusal {
            tracing::error!(
                "Benchmark plan {} not recorded: {why}.",
                signal.bench_plan_id
            );
            return;
        }
        *current = Some(Recording {
            begin: signal.clone(),
            records: vec![vec![(0, 0); signal.send_num as usize]; topics as usize],
            wrong_size: 0,
            bad_seq: 0,
            duplicates: 0,
            before_sent: 0,
        });
    }

    fn message(&self, topic: usize, msg: &BenchmarkMessage, recv_ns: u64) {
        let mut current = self.lock();
        let Some(rec) = current.as_mut() else {
            drop(current);
            if let Some(held) = self.outside.admit() {
                tracing::warn!(
                    "A message on '{}' arrived outside a benchmark plan ({} more since the last warning): ignored.",
                    test_topic(topic),
                    held
                );
            }
            return;
        };
        let odd = if msg.data.len() != rec.begin.message_size as usize {
            rec.wrong_size += 1;
            Some("has the wrong size")
        } else if let Some(slot) = rec
            .records
            .get_mut(topic)
            .and_then(|t| t.get_mut(msg.seq as usize))
        {
            if slot.1 != 0 {
                rec.duplicates += 1;
                Some("was received twice")
            } else {
                if recv_ns < msg.timestamp {
                    rec.before_sent += 1;
                }
                *slot = (msg.timestamp, recv_ns.max(1));
                None
            }
        } else {
            rec.bad_seq += 1;
            Some("has a seq or topic outside the plan")
        };
        drop(current);
        if let Some(what) = odd {
            if let Some(held) = self.odd.admit() {
                tracing::warn!(
                    "Message {} on '{}' {what} ({held} more odd messages since the last warning).",
                    msg.seq,
                    test_topic(topic)
                );
            }
        }
    }
}

impl Recording {
    /// AimRT's report, then ours.
    fn report(&self) -> String {
        let b = &self.begin;
        let send_count = u64::from(b.send_num) * u64::from(b.topic_number);
        let mut latencies: Vec<u64> = self
            .records
            .iter()
            .flatten()
            .filter(|r| r.1 != 0)
            .map(|&(sent, recv)| recv.saturating_sub(sent))
            .collect();
        latencies.sort_unstable();
        let n = latencies.len();
        let loss = if send_count == 0 {
            0.0
        } else {
            (send_count as f64 - n as f64) / send_count as f64 * 100.0
        };
        let us = |ns: u64| format!("{}", ns as f64 / 1000.0);
        let at = |p: f64| match n {
            0 => "n/a".to_owned(),
            _ => us(latencies[((n as f64 * p) as usize).min(n - 1)]),
        };
        let (min, max, avg) = match (latencies.first(), latencies.last()) {
            (Some(&lo), Some(&hi)) => (
                us(lo),
                us(hi),
                us((latencies.iter().map(|&l| u128::from(l)).sum::<u128>() / n as u128) as u64),
            ),
            _ => ("n/a".into(), "n/a".into(), "n/a".into()),
        };
        format!(
            "Benchmark plan {} completed, report:\nmode: {}\nfrequency: {} hz\ntopic number: {}\nparallel number: {}\nmsg size: {} bytes\nmsg count per topic: {}\nsend count : {}\nrecv count: {}\nloss rate: {} %\nmin latency: {min} us\nmax latency: {max} us\navg latency: {avg} us\np90 latency: {} us\np99 latency: {} us\np999 latency: {} us\nwrong size: {}\nseq outside the plan: {}\nreceived twice: {}\nreceived before sent: {}\n",
            b.bench_plan_id,
            b.mode,
            b.send_frequency,
            b.topic_number,
            b.parallel_number,
            b.message_size,
            b.send_num,
            send_count,
            n,
            loss,
            at(0.9),
            at(0.99),
            at(0.999),
            self.wrong_size,
            self.bad_seq,
            self.duplicates,
            self.before_sent,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan(mode: PerfMode, senders: u32, msg_count: u32) -> Plan {
        Plan {
            mode,
            frequency: 1000,
            msg_size: 4,
            msg_count,
            senders,
        }
    }

    #[test]
    fn parallel_senders_split_the_seqs_without_gap_or_overlap() {
        let p = plan(PerfMode::Parallel, 3, 10);
        let ranges: Vec<_> = (0..3).map(|s| p.sender(s)).collect();
        assert_eq!(ranges, [(0, 0..3), (0, 3..6), (0, 6..10)]);
        let p = plan(PerfMode::MultiTopic, 2, 10);
        assert_eq!(p.sender(1), (1, 0..10));
        assert_eq!(p.begin(7).topic_number, 2);
        assert_eq!(plan(PerfMode::Parallel, 4, 8).begin(0).parallel_number, 4);
    }

    fn check(plan: &str) -> Result<Plan, String> {
        let cfg: PublisherConfig = serde_json::from_str(&format!(
            r#"{{"max_topic_number": 2, "max_parallel_number": 3, "bench_plans": [{plan}]}}"#
        ))
        .map_err(|e| e.to_string())?;
        Plan::check(0, &cfg.bench_plans[0], &cfg).map_err(|e| e.to_string())
    }

    #[test]
    fn plans_aimrt_would_divide_by_zero_on_or_overrun_are_refused() {
        let ok = r#""perf_mode": "parallel", "channel_frq": 10, "msg_size": 8, "msg_count": 5"#;
        assert_eq!(
            check(&format!("{{{ok}, \"parallel_number\": 3}}"))
                .unwrap()
                .senders,
            3
        );
        for (plan, says) in [
            (format!("{{{ok}}}"), "a parallel plan needs parallel_number"),
            (format!("{{{ok}, \"parallel_number\": 4}}"), "1 ..= max_parallel_number (3)"),
            (format!("{{{ok}, \"parallel_number\": 0}}"), "parallel_number is 0"),
            (
                format!("{{{}, \"parallel_number\": 1}}", ok.replace("10", "0")),
                "channel_frq is 0",
            ),
            (
                r#"{"perf_mode": "multi-topic", "channel_frq": 1, "msg_size": 1, "msg_count": 0, "topic_number": 1}"#.into(),
                "msg_count is 0",
            ),
            (
                r#"{"perf_mode": "multi-topic", "channel_frq": 1, "msg_size": 4000000000, "msg_count": 1, "topic_number": 1}"#.into(),
                "msg_size is 4000000000",
            ),
            (
                r#"{"perf_mode": "multi-topic", "channel_frq": 1, "msg_size": 1, "msg_count": 6000000, "topic_number": 2}"#.into(),
                "msg_count × topics is 12000000",
            ),
        ] {
            let err = check(&plan).unwrap_err();
            assert!(err.contains(says), "{plan}: {err}");
        }
    }

    fn receiver() -> Receiver {
        Receiver {
            max_topics: 2,
            current: Mutex::new(None),
            outside: RateLimit::from_millis(1000),
            odd: RateLimit::from_millis(1000),
        }
    }

    fn begin(id: u32, topics: u32, send_num: u32) -> BenchmarkSignal {
        BenchmarkSignal {
            status: BenchmarkStatus::Begin.into(),
            bench_plan_id: id,
            mode: "multi-topic".into(),
            topic_number: topics,
            parallel_number: 1,
            send_num,
            message_size: 3,
            send_frequency: 100,
        }
    }

    fn end() -> BenchmarkSignal {
        BenchmarkSignal {
            status: BenchmarkStatus::End.into(),
            ..Default::default()
        }
    }

    fn msg(seq: u32, sent: u64, size: usize) -> BenchmarkMessage {
        BenchmarkMessage {
            seq,
            timestamp: sent,
            data: vec![b'x'; size],
        }
    }

    fn line<'a>(report: &'a str, key: &str) -> &'a str {
        report
            .lines()
            .find_map(|l| l.strip_prefix(key))
            .unwrap_or_else(|| panic!("no '{key}' in {report}"))
    }

    #[test]
    fn a_plan_reports_aimrts_figures_and_counts_what_aimrt_does_not() {
        let r = receiver();
        assert_eq!(r.signal(&begin(5, 2, 4)), None);
        // Latencies 1, 2, 3, 4 µs on topic 0; one on topic 1; then the odd ones.
        for seq in 0..4 {
            r.message(
                0,
                &msg(seq, 1_000_000, 3),
                1_000_000 + 1000 * u64::from(seq + 1),
            );
        }
        r.message(1, &msg(0, 2_000, 3), 12_000);
        r.message(1, &msg(0, 2_000, 3), 13_000); // again
        r.message(1, &msg(1, 2_000, 5), 12_000); // wrong size
        r.message(1, &msg(4, 2_000, 3), 12_000); // seq beyond send_num
        r.message(5, &msg(0, 2_000, 3), 12_000); // a topic beyond the plan's
        r.message(1, &msg(2, 9_000, 3), 8_000); // received before sent: latency 0
        let report = r.signal(&end()).expect("a report");
        assert!(
            report.starts_with("Benchmark plan 5 completed, report:\n"),
            "{report}"
        );
        assert_eq!(line(&report, "send count : "), "8");
        assert_eq!(line(&report, "recv count: "), "6");
        assert_eq!(line(&report, "loss rate: "), "25 %");
        assert_eq!(line(&report, "min latency: "), "0 us");
        assert_eq!(line(&report, "max latency: "), "10 us");
        // (1 + 2 + 3 + 4 + 10 + 0) / 6 µs, in whole ns as AimRT divides.
        assert_eq!(line(&report, "avg latency: "), "3.333 us");
        assert_eq!(line(&report, "p90 latency: "), "10 us");
        assert_eq!(line(&report, "wrong size: "), "1");
        assert_eq!(line(&report, "seq outside the plan: "), "2");
        assert_eq!(line(&report, "received twice: "), "1");
        assert_eq!(line(&report, "received before sent: "), "1");
        // The plan is over: an End again and late messages report nothing.
        r.message(0, &msg(0, 1, 3), 2);
        assert_eq!(r.signal(&end()), None);
    }

    #[test]
    fn a_plan_with_nothing_received_reports_no_latency_instead_of_reading_an_empty_list() {
        let r = receiver();
        r.signal(&begin(0, 1, 10));
        let report = r.signal(&end()).expect("a report");
        assert_eq!(line(&report, "recv count: "), "0");
        assert_eq!(line(&report, "loss rate: "), "100 %");
        for key in ["min", "max", "avg", "p90", "p99", "p999"] {
            assert_eq!(line(&report, &format!("{key} latency: ")), "n/a us");
        }
    }

    #[test]
    fn a_begin_beyond_the_limits_is_refused_without_allocating() {
        let r = receiver();
        // u32::MAX × 2 records would be 128 GiB.
        r.signal(&begin(0, 2, u32::MAX));
        assert!(r.lock().is_none());
        r.signal(&begin(1, 3, 10));
        assert!(r.lock().is_none(), "more topics than max_topic_number");
        r.signal(&begin(2, 0, 10));
        assert!(r.lock().is_none(), "no topic");
        r.message(0, &msg(0, 1, 3), 2);
        assert_eq!(r.signal(&end()), None);
    }

    #[test]
    fn signals_carry_aimrts_type_name_and_print_as_aimrt_prints_them() {
        use aimrt_plugin_api::channel::Message;
        assert_eq!(
            BenchmarkSignal::type_name(),
            "pb:aimrt.protocols.example.BenchmarkSignal"
        );
        assert_eq!(
            BenchmarkMessage::type_name(),
            "pb:aimrt.protocols.example.BenchmarkMessage"
        );
        // AimRT's Pb2CompactJson: proto field names, enum by name, defaults included.
        assert_eq!(
            signal_json(&plan(PerfMode::Parallel, 4, 5000).begin(2)),
            r#"{"status":"Begin","bench_plan_id":2,"mode":"parallel","topic_number":1,"parallel_number":4,"send_num":5000,"message_size":4,"send_frequency":1000}"#
        );
        assert_eq!(
            signal_json(&end()),
            r#"{"status":"End","bench_plan_id":0,"mode":"","topic_number":0,"parallel_number":0,"send_num":0,"message_size":0,"send_frequency":0}"#
        );
    }

    #[test]
    fn the_subscriber_needs_no_config_node() {
        let cfg: SubscriberConfig = serde_json::from_str("{}").unwrap();
        assert_eq!(cfg.max_topic_number, 0);
    }

    #[test]
    fn a_begin_during_a_plan_starts_the_new_plan() {
        let r = receiver();
        r.signal(&begin(0, 1, 10));
        r.message(0, &msg(0, 1, 3), 2);
        r.signal(&begin(1, 1, 2));
        r.message(0, &msg(1, 1, 3), 2);
        let report = r.signal(&end()).expect("a report");
        assert!(report.starts_with("Benchmark plan 1 completed"), "{report}");
        assert_eq!(line(&report, "recv count: "), "1");
        assert_eq!(line(&report, "send count : "), "2");
    }
}
