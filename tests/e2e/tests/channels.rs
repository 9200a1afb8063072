//! Channels in process: modules registered in code publish and subscribe through the real
//! runtime, channel manager and `local` backend. Runtimes in one process run one after
//! another, so each test holds `SERIAL`.
//!
//! "Another library" is simulated with a second Rust type that declares the same message
//! type name: it has its own type-support table, exactly like the same type compiled into
//! another `.so`, so delivery goes through encode → decode.

use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use aimrt_e2e::lib;
use aimrt_plugin_api::channel::{
    ChannelRef, Context, ContextKind, DropReason, Publisher, KEY_BACKEND, KEY_PUB_SEQ, KEY_PUB_TS,
    KEY_SERIALIZATION_TYPE,
};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_runtime::{Runtime, RuntimeOptions};

static SERIAL: Mutex<()> = Mutex::new(());

fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

const WAIT: Duration = Duration::from_secs(10);

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Pose {
    frame: String,
    xyz: [f64; 3],
    stamp: u64,
}
aimrt_plugin_api::serde_message!(Pose, "test.Pose");

/// The same message type as built into "another library": same name, its own table.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct ForeignPose {
    frame: String,
    xyz: [f64; 3],
    stamp: u64,
}
aimrt_plugin_api::serde_message!(ForeignPose, "test.Pose");

fn pose(n: u64) -> Pose {
    Pose {
        frame: format!("map-ü-{n}"),
        xyz: [1.5, -2.25, n as f64],
        stamp: u64::MAX - n,
    }
}

type Hook = Box<dyn FnMut(CoreRef) -> Result<(), Error> + Send>;
type StartHook = Box<dyn FnMut() -> Result<(), Error> + Send>;

/// A module made of closures.
struct Probe {
    name: &'static str,
    init: Hook,
    start: StartHook,
    stop: Box<dyn FnMut() + Send>,
}

impl Probe {
    fn new(
        name: &'static str,
        init: impl FnMut(CoreRef) -> Result<(), Error> + Send + 'static,
    ) -> Probe {
        Probe {
            name,
            init: Box::new(init),
            start: Box::new(|| Ok(())),
            stop: Box::new(|| {}),
        }
    }
    fn on_shutdown(mut self, stop: impl FnMut() + Send + 'static) -> Probe {
        self.stop = Box::new(stop);
        self
    }
    fn on_start(mut self, start: impl FnMut() -> Result<(), Error> + Send + 'static) -> Probe {
        self.start = Box::new(start);
        self
    }
}

impl Module for Probe {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new(self.name)
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        (self.init)(core)
    }
    fn start(&mut self) -> Result<(), Error> {
        (self.start)()
    }
    fn shutdown(&mut self) {
        (self.stop)()
    }
}

const LOCAL_ALL: &str = "  channel:\n    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [local]\n    sub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [local]\n";

/// Runs the modules under a config with executor `w` (asio_thread, one thread) and
/// `channel` (a YAML tail under `aimrt:`), plus `log` when given.
fn run(
    channel: &str,
    log_file: Option<&std::path::Path>,
    modules: Vec<Probe>,
) -> Result<(), aimrt_runtime::Error> {
    run_with(channel, log_file, modules, Vec::new())
}

/// [`run`] with statically linked plugins.
fn run_with(
    channel: &str,
    log_file: Option<&std::path::Path>,
    modules: Vec<Probe>,
    plugins: Vec<Box<dyn aimrt_plugin_api::Plugin>>,
) -> Result<(), aimrt_runtime::Error> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    let log = log_file.map_or_else(String::new, |f| {
        format!("  log:\n    core_lvl: INFO\n    backends:\n      - type: rotate_file\n        options:\n          path: {}\n          filename: {}\n",
            f.parent().unwrap().display(), f.file_name().unwrap().to_string_lossy())
    });
    let cfg = format!(
        "aimrt:\n{log}  plugin:\n    plugins:\n      - name: std_executors\n        path: {}\n  executor:\n    executors:\n      - name: w\n        type: asio_thread\n        options:\n          thread_num: 1\n      - name: tiny\n        type: simple_thread\n        options:\n          queue_threshold: 1\n      - name: pair\n        type: simple_thread\n        options:\n          queue_threshold: 2\n{channel}",
        lib("libaimrt_std_executors_plugin.so").display()
    );
    std::fs::write(&path, cfg).unwrap();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_millis(50)),
        ..Default::default()
    });
    for m in modules {
        runtime.register_module(Box::new(m));
    }
    for p in plugins {
        runtime.builtin_plugin(p);
    }
    runtime.run()
}

/// A value one hook leaves for another.
type Slot<T> = Arc<Mutex<Option<T>>>;

fn slot<T: Send + 'static>() -> (Slot<T>, Slot<T>) {
    let s = Arc::new(Mutex::new(None));
    (s.clone(), s)
}

