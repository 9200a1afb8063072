//! App mode in process: a runtime built from a config value with modules registered in
//! code, its main-thread executor driven by the `spin*` calls (seed 001's rules). One
//! runtime at a time per process, so each test holds `SERIAL`.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use aimrt_e2e::lib;
use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};
use aimrt_runtime::{App, Runtime, RuntimeOptions, SpinDuration, SpinError};

static SERIAL: Mutex<()> = Mutex::new(());

type Slot = Arc<Mutex<Option<ExecutorRef>>>;

/// Hands the main-thread executor (`main`) to the test.
struct Grab(Slot);

impl Module for Grab {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Grab")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        *self.0.lock().unwrap() = Some(core.executor("main")?);
        Ok(())
    }
}

const CFG: &str = "aimrt:\n  log:\n    core_lvl: Warn\n  main_thread:\n    name: main\n";

fn start_with(options: RuntimeOptions) -> Result<(App, ExecutorRef), aimrt_runtime::Error> {
    let slot = Slot::default();
    let mut runtime = Runtime::new(options);
    runtime.register_module(Box::new(Grab(slot.clone())));
    let app = runtime.start()?;
    let main = slot.lock().unwrap().take().expect("Grab initialized");
    Ok((app, main))
}

fn start() -> (App, ExecutorRef) {
    start_with(RuntimeOptions {
        cfg_yaml: Some(CFG.into()),
        ..Default::default()
    })
    .expect("starts")
}

/// Ends any blocking spin after 30 s (a failed helper thread must not hang the test): it
/// cancels the spin and requests shutdown, and the test's own checks then fail.
struct Watchdog(Option<std::sync::mpsc::Sender<()>>);

impl Drop for Watchdog {
    fn drop(&mut self) {
        self.0.take();
    }
}

fn watchdog(app: &App) -> Watchdog {
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    let (spinner, handle) = (app.spinner(), app.shutdown_handle());
    std::thread::spawn(move || {
        if rx.recv_timeout(Duration::from_secs(30))
            == Err(std::sync::mpsc::RecvTimeoutError::Timeout)
        {
            eprintln!("watchdog: a spin blocked for 30 s; ending it");
            handle.request();
            spinner.cancel();
        }
    });
    Watchdog(Some(tx))
}

/// Waits until `spinner` spins (at most 10 s).
fn until_spinning(spinner: &aimrt_runtime::Spinner) {
    let end = Instant::now() + Duration::from_secs(10);
    while !spinner.is_spinning() {
        assert!(Instant::now() < end, "spin never began");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// One test's runtime: the `SERIAL` guard (dropped last), the started app, its main-thread
/// executor, and a watchdog over its spins.
fn session() -> (
    std::sync::MutexGuard<'static, ()>,
    App,
    ExecutorRef,
    Watchdog,
) {
    let serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let (app, main) = start();
    let dog = watchdog(&app);
    (serial, app, main, dog)
}

fn counter() -> (Arc<AtomicUsize>, impl Fn() -> usize) {
    let c = Arc::new(AtomicUsize::new(0));
    let r = c.clone();
    (c, move || r.load(Ordering::SeqCst))
}

fn post_count(main: ExecutorRef, c: &Arc<AtomicUsize>) {
    let c = c.clone();
    main.execute(move || {
        c.fetch_add(1, Ordering::SeqCst);
    })
    .unwrap();
}

#[test]
fn spin_once_runs_one_task_and_waits_at_most_its_timeout() {
    let (_serial, app, main, _dog) = session();
    // Nothing queued: zero returns at once, a timeout waits that long.
    assert_eq!(app.spin_once(SpinDuration::ZERO), Ok(false));
    let t = Instant::now();
    assert_eq!(app.spin_once(Duration::from_millis(100)), Ok(false));
    let waited = t.elapsed();
    assert!(
        waited >= Duration::from_millis(100) && waited < Duration::from_secs(10),
        "{waited:?}"
    );

    let (c, count) = counter();
    for _ in 0..3 {
        post_count(main, &c);
    }
    assert_eq!(app.spin_once(SpinDuration::ZERO), Ok(true));
    assert_eq!(count(), 1, "spin_once runs one task");

    // A negative timeout waits as long as it takes: here for a task posted 50 ms later.
    assert_eq!(app.spin_all(SpinDuration::ZERO), Ok(2));
    let later = c.clone();
    let poster = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(50));
        post_count(main, &later);
    });
    assert_eq!(app.spin_once(SpinDuration::FOREVER), Ok(true));
    poster.join().unwrap();
    assert_eq!(count(), 4);
    app.shutdown();
}

