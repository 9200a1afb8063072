//! Scenario 6: local publish → subscribe through the real runtime, channel manager and
//! `local` backend, for 64 B and 1 MiB messages, delivered inline and on an executor,
//! within one library and across libraries.
//!
//! "Across libraries" uses a second Rust type declaring the same message type name: it has
//! its own type-support table, exactly as the same type built into another `.so`, so the
//! message is encoded once (postcard) and decoded for the subscriber — the code path a
//! second library takes. The payload is a `Vec<u8>` marked `#[serde(with = "serde_bytes")]`
//! (one copy per encode and per decode, instead of a loop over the bytes).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::{ChannelRef, Message, Publisher};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_runtime::{Runtime, RuntimeOptions};

use crate::stats::percentile;

#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct Blob {
    sent_ns: u64,
    #[serde(with = "serde_bytes")]
    data: Vec<u8>,
}
aimrt_plugin_api::serde_message!(Blob, "bench.Blob");

/// The same message type as another library would have it.
#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct ForeignBlob {
    sent_ns: u64,
    #[serde(with = "serde_bytes")]
    data: Vec<u8>,
}
aimrt_plugin_api::serde_message!(ForeignBlob, "bench.Blob");

fn now_ns() -> u64 {
    static START: OnceLock<Instant> = OnceLock::new();
    START.get_or_init(Instant::now).elapsed().as_nanos() as u64
}

/// What one subscriber saw: how many messages, and the latency of the last.
#[derive(Default)]
struct Counter {
    received: AtomicU64,
    last_latency_ns: AtomicU64,
}

impl Counter {
    fn hit(&self, sent_ns: u64) {
        self.last_latency_ns
            .store(now_ns().saturating_sub(sent_ns), Ordering::Relaxed);
        self.received.fetch_add(1, Ordering::Release);
    }
}

/// One measured case.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct Case {
    pub(crate) size: &'static str,
    pub(crate) delivery: &'static str,
    pub(crate) library: &'static str,
    /// Messages per second, publish of the first to receipt of the last.
    pub(crate) msgs_per_s: f64,
    /// Publish-to-callback latency, one message in flight, µs.
    pub(crate) p50_us: f64,
    pub(crate) p99_us: f64,
    /// Drops the runtime counted (must be 0).
    pub(crate) dropped: u64,
}

struct Bench {
    topics: Vec<(String, bool)>,
    counters: Vec<Arc<Counter>>,
    out: mpsc::Sender<(ChannelRef, Vec<Publisher<Blob>>)>,
    publishers: Vec<Publisher<Blob>>,
    channel: Option<ChannelRef>,
}

impl Module for Bench {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("ChannelBench")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let ch = core.channel()?;
        for ((topic, foreign), counter) in self.topics.iter().zip(&self.counters) {
            let c = counter.clone();
            if *foreign {
                ch.subscriber(topic)
                    .subscribe_msg(move |m: Arc<ForeignBlob>| c.hit(m.sent_ns))?;
            } else {
                ch.subscriber(topic)
                    .subscribe_msg(move |m: Arc<Blob>| c.hit(m.sent_ns))?;
            }
            self.publishers.push(ch.publisher::<Blob>(topic)?);
        }
        self.channel = Some(ch);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        if let Some(ch) = self.channel {
            let _ = self.out.send((ch, std::mem::take(&mut self.publishers)));
        }
        Ok(())
    }
}

const SIZES: [(&str, usize); 2] = [("64 B", 64), ("1 MiB", 1 << 20)];
const LIBRARIES: [(&str, bool); 2] = [("same", false), ("across", true)];

fn wait_for(counter: &Counter, n: u64) -> bool {
    let deadline = Instant::now() + Duration::from_secs(60);
    while counter.received.load(Ordering::Acquire) < n {
        if Instant::now() > deadline {
            return false;
        }
        std::hint::spin_loop();
    }
    true
}