#[test]
fn phase_rules_name_the_phase() {
    let _g = serial();
    let (errors_tx, errors) = channel::<String>();
    let (keep, kept) = slot::<Publisher<Pose>>();
    let in_start = errors_tx.clone();
    let (chan_slot, chan_kept) = slot::<ChannelRef>();
    let init_tx = errors_tx.clone();
    let m = Probe::new("Phases", move |core| {
        let ch = core.channel()?;
        let p = ch.publisher::<Pose>("/phase")?;
        ch.subscriber("/phase").subscribe_msg(|_: Arc<Pose>| {})?;
        // Publishing in initialize is refused, naming the phase.
        init_tx
            .send(p.publish(pose(0)).unwrap_err().to_string())
            .unwrap();
        *chan_slot.lock().unwrap() = Some(ch);
        *keep.lock().unwrap() = Some(p);
        Ok(())
    })
    .on_start(move || {
        let ch = chan_kept.lock().unwrap().unwrap();
        // Registering and subscribing after initialize are refused, naming the phase.
        in_start
            .send(
                ch.publisher::<ForeignPose>("/late")
                    .unwrap_err()
                    .to_string(),
            )
            .unwrap();
        in_start
            .send(
                ch.subscriber("/late")
                    .subscribe_msg(|_: Arc<Pose>| {})
                    .unwrap_err()
                    .to_string(),
            )
            .unwrap();
        Ok(())
    });
    run(LOCAL_ALL, None, vec![m]).unwrap();
    let got: Vec<String> = errors.try_iter().collect();
    assert_eq!(got.len(), 3, "{got:?}");
    assert!(
        got[0].contains("during initialize") && got[0].contains("from start() on"),
        "{}",
        got[0]
    );
    assert!(
        got[1].contains("can be registered only in initialize; the runtime has started"),
        "{}",
        got[1]
    );
    assert!(
        got[2].contains("can be subscribed only in initialize; the runtime has started"),
        "{}",
        got[2]
    );
    // After the runtime shut the channel down, publishing is refused and counted.
    let p = kept.lock().unwrap().take().unwrap();
    let e = p.publish(pose(1)).unwrap_err().to_string();
    assert!(e.contains("after the channel shut down"), "{e}");
}

#[test]
fn registrations_are_deduplicated_per_type_topic_and_module() {
    let _g = serial();
    let (tx, rx) = channel::<String>();
    let m = Probe::new("Dedupe", move |core| {
        let ch = core.channel()?;
        ch.publisher::<Pose>("/d")?;
        tx.send(ch.publisher::<Pose>("/d").unwrap_err().to_string())
            .unwrap();
        // Another type with another table but the same name is the same message type.
        tx.send(ch.publisher::<ForeignPose>("/d").unwrap_err().to_string())
            .unwrap();
        // Another topic is fine.
        ch.publisher::<Pose>("/d2")?;
        let sub = ch.subscriber("/d");
        sub.subscribe_msg(|_: Arc<Pose>| {})?;
        tx.send(
            sub.subscribe_msg(|_: Arc<Pose>| {})
                .unwrap_err()
                .to_string(),
        )
        .unwrap();
        tx.send(ch.publisher::<Pose>("").unwrap_err().to_string())
            .unwrap();
        Ok(())
    });
    // A second module may register the same type on the same topic.
    let other = Probe::new("Dedupe2", |core| {
        core.channel()?.publisher::<Pose>("/d")?;
        Ok(())
    });
    run(LOCAL_ALL, None, vec![m, other]).unwrap();
    let got: Vec<String> = rx.try_iter().collect();
    assert_eq!(got.len(), 4, "{got:?}");
    for e in &got[..2] {
        assert!(e.contains("publish type 'serde:test.Pose' is registered repeatedly on topic '/d' by module 'Dedupe'"), "{e}");
    }
    assert!(
        got[2].contains("is subscribed repeatedly on topic '/d'"),
        "{}",
        got[2]
    );
    assert!(
        got[3].contains("topic name must not be empty"),
        "{}",
        got[3]
    );
}

/// What a subscriber saw.
#[derive(Debug)]
struct Seen<T> {
    ctx: Context,
    msg: Arc<T>,
    thread: std::thread::ThreadId,
}

fn subscribe_into<T: aimrt_plugin_api::channel::Message>(
    ch: &ChannelRef,
    topic: &str,
    tx: Sender<Seen<T>>,
) -> Result<(), Error> {
    let tx = Mutex::new(tx);
    ch.subscriber(topic)
        .subscribe(move |ctx: &Context, msg: Arc<T>| {
            let _ = tx.lock().unwrap().send(Seen {
                ctx: ctx.clone(),
                msg,
                thread: std::thread::current().id(),
            });
        })
}

/// [`LOCAL_ALL`] with `local` delivering on `executor`.
fn local_on(executor: &str) -> String {
    LOCAL_ALL.replace(
        "      - type: local\n",
        &format!("      - type: local\n        options:\n          subscriber_use_inline_executor: false\n          subscriber_executor: {executor}\n"),
    )
}

fn recv<T>(rx: &Receiver<T>) -> T {
    rx.recv_timeout(WAIT).expect("a delivery within 10 s")
}

