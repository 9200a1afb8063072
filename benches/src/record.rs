//! Scenario `record`: what recording costs the publisher (issue 22's target: recording
//! 100 000 small messages a second for 10 s slows the publisher by at most 10 % and
//! drops nothing).
//!
//! A module publishes `ExampleEventMsg` (about 20 bytes) at 100 000 messages a second,
//! paced to absolute slot times, on AimRT's record example setup: the `local` backend
//! delivering on a pool of 2 threads to a counting subscriber. It runs twice in this
//! process: without a recorder, and with `record_playback_plugin` recording the topic
//! (imd, zstd, the example's storage policy) on its own `simple_thread`. Measured: the
//! time spent inside `publish()` per message (mean and p99), the achieved rate, and the
//! messages in the bag against those published.
//!
//! Playback precision: 1 000 messages a second recorded for a few seconds, then played
//! back (imd, rate 1, on an `asio_thread`) to a subscriber delivered inline that notes when
//! each message arrives; each gap between arrivals is compared with the recorded gap.

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::Publisher;
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_protocols::example::ExampleEventMsg;
use aimrt_runtime::{Runtime, RuntimeOptions};

use crate::stats::percentile;

/// One run.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct Case {
    pub(crate) recording: bool,
    pub(crate) published: u64,
    pub(crate) msgs_per_s: f64,
    pub(crate) publish_mean_ns: f64,
    pub(crate) publish_p99_ns: f64,
    pub(crate) delivered: u64,
    /// Messages in the bag (recording runs).
    pub(crate) recorded: Option<u64>,
}

const RATE: u64 = 100_000;

struct Pub {
    out: mpsc::Sender<Publisher<ExampleEventMsg>>,
    publisher: Option<Publisher<ExampleEventMsg>>,
    delivered: Arc<AtomicU64>,
}

impl Module for Pub {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("RecordBenchModule")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let ch = core.channel()?;
        let delivered = self.delivered.clone();
        ch.subscriber("test_topic")
            .subscribe_msg(move |_: Arc<ExampleEventMsg>| {
                delivered.fetch_add(1, Ordering::Relaxed);
            })?;
        self.publisher = Some(ch.publisher("test_topic")?);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        if let Some(p) = self.publisher.take() {
            let _ = self.out.send(p);
        }
        Ok(())
    }
}

fn config(dir: &Path, recording: bool) -> Result<String, String> {
    let mut cfg = String::from("aimrt:\n");
    if recording {
        cfg.push_str(&format!(
            "  plugin:\n    plugins:\n      - name: record_playback_plugin\n        path: {}\n        options:\n          type_support_pkgs: [{{path: {}}}]\n          timer_executor: storage_executor\n          record_actions:\n            - name: bench\n              options:\n                bag_path: {}\n                mode: imd\n                executor: record_thread\n                storage_policy: {{max_bag_size_m: 2048, msg_write_interval: 1000, msg_write_interval_time: 1000, compression_mode: zstd, compression_level: default}}\n                topic_meta_list:\n                  - {{topic_name: test_topic, msg_type: pb:aimrt.protocols.example.ExampleEventMsg}}\n",
            crate::built("libaimrt_record_playback_plugin.so")?.display(),
            crate::built("libexample_pb_ts.so")?.display(),
            dir.join("bag").display()
        ));
    }
    cfg.push_str("  log:\n    core_lvl: Warn\n    backends:\n      - type: console\n  executor:\n    executors:\n      - {name: work_thread_pool, type: asio_thread, options: {thread_num: 2}}\n      - {name: record_thread, type: simple_thread}\n      - {name: storage_executor, type: asio_thread, options: {thread_num: 1}}\n  channel:\n    backends:\n      - type: local\n        options:\n          subscriber_use_inline_executor: false\n          subscriber_executor: work_thread_pool\n    pub_topics_options:\n      - {topic_name: \"(.*)\", enable_backends: [local]}\n    sub_topics_options:\n      - {topic_name: \"(.*)\", enable_backends: [local]}\n");
    Ok(cfg)
}

/// Playback timing: how far the gaps between played messages are from the recorded ones.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct Precision {
    pub(crate) recorded: u64,
    pub(crate) played: u64,
    pub(crate) gap_error_median_us: f64,
    pub(crate) gap_error_p99_us: f64,
    pub(crate) gap_error_max_us: f64,
}