#[test]
fn spin_some_runs_what_was_queued_at_the_call_once_each() {
    let (_serial, app, main, _dog) = session();
    let (c, count) = counter();
    // Three tasks, each queueing a follow-up: only the three run.
    for _ in 0..3 {
        let c = c.clone();
        main.execute(move || {
            c.fetch_add(1, Ordering::SeqCst);
            post_count(main, &c);
        })
        .unwrap();
    }
    assert_eq!(app.spin_some(SpinDuration::ZERO), Ok(3));
    assert_eq!(count(), 3);
    // The follow-ups are the next call's work.
    assert_eq!(app.spin_some(Duration::ZERO), Ok(3));
    assert_eq!(count(), 6);
    assert_eq!(
        app.spin_some(Duration::ZERO),
        Ok(0),
        "no work: returns at once"
    );

    // max_duration is checked before each task: 5 tasks of 40 ms in a 60 ms budget.
    for _ in 0..5 {
        main.execute(|| std::thread::sleep(Duration::from_millis(40)))
            .unwrap();
    }
    let ran = app.spin_some(Duration::from_millis(60)).unwrap();
    assert!((1..5).contains(&ran), "ran {ran} of 5");
    assert_eq!(app.spin_some(Duration::ZERO), Ok(5 - ran));
    let err = app.spin_some(SpinDuration::from_nanos(-1)).unwrap_err();
    assert!(
        matches!(
            err,
            SpinError::NegativeDuration {
                call: "spin_some",
                nanos: -1
            }
        ),
        "{err}"
    );
    app.shutdown();
}

#[test]
fn spin_all_runs_until_no_work_is_left_or_time_is_up() {
    let (_serial, app, main, _dog) = session();
    // A chain: each task queues the next, five deep. spin_all follows it to the end.
    fn chain(main: ExecutorRef, left: usize, c: Arc<AtomicUsize>) {
        main.execute(move || {
            c.fetch_add(1, Ordering::SeqCst);
            if left > 1 {
                chain(main, left - 1, c);
            }
        })
        .unwrap();
    }
    let (c, count) = counter();
    chain(main, 5, c.clone());
    assert_eq!(app.spin_all(SpinDuration::ZERO), Ok(5));
    assert_eq!(count(), 5);

    // Work that never ends: spin_all stops once max_duration has passed.
    fn forever(main: ExecutorRef, c: Arc<AtomicUsize>) {
        let _ = main.execute(move || {
            c.fetch_add(1, Ordering::SeqCst);
            std::thread::sleep(Duration::from_millis(5));
            forever(main, c);
        });
    }
    forever(main, c.clone());
    let t = Instant::now();
    let ran = app.spin_all(Duration::from_millis(100)).unwrap();
    let took = t.elapsed();
    assert!(ran > 1, "ran {ran}");
    assert!(
        took >= Duration::from_millis(100) && took < Duration::from_secs(10),
        "{took:?}"
    );

    let err = app.spin_all(SpinDuration::from_nanos(-5)).unwrap_err();
    assert_eq!(
        err,
        SpinError::NegativeDuration {
            call: "spin_all",
            nanos: -5
        }
    );
    assert!(
        err.to_string().contains("max_duration must be >= 0"),
        "{err}"
    );
    app.shutdown();
}

