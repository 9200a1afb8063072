//! Scenario `zenoh`: zenoh_plugin between two processes on one machine, beside a raw zenoh
//! baseline of two processes in the same run, at 64 B, 1 KiB, 64 KiB and 1 MiB, with shared
//! memory off and on.
//!
//! - Ours: this process runs the real runtime with `libaimrt_zenoh_plugin.so` and a module
//!   that publishes `ExampleEventMsg` on `/bench/ping` and counts what comes back on
//!   `/bench/pong`; an `aimrt_main` with `RelayModule` (libpb_chn_pkg.so) republishes each
//!   message.
//! - Raw: `aimrt_zenoh_probe ping` and `aimrt_zenoh_probe pong` (bins of the plugin crate,
//!   only the zenoh crate) put the same AimRT payloads on the same keys. The baseline the
//!   targets compare with is `typed`: the raw sides do the message's own work that ours
//!   does (the ping encodes each message and decodes each echo, the pong decodes and
//!   encodes), so the comparison is of the plugin and the runtime alone. A `bytes` baseline
//!   (the pong forwards bytes, the ping never decodes) is measured beside it and reported.
//!
//! - Relay (reported, not a target): the typed raw ping against a second `aimrt_main` with
//!   `RelayModule`, in place of the raw pong. Its ratio to `typed` is our receiving,
//!   republishing side alone, with the same ping on both: steadier on a small machine,
//!   where the ping side of ours shares the cores.
//! - Ping (reported, not a target): ours' ping (the runtime in this process) against the
//!   typed raw pong, in place of our relay. Its ratio to `typed` is our publishing and
//!   echo-counting side alone, with the same pong on both; with the relay's ratio it
//!   says which side a gap of ours is on.
//! - Ping sides' threads (reported, not a target): over the throughput phase, each ping
//!   side's threads from the kernel's scheduler statistics ([`sched`]), a message.
//!
//! Both sides measure alike: throughput is echoes a second with at most 64 messages and
//! 8 MiB unanswered (zenoh's default congestion control drops what it cannot queue),
//! and latency is the round trip of one message in flight. Both peers use explicit
//! loopback endpoints with multicast scouting off (the echo side listens, the ping side
//! connects: one connection a pair, whichever starts first), zenoh's implicit shared
//! memory for large payloads off (so "shm off" is the network path), and a wait of up
//! to 1 s for room in zenoh's send queue before it drops a message (zenoh's defaults:
//! 1 ms, 50 ms for a fragmented one): a drop stalls the window until the round gives up
//! on it, which measures the scheduler of a busy machine, not the transport. Each round
//! runs every size through ours and through raw zenoh back to back behind the quiet
//! gate; the first round warms up and is discarded; the verdicts are the medians of the
//! per-round ratios and differences. Every measurement starts its own processes and
//! sessions, ours as the raw ones: none inherits a connection, a session or a heap from
//! an earlier size.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{mpsc, Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::Publisher;
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_protocols::example::ExampleEventMsg;
use aimrt_runtime::{Runtime, RuntimeOptions};

use crate::sched::{self, SideCost};
use crate::stats::{alternate, percentile, quiet_gate, Scale};

/// What one measurement gives.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub(crate) struct Figures {
    pub(crate) msgs_per_s: f64,
    pub(crate) rtt_p50_us: f64,
    pub(crate) rtt_p99_us: f64,
    /// The ping side's threads over the throughput phase, a message (`None`: not read).
    pub(crate) ping_side: Option<SideCost>,
    /// The ping side's window waits of [`STALL`] or more in the throughput phase, a
    /// thousand messages delivered (NaN: none delivered, or not said).
    pub(crate) stalls_per_k: f64,
}

/// `stalls` a thousand of `delivered` messages (NaN when none was delivered, or either is
/// NaN: not said).
fn per_thousand(stalls: f64, delivered: f64) -> f64 {
    if delivered > 0.0 {
        stalls * 1000.0 / delivered
    } else {
        f64::NAN
    }
}