/// Runs every size × library case under one delivery mode (one runtime).
fn run_mode(delivery: &'static str, quick: bool) -> Result<Vec<Case>, String> {
    let local = if delivery == "inline" {
        "      - type: local\n".to_owned()
    } else {
        "      - type: local\n        options:\n          subscriber_use_inline_executor: false\n          subscriber_executor: sub\n".to_owned()
    };
    let cfg = format!(
        "aimrt:\n  log:\n    core_lvl: Warn\n    backends:\n      - type: console\n  executor:\n    executors:\n      - name: sub\n        type: asio_thread\n        options:\n          thread_num: 1\n  channel:\n    backends:\n{local}    pub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [local]\n    sub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [local]\n"
    );
    let path = std::env::temp_dir().join(format!(
        "aimrt-bench-channel-{}-{delivery}.yaml",
        std::process::id()
    ));
    std::fs::write(&path, cfg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    let mut topics = Vec::new();
    for (size, _) in SIZES {
        for (library, foreign) in LIBRARIES {
            topics.push((format!("/bench/{size}/{library}"), foreign));
        }
    }
    let counters: Vec<Arc<Counter>> = topics.iter().map(|_| Arc::default()).collect();
    let (tx, rx) = mpsc::channel();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path.clone()),
        ..Default::default()
    });
    runtime.builtin_plugin(aimrt_std_executors::plugin());
    runtime.register_module(Box::new(Bench {
        topics: topics.clone(),
        counters: counters.clone(),
        out: tx,
        publishers: Vec::new(),
        channel: None,
    }));
    let handle = runtime.shutdown_handle();
    let thread = std::thread::spawn(move || runtime.run());
    let got = rx.recv_timeout(Duration::from_secs(30));
    let _ = std::fs::remove_file(&path);
    let Ok((ch, publishers)) = got else {
        handle.request();
        return Err(match thread.join() {
            Ok(Err(e)) => format!("the runtime failed: {e}"),
            _ => "the runtime did not start within 30 s".to_owned(),
        });
    };
    let mut cases = Vec::new();
    let mut i = 0;
    for (size, bytes) in SIZES {
        for (library, _) in LIBRARIES {
            let (p, c, topic) = (&publishers[i], &counters[i], &topics[i].0);
            i += 1;
            let big = bytes > 4096;
            let (n, samples) = match (big, quick) {
                (false, false) => (200_000, 2_000),
                (false, true) => (50_000, 500),
                (true, false) => (2_000, 300),
                (true, true) => (300, 100),
            };
            let data = vec![0xA5u8; bytes];
            // Throughput: publish n, wait for the last.
            let base = c.received.load(Ordering::Acquire);
            let t0 = Instant::now();
            for _ in 0..n {
                p.publish(Blob {
                    sent_ns: now_ns(),
                    data: data.clone(),
                })
                .map_err(|e| e.to_string())?;
            }
            if !wait_for(c, base + n) {
                handle.request();
                return Err(format!("{topic}: not every message arrived within 60 s"));
            }
            let rate = n as f64 / t0.elapsed().as_secs_f64();
            // Latency: one in flight.
            let mut lat = Vec::with_capacity(samples);
            for _ in 0..samples {
                let before = c.received.load(Ordering::Acquire);
                let data = data.clone();
                p.publish(Blob {
                    sent_ns: now_ns(),
                    data,
                })
                .map_err(|e| e.to_string())?;
                if !wait_for(c, before + 1) {
                    handle.request();
                    return Err(format!("{topic}: a message did not arrive within 60 s"));
                }
                lat.push(c.last_latency_ns.load(Ordering::Relaxed) as f64 / 1e3);
            }
            lat.sort_by(f64::total_cmp);
            let dropped = ch.stats(topic).map_or(0, |s| s.dropped_total());
            eprintln!("channel: {delivery} {size} {library} done");
            cases.push(Case {
                size,
                delivery,
                library,
                msgs_per_s: rate,
                p50_us: percentile(&lat, 50.0),
                p99_us: percentile(&lat, 99.0),
                dropped,
            });
        }
    }
    handle.request();
    match thread.join() {
        Ok(Ok(())) => Ok(cases),
        Ok(Err(e)) => Err(format!("the runtime failed: {e}")),
        Err(_) => Err("the runtime thread panicked".into()),
    }
}

/// Every case: inline, then on an executor.
pub(crate) fn run(quick: bool) -> Result<Vec<Case>, String> {
    // Type names agree, tables differ: the "across" subscriber really decodes.
    assert_eq!(Blob::type_name(), ForeignBlob::type_name());
    let mut all = run_mode("inline", quick)?;
    all.extend(run_mode("executor", quick)?);
    Ok(all)
}