#[test]
fn a_spin_while_spinning_is_an_error_and_is_spinning_tells() {
    let (_serial, app, main, _dog) = session();
    assert!(!app.is_spinning());
    let spinner = app.spinner();
    let seen = Arc::new(Mutex::new(Vec::new()));
    let s = seen.clone();
    let inner = spinner.clone();
    main.execute(move || {
        // From one of the spin's own tasks.
        s.lock()
            .unwrap()
            .push((inner.is_spinning(), inner.spin_once(SpinDuration::ZERO)));
    })
    .unwrap();
    assert_eq!(app.spin_once(SpinDuration::ZERO), Ok(true));
    let (spinning, nested) = seen.lock().unwrap().pop().unwrap();
    assert!(spinning);
    let err = nested.unwrap_err();
    assert!(
        err.to_string()
            .contains("already being spun by this thread"),
        "{err}"
    );

    // From another thread while the main thread spins.
    let other = spinner.clone();
    let prober = std::thread::spawn(move || {
        until_spinning(&other);
        let results = (
            other.spin(),
            other.spin_some(Duration::ZERO),
            other.spin_all(Duration::ZERO),
        );
        other.cancel();
        results
    });
    app.spin().unwrap();
    let (a, b, c) = prober.join().unwrap();
    for r in [a.map(|_| 0), b, c] {
        assert!(matches!(r, Err(SpinError::AlreadySpinning { .. })), "{r:?}");
    }
    assert!(!app.is_spinning());
    app.shutdown();
}

#[test]
fn cancel_from_another_thread_ends_spin_promptly() {
    let (_serial, app, main, _dog) = session();
    // With no spin running, cancel does nothing, and the next spin is not affected.
    assert!(!app.cancel());
    let (c, count) = counter();
    post_count(main, &c);
    assert_eq!(app.spin_once(SpinDuration::ZERO), Ok(true));

    let spinner = app.spinner();
    let canceller = std::thread::spawn(move || {
        until_spinning(&spinner);
        std::thread::sleep(Duration::from_millis(100));
        let at = Instant::now();
        assert!(spinner.cancel(), "a spin was running");
        at
    });
    let t = Instant::now();
    app.spin().unwrap();
    let returned = Instant::now();
    let cancelled = canceller.join().unwrap();
    assert!(t.elapsed() >= Duration::from_millis(100));
    let lag = returned.saturating_duration_since(cancelled);
    assert!(
        lag < Duration::from_secs(2),
        "spin returned {lag:?} after cancel"
    );

    // A cancelled spin leaves queued work for the next one.
    post_count(main, &c);
    let again = app.spinner();
    main.execute(move || {
        again.cancel();
    })
    .unwrap();
    post_count(main, &c);
    app.spin().unwrap();
    assert_eq!(
        count(),
        2,
        "the task after the cancelling one is left queued"
    );
    assert_eq!(app.spin_all(SpinDuration::ZERO), Ok(1));
    app.shutdown();
}

#[test]
fn a_shutdown_request_ends_spin_and_later_spins_return_at_once() {
    let (_serial, app, _main, _dog) = session();
    let handle = app.shutdown_handle();
    let requester = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(50));
        handle.request()
    });
    app.spin().unwrap();
    assert!(requester.join().unwrap());
    let t = Instant::now();
    app.spin().unwrap();
    assert_eq!(app.spin_once(SpinDuration::FOREVER), Ok(false));
    assert!(t.elapsed() < Duration::from_secs(5));
    app.shutdown();
}