#[test]
fn inline_delivery_shares_within_a_library_and_decodes_across() {
    let _g = serial();
    let (same_tx, same_rx) = channel::<Seen<Pose>>();
    let (foreign_tx, foreign_rx) = channel::<Seen<ForeignPose>>();
    let (sent_tx, sent_rx) = channel::<(Arc<Pose>, std::thread::ThreadId, Context)>();
    let (keep, kept) = slot::<Publisher<Pose>>();
    let sub = Probe::new("Sub", move |core| {
        subscribe_into(&core.channel()?, "/pose", same_tx.clone())
    });
    let foreign_sub = Probe::new("ForeignSub", move |core| {
        subscribe_into(&core.channel()?, "/pose", foreign_tx.clone())
    });
    let publ = Probe::new("Pub", move |core| {
        let mut p = core.channel()?.publisher::<Pose>("/pose")?;
        p.set_default_meta("robot", "r2");
        *keep.lock().unwrap() = Some(p);
        Ok(())
    })
    .on_start(move || {
        let p = kept.lock().unwrap().clone().unwrap();
        for (n, format) in [(1, None), (2, Some("json")), (3, Some("postcard"))] {
            let msg = Arc::new(pose(n));
            let mut ctx = p.new_context(None);
            ctx.set("trace_id", &format!("t{n}"));
            if let Some(f) = format {
                ctx.set_serialization_type(f);
            }
            p.publish_with(&mut ctx, msg.clone())?;
            // Single use: a published context is refused until reset.
            let again = p
                .publish_with(&mut ctx, msg.clone())
                .unwrap_err()
                .to_string();
            assert!(again.contains("published already"), "{again}");
            sent_tx
                .send((msg, std::thread::current().id(), ctx.clone()))
                .unwrap();
        }
        // `publish` starts from the default meta too.
        p.publish(pose(4))?;
        // A format the type does not have is refused before anything is sent.
        let mut bad = p.new_context(None);
        bad.set_serialization_type("pb");
        let e = p.publish_with(&mut bad, pose(9)).unwrap_err().to_string();
        assert!(
            e.contains("'pb', which 'serde:test.Pose' does not support"),
            "{e}"
        );
        // A subscribe context cannot be published.
        let mut sub_ctx = Context::new(ContextKind::Subscribe);
        assert!(p.publish_with(&mut sub_ctx, pose(9)).is_err());
        Ok(())
    });
    run(LOCAL_ALL, None, vec![sub, foreign_sub, publ]).unwrap();
    for (n, format) in [(1u64, "postcard"), (2, "json"), (3, "postcard")] {
        let (sent, publisher_thread, _) = recv(&sent_rx);
        let same = recv(&same_rx);
        let foreign = recv(&foreign_rx);
        // Inline: on the publisher's thread, before publish returned.
        assert_eq!(same.thread, publisher_thread);
        assert_eq!(foreign.thread, publisher_thread);
        // Same table: the very object published. Another table: an equal copy.
        assert!(Arc::ptr_eq(&same.msg, &sent), "message {n} was not shared");
        let f = &foreign.msg;
        assert_eq!(
            (f.frame.as_str(), f.xyz, f.stamp),
            (sent.frame.as_str(), sent.xyz, sent.stamp)
        );
        for seen in [&same.ctx, &foreign.ctx] {
            assert_eq!(seen.kind(), ContextKind::Subscribe);
            assert_eq!(seen.get("robot"), Some("r2"));
            assert_eq!(seen.get("trace_id"), Some(format!("t{n}").as_str()));
            assert_eq!(
                seen.get(KEY_PUB_SEQ),
                Some(n.to_string().as_str()),
                "pub_seq counts per topic from 1"
            );
            assert_eq!(seen.get(KEY_BACKEND), Some("local"));
            assert_eq!(seen.get(KEY_SERIALIZATION_TYPE), Some(format));
            let ts: u128 = seen.get(KEY_PUB_TS).unwrap().parse().unwrap();
            assert!(ts > 1_600_000_000_000_000_000, "{ts}");
        }
    }
    for seen in [recv(&same_rx).ctx, recv(&foreign_rx).ctx] {
        assert_eq!(seen.get("robot"), Some("r2"), "publish without a context");
        assert_eq!(seen.get("trace_id"), None);
        assert_eq!(seen.get(KEY_PUB_SEQ), Some("4"));
        assert_eq!(seen.get(KEY_SERIALIZATION_TYPE), Some("postcard"));
    }
}

#[test]
fn executor_delivery_runs_subscribers_on_the_subscriber_executor() {
    let _g = serial();
    let cfg = local_on("w");
    let (seen_tx, seen_rx) = channel::<Seen<ForeignPose>>();
    let (second_tx, second_rx) = channel::<Seen<Pose>>();
    let (done_tx, done_rx) = channel::<std::thread::ThreadId>();
    let (keep, kept) = slot::<Publisher<Pose>>();
    let (w_slot, w_kept) = slot::<aimrt_plugin_api::ExecutorRef>();
    let sub = Probe::new("Sub", move |core| {
        let ch = core.channel()?;
        *w_slot.lock().unwrap() = Some(core.executor("w")?);
        subscribe_into(&ch, "/e", seen_tx.clone())
    });
    // Two subscribers of one type: the publisher posts one task, which posts the other's.
    let second = Probe::new("Second", move |core| {
        subscribe_into(&core.channel()?, "/e", second_tx.clone())
    });
    let publ = Probe::new("Pub", move |core| {
        *keep.lock().unwrap() = Some(core.channel()?.publisher::<Pose>("/e")?);
        Ok(())
    })
    .on_start(move || {
        let p = kept.lock().unwrap().clone().unwrap();
        for n in 0..20 {
            let mut ctx = Context::new(ContextKind::Publish);
            ctx.set("trace_id", &format!("t{n}"));
            p.publish_with(&mut ctx, pose(n))?;
        }
        done_tx.send(std::thread::current().id()).unwrap();
        Ok(())
    });
    run(&cfg, None, vec![sub, second, publ]).unwrap();
    let publisher_thread = recv(&done_rx);
    let w = w_kept.lock().unwrap().unwrap();
    for n in 0..20 {
        let other = recv(&second_rx);
        assert_ne!(other.thread, publisher_thread);
        assert_eq!(
            other.msg.stamp,
            u64::MAX - n,
            "the second subscriber keeps order too"
        );
        assert_eq!(
            other.ctx.get(KEY_PUB_SEQ),
            Some((n + 1).to_string().as_str())
        );
        let seen = recv(&seen_rx);
        assert_ne!(seen.thread, publisher_thread);
        // One asio thread: order is kept.
        assert_eq!(seen.msg.stamp, u64::MAX - n);
        // The context the task kept for later: the user's key and the runtime's stamps.
        let trace = format!("t{n}");
        let seq = (n + 1).to_string();
        assert_eq!(seen.ctx.get("trace_id"), Some(trace.as_str()));
        assert_eq!(seen.ctx.get(KEY_PUB_SEQ), Some(seq.as_str()));
        assert!(seen
            .ctx
            .get(KEY_PUB_TS)
            .is_some_and(|t| t.parse::<u64>().is_ok()));
        assert_eq!(seen.ctx.get(KEY_BACKEND), Some("local"));
        assert!(seen.ctx.get(KEY_SERIALIZATION_TYPE).is_some());
    }
    assert!(w.stats().run >= 40, "{:?}", w.stats());
}