/// The log times of the messages in the bag folders under `dir/bag`, in file order.
fn bag_log_times(dir: &Path) -> Result<Vec<u64>, String> {
    let mut times = Vec::new();
    for folder in std::fs::read_dir(dir.join("bag")).map_err(|e| e.to_string())? {
        let folder = folder.map_err(|e| e.to_string())?.path();
        for f in std::fs::read_dir(&folder).map_err(|e| e.to_string())? {
            let f = f.map_err(|e| e.to_string())?.path();
            if f.extension().is_some_and(|x| x == "mcap") {
                let bytes = std::fs::read(&f).map_err(|e| e.to_string())?;
                let stream = mcap::MessageStream::new(&bytes).map_err(|e| e.to_string())?;
                for m in stream {
                    times.push(m.map_err(|e| format!("{}: {e}", f.display()))?.log_time);
                }
            }
        }
    }
    Ok(times)
}

/// The bag folder under `dir/bag` (the one a run made).
fn bag_folder(dir: &Path) -> Result<std::path::PathBuf, String> {
    std::fs::read_dir(dir.join("bag"))
        .map_err(|e| e.to_string())?
        .next()
        .ok_or("no bag folder was made")?
        .map(|e| e.path())
        .map_err(|e| e.to_string())
}

/// A runtime on its own thread, with `module`.
struct Launched {
    handle: aimrt_runtime::ShutdownHandle,
    thread: std::thread::JoinHandle<Result<(), aimrt_runtime::Error>>,
}

fn launch(cfg: &str, dir: &Path, module: Box<dyn Module>) -> Result<Launched, String> {
    let cfg_path = dir.join("cfg.yaml");
    std::fs::write(&cfg_path, cfg).map_err(|e| e.to_string())?;
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(cfg_path),
        ..Default::default()
    });
    runtime.builtin_plugin(aimrt_std_executors::plugin());
    runtime.register_module(module);
    let handle = runtime.shutdown_handle();
    let thread = std::thread::spawn(move || runtime.run());
    Ok(Launched { handle, thread })
}

impl Launched {
    fn stop(self) -> Result<(), String> {
        self.handle.request();
        match self.thread.join() {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(format!("the runtime failed: {e}")),
            Err(_) => Err("the runtime thread panicked".into()),
        }
    }
}