#[test]
fn config_from_a_value_or_a_file_and_pkgs_after_code_modules() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("report.txt");
    let cfg = format!(
        "{CFG}  module:\n    pkgs:\n      - path: {}\n        enable_modules: [NormalSubscriberModule]\nNormalSubscriberModule:\n  topic_name: t\n",
        lib("libpb_chn_sub_pkg.so").display()
    );
    let (app, _) = start_with(RuntimeOptions {
        cfg_yaml: Some(cfg.clone()),
        dump_init_report: Some(report.clone()),
        ..Default::default()
    })
    .expect("starts from a config value");
    app.shutdown();
    let text = std::fs::read_to_string(&report).unwrap();
    let text = &text[text.find("Module Info List").expect("module table")..];
    let grab = text.find("|  Grab ").expect("code module listed");
    let sub = text
        .find("|  NormalSubscriberModule ")
        .expect("pkg module listed");
    assert!(
        grab < sub,
        "modules registered in code come before pkg modules:\n{text}"
    );

    // The same from a file.
    let path = dir.path().join("cfg.yaml");
    std::fs::write(&path, &cfg).unwrap();
    let (app, _) = start_with(RuntimeOptions {
        cfg_file_path: Some(path.clone()),
        ..Default::default()
    })
    .expect("starts from a file");
    app.shutdown();

    // Both at once, or a bad value: a clear error, nothing left running.
    let err = start_with(RuntimeOptions {
        cfg_file_path: Some(path),
        cfg_yaml: Some(cfg),
        ..Default::default()
    })
    .unwrap_err()
    .to_string();
    assert!(err.contains("both cfg_yaml and cfg_file_path"), "{err}");
    let err = start_with(RuntimeOptions {
        cfg_yaml: Some("aimrt:\n  executor: [".into()),
        ..Default::default()
    })
    .unwrap_err()
    .to_string();
    assert!(err.starts_with("<cfg_yaml>:"), "{err}");
}

/// Each start of zenoh_plugin opens a session and, with `shm_enabled`, a shared-memory
/// pool: each a `/dev/shm` file this process holds open. Shutting the runtime down frees
/// both. Before, every session's segment and pool stayed open until the process exited
/// (2, 4, 6 files after three starts), and stayed in `/dev/shm` after it.
#[test]
fn zenoh_sessions_started_again_and_again_hold_no_more_shared_memory() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let peers = aimrt_e2e::ZenohPeers::new("app_mode_shm");
    let lib_dir = aimrt_e2e::profile_dir().display().to_string();
    let native = peers.native("a").display().to_string();
    let own = |example: &str| {
        aimrt_e2e::zenoh_example(example)
            .replace("${AIMRT_LIB_DIR:-./target/debug}", &lib_dir)
            .replace("${AIMRT_ZENOH_NATIVE_CFG:-./config/zenoh_native_a.json5}", &native)
            .replace("${AIMRT_ZENOH_LIMIT_DOMAIN:-}", &peers.domain)
            .replace("core_lvl: INFO", "core_lvl: Warn")
            // The example's executors, which aimrt_main has built in, from their library.
            .replacen(
                "    plugins:\n",
                &format!("    plugins:\n      - name: std_executors\n        path: {lib_dir}/libaimrt_std_executors_plugin.so\n"),
                1,
            )
    };
    for example in ["pb_chn_pub_with_shm", "pb_rpc_client_with_shm"] {
        let cfg = own(example);
        assert!(cfg.contains(&native), "{cfg}");
        let mut held = Vec::new();
        for _ in 0..3 {
            let app = Runtime::new(RuntimeOptions {
                cfg_yaml: Some(cfg.clone()),
                ..Default::default()
            })
            .start()
            .unwrap_or_else(|e| panic!("{example} starts: {e}"));
            assert!(
                !aimrt_e2e::zenoh_shm_files(None).is_empty(),
                "{example}: no zenoh segment open"
            );
            app.shutdown();
            // zenoh lets go of what its tasks still held a moment after the close.
            let until = Instant::now() + Duration::from_secs(3);
            while !aimrt_e2e::zenoh_shm_files(None).is_empty() && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(20));
            }
            held.push(aimrt_e2e::zenoh_shm_files(None).len());
        }
        assert_eq!(
            held,
            [0, 0, 0],
            "{example}: zenoh segments still open after each shutdown"
        );
    }
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Hop {
    n: u64,
}
aimrt_plugin_api::serde_message!(Hop, "test.Hop");