/// Says when the runtime shuts plugins down.
struct ShutdownMark(Mutex<Sender<String>>);

impl aimrt_plugin_api::Plugin for ShutdownMark {
    fn name(&self) -> &str {
        "shutdown_mark"
    }
    fn initialize(
        &mut self,
        _: &mut aimrt_plugin_api::Registrar<'_>,
        _: &aimrt_plugin_api::PluginOptions,
    ) -> Result<(), Error> {
        Ok(())
    }
    fn shutdown(&mut self) {
        let _ = self.0.lock().unwrap().send("plugins shut down".into());
    }
}

#[test]
fn deliveries_queued_at_shutdown_run_before_plugins_shut_down() {
    let _g = serial();
    // One worker, 10 ms per message, 20 messages published at start: 200 ms of deliveries
    // against a 50 ms run. A recording plugin must see every one before it shuts down.
    let cfg = local_on("w");
    let (tx, rx) = channel::<String>();
    let mark = ShutdownMark(Mutex::new(tx.clone()));
    let (keep, kept) = slot::<Publisher<Pose>>();
    let sub = Probe::new("Slow", move |core| {
        let tx = Mutex::new(tx.clone());
        core.channel()?
            .subscriber("/q")
            .subscribe_msg(move |m: Arc<Pose>| {
                std::thread::sleep(Duration::from_millis(10));
                let _ = tx.lock().unwrap().send(format!("delivered {}", m.stamp));
            })
    });
    let publ = Probe::new("Pub", move |core| {
        *keep.lock().unwrap() = Some(core.channel()?.publisher::<Pose>("/q")?);
        Ok(())
    })
    .on_start(move || {
        let p = kept.lock().unwrap().clone().unwrap();
        for n in 0..20 {
            p.publish(pose(n))?;
        }
        Ok(())
    });
    run_with(&cfg, None, vec![sub, publ], vec![Box::new(mark)]).unwrap();
    let order: Vec<String> = rx.try_iter().collect();
    let want: Vec<String> = (0..20)
        .map(|n| format!("delivered {}", u64::MAX - n))
        .chain(["plugins shut down".to_string()])
        .collect();
    assert_eq!(order, want);
}

#[test]
fn a_delivery_left_on_the_main_thread_at_shutdown_runs_and_does_not_stall_it() {
    let _g = serial();
    // Published from a module's shutdown to a subscriber on the main thread's executor:
    // the main thread itself is shutting down, so its queue runs after the plugins, and
    // the local backend must not wait for it.
    let cfg = local_on("aimrt_main");
    let (tx, rx) = channel::<u64>();
    let (keep, kept) = slot::<Publisher<Pose>>();
    let sub = Probe::new("Sub", move |core| {
        let tx = Mutex::new(tx.clone());
        core.channel()?
            .subscriber("/late")
            .subscribe_msg(move |m: Arc<Pose>| {
                let _ = tx.lock().unwrap().send(m.stamp);
            })
    });
    let publ = Probe::new("Pub", move |core| {
        *keep.lock().unwrap() = Some(core.channel()?.publisher::<Pose>("/late")?);
        Ok(())
    })
    .on_shutdown(move || {
        let p = kept.lock().unwrap().take().unwrap();
        p.publish(pose(7)).unwrap();
    });
    let t0 = std::time::Instant::now();
    run(&cfg, None, vec![sub, publ]).unwrap();
    let took = t0.elapsed();
    assert_eq!(rx.try_iter().collect::<Vec<_>>(), [u64::MAX - 7]);
    assert!(took < Duration::from_secs(3), "shutdown took {took:?}");
}

#[test]
fn a_refused_fan_out_is_reported_to_every_subscriber() {
    let _g = serial();
    // pair holds two tasks in flight, the one running included.
    let cfg = local_on("pair");
    let (keep, kept) = slot::<(Publisher<Pose>, ChannelRef, aimrt_plugin_api::ExecutorRef)>();
    let (out_tx, out_rx) = channel();
    let other = Probe::new("Other", |core| {
        core.channel()?
            .subscriber("/fan")
            .subscribe_msg(|_: Arc<Pose>| {})
    });
    let m = Probe::new("Fan", move |core| {
        let ch = core.channel()?;
        ch.subscriber("/fan").subscribe_msg(|_: Arc<Pose>| {})?;
        *keep.lock().unwrap() = Some((ch.publisher::<Pose>("/fan")?, ch, core.executor("pair")?));
        Ok(())
    })
    .on_start(move || {
        let (p, ch, pair) = kept.lock().unwrap().take().unwrap();
        // Block pair's only worker: one more task fits, the first publication.
        publish_while_blocked(&pair, &p, 5)?;
        // The queued publication posts its second delivery when it runs: wait for both.
        let deadline = std::time::Instant::now() + WAIT;
        let mut s = ch.stats("/fan").unwrap();
        while s.delivered + s.dropped_for(DropReason::Refused) < 10
            && std::time::Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(5));
            s = ch.stats("/fan").unwrap();
        }
        out_tx.send(s).unwrap();
        Ok(())
    });
    run(&cfg, None, vec![other, m]).unwrap();
    let s = recv(&out_rx);
    assert_eq!(s.published, 5);
    // Five publications to two subscribers: each delivery is made or refused. The first
    // publication is one task, which posts the second delivery once it runs; the other
    // four are refused for both subscribers.
    let refused = s.dropped_for(DropReason::Refused);
    assert_eq!(refused + s.delivered, 10, "{s}");
    assert_eq!(refused, 8, "{s}");
}