/// A fresh scratch folder.
fn scratch(what: &str) -> Result<std::path::PathBuf, String> {
    let dir = std::env::temp_dir().join(format!("aimrt-bench-{what}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    Ok(dir)
}

/// Publishes `rate` messages a second for `secs` seconds, recording into `dir/bag` when
/// `recording`.
fn one(recording: bool, rate: u64, secs: u64, dir: &Path) -> Result<Case, String> {
    let delivered = Arc::new(AtomicU64::new(0));
    let (tx, rx) = mpsc::channel();
    let launched = launch(
        &config(dir, recording)?,
        dir,
        Box::new(Pub {
            out: tx,
            publisher: None,
            delivered: delivered.clone(),
        }),
    )?;
    let Ok(publisher) = rx.recv_timeout(Duration::from_secs(30)) else {
        return Err(launched
            .stop()
            .err()
            .unwrap_or_else(|| "the runtime did not start within 30 s".to_owned()));
    };
    let n = rate * secs;
    let slot = Duration::from_nanos(1_000_000_000 / rate);
    let mut costs = Vec::with_capacity(n as usize);
    let t0 = Instant::now();
    let mut failed = None;
    for k in 0..n {
        let due = t0 + slot * k as u32;
        while Instant::now() < due {
            std::hint::spin_loop();
        }
        let msg = Arc::new(ExampleEventMsg {
            msg: format!("count: {k}"),
            num: k as i32,
        });
        let t = Instant::now();
        if let Err(e) = publisher.publish(msg) {
            failed = Some(e.to_string());
            break;
        }
        costs.push(t.elapsed().as_nanos() as f64);
    }
    let elapsed = t0.elapsed().as_secs_f64();
    // Let the pool deliver what is queued before the runtime stops.
    let wait = Instant::now() + Duration::from_secs(10);
    while delivered.load(Ordering::Relaxed) < costs.len() as u64 && Instant::now() < wait {
        std::thread::sleep(Duration::from_millis(5));
    }
    drop(publisher);
    launched.stop()?;
    if let Some(e) = failed {
        return Err(format!("publish failed: {e}"));
    }
    let recorded = if recording {
        Some(bag_log_times(dir)?.len() as u64)
    } else {
        None
    };
    let published = costs.len() as u64;
    let mean = costs.iter().sum::<f64>() / costs.len().max(1) as f64;
    costs.sort_by(f64::total_cmp);
    Ok(Case {
        recording,
        published,
        msgs_per_s: published as f64 / elapsed,
        publish_mean_ns: mean,
        publish_p99_ns: percentile(&costs, 99.0),
        delivered: delivered.load(Ordering::Relaxed),
        recorded,
    })
}

/// Without and with recording, `rounds` times each, alternating.
pub(crate) fn run(scale: crate::stats::Scale) -> Result<Vec<Case>, String> {
    let quick = scale.quick;
    let secs = if quick { 2 } else { 10 };
    let rounds = scale.rounds(3, 5);
    let mut cases = Vec::new();
    for _ in 0..rounds {
        let load = crate::stats::quiet_gate(Duration::from_secs(if quick { 3 } else { 30 }));
        eprintln!("record: foreign load before the round {load:.2} core");
        for recording in [false, true] {
            let dir = scratch("record")?;
            cases.push(one(recording, RATE, secs, &dir)?);
            let _ = std::fs::remove_dir_all(&dir);
            eprintln!("record: recording {recording} done");
        }
    }
    Ok(cases)
}

/// Notes when each message of `test_topic` arrives.
struct Arrivals {
    at: Arc<std::sync::Mutex<Vec<Instant>>>,
}

impl Module for Arrivals {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("PlaybackBenchModule")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let at = self.at.clone();
        core.channel()?.subscriber("test_topic").subscribe_msg(
            move |_: Arc<ExampleEventMsg>| {
                at.lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push(Instant::now());
            },
        )?;
        Ok(())
    }
}

/// Records 1 000 messages a second, plays them back at rate 1 and compares the gaps.
pub(crate) fn precision(quick: bool) -> Result<Precision, String> {
    let secs = if quick { 2 } else { 5 };
    let dir = scratch("playback")?;
    one(true, 1_000, secs, &dir)?;
    let folder = bag_folder(&dir)?;
    let recorded = bag_log_times(&dir)?;
    let cfg = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: record_playback_plugin\n        path: {}\n        options:\n          type_support_pkgs: [{{path: {}}}]\n          playback_actions:\n            - name: bench\n              options: {{bag_path: {}, mode: imd, executor: playback}}\n  log:\n    core_lvl: Warn\n    backends:\n      - type: console\n  executor:\n    executors:\n      - {{name: playback, type: asio_thread, options: {{thread_num: 1}}}}\n  channel:\n    backends:\n      - type: local\n        options: {{subscriber_use_inline_executor: true}}\n    pub_topics_options:\n      - {{topic_name: \"(.*)\", enable_backends: [local]}}\n    sub_topics_options:\n      - {{topic_name: \"(.*)\", enable_backends: [local]}}\n",
        crate::built("libaimrt_record_playback_plugin.so")?.display(),
        crate::built("libexample_pb_ts.so")?.display(),
        folder.display()
    );
    let at = Arc::new(std::sync::Mutex::new(Vec::new()));
    let launched = launch(&cfg, &dir, Box::new(Arrivals { at: at.clone() }))?;
    let deadline = Instant::now() + Duration::from_secs(secs * 2 + 20);
    while at.lock().unwrap_or_else(|e| e.into_inner()).len() < recorded.len()
        && Instant::now() < deadline
    {
        std::thread::sleep(Duration::from_millis(20));
    }
    launched.stop()?;
    let _ = std::fs::remove_dir_all(&dir);
    let played = at.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let mut errors: Vec<f64> = recorded
        .windows(2)
        .zip(played.windows(2))
        .map(|(r, p)| {
            let want = (r[1] as f64 - r[0] as f64) / 1e3;
            let got = p[1].duration_since(p[0]).as_secs_f64() * 1e6;
            (got - want).abs()
        })
        .collect();
    errors.sort_by(f64::total_cmp);
    Ok(Precision {
        recorded: recorded.len() as u64,
        played: played.len() as u64,
        gap_error_median_us: percentile(&errors, 50.0),
        gap_error_p99_us: percentile(&errors, 99.0),
        gap_error_max_us: errors.last().copied().unwrap_or(f64::NAN),
    })
}