type HopPublisher = Arc<Mutex<Option<aimrt_plugin_api::channel::Publisher<Hop>>>>;

/// Subscribes `/hop` and, inside its callback, publishes the next hop on `/hop` again
/// until hop 3; hop 0 goes out half a second after start.
struct Hops(std::sync::mpsc::Sender<u64>, HopPublisher);

impl Module for Hops {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Hops")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let channel = core.channel()?;
        *self.1.lock().unwrap() = Some(channel.publisher::<Hop>("/hop")?);
        let (publisher, heard) = (self.1.clone(), self.0.clone());
        channel
            .subscriber("/hop")
            .subscribe_msg(move |hop: Arc<Hop>| {
                let _ = heard.send(hop.n);
                if hop.n < 3 {
                    let next = publisher.lock().unwrap().clone().expect("registered");
                    let _ = next.publish(Hop { n: hop.n + 1 });
                }
            })?;
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let first = self.1.lock().unwrap().clone().expect("registered");
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(500));
            let _ = first.publish(Hop { n: 0 });
        });
        Ok(())
    }
}

type Hook = Box<dyn FnMut(&CoreRef) -> Result<(), Error> + Send>;

/// A module made of an `initialize` and a `start` closure.
struct Steps(
    &'static str,
    Hook,
    Box<dyn FnMut() -> Result<(), Error> + Send>,
);

impl Module for Steps {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new(self.0)
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        (self.1)(&core)
    }
    fn start(&mut self) -> Result<(), Error> {
        (self.2)()
    }
}

fn zenoh_alone(peers: &aimrt_e2e::ZenohPeers, send_sequence: bool) -> String {
    format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: zenoh_plugin\n        path: {}\n        options:\n          native_cfg_path: {}\n          limit_domain: {}\n  log:\n    core_lvl: Warn\n  channel:\n    backends:\n      - type: zenoh\n        options:\n          pub_topics_options:\n            - topic_name: \".*\"\n              send_sequence: {send_sequence}\n    pub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [zenoh]\n    sub_topics_options:\n      - topic_name: \".*\"\n        enable_backends: [zenoh]\n",
        lib("libaimrt_zenoh_plugin.so").display(),
        peers.native("a").display(),
        peers.domain
    )
}

/// A subscriber in the publishing process that subscribed after the publisher registered
/// hears the first message, published as soon as the last module starts. (zenoh's
/// matching listener says a moment later, on another thread, that the subscriber came.)
#[test]
fn a_zenoh_subscriber_registered_after_its_publisher_hears_the_first_message() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let peers = aimrt_e2e::ZenohPeers::new("app_mode_first_hop");
    let (tx, rx) = std::sync::mpsc::channel();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_yaml: Some(zenoh_alone(&peers, true)),
        ..Default::default()
    });
    let first: HopPublisher = Arc::default();
    let registered = first.clone();
    runtime.register_module(Box::new(Steps(
        "Registers",
        Box::new(move |core: &CoreRef| {
            *registered.lock().unwrap() = Some(core.channel()?.publisher::<Hop>("/first")?);
            Ok(())
        }),
        Box::new(|| Ok(())),
    )));
    runtime.register_module(Box::new(Steps(
        "Hears",
        Box::new(move |core: &CoreRef| {
            let tx = tx.clone();
            core.channel()?
                .subscriber("/first")
                .subscribe_msg(move |hop: Arc<Hop>| {
                    let _ = tx.send(hop.n);
                })
        }),
        Box::new(|| Ok(())),
    )));
    let publisher = first.clone();
    runtime.register_module(Box::new(Steps(
        "Publishes",
        Box::new(|_: &CoreRef| Ok(())),
        Box::new(move || {
            let p = publisher.lock().unwrap().clone().expect("registered");
            p.publish(Hop { n: 7 })
        }),
    )));
    let app = runtime.start().expect("starts");
    let heard = rx.recv_timeout(Duration::from_secs(10));
    app.shutdown();
    assert_eq!(heard, Ok(7));
}