#[test]
fn async_subscribers_run_as_tasks_and_panics_are_contained_and_counted() {
    let _g = serial();
    let (async_tx, async_rx) = channel::<(String, u64)>();
    let (ok_tx, ok_rx) = channel::<u64>();
    let (keep, kept) = slot::<(Publisher<Pose>, ChannelRef)>();
    let (stats_tx, stats_rx) = channel();
    let m = Probe::new("Mixed", move |core| {
        let ch = core.channel()?;
        let w = core.executor("w")?;
        let tx = Mutex::new(async_tx.clone());
        ch.subscriber("/p")
            .subscribe_async(&w, move |ctx: Context, msg: Arc<Pose>| {
                let tx = tx.lock().unwrap().clone();
                async move {
                    let on_w = if w.is_in_current_executor() {
                        "on w"
                    } else {
                        "elsewhere"
                    };
                    let _ = tx.send((
                        format!("{on_w}|{}", ctx.get(KEY_PUB_SEQ).unwrap_or("")),
                        msg.stamp,
                    ));
                }
            })?;
        let ok = Mutex::new(ok_tx.clone());
        let other = ch.subscriber("/q");
        other.subscribe_msg(move |msg: Arc<Pose>| {
            let _ = ok.lock().unwrap().send(msg.stamp);
        })?;
        *keep.lock().unwrap() = Some((ch.publisher::<Pose>("/p")?, ch));
        Ok(())
    })
    .on_start(move || {
        let (p, ch) = kept.lock().unwrap().clone().unwrap();
        for n in 0..4 {
            // A panicking subscriber does not fail the publish.
            p.publish(pose(n))?;
        }
        stats_tx.send(ch).unwrap();
        Ok(())
    });
    let panicky = Probe::new("Panicky", |core| {
        core.channel()?
            .subscriber("/p")
            .subscribe_msg(|msg: Arc<ForeignPose>| {
                if msg.stamp % 2 == 0 {
                    panic!("subscriber refuses even stamps");
                }
            })
    });
    run(LOCAL_ALL, None, vec![panicky, m]).unwrap();
    let mut got: Vec<(String, u64)> = (0..4).map(|_| recv(&async_rx)).collect();
    got.sort_by_key(|(_, s)| u64::MAX - s);
    for (i, (where_seq, _)) in got.iter().enumerate() {
        assert!(where_seq.ends_with(&format!("|{}", i + 1)), "{where_seq}");
        assert!(
            where_seq.starts_with("on w|"),
            "ran on the executor's thread: {where_seq}"
        );
    }
    assert!(ok_rx.try_recv().is_err(), "nothing was published on /q");
    let ch: ChannelRef = recv(&stats_rx);
    let s = ch.stats("/p").unwrap();
    assert_eq!(s.published, 4);
    // Two of four messages made the plain subscriber panic; the async one got all four.
    assert_eq!(s.dropped_for(DropReason::SubscriberFailed), 2, "{s}");
    assert_eq!(s.delivered, 4 + 2, "{s}");
}

#[test]
fn drops_are_reported_once_and_counted() {
    let _g = serial();
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("aimrt.log");
    // Only /routed/.* has a publish rule.
    let cfg = "  channel:\n    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \"/routed/.*\"\n        enable_backends: [local]\n    sub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [local]\n";
    let (keep, kept) = slot::<(Publisher<Pose>, Publisher<Pose>, ChannelRef)>();
    let (out_tx, out_rx) = channel();
    let m = Probe::new("Dropper", move |core| {
        let ch = core.channel()?;
        let lonely = ch.publisher::<Pose>("/routed/lonely")?;
        let unrouted = ch.publisher::<Pose>("/nowhere")?;
        *keep.lock().unwrap() = Some((lonely, unrouted, ch));
        Ok(())
    })
    .on_start(move || {
        let (lonely, unrouted, ch) = kept.lock().unwrap().take().unwrap();
        for n in 0..3 {
            lonely.publish(pose(n))?;
            unrouted.publish(pose(n))?;
        }
        out_tx
            .send((
                ch.stats("/routed/lonely"),
                ch.stats("/nowhere"),
                ch.stats("/never"),
            ))
            .unwrap();
        Ok(())
    });
    run(cfg, Some(&log), vec![m]).unwrap();
    let (lonely, nowhere, never) = recv(&out_rx);
    let lonely = lonely.unwrap();
    assert_eq!(lonely.published, 3);
    assert_eq!(lonely.dropped_for(DropReason::NoSubscriber), 3, "{lonely}");
    let nowhere = nowhere.unwrap();
    assert_eq!(nowhere.dropped_for(DropReason::NoRoute), 3, "{nowhere}");
    assert_eq!(never, None, "a topic nobody registered has no stats");
    let text = std::fs::read_to_string(&log).unwrap();
    let count = |needle: &str| text.matches(needle).count();
    assert_eq!(
        count("no module subscribes to 'serde:test.Pose' on it"),
        1,
        "{text}"
    );
    assert_eq!(
        count("no aimrt.channel.pub_topics_options rule enables a backend for it"),
        1,
        "{text}"
    );
    assert_eq!(
        count("matches no aimrt.channel.pub_topics_options rule: what module 'Dropper' publishes"),
        1,
        "{text}"
    );
    // The counters are also logged at shutdown.
    assert!(text.contains("Channel topic '/routed/lonely': published 3, delivered 0, dropped 3 (no subscriber: 3)"), "{text}");
    assert!(
        text.contains(
            "Channel topic '/nowhere': published 3, delivered 0, dropped 3 (no route: 3)"
        ),
        "{text}"
    );
}

