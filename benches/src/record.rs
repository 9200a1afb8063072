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

/// Messages in the bag folders under `dir/bag`.
fn bag_messages(dir: &Path) -> Result<u64, String> {
    let mut n = 0;
    for folder in std::fs::read_dir(dir.join("bag")).map_err(|e| e.to_string())? {
        let folder = folder.map_err(|e| e.to_string())?.path();
        for f in std::fs::read_dir(&folder).map_err(|e| e.to_string())? {
            let f = f.map_err(|e| e.to_string())?.path();
            if f.extension().is_some_and(|x| x == "mcap") {
                let bytes = std::fs::read(&f).map_err(|e| e.to_string())?;
                let stream = mcap::MessageStream::new(&bytes).map_err(|e| e.to_string())?;
                for m in stream {
                    m.map_err(|e| format!("{}: {e}", f.display()))?;
                    n += 1;
                }
            }
        }
    }
    Ok(n)
}

fn one(recording: bool, secs: u64) -> Result<Case, String> {
    let dir = std::env::temp_dir().join(format!("aimrt-bench-record-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    let cfg_path = dir.join("cfg.yaml");
    std::fs::write(&cfg_path, config(&dir, recording)?).map_err(|e| e.to_string())?;
    let delivered = Arc::new(AtomicU64::new(0));
    let (tx, rx) = mpsc::channel();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(cfg_path),
        ..Default::default()
    });
    runtime.builtin_plugin(aimrt_std_executors::plugin());
    runtime.register_module(Box::new(Pub {
        out: tx,
        publisher: None,
        delivered: delivered.clone(),
    }));
    let handle = runtime.shutdown_handle();
    let thread = std::thread::spawn(move || runtime.run());
    let Ok(publisher) = rx.recv_timeout(Duration::from_secs(30)) else {
        handle.request();
        return Err(match thread.join() {
            Ok(Err(e)) => format!("the runtime failed: {e}"),
            _ => "the runtime did not start within 30 s".to_owned(),
        });
    };
    let n = RATE * secs;
    let slot = Duration::from_nanos(1_000_000_000 / RATE);
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
    handle.request();
    match thread.join() {
        Ok(Ok(())) => {}
        Ok(Err(e)) => return Err(format!("the runtime failed: {e}")),
        Err(_) => return Err("the runtime thread panicked".into()),
    }
    if let Some(e) = failed {
        return Err(format!("publish failed: {e}"));
    }
    let recorded = if recording {
        Some(bag_messages(&dir)?)
    } else {
        None
    };
    let _ = std::fs::remove_dir_all(&dir);
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
pub(crate) fn run(quick: bool) -> Result<Vec<Case>, String> {
    let (secs, rounds) = if quick { (2, 1) } else { (10, 3) };
    let mut cases = Vec::new();
    for _ in 0..rounds {
        for recording in [false, true] {
            cases.push(one(recording, secs)?);
            eprintln!("record: recording {recording} done");
        }
    }
    Ok(cases)
}