/// A client in this process calls a function a module of this process serves, as soon
/// as it starts, the client registered before the server: the call is served, not
/// answered "no server" (zenoh's matching listener says a moment later, on another
/// thread, that the server came).
#[test]
fn a_zenoh_call_at_start_reaches_a_server_of_this_process_registered_after_the_client() {
    use aimrt_e2e::rpc_modules::{f, req, show, Req, Rsp};
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let peers = aimrt_e2e::ZenohPeers::new("app_mode_first_call");
    let cfg = zenoh_alone(&peers, true).replace(
        "  channel:",
        "  rpc:\n    backends:\n      - type: zenoh\n    clients_options:\n      - func_name: \".*\"\n        enable_backends: [zenoh]\n    servers_options:\n      - func_name: \".*\"\n        enable_backends: [zenoh]\n  channel:",
    );
    let (tx, rx) = std::sync::mpsc::channel();
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_yaml: Some(cfg),
        ..Default::default()
    });
    let client: Arc<Mutex<Option<aimrt_plugin_api::RpcClient<Req, Rsp>>>> = Arc::default();
    let registered = client.clone();
    runtime.register_module(Box::new(Steps(
        "Calls",
        Box::new(move |core: &CoreRef| {
            *registered.lock().unwrap() = Some(core.rpc()?.client::<Req, Rsp>(&f("Echo"))?);
            Ok(())
        }),
        Box::new(move || {
            let echo = client.lock().unwrap().clone().expect("registered");
            let tx = tx.clone();
            std::thread::spawn(move || {
                let mut ctx = aimrt_plugin_api::RpcContext::client();
                let _ = tx.send(show(&echo.call(&mut ctx, req("first"))));
            });
            Ok(())
        }),
    )));
    runtime.register_module(Box::new(Steps(
        "Serves",
        Box::new(|core: &CoreRef| {
            core.rpc()?
                .serve_sync(&f("Echo"), |_: &aimrt_plugin_api::RpcContext, r: &Req| {
                    Ok(Rsp {
                        text: format!("echo {}", r.text),
                    })
                })
        }),
        Box::new(|| Ok(())),
    )));
    let app = runtime.start().expect("starts");
    let answer = rx.recv_timeout(Duration::from_secs(10));
    app.shutdown();
    assert_eq!(answer.as_deref(), Ok("ok: echo first"));
}

/// zenoh calls this process's own subscribers of a key inside the put. One that publishes
/// on the same topic from there goes on, with or without sequence numbers: before, the
/// publish waited for the lock its own put held, and the process hung.
#[test]
fn a_zenoh_subscriber_that_publishes_on_its_own_topic_goes_on() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    for send_sequence in [true, false] {
        let peers = aimrt_e2e::ZenohPeers::new(&format!("app_mode_hops_{send_sequence}"));
        let cfg = zenoh_alone(&peers, send_sequence);
        let (tx, rx) = std::sync::mpsc::channel();
        let mut runtime = Runtime::new(RuntimeOptions {
            cfg_yaml: Some(cfg),
            ..Default::default()
        });
        runtime.register_module(Box::new(Hops(tx, Arc::default())));
        let app = runtime.start().expect("starts");
        let heard: Vec<u64> = (0..4)
            .map_while(|_| rx.recv_timeout(Duration::from_secs(10)).ok())
            .collect();
        if heard != [0, 1, 2, 3] {
            // A hung publish holds what the shutdown would wait for.
            std::mem::forget(app);
            panic!("send_sequence {send_sequence}: heard {heard:?}");
        }
        app.shutdown();
    }
}