#[test]
fn a_chain_carries_user_keys_and_restamps_pub_seq() {
    let _g = serial();
    let (seen_tx, seen_rx) = channel::<Seen<Pose>>();
    let (keep, kept) = slot::<(Publisher<Pose>, Publisher<Pose>)>();
    // Relay: /up → /down with the received context merged into a fresh one.
    let relay = Probe::new("Relay", |core| {
        let ch = core.channel()?;
        let down = ch.publisher::<Pose>("/down")?;
        ch.subscriber("/up")
            .subscribe(move |ctx: &Context, msg: Arc<Pose>| {
                let mut out = down.new_context(Some(ctx));
                down.publish_with(&mut out, msg).unwrap();
            })
    });
    let sink = Probe::new("Sink", move |core| {
        subscribe_into(&core.channel()?, "/down", seen_tx.clone())
    });
    let source = Probe::new("Source", move |core| {
        let ch = core.channel()?;
        *keep.lock().unwrap() =
            Some((ch.publisher::<Pose>("/up")?, ch.publisher::<Pose>("/down")?));
        Ok(())
    })
    .on_start(move || {
        let (up, down) = kept.lock().unwrap().clone().unwrap();
        // Two direct messages on /down first, so its counter is ahead of /up's.
        down.publish(pose(1))?;
        down.publish(pose(2))?;
        let mut ctx = up.new_context(None);
        ctx.set("trace_id", "abc");
        up.publish_with(&mut ctx, pose(3))
    });
    run(LOCAL_ALL, None, vec![relay, sink, source]).unwrap();
    let seen: Vec<Seen<Pose>> = (0..3).map(|_| recv(&seen_rx)).collect();
    let last = &seen[2].ctx;
    assert_eq!(seen[2].msg.stamp, u64::MAX - 3);
    assert_eq!(
        last.get("trace_id"),
        Some("abc"),
        "the user key travels downstream"
    );
    assert_eq!(
        last.get(KEY_PUB_SEQ),
        Some("3"),
        "/down's own counter, not /up's 1"
    );
    assert_eq!(seen[0].ctx.get("trace_id"), None);
}

/// A backend as a plugin would write it: it carries each message as JSON bytes and decodes
/// them with each subscriber's table, adding its `tag` option to the context.
#[derive(Default)]
struct Loopback {
    tag: Mutex<String>,
    subs: Mutex<Vec<(String, aimrt_plugin_api::channel::Sink)>>,
}

impl aimrt_plugin_api::channel::ChannelBackend for Loopback {
    fn type_name(&self) -> &str {
        "loopback"
    }
    fn init(&self, options: &aimrt_plugin_api::BackendOptions) -> Result<(), Error> {
        #[derive(serde::Deserialize)]
        struct Opts {
            tag: String,
        }
        *self.tag.lock().unwrap() = options.get::<Opts>()?.tag;
        Ok(())
    }
    fn register_publish_type(
        &self,
        _: &aimrt_plugin_api::channel::PublisherInfo<'_>,
    ) -> Result<(), Error> {
        Ok(())
    }
    fn subscribe(&self, s: aimrt_plugin_api::channel::Subscription) -> Result<(), Error> {
        self.subs.lock().unwrap().push((s.topic, s.sink));
        Ok(())
    }
    fn publish(&self, p: &aimrt_plugin_api::channel::Publication<'_>) -> Result<u64, Error> {
        let bytes = p.message().encode("json").map_err(Error::msg)?;
        let tag = self.tag.lock().unwrap().clone();
        let mut ctx: Vec<(&str, &str)> = p.ctx().collect();
        ctx.push(("via", &tag));
        // Pairs the publisher asks it to add last (`then: "k=v;k=v"`), as a backend of
        // another library may hand them to the sink.
        let then = p.get("then").unwrap_or_default();
        ctx.extend(then.split(';').filter_map(|kv| kv.split_once('=')));
        let pairs = aimrt_plugin_api::ffi::meta_of(ctx.into_iter());
        let mut n = 0;
        for (topic, sink) in self.subs.lock().unwrap().iter() {
            if topic != p.topic() {
                continue;
            }
            n += 1;
            match aimrt_plugin_api::ffi::RawMessage::decode(sink.type_support(), "json", &bytes) {
                Ok(m) => drop(sink.deliver(&pairs, m)),
                Err(e) => sink.report_drop(DropReason::DecodeFailed, &e),
            }
        }
        Ok(n)
    }
}

struct LoopbackPlugin;

impl aimrt_plugin_api::Plugin for LoopbackPlugin {
    fn name(&self) -> &str {
        "loopback_plugin"
    }
    fn initialize(
        &mut self,
        registrar: &mut aimrt_plugin_api::Registrar<'_>,
        _: &aimrt_plugin_api::PluginOptions,
    ) -> Result<(), Error> {
        registrar.register_channel_backend(Loopback::default())?;
        // `local` is the runtime's own.
        struct Impostor;
        impl aimrt_plugin_api::channel::ChannelBackend for Impostor {
            fn type_name(&self) -> &str {
                "local"
            }
            fn init(&self, _: &aimrt_plugin_api::BackendOptions) -> Result<(), Error> {
                Ok(())
            }
            fn register_publish_type(
                &self,
                _: &aimrt_plugin_api::channel::PublisherInfo<'_>,
            ) -> Result<(), Error> {
                Ok(())
            }
            fn subscribe(&self, _: aimrt_plugin_api::channel::Subscription) -> Result<(), Error> {
                Ok(())
            }
            fn publish(
                &self,
                _: &aimrt_plugin_api::channel::Publication<'_>,
            ) -> Result<u64, Error> {
                Ok(0)
            }
        }
        let e = registrar
            .register_channel_backend(Impostor)
            .unwrap_err()
            .to_string();
        assert!(e.contains("'local' is built into the runtime"), "{e}");
        Ok(())
    }
}