/// One case over the measured rounds: ours and the raw baseline, round by round.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct Case {
    pub(crate) size: usize,
    pub(crate) shm: bool,
    /// Echoes expected and counted over the measured rounds (ours).
    pub(crate) sent: u64,
    pub(crate) delivered: u64,
    pub(crate) ours: Vec<Figures>,
    /// The baseline of the targets: raw zenoh doing the typed message's work.
    pub(crate) raw: Vec<Figures>,
    /// Raw zenoh forwarding bytes (reported, not a target).
    pub(crate) raw_bytes: Vec<Figures>,
    /// The typed raw ping against our relay (reported, not a target).
    pub(crate) relay: Vec<Figures>,
    /// Ours' ping against the typed raw pong (reported, not a target).
    pub(crate) ping: Vec<Figures>,
}

/// The sizes of a run without `--zenoh-sizes`.
const SIZES: [usize; 4] = [64, 1024, 64 << 10, 1 << 20];
/// Messages of `size` bytes a ping side keeps unanswered at most, as `aimrt_zenoh_probe
/// ping`: 64, and no more than 8 MiB (8 at 1 MiB). More only measures zenoh's `Drop`
/// congestion control: a dropped message stalls the window for its 2 s patience.
fn window(size: usize) -> u64 {
    ((8usize << 20) / size.max(1)).clamp(1, 64) as u64
}

/// The files the scenario runs, next to this binary.
struct Files {
    aimrt_main: PathBuf,
    probe: PathBuf,
    plugin: PathBuf,
    pkg: PathBuf,
}

fn files() -> Result<Files, String> {
    let need = crate::built;
    Ok(Files {
        aimrt_main: need("aimrt_main")?,
        probe: need("aimrt_zenoh_probe")?,
        plugin: need("libaimrt_zenoh_plugin.so")?,
        pkg: need("libpb_chn_pkg.so")?,
    })
}