#[test]
fn a_plugin_backend_carries_messages_through_the_same_interface_as_local() {
    let _g = serial();
    let cfg = "  channel:\n    backends:\n      - type: local\n      - type: loopback\n        options: {tag: lb1}\n    pub_topics_options:\n      - topic_name: \"/both\"\n        enable_backends: [local, loopback]\n      - topic_name: \".*\"\n        enable_backends: [loopback]\n    sub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [local, loopback]\n";
    let (seen_tx, seen_rx) = channel::<Seen<Pose>>();
    let (keep, kept) = slot::<(Publisher<Pose>, Publisher<Pose>)>();
    let sub = Probe::new("Sub", move |core| {
        let ch = core.channel()?;
        subscribe_into(&ch, "/lb", seen_tx.clone())?;
        subscribe_into(&ch, "/both", seen_tx.clone())
    });
    let publ = Probe::new("Pub", move |core| {
        let ch = core.channel()?;
        *keep.lock().unwrap() =
            Some((ch.publisher::<Pose>("/lb")?, ch.publisher::<Pose>("/both")?));
        Ok(())
    })
    .on_start(move || {
        let (lb, both) = kept.lock().unwrap().clone().unwrap();
        lb.publish(pose(7))?;
        both.publish(pose(8))
    });
    run_with(cfg, None, vec![sub, publ], vec![Box::new(LoopbackPlugin)]).unwrap();
    let first = recv(&seen_rx);
    assert_eq!(*first.msg, pose(7), "decoded from the backend's JSON");
    assert_eq!(first.ctx.get(KEY_BACKEND), Some("loopback"));
    assert_eq!(first.ctx.get("via"), Some("lb1"));
    // A topic routed to two backends reaches the subscriber once through each, in rule order.
    let a = recv(&seen_rx);
    let b = recv(&seen_rx);
    assert_eq!(
        (a.ctx.get(KEY_BACKEND), b.ctx.get(KEY_BACKEND)),
        (Some("local"), Some("loopback"))
    );
    assert_eq!((*a.msg == pose(8), *b.msg == pose(8)), (true, true));
}

#[test]
fn a_subscriber_sees_its_backends_name_once_and_last_whatever_pairs_the_backend_hands_over() {
    let _g = serial();
    let cfg = "  channel:\n    backends:\n      - type: loopback\n        options: {tag: lb1}\n    pub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [loopback]\n    sub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [loopback]\n";
    // What the backend adds last: nothing; its own name (handed through as it is);
    // another name; another name early and its own last.
    const THEN: [&str; 4] = [
        "",
        "aimrt-backend=loopback",
        "aimrt-backend=forged",
        "aimrt-backend=early;x=1;aimrt-backend=loopback",
    ];
    let (seen_tx, seen_rx) = channel::<Seen<Pose>>();
    let (keep, kept) = slot::<Publisher<Pose>>();
    let sub = Probe::new("Sub", move |core| {
        subscribe_into(&core.channel()?, "/lb", seen_tx.clone())
    });
    let publ = Probe::new("Pub", move |core| {
        *keep.lock().unwrap() = Some(core.channel()?.publisher::<Pose>("/lb")?);
        Ok(())
    })
    .on_start(move || {
        let p = kept.lock().unwrap().clone().unwrap();
        for (k, then) in THEN.iter().enumerate() {
            let mut ctx = p.new_context(None);
            ctx.set("then", then);
            p.publish_with(&mut ctx, pose(k as u64))?;
        }
        Ok(())
    });
    run_with(cfg, None, vec![sub, publ], vec![Box::new(LoopbackPlugin)]).unwrap();
    for then in THEN {
        let seen = recv(&seen_rx);
        let pairs: Vec<(&str, &str)> = seen.ctx.iter().collect();
        let named: Vec<&str> = pairs
            .iter()
            .filter(|(k, _)| *k == KEY_BACKEND)
            .map(|(_, v)| *v)
            .collect();
        assert_eq!(named, ["loopback"], "then '{then}': {pairs:?}");
        assert_eq!(
            pairs.last(),
            Some(&(KEY_BACKEND, "loopback")),
            "then '{then}'"
        );
        assert_eq!(seen.ctx.get("via"), Some("lb1"), "then '{then}'");
    }
}

/// Blocks `exec`'s only worker, publishes `n` poses, then lets the worker go.
fn publish_while_blocked(
    exec: &aimrt_plugin_api::ExecutorRef,
    p: &Publisher<Pose>,
    n: u64,
) -> Result<(), Error> {
    let (release_tx, release_rx) = channel::<()>();
    let (started_tx, started_rx) = channel::<()>();
    exec.execute(move || {
        started_tx.send(()).unwrap();
        let _ = release_rx.recv_timeout(WAIT);
    })?;
    started_rx.recv_timeout(WAIT).unwrap();
    for k in 0..n {
        p.publish(pose(k))?;
    }
    release_tx.send(()).unwrap();
    Ok(())
}

#[test]
fn a_refused_async_delivery_is_counted_as_refused() {
    let _g = serial();
    let (keep, kept) = slot::<(Publisher<Pose>, ChannelRef, aimrt_plugin_api::ExecutorRef)>();
    let (out_tx, out_rx) = channel();
    let m = Probe::new("Flood", move |core| {
        let ch = core.channel()?;
        let tiny = core.executor("tiny")?;
        ch.subscriber("/flood")
            .subscribe_async(&tiny, |_: Context, _: Arc<Pose>| async {})?;
        *keep.lock().unwrap() = Some((ch.publisher::<Pose>("/flood")?, ch, tiny));
        Ok(())
    })
    .on_start(move || {
        let (p, ch, tiny) = kept.lock().unwrap().take().unwrap();
        // Block tiny's only worker; its queue holds at most one more task.
        publish_while_blocked(&tiny, &p, 5)?;
        out_tx.send(ch.stats("/flood").unwrap()).unwrap();
        Ok(())
    });
    run(LOCAL_ALL, None, vec![m]).unwrap();
    let s = recv(&out_rx);
    assert_eq!(s.published, 5);
    // Each message is either posted (delivered) or refused; with the worker blocked and a
    // queue of one, at least four are refused.
    let refused = s.dropped_for(DropReason::Refused);
    assert!(refused >= 4, "{s}");
    assert_eq!(refused + s.delivered, 5, "{s}");
    assert_eq!(s.dropped_for(DropReason::SubscriberFailed), 0, "{s}");
}

/// A plugin with filters that fail in each way a filter can.
struct FailingFilters(Sender<String>);

impl aimrt_plugin_api::Plugin for FailingFilters {
    fn name(&self) -> &str {
        "failing_filters"
    }
    fn initialize(
        &mut self,
        registrar: &mut aimrt_plugin_api::Registrar<'_>,
        _: &aimrt_plugin_api::PluginOptions,
    ) -> Result<(), Error> {
        use aimrt_plugin_api::channel::{FilterSide, Next, Publication};
        registrar.register_channel_filter(
            "refuse",
            FilterSide::Publish,
            |_: &Publication<'_>, _: Next<'_>| Err("not today".to_owned()),
        )?;
        registrar.register_channel_filter(
            "boom",
            FilterSide::Subscribe,
            |_: &Publication<'_>, _: Next<'_>| -> Result<(), String> { panic!("a filter panics") },
        )?;
        registrar.register_channel_filter(
            "late",
            FilterSide::Subscribe,
            |_: &Publication<'_>, next: Next<'_>| {
                next.pass()?;
                Err("failed after passing on".to_owned())
            },
        )?;
        // Refused: a name taken on its side, and the built-in one.
        let pass = |_: &Publication<'_>, next: Next<'_>| next.pass();
        for (name, side) in [
            ("refuse", FilterSide::Publish),
            ("debug_log", FilterSide::Subscribe),
        ] {
            let err = registrar
                .register_channel_filter(name, side, pass)
                .unwrap_err();
            self.0.send(err.to_string()).unwrap();
        }
        // The same name on the other side is another filter.
        registrar.register_channel_filter("refuse", FilterSide::Subscribe, pass)?;
        Ok(())
    }
}

#[test]
fn filters_that_fail_before_or_after_passing_on_are_told_apart() {
    let _g = serial();
    let cfg = "  channel:\n    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \"/refused\"\n        enable_backends: [local]\n        enable_filters: [refuse]\n      - topic_name: \".*\"\n        enable_backends: [local]\n    sub_topics_options:\n      - topic_name: \"/boom\"\n        enable_backends: [local]\n        enable_filters: [boom]\n      - topic_name: \"/late\"\n        enable_backends: [local]\n        enable_filters: [late, refuse]\n";
    let (registered_tx, registered_rx) = channel();
    let (out_tx, out_rx) = channel();
    let (got_tx, got_rx) = channel::<String>();
    let (keep, kept) = slot::<(Vec<Publisher<Pose>>, ChannelRef)>();
    let m = Probe::new("Filtered", move |core| {
        let ch = core.channel()?;
        let mut pubs = Vec::new();
        for topic in ["/refused", "/boom", "/late"] {
            pubs.push(ch.publisher::<Pose>(topic)?);
            let tx = got_tx.clone();
            ch.subscriber(topic).subscribe_msg(move |_: Arc<Pose>| {
                tx.send(topic.to_owned()).unwrap();
            })?;
        }
        *keep.lock().unwrap() = Some((pubs, ch));
        Ok(())
    })
    .on_start(move || {
        let (pubs, ch) = kept.lock().unwrap().take().unwrap();
        let results: Vec<Result<(), String>> = pubs
            .iter()
            .map(|p| p.publish(pose(1)).map_err(|e| e.to_string()))
            .collect();
        let stats = ["/refused", "/boom", "/late"].map(|t| ch.stats(t).unwrap());
        out_tx.send((results, stats)).unwrap();
        Ok(())
    });
    let plugin = FailingFilters(registered_tx);
    run_with(cfg, None, vec![m], vec![Box::new(plugin)]).unwrap();
    let refusals: Vec<String> = registered_rx.try_iter().collect();
    assert_eq!(refusals.len(), 2, "{refusals:?}");
    assert!(
        refusals[0]
            .contains("channel publish filter 'refuse' is already registered by 'failing_filters'"),
        "{}",
        refusals[0]
    );
    assert!(
        refusals[1].contains("'debug_log' is built into the runtime"),
        "{}",
        refusals[1]
    );
    let (results, [refused, boom, late]) = recv(&out_rx);
    // Before passing on: the publisher gets the publish filter's error; counted.
    let err = results[0].as_ref().unwrap_err();
    assert!(
        err.contains("publish filter 'refuse' failed: not today"),
        "{err}"
    );
    assert_eq!(
        (refused.delivered, refused.dropped_for(DropReason::Filtered)),
        (0, 1),
        "{refused}"
    );
    // A subscribe filter's panic: not delivered, counted; the publisher is not told.
    assert!(results[1].is_ok(), "{:?}", results[1]);
    assert_eq!(
        (boom.delivered, boom.dropped_for(DropReason::Filtered)),
        (0, 1),
        "{boom}"
    );
    // After passing on (through the subscribe side's `refuse`, which passes): delivered,
    // not a drop.
    assert!(results[2].is_ok(), "{:?}", results[2]);
    assert_eq!(
        (late.delivered, late.dropped_for(DropReason::Filtered)),
        (1, 0),
        "{late}"
    );
    let got: Vec<String> = got_rx.try_iter().collect();
    assert_eq!(got, ["/late"]);
}