fn free_port() -> Result<u16, String> {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

/// The native config of a side, with `LISTEN_ENDPOINTS` and `CONNECT_ENDPOINTS` to fill in.
const NATIVE: &str = include_str!("../zenoh_native.json5");

/// Native configs of the two sides in `dir`: the pong listens on a free port, the ping
/// connects to it and listens nowhere, so a pair has one connection, opened by the ping,
/// whichever starts first (benches/zenoh_native.json5). The files are named by `tag`, so a
/// side that reads its file again later (the relay's ping, each round) finds its own port,
/// not another side's.
fn natives(dir: &Path, tag: &str) -> Result<(PathBuf, PathBuf), String> {
    let endpoint = format!("\"tcp/127.0.0.1:{}\"", free_port()?);
    let mut out = Vec::new();
    for (name, listen, connect) in [("ping", "", endpoint.as_str()), ("pong", &endpoint, "")] {
        let path = dir.join(format!("zenoh_{tag}_{name}.json5"));
        std::fs::write(
            &path,
            NATIVE
                .replace("LISTEN_ENDPOINTS", listen)
                .replace("CONNECT_ENDPOINTS", connect),
        )
        .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        out.push(path);
    }
    Ok((out[0].clone(), out[1].clone()))
}

/// A child process killed when dropped.
struct Kid(Child);

impl Drop for Kid {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `program`; its standard output is piped only when `read`: a pipe nobody reads
/// fills, and a side that then writes a log line would stand still mid-measurement.
fn spawn(program: &Path, args: &[&str], read: bool) -> Result<Kid, String> {
    Command::new(program)
        .args(args)
        .stdout(if read { Stdio::piped() } else { Stdio::null() })
        .stderr(Stdio::null())
        .spawn()
        .map(Kid)
        .map_err(|e| format!("cannot start {}: {e}", program.display()))
}

/// The config of a runtime side: the zenoh plugin, `shm` for every topic, log at Warn.
fn config(f: &Files, native: &Path, shm: bool, pkg_and_relay: bool) -> String {
    let mut cfg = format!(
        "aimrt:\n  plugin:\n    plugins:\n      - name: zenoh_plugin\n        path: {}\n        options:\n          native_cfg_path: {}\n          shm_pool_size: 67108864\n  log:\n    core_lvl: Warn\n    backends:\n      - type: console\n  channel:\n    backends:\n      - type: zenoh\n        options:\n          pub_topics_options:\n            - topic_name: \"(.*)\"\n              shm_enabled: {shm}\n    pub_topics_options:\n      - topic_name: \"(.*)\"\n        enable_backends: [zenoh]\n    sub_topics_options:\n      - topic_name: \"(.*)\"\n        enable_backends: [zenoh]\n",
        f.plugin.display(),
        native.display()
    );
    if pkg_and_relay {
        cfg.push_str(&format!(
            "  module:\n    pkgs:\n      - path: {}\n        enable_modules: [RelayModule]\n    modules:\n      - name: RelayModule\n        log_lvl: Warn\nRelayModule:\n  sub_topic_name: /bench/ping\n  pub_topic_name: /bench/pong\n",
            f.pkg.display()
        ));
    }
    cfg
}

/// Echoes counted by the subscriber, waited for without spinning (a spinning waiter takes a
/// core from the processes it measures on a small machine).
#[derive(Default)]
struct Echoes {
    count: Mutex<u64>,
    cv: Condvar,
}

impl Echoes {
    fn hit(&self) {
        *self.count.lock().unwrap_or_else(|e| e.into_inner()) += 1;
        self.cv.notify_all();
    }

    fn now(&self) -> u64 {
        *self.count.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Waits until `target` echoes arrived; `false` after `patience`.
    fn wait(&self, target: u64, patience: Duration) -> bool {
        self.wait_counting(target, patience, &mut 0)
    }

    /// [`wait`](Self::wait), adding one to `stalls` when it blocked for [`STALL`] or
    /// more (the clock is read only when it blocks, as the raw ping does).
    fn wait_counting(&self, target: u64, patience: Duration, stalls: &mut u64) -> bool {
        let guard = self.count.lock().unwrap_or_else(|e| e.into_inner());
        if *guard >= target {
            return true;
        }
        let blocked = Instant::now();
        let (guard, _) = self
            .cv
            .wait_timeout_while(guard, patience, |n| *n < target)
            .unwrap_or_else(|e| e.into_inner());
        if blocked.elapsed() >= STALL {
            *stalls += 1;
        }
        *guard >= target
    }
}

/// A window wait this long or longer is a stall. For small messages, whose round trip takes
/// about 0.1 ms, it is most likely zenoh's transmit task backing off while a batch is being
/// written: it sleeps until `batching.time_limit` (1 ms) has passed since the batch's first
/// write, on tokio's 1 ms timer (zenoh-transport 1.10.2, `pipeline.rs`). For large ones it
/// is as likely their own time. `aimrt_zenoh_probe ping` counts the same.
const STALL: Duration = Duration::from_micros(900);

struct Ping {
    echoes: Arc<Echoes>,
    out: mpsc::Sender<Publisher<ExampleEventMsg>>,
    publisher: Option<Publisher<ExampleEventMsg>>,
}

impl Module for Ping {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("ZenohPing")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let ch = core.channel()?;
        let echoes = self.echoes.clone();
        ch.subscriber("/bench/pong")
            .subscribe_msg(move |_: Arc<ExampleEventMsg>| echoes.hit())?;
        self.publisher = Some(ch.publisher("/bench/ping")?);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        if let Some(p) = self.publisher.take() {
            let _ = self.out.send(p);
        }
        Ok(())
    }
}

/// The figures of one size through the runtime, and the echoes counted.
fn measure(
    p: &Publisher<ExampleEventMsg>,
    echoes: &Echoes,
    size: usize,
    n: u64,
    samples: usize,
) -> Result<(Figures, u64), String> {
    let msg = Arc::new(ExampleEventMsg {
        msg: "x".repeat(size),
        num: 1,
    });
    let send = || {
        p.publish(msg.clone())
            .map_err(|e| format!("publish failed: {e}"))
    };
    // The echo must be there: a message every 10 ms until one comes back.
    let ready = Instant::now() + Duration::from_secs(20);
    let first = echoes.now();
    while echoes.now() == first {
        if Instant::now() > ready {
            return Err("no echo on /bench/pong within 20 s".into());
        }
        send()?;
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(100));
    let before = sched::snapshot(None);
    let base = echoes.now();
    let t0 = Instant::now();
    let window = window(size);
    let mut stalls = 0;
    for k in 0..n {
        if k >= window {
            echoes.wait_counting(base + k + 1 - window, Duration::from_secs(2), &mut stalls);
        }
        send()?;
    }
    echoes.wait_counting(base + n, Duration::from_secs(10), &mut stalls);
    let delivered = echoes.now() - base;
    let rate = delivered as f64 / t0.elapsed().as_secs_f64();
    let ping_side = sched::this_thread()
        .and_then(|me| sched::cost(&before, &sched::snapshot(None), me, delivered));
    let mut lat = Vec::with_capacity(samples);
    for _ in 0..samples {
        let before = echoes.now();
        let t = Instant::now();
        send()?;
        if echoes.wait(before + 1, Duration::from_secs(2)) {
            lat.push(t.elapsed().as_secs_f64() * 1e6);
        }
    }
    lat.sort_by(f64::total_cmp);
    Ok((
        Figures {
            msgs_per_s: rate,
            rtt_p50_us: percentile(&lat, 50.0),
            rtt_p99_us: percentile(&lat, 99.0),
            ping_side,
            stalls_per_k: per_thousand(stalls as f64, delivered as f64),
        },
        delivered,
    ))
}

/// Messages of the throughput phase and round trips of the latency phase at `size`:
/// `messages` when given (`--zenoh-messages`), else by size (a quarter with `--quick`).
fn counts(size: usize, quick: bool, messages: Option<u64>) -> (u64, usize) {
    let (n, samples) = match size {
        s if s >= 1 << 20 => (400, 100),
        s if s >= 64 << 10 => (2_000, 200),
        _ => (20_000, 1_000),
    };
    let (n, samples) = if quick {
        (n / 4, samples / 2)
    } else {
        (n, samples)
    };
    (messages.unwrap_or(n), samples)
}

/// What answers ours' ping.
#[derive(Debug, Clone, Copy)]
enum Echo {
    /// Our relay: `aimrt_main` with `RelayModule`.
    Relay,
    /// The typed raw pong.
    RawPong,
}

/// Our side with shared memory `shm`: its echo side (our relay, or the raw pong) and a
/// runtime in this process with the ping module, up for one measurement.
struct Ours {
    _pong: Kid,
    publisher: Publisher<ExampleEventMsg>,
    echoes: Arc<Echoes>,
    handle: aimrt_runtime::ShutdownHandle,
    thread: std::thread::JoinHandle<Result<(), aimrt_runtime::Error>>,
}

/// An `aimrt_main` with `RelayModule` on `native`, shared memory `shm`; its config is
/// `dir/<name>.yaml`.
fn relay(f: &Files, dir: &Path, name: &str, native: &Path, shm: bool) -> Result<Kid, String> {
    let cfg = dir.join(format!("{name}.yaml"));
    std::fs::write(&cfg, config(f, native, shm, true)).map_err(|e| e.to_string())?;
    spawn(
        &f.aimrt_main,
        &[&format!("--cfg_file_path={}", cfg.display())],
        false,
    )
}

/// The typed raw ping against our relay, up for one measurement.
struct Relay {
    _relay: Kid,
    ping_native: PathBuf,
}

impl Relay {
    fn start(f: &Files, dir: &Path, shm: bool) -> Result<Relay, String> {
        let (ping_native, pong_native) = natives(dir, "relay")?;
        Ok(Relay {
            _relay: relay(f, dir, &format!("relay_{shm}"), &pong_native, shm)?,
            ping_native,
        })
    }

    fn measure(
        &self,
        f: &Files,
        case: (usize, bool),
        counts: (u64, usize),
    ) -> Result<Figures, String> {
        probe_ping(f, &self.ping_native, case, "typed", counts)
    }
}

impl Ours {
    fn start(f: &Files, dir: &Path, shm: bool, echo: Echo) -> Result<Ours, String> {
        let (ping_native, pong_native) = natives(dir, "ours")?;
        let pong = match echo {
            Echo::Relay => relay(f, dir, &format!("pong_{shm}"), &pong_native, shm)?,
            Echo::RawPong => raw_pong(f, &pong_native, shm, "typed")?,
        };
        let ping_cfg = dir.join(format!("ping_{shm}.yaml"));
        std::fs::write(&ping_cfg, config(f, &ping_native, shm, false))
            .map_err(|e| e.to_string())?;
        let echoes = Arc::new(Echoes::default());
        let (tx, rx) = mpsc::channel();
        let mut runtime = Runtime::new(RuntimeOptions {
            cfg_file_path: Some(ping_cfg),
            ..Default::default()
        });
        runtime.register_module(Box::new(Ping {
            echoes: echoes.clone(),
            out: tx,
            publisher: None,
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
        Ok(Ours {
            _pong: pong,
            publisher,
            echoes,
            handle,
            thread,
        })
    }

    fn measure(&self, size: usize, n: u64, samples: usize) -> Result<(Figures, u64), String> {
        measure(&self.publisher, &self.echoes, size, n, samples)
    }

    fn stop(self) -> Result<(), String> {
        drop(self.publisher);
        self.handle.request();
        match self.thread.join() {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(format!("the runtime failed: {e}")),
            Err(_) => Err("the runtime thread panicked".into()),
        }
    }
}

/// The raw baseline of `size` with shared memory `shm`: a pong and a ping probe, in `mode`
/// (`typed` or `bytes`), with `counts` as [`counts`] gives them.
fn raw(
    f: &Files,
    dir: &Path,
    (size, shm): (usize, bool),
    mode: &str,
    counts: (u64, usize),
) -> Result<Figures, String> {
    let (ping_native, pong_native) = natives(dir, "raw")?;
    let _pong = raw_pong(f, &pong_native, shm, mode)?;
    probe_ping(f, &ping_native, (size, shm), mode, counts)
}

/// `aimrt_zenoh_probe pong` on `pong_native` in `mode`, with shared memory `shm`.
fn raw_pong(f: &Files, pong_native: &Path, shm: bool, mode: &str) -> Result<Kid, String> {
    spawn(
        &f.probe,
        &[
            "pong",
            &pong_native.display().to_string(),
            PING_KEY,
            PONG_KEY,
            if shm { "1" } else { "0" },
            mode,
        ],
        false,
    )
}

/// AimRT's keys of the bench's topics for `ExampleEventMsg`.
const PING_KEY: &str = "channel/%2Fbench%2Fping/pb%3Aaimrt.protocols.example.ExampleEventMsg";
const PONG_KEY: &str = "channel/%2Fbench%2Fpong/pb%3Aaimrt.protocols.example.ExampleEventMsg";

/// The figures of `aimrt_zenoh_probe ping` on `ping_native` in `mode`, against whatever
/// pong listens there.
fn probe_ping(
    f: &Files,
    ping_native: &Path,
    (size, shm): (usize, bool),
    mode: &str,
    (n, samples): (u64, usize),
) -> Result<Figures, String> {
    use std::io::BufRead as _;
    let shm = if shm { "1" } else { "0" };
    let mut child = spawn(
        &f.probe,
        &[
            "ping",
            &ping_native.display().to_string(),
            PING_KEY,
            PONG_KEY,
            &size.to_string(),
            &n.to_string(),
            &samples.to_string(),
            shm,
            mode,
        ],
        true,
    )?;
    let pid = child.0.id();
    let out = child
        .0
        .stdout
        .take()
        .ok_or("the raw ping's output is not piped")?;
    // Its threads are read when it says the throughput phase begins and ends.
    let (mut before, mut after, mut text) = (None, None, String::new());
    for line in std::io::BufReader::new(out).lines() {
        let line = line.map_err(|e| format!("cannot read the raw ping's output: {e}"))?;
        match line.as_str() {
            "measuring" => before = Some(sched::snapshot(Some(pid))),
            "measured" => after = Some(sched::snapshot(Some(pid))),
            _ => {
                text.push_str(&line);
                text.push('\n');
            }
        }
    }
    let _ = child.0.wait();
    let line = text
        .lines()
        .find(|l| l.starts_with('{'))
        .ok_or_else(|| format!("raw ping {size} B ({mode}) printed no result: {text}"))?;
    let v: serde_json::Value = serde_json::from_str(line).map_err(|e| e.to_string())?;
    let num = |k: &str| {
        v.get(k)
            .and_then(serde_json::Value::as_f64)
            .unwrap_or(f64::NAN)
    };
    let ping_side = match (before, after) {
        (Some(b), Some(a)) => sched::cost(&b, &a, pid.into(), num("delivered") as u64),
        _ => None,
    };
    Ok(Figures {
        msgs_per_s: num("msgs_per_s"),
        rtt_p50_us: num("rtt_p50_us"),
        rtt_p99_us: num("rtt_p99_us"),
        ping_side,
        stalls_per_k: per_thousand(num("stalls"), num("delivered")),
    })
}

/// Ours at `size` with shared memory `shm`, `n` messages and `samples` round trips: a
/// fresh echo side and a fresh runtime for this measurement alone, as the raw baseline's
/// processes are.
fn ours(
    f: &Files,
    dir: &Path,
    (size, shm): (usize, bool),
    (n, samples): (u64, usize),
    echo: Echo,
) -> Result<(Figures, u64), String> {
    let side = Ours::start(f, dir, shm, echo)?;
    let measured = side.measure(size, n, samples);
    let stopped = side.stop();
    let figures = measured?;
    stopped?;
    Ok(figures)
}

/// For each shared-memory setting (`shm`, else off, then on): rounds in which every size
/// (`sizes`, else [`SIZES`]) runs ours and its raw baseline back to back (which goes
/// first alternates), behind the quiet gate; round 0 warms up and is discarded. Every
/// measurement starts its own processes (ours, the relay's, the raw ones), so none runs
/// on a session, a connection or a heap that an earlier size shaped. `messages`: the
/// throughput phase's messages at every size, else [`counts`]'s.
pub(crate) fn run(
    scale: Scale,
    sizes: Option<&[usize]>,
    shm: Option<&[bool]>,
    messages: Option<u64>,
) -> Result<Vec<Case>, String> {
    let sizes = sizes.unwrap_or(&SIZES);
    let f = files()?;
    let dir = std::env::temp_dir().join(format!("aimrt-bench-zenoh-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    let measured = measure_all(
        &f,
        &dir,
        scale,
        sizes,
        shm.unwrap_or(&[false, true]),
        messages,
    );
    let _ = std::fs::remove_dir_all(&dir);
    measured
}

/// The rounds of [`run`] in `dir`.
fn measure_all(
    f: &Files,
    dir: &Path,
    scale: Scale,
    sizes: &[usize],
    shm: &[bool],
    messages: Option<u64>,
) -> Result<Vec<Case>, String> {
    let quick = scale.quick;
    // 9 rounds: since each pair has one connection (benches/zenoh_native.json5), a round
    // of every size with both settings takes about 20 s on 16 cores and 17 s on 2, and
    // the small messages' ratio spreads by a third between rounds on a lent machine
    // (0.69..1.06 at 1 KiB), so more rounds steady the median.
    let rounds = scale.rounds(3, 9);
    let mut all = Vec::new();
    for &shm in shm {
        let mut cases: Vec<Case> = sizes
            .iter()
            .map(|&size| Case {
                size,
                shm,
                sent: 0,
                delivered: 0,
                ours: Vec::new(),
                raw: Vec::new(),
                raw_bytes: Vec::new(),
                relay: Vec::new(),
                ping: Vec::new(),
            })
            .collect();
        for round in 0..=rounds {
            let load = quiet_gate(Duration::from_secs(if quick { 3 } else { 30 }));
            eprintln!("zenoh: shm {shm}, round {round} of {rounds} (0 warms up), foreign load {load:.2} core");
            for c in cases.iter_mut() {
                let counts = counts(c.size, quick, messages);
                let at = |e: String| format!("{} B, shm {shm}: {e}", c.size);
                let case = (c.size, shm);
                let ((o, delivered), b) = alternate(
                    round,
                    || ours(f, dir, case, counts, Echo::Relay),
                    || raw(f, dir, case, "typed", counts),
                )
                .map_err(at)?;
                let bytes = raw(f, dir, case, "bytes", counts).map_err(at)?;
                let relayed = Relay::start(f, dir, shm)
                    .and_then(|relay| relay.measure(f, case, counts))
                    .map_err(at)?;
                let (pinged, _) = ours(f, dir, case, counts, Echo::RawPong).map_err(at)?;
                if round > 0 {
                    c.ours.push(o);
                    c.raw.push(b);
                    c.raw_bytes.push(bytes);
                    c.relay.push(relayed);
                    c.ping.push(pinged);
                    c.sent += counts.0;
                    c.delivered += delivered;
                }
            }
        }
        all.extend(cases);
    }
    Ok(all)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The endpoints between `key: { endpoints: [` (or `key: {\n endpoints: [`) and `]`.
    fn endpoints(config: &str, key: &str) -> String {
        let at = config.find(&format!("{key}: {{")).expect(key);
        let rest = &config[at..];
        let open = rest.find("endpoints: [").expect("endpoints") + "endpoints: [".len();
        let close = rest[open..].find(']').expect("]");
        rest[open..open + close].to_owned()
    }

    #[test]
    fn a_wait_counts_as_a_stall_only_when_it_blocks_for_0_9_ms_or_more() {
        let echoes = Arc::new(Echoes::default());
        let mut stalls = 0;
        echoes.hit();
        // Reached already: no block, no stall.
        assert!(echoes.wait_counting(1, Duration::from_secs(1), &mut stalls));
        assert_eq!(stalls, 0);
        let late = echoes.clone();
        let hitter = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(5));
            late.hit();
        });
        assert!(echoes.wait_counting(2, Duration::from_secs(10), &mut stalls));
        hitter.join().unwrap();
        assert_eq!(stalls, 1);
        assert_eq!(per_thousand(3.0, 1500.0), 2.0);
        assert!(per_thousand(1.0, 0.0).is_nan());
        assert!(per_thousand(f64::NAN, 1500.0).is_nan());
    }

    #[test]
    fn the_pong_listens_and_the_ping_only_connects_to_it() {
        let dir = std::env::temp_dir().join(format!("aimrt-bench-natives-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (ping, pong) = natives(&dir, "t").unwrap();
        let (ping, pong) = (
            std::fs::read_to_string(ping).unwrap(),
            std::fs::read_to_string(pong).unwrap(),
        );
        let _ = std::fs::remove_dir_all(&dir);
        let listen = endpoints(&pong, "listen");
        assert!(listen.starts_with("\"tcp/127.0.0.1:"), "{listen}");
        assert_eq!(endpoints(&pong, "connect"), "");
        assert_eq!(endpoints(&ping, "listen"), "");
        assert_eq!(endpoints(&ping, "connect"), listen);
        assert!(!ping.contains("_ENDPOINTS") && !pong.contains("_ENDPOINTS"));
    }
}
