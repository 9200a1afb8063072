//! Helpers for the end-to-end tests: find the built `aimrt_main` and libraries, and run
//! `aimrt_main` in its own temporary working directory with a timeout.
#![forbid(unsafe_code)]

pub mod rpc_modules;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The cargo target directory of this build (e.g. `target/`).
pub fn target_root() -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    // target/<profile>/deps/<test-binary>
    exe.parent()
        .and_then(Path::parent)
        .and_then(Path::parent)
        .expect("test binary lives in target/<profile>/deps")
        .to_path_buf()
}

/// `target/debug` (the profile the tests were built with).
pub fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    exe.parent()
        .and_then(Path::parent)
        .expect("target/<profile>")
        .to_path_buf()
}

fn must_exist(path: PathBuf, how: &str) -> PathBuf {
    assert!(
        path.exists(),
        "{} is missing: run `{how}` first (the README's test command does)",
        path.display()
    );
    path
}

/// The text of one of AimRT's own example configs, copied unmodified into
/// `tests/aimrt-configs/`.
pub fn corpus(file: &str) -> String {
    let path = format!("{}/../aimrt-configs/{file}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// The path of test TLS file `name` in `tests/tls/` (made by its `make.sh`: a test CA,
/// server and client certificates; `""`: the folder with a trailing `/`).
pub fn tls_file(name: &str) -> String {
    format!("{}/../../tests/tls/{name}", env!("CARGO_MANIFEST_DIR"))
}

/// `config/<name>.yaml` of this repository, as is.
pub fn repo_config(name: &str) -> String {
    let path = format!("{}/../../config/{name}.yaml", env!("CARGO_MANIFEST_DIR"));
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// `config/<name>.yaml`, checked to be AimRT's `examples_cpp_<name>_cfg.yaml` with only
/// the pkg paths changed (`./libx.so` → `${AIMRT_LIB_DIR:-./target/debug}/libx.so`).
pub fn example_config(name: &str) -> String {
    aimrt_example(name, &format!("examples_cpp_{name}_cfg.yaml"))
}

/// `config/<name>.yaml`, checked to be AimRT's `aimrt_file` (in `tests/aimrt-configs/`)
/// with only the library paths changed.
pub fn aimrt_example(name: &str, aimrt_file: &str) -> String {
    let path = format!("config/{name}.yaml");
    let ours = repo_config(name);
    let aimrt =
        corpus(aimrt_file).replace("path: ./lib", "path: ${AIMRT_LIB_DIR:-./target/debug}/lib");
    let body: String = ours
        .lines()
        .skip_while(|l| !l.starts_with("# Copyright") && !l.starts_with("aimrt:"))
        .map(|l| format!("{l}\n"))
        .collect();
    assert_eq!(
        body.trim_end(),
        aimrt.trim_end(),
        "{path} differs from AimRT's config beyond the library paths"
    );
    ours
}

/// The built `aimrt_main`.
pub fn aimrt_main() -> PathBuf {
    must_exist(profile_dir().join("aimrt_main"), "cargo build --workspace")
}

/// A binary built by `cargo build --workspace` (e.g. an app-mode example), by name.
pub fn binary(name: &str) -> PathBuf {
    must_exist(profile_dir().join(name), "cargo build --workspace")
}

/// `tests/fixtures/aimrt-wire/<file>`: its `<label> <hex>` lines as bytes, by label.
pub fn wire_fixture(file: &str) -> std::collections::HashMap<String, Vec<u8>> {
    let path = format!(
        "{}/../fixtures/aimrt-wire/{file}",
        env!("CARGO_MANIFEST_DIR")
    );
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    aimrt_plugin_api::__private::hex_lines(&text)
        .into_iter()
        .collect()
}

/// The ports AimRT's net_plugin example configs use (udp 50040, tcp 50060, http 50080):
/// tests never keep them, see [`with_port`].
const AIMRT_EXAMPLE_PORTS: [u16; 3] = [50040, 50060, 50080];

/// `cfg` with every port of AimRT's net_plugin examples — in `listen_port:` and in
/// `127.0.0.1:<port>` addresses — replaced by `port` (a free one, or 0 for a listener).
pub fn with_port(cfg: &str, port: u16) -> String {
    let mut out = cfg.to_owned();
    for aimrt in AIMRT_EXAMPLE_PORTS {
        out = out
            .replace(
                &format!("listen_port: {aimrt}"),
                &format!("listen_port: {port}"),
            )
            .replace(&format!("127.0.0.1:{aimrt}"), &format!("127.0.0.1:{port}"));
    }
    for aimrt in AIMRT_EXAMPLE_PORTS {
        assert!(
            !out.contains(&format!(":{aimrt}")) || port == aimrt,
            "a fixed port {aimrt} is left in the config"
        );
    }
    out
}

/// AimRT's `examples_plugins_net_plugin_<name>_cfg.yaml` as `config/<name>.yaml` has it,
/// on `port` instead of AimRT's fixed one.
pub fn net_example(name: &str, port: u16) -> String {
    with_port(
        &aimrt_example(
            name,
            &format!("examples_plugins_net_plugin_{name}_cfg.yaml"),
        ),
        port,
    )
}

/// A loopback port that is free for TCP (or UDP) now: the process under test binds it
/// right away.
///
/// Ports come from 20000..32000, below Linux's ephemeral range (32768–60999): a port
/// handed out by `bind(0)` is one the kernel also gives to outgoing connections, so a
/// zenoh peer of a parallel test could take it as its local port before the process under
/// test binds it. Each test process starts at its own offset and walks on; a port that
/// does not bind now is skipped.
pub fn free_port(udp: bool) -> u16 {
    use std::sync::atomic::{AtomicU32, Ordering};
    const LOW: u32 = 20_000;
    const SPAN: u32 = 12_000;
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let base = std::process::id().wrapping_mul(7919) % SPAN;
    let free = |port: u16| {
        if udp {
            std::net::UdpSocket::bind(("127.0.0.1", port)).is_ok()
        } else {
            std::net::TcpListener::bind(("127.0.0.1", port)).is_ok()
        }
    };
    for _ in 0..SPAN {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let port = (LOW + (base + n) % SPAN) as u16;
        if free(port) {
            return port;
        }
    }
    panic!("no free loopback port in {LOW}..{}", LOW + SPAN)
}

/// A library built by `cargo build --workspace`, by file name.
pub fn lib(file: &str) -> PathBuf {
    must_exist(profile_dir().join(file), "cargo build --workspace")
}

/// The `panic = "abort"` fixture, built with the `panic-abort` profile.
pub fn panic_abort_fixture() -> PathBuf {
    must_exist(
        target_root()
            .join("panic-abort")
            .join("libfixture_panic_abort.so"),
        "cargo build -p aimrt-fixture-panic-abort --profile panic-abort",
    )
}

/// What a run of `aimrt_main` produced.
#[derive(Debug)]
pub struct Output {
    /// Exit code (`None` if killed by a signal).
    pub code: Option<i32>,
    /// Standard output.
    pub stdout: String,
    /// Standard error.
    pub stderr: String,
}

impl Output {
    /// Fails the test, showing `what`, both outputs, unless the process exited with `code`.
    #[track_caller]
    pub fn assert_exit(&self, code: i32, what: &str) {
        assert_eq!(
            self.code,
            Some(code),
            "{what}\nstdout:\n{}\nstderr:\n{}",
            self.stdout,
            self.stderr
        );
    }

    /// The `AimRT run with exception and exit.` line, if any.
    pub fn failure_line(&self) -> Option<&str> {
        self.stdout
            .lines()
            .find(|l| l.starts_with("AimRT run with exception and exit. "))
    }
}

/// A pair of zenoh peers on loopback for one test, as `config/zenoh_native_{a,b}.json5`
/// but on free ports: each listens on its own port and connects to the other's, multicast
/// scouting off, and a `limit_domain` of the test's own, so tests running in parallel never
/// hear each other. As in those files, zenoh's own shared memory for large payloads
/// (`transport_optimization`) is off: `shm_enabled` alone decides what crosses through
/// shared memory.
pub struct ZenohPeers {
    dir: tempfile::TempDir,
    /// The test's `limit_domain`.
    pub domain: String,
}

/// The link a [`ZenohPeers`] pair talks over.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ZenohLink {
    /// `tcp/127.0.0.1:<free port>`.
    Tcp,
    /// `unixsock-stream/<the test's folder>/<side>.sock`.
    Unix,
}

impl ZenohPeers {
    /// Native configs for `test` (a unique name: it becomes part of the domain) over TCP.
    pub fn new(test: &str) -> ZenohPeers {
        ZenohPeers::over(test, ZenohLink::Tcp)
    }

    /// Native configs for `test` over `link`.
    pub fn over(test: &str, link: ZenohLink) -> ZenohPeers {
        let dir = tempfile::tempdir().expect("tempdir");
        let ep = |side: &str| match link {
            ZenohLink::Tcp => format!("\"tcp/127.0.0.1:{}\"", free_port(false)),
            ZenohLink::Unix => format!(
                "\"unixsock-stream/{}\"",
                dir.path().join(format!("{side}.sock")).display()
            ),
        };
        let (pa, pb, pc) = (ep("a"), ep("b"), ep("c"));
        // A third side, "c", connects to both (e.g. a second client).
        for (side, listen, connect) in [
            ("a", &pa, pb.clone()),
            ("b", &pb, pa.clone()),
            ("c", &pc, format!("{pa}, {pb}")),
        ] {
            let text = format!(
                "{{ mode: \"peer\", listen: {{ endpoints: [{listen}] }}, connect: {{ endpoints: [{connect}] }}, scouting: {{ multicast: {{ enabled: false }} }}, transport: {{ shared_memory: {{ transport_optimization: {{ enabled: false }} }} }} }}\n"
            );
            std::fs::write(dir.path().join(format!("zenoh_{side}.json5")), text)
                .expect("write the native config");
        }
        ZenohPeers {
            dir,
            domain: format!("e2e/{test}/{}", std::process::id()),
        }
    }

    /// Native configs for `test` around a router: side `r` is the router (on a free port),
    /// and `a`, `b` and `c` are one client config (a client listens on nothing, so any
    /// number of processes can share it) that waits for the router however long it takes.
    pub fn routed(test: &str) -> ZenohPeers {
        let peers = ZenohPeers::new(test);
        let port = free_port(false);
        let tail = "scouting: { multicast: { enabled: false } }, transport: { shared_memory: { transport_optimization: { enabled: false } } } }\n";
        let router = format!(
            "{{ mode: \"router\", listen: {{ endpoints: [\"tcp/127.0.0.1:{port}\"] }}, {tail}"
        );
        let client = format!(
            "{{ mode: \"client\", connect: {{ endpoints: [\"tcp/127.0.0.1:{port}\"], timeout_ms: -1 }}, {tail}"
        );
        for (side, text) in [
            ("r", &router),
            ("a", &client),
            ("b", &client),
            ("c", &client),
        ] {
            std::fs::write(peers.native(side), text).expect("write the native config");
        }
        peers
    }

    /// The native config of side `a`, `b` or `c` (or `r`, the router of [`routed`]).
    ///
    /// [`routed`]: ZenohPeers::routed
    pub fn native(&self, side: &str) -> PathBuf {
        self.dir.path().join(format!("zenoh_{side}.json5"))
    }

    /// The environment the `config/zenoh_*.yaml` examples read for side `a`, `b` or `c`.
    pub fn env(&self, side: &str) -> Vec<(String, String)> {
        vec![
            (
                "AIMRT_ZENOH_NATIVE_CFG".into(),
                self.native(side).display().to_string(),
            ),
            ("AIMRT_ZENOH_LIMIT_DOMAIN".into(), self.domain.clone()),
        ]
    }
}

/// The `/dev/shm/*.zenoh` files (zenoh's shared-memory segments and pools) process `pid`
/// holds open; `None`: this process.
pub fn zenoh_shm_files(pid: Option<u32>) -> Vec<PathBuf> {
    let fds = pid.map_or_else(|| "/proc/self/fd".into(), |p| format!("/proc/{p}/fd"));
    std::fs::read_dir(&fds)
        .unwrap_or_else(|e| panic!("{fds}: {e}"))
        .filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
        .filter(|t| t.starts_with("/dev/shm") && t.extension().is_some_and(|x| x == "zenoh"))
        .collect()
}

/// `config/zenoh_<name>.yaml`, checked to be AimRT's
/// `examples_plugins_zenoh_plugin_<name>_cfg.yaml` with only the library paths, the
/// `native_cfg_path` and the `limit_domain` changed.
pub fn zenoh_example(name: &str) -> String {
    aimrt_zenoh_example(
        &format!("zenoh_{name}"),
        &format!("examples_plugins_zenoh_plugin_{name}_cfg.yaml"),
    )
}

/// `config/<name>.yaml`, checked to be AimRT's `aimrt_file` (in `tests/aimrt-configs/`)
/// with only the library paths and the zenoh plugin's `native_cfg_path` and `limit_domain`
/// changed (or added, with the `options:` line that holds them).
pub fn aimrt_zenoh_example(name: &str, aimrt_file: &str) -> String {
    let ours = repo_config(name);
    let aimrt =
        corpus(aimrt_file).replace("path: ./lib", "path: ${AIMRT_LIB_DIR:-./target/debug}/lib");
    let normal = |text: &str| -> String {
        text.lines()
            .skip_while(|l| !l.starts_with("# Copyright") && !l.starts_with("aimrt:"))
            .map(str::trim_end)
            .filter(|l| {
                let t = l.trim_start();
                !t.starts_with("native_cfg_path:")
                    && !t.starts_with("limit_domain:")
                    && t != "options:"
            })
            .map(|l| format!("{l}\n"))
            .collect()
    };
    assert_eq!(
        normal(&ours).trim_end(),
        normal(&aimrt).trim_end(),
        "config/{name}.yaml differs from {aimrt_file} beyond the library paths, native_cfg_path and limit_domain"
    );
    ours
}

/// `config` run for `secs` seconds (`--running_duration`), which must end with exit code 0
/// and no panic within a minute; its output.
pub fn run_for(config: &str, secs: u32) -> Output {
    let out = run_main(
        Some(config),
        &[
            "--cfg_file_path=./cfg.yaml",
            &format!("--running_duration={secs}"),
        ],
        Duration::from_secs(60),
    );
    out.assert_exit(0, config);
    assert!(!out.stdout.contains("panicked:"), "{}", out.stdout);
    out
}

/// `config` (if given), with `AIMRT_LIB_DIR` set to the build directory. Fails the test if
/// it does not exit within `timeout`.
pub fn run_main(config: Option<&str>, args: &[&str], timeout: Duration) -> Output {
    let dir = tempfile::tempdir().expect("tempdir");
    run_main_in(dir.path(), config, args, timeout)
}

/// [`run_main`] in `dir`, which the caller keeps to inspect the files the run wrote.
pub fn run_main_in(dir: &Path, config: Option<&str>, args: &[&str], timeout: Duration) -> Output {
    if let Some(text) = config {
        std::fs::write(dir.join("cfg.yaml"), text).expect("write cfg");
    }
    let args: Vec<std::ffi::OsString> = args.iter().map(Into::into).collect();
    run_main_args(dir, &args, timeout)
}

/// Runs `aimrt_main` in `dir` with `args` (any bytes, not only UTF-8), as [`run_main`].
pub fn run_main_args(dir: &Path, args: &[std::ffi::OsString], timeout: Duration) -> Output {
    let mut cmd = Command::new(aimrt_main());
    cmd.args(args);
    run_in(cmd, dir, timeout)
}

/// Runs `aimrt_main` in `dir` with `args`, as [`run_main`], from a `sh` that runs `setup`
/// first (e.g. `ulimit -f 128` to limit the size of the files it writes).
pub fn run_main_after(dir: &Path, setup: &str, args: &[&str], timeout: Duration) -> Output {
    let mut cmd = Command::new("sh");
    cmd.arg("-c")
        .arg(format!("{setup}; exec \"$0\" \"$@\""))
        .arg(aimrt_main())
        .args(args);
    run_in(cmd, dir, timeout)
}

/// Runs `config` for a second under `sh`'s `ulimit <flag> N` for each `N` of `limits` in
/// turn (e.g. `-n`, file descriptors; `-v`, KiB of address space), until a run exits 0,
/// and returns `(N, failure line)` of each run before it. Every such run must be a clear
/// refusal ([`assert_failure`], and no contained panic's `panicked:` line; the shutdown
/// counters' `panicked 0` is neither) or an out-of-memory abort no code can answer (Rust's
/// `memory allocation of N bytes failed`, glibc's `failed to register TLS destructor: out
/// of memory`, the dynamic loader's exit 127 with `error while loading shared libraries` or
/// `cannot allocate memory for thread-local data: ABORT`; left out of the result); a run
/// that does not end within 30 s fails the test, as does no run that exits 0.
pub fn refusals_until_it_runs(
    config: &str,
    flag: &str,
    limits: impl IntoIterator<Item = u64>,
) -> Vec<(u64, String)> {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("cfg.yaml"), config).expect("write cfg");
    let mut refusals = Vec::new();
    for limit in limits {
        let out = run_main_after(
            dir.path(),
            &format!("ulimit {flag} {limit}"),
            &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
            Duration::from_secs(30),
        );
        match out.code {
            Some(0) => return refusals,
            // Out of memory where no code can answer: Rust's allocation failure, or
            // glibc's when a thread's first thread-local cannot register its destructor.
            None if out.stderr.contains("memory allocation of")
                || out.stderr.contains(
                    "Fatal glibc error: failed to register TLS destructor: out of memory",
                ) =>
            {
                continue
            }
            // The dynamic loader's fatal exit: it could not map a library before any code
            // of ours ran, or a thread's first use of a loaded library's thread-locals
            // found no memory (glibc allocates those lazily and cannot report it).
            Some(127)
                if out.stderr.contains("error while loading shared libraries")
                    || out
                        .stderr
                        .contains("cannot allocate memory for thread-local data: ABORT") =>
            {
                continue
            }
            _ => {}
        }
        assert_failure(&out, &[]);
        assert!(
            !out.stdout.contains("panicked:"),
            "ulimit {flag} {limit}:\n{}",
            out.stdout
        );
        refusals.push((limit, out.failure_line().unwrap_or_default().to_owned()));
    }
    panic!("no run exited 0 under ulimit {flag}; refused: {refusals:#?}");
}

/// Runs `cmd` (`aimrt_main`, what execs it, or any program) in `dir` to its end, with the
/// libraries' directories in its environment; fails the test after `timeout`.
pub fn run_in(mut cmd: Command, dir: &Path, timeout: Duration) -> Output {
    let mut child = cmd
        .current_dir(dir)
        .env("AIMRT_LIB_DIR", profile_dir())
        .env("AIMRT_ABORT_FIXTURE_DIR", target_root().join("panic-abort"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("spawn {cmd:?}: {e}"));
    let mut out = child.stdout.take().expect("stdout");
    let mut err = child.stderr.take().expect("stderr");
    let t_out = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = out.read_to_string(&mut s);
        s
    });
    let t_err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = err.read_to_string(&mut s);
        s
    });
    let deadline = Instant::now() + timeout;
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "{:?} did not exit within {timeout:?}; stdout so far:\n{}",
                cmd.get_program(),
                t_out.join().unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Output {
        code: status.code(),
        stdout: t_out.join().unwrap_or_default(),
        stderr: t_err.join().unwrap_or_default(),
    }
}

/// Runs `aimrt_main` on `config` (as `./cfg.yaml` in a fresh directory) and sends
/// `signals[i].1` (`INT`, `TERM`) once a stdout line contains `signals[i].0`, in order.
/// Returns the exit code and the stdout lines; fails the test after `timeout`.
pub fn run_with_signals(
    config: &str,
    signals: &[(&str, &str)],
    timeout: Duration,
) -> (Option<i32>, Vec<String>) {
    let mut run = Running::start(config);
    let mut next = 0;
    let deadline = Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match run.lines.recv_timeout(left) {
            Ok((at, line)) => {
                if next < signals.len() && line.contains(signals[next].0) {
                    run.signal(signals[next].1);
                    next += 1;
                }
                run.seen.push((at, line));
            }
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                panic!("aimrt_main did not finish in time:\n{}", run.text())
            }
        }
    }
    let status = run.child.wait().expect("wait");
    assert_eq!(
        next,
        signals.len(),
        "not every trigger line was seen:\n{}",
        run.text()
    );
    let lines = std::mem::take(&mut run.seen)
        .into_iter()
        .map(|(_, l)| l)
        .collect();
    (status.code(), lines)
}

/// A failure: exit code 255, one line naming the cause (each of `expected` in it), never
/// raw panic text or a dependency's source path.
pub fn assert_failure(out: &Output, expected: &[&str]) {
    out.assert_exit(255, "expected AimRT's failure exit");
    let line = out
        .failure_line()
        .unwrap_or_else(|| panic!("no failure line in:\n{}", out.stdout));
    for e in expected {
        assert!(line.contains(e), "failure line lacks {e:?}:\n{line}");
    }
    // A dependency's source path (`/root/.cargo/registry/…/borrowed.rs:777`) means nothing
    // to the user.
    assert!(
        !line.contains(".cargo/registry"),
        "a registry path in:\n{line}"
    );
    for (name, text) in [("stderr", &out.stderr), ("stdout", &out.stdout)] {
        assert!(
            !text.contains("panicked at"),
            "raw panic text on {name}:\n{text}"
        );
    }
}

/// A running `aimrt_main` whose stdout lines arrive with the instant they were read.
/// Dropping it kills the process.
pub struct Running {
    child: std::process::Child,
    lines: std::sync::mpsc::Receiver<(Instant, String)>,
    /// Every line read so far, with its arrival instant.
    pub seen: Vec<(Instant, String)>,
    _dir: tempfile::TempDir,
}

impl Running {
    /// Starts `aimrt_main` on `config` (as `./cfg.yaml` in a fresh directory).
    pub fn start(config: &str) -> Running {
        Running::start_program(&aimrt_main(), &["--cfg_file_path=./cfg.yaml"], config)
    }

    /// Starts `program` with `args` in a fresh directory holding `config` as `./cfg.yaml`
    /// (e.g. an app-mode binary, whose argument is the config path).
    pub fn start_program(program: &Path, args: &[&str], config: &str) -> Running {
        Running::start_program_env(program, args, config, &[])
    }

    /// [`Running::start`] with extra environment variables (for a config's `${VAR}`s).
    pub fn start_env(config: &str, env: &[(String, String)]) -> Running {
        Running::start_program_env(&aimrt_main(), &["--cfg_file_path=./cfg.yaml"], config, env)
    }

    /// [`Running::start_program`] with extra environment variables.
    pub fn start_program_env(
        program: &Path,
        args: &[&str],
        config: &str,
        env: &[(String, String)],
    ) -> Running {
        use std::io::{BufRead, BufReader};
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("cfg.yaml"), config).expect("write cfg");
        let mut child = Command::new(program)
            .args(args)
            .current_dir(dir.path())
            .envs(env.iter().map(|(k, v)| (k, v)))
            .env("AIMRT_LIB_DIR", profile_dir())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("spawn {}: {e}", program.display()));
        let stdout = child.stdout.take().expect("stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send((Instant::now(), line)).is_err() {
                    break;
                }
            }
        });
        Running {
            child,
            lines: rx,
            seen: Vec::new(),
            _dir: dir,
        }
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The directory the process runs in (its `./cfg.yaml` and what it writes).
    pub fn dir(&self) -> &Path {
        self._dir.path()
    }

    /// Waits for the next line containing `needle`; fails the test after `timeout`.
    pub fn wait_for(&mut self, needle: &str, timeout: Duration) -> (Instant, String) {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok((at, line)) => {
                    self.seen.push((at, line.clone()));
                    if line.contains(needle) {
                        return (at, line);
                    }
                }
                Err(_) => panic!(
                    "no line with '{needle}' within {timeout:?}:\n{}",
                    self.text()
                ),
            }
        }
    }

    /// Waits for net_plugin's "http server listening on <ip:port>" line and returns the
    /// address; fails the test after `timeout`.
    pub fn http_address(&mut self, timeout: Duration) -> String {
        let (_, line) = self.wait_for("http server listening on ", timeout);
        line.split("listening on ")
            .nth(1)
            .and_then(|rest| rest.split(';').next())
            .unwrap_or_else(|| panic!("no address in {line}"))
            .to_owned()
    }

    /// Reads what arrives during `d`, returning the lines that contain `needle`.
    pub fn collect_for(&mut self, d: Duration, needle: &str) -> Vec<(Instant, String)> {
        let deadline = Instant::now() + d;
        let mut out = Vec::new();
        while let Ok((at, line)) = self
            .lines
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
        {
            self.seen.push((at, line.clone()));
            if line.contains(needle) {
                out.push((at, line));
            }
        }
        out
    }

    /// Everything read so far.
    pub fn text(&self) -> String {
        self.seen
            .iter()
            .map(|(_, l)| l.as_str())
            .collect::<Vec<_>>()
            .join("\n")
    }

    /// Sends signal `name` (`INT`, `TERM`) to the process.
    pub fn signal(&self, name: &str) {
        let sent = Command::new("kill")
            .args([&format!("-{name}"), &self.child.id().to_string()])
            .status()
            .expect("run kill")
            .success();
        assert!(sent, "kill -{name} failed");
    }

    /// The exit code once the process has exited (`Some(None)` when a signal killed it),
    /// `None` while it runs.
    pub fn exit_code(&mut self) -> Option<Option<i32>> {
        self.child.try_wait().expect("wait").map(|s| s.code())
    }

    /// A benchmark publisher's whole output: waits (within `timeout`) for its `Bench
    /// completed.`, then stops it with SIGINT; it must exit 0.
    pub fn bench_output(mut self, timeout: Duration) -> String {
        self.wait_for("Bench completed.", timeout);
        assert_eq!(self.interrupt(timeout), Some(0), "{}", self.text());
        self.text()
    }

    /// Sends SIGINT and waits for the exit code; fails the test after `timeout`.
    pub fn interrupt(&mut self, timeout: Duration) -> Option<i32> {
        self.signal("INT");
        self.wait_exit(timeout)
    }

    /// Waits for the process to exit and returns its exit code, having read the rest of
    /// its output; fails the test after `timeout`.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<i32> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                self.collect_for(Duration::from_millis(100), "");
                return status.code();
            }
            assert!(
                Instant::now() < deadline,
                "aimrt_main did not exit within {timeout:?}:\n{}",
                self.text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 request over a fresh connection (`Connection: close`): `(status, body)`.
/// `headers` are sent as given; `Content-Length` is added. Fails the test after 10 s.
pub fn http(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> (u16, String) {
    use std::io::Write;
    let mut stream = std::net::TcpStream::connect(addr).expect("connect");
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .expect("timeout");
    let mut request = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        request.push_str(&format!("{k}: {v}\r\n"));
    }
    request.push_str(&format!("Content-Length: {}\r\n\r\n", body.len()));
    stream.write_all(request.as_bytes()).expect("send head");
    // The server may answer (413) and close before the whole body is sent.
    let _ = stream.write_all(body);
    let mut response = Vec::new();
    if let Err(e) = stream.read_to_end(&mut response) {
        assert!(!response.is_empty(), "no response to {method} {path}: {e}");
    }
    let text = String::from_utf8_lossy(&response).into_owned();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP response: {text:?}"));
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default();
    (status, body)
}

/// A channel benchmark config (AimRT's `BenchmarkPublisherModule` plans) with every
/// plan's `msg_count` divided by `by`, so that a test runs all of AimRT's plans in about
/// ten seconds (each plan still waits 3 s around its messages).
pub fn shorter_bench_plans(cfg: &str, by: u32) -> String {
    let out: String = cfg
        .lines()
        .map(|l| match l.trim_start().strip_prefix("msg_count: ") {
            Some(n) => {
                let n: u32 = n.trim().parse().expect("msg_count is a number");
                let indent = &l[..l.len() - l.trim_start().len()];
                format!("{indent}msg_count: {}\n", (n / by).max(1))
            }
            None => format!("{l}\n"),
        })
        .collect();
    assert_ne!(out, format!("{cfg}\n"), "no msg_count in the config");
    out
}

/// A benchmark publisher's config with its `bench_plans` (the last section of AimRT's
/// configs) replaced by one plan: `count` messages of `size` bytes on one topic, at
/// 1 000 a second.
pub fn one_bench_plan(cfg: &str, size: usize, count: u32) -> String {
    let plans = cfg.find("  bench_plans:").expect("bench_plans");
    format!(
        "{}  bench_plans:\n    - perf_mode: multi-topic\n      channel_frq: 1000\n      msg_size: {size}\n      topic_number: 1\n      msg_count: {count}\n",
        &cfg[..plans]
    )
}

/// Waits for the `BenchmarkSubscriberModule` reports of plans `0..plans` in `sub`'s
/// output and checks that each plan arrived whole: received = sent, no loss, nothing of
/// the wrong size, outside the plan, twice or before it was sent. Fails the test after
/// `timeout` or on the first plan that lost anything.
pub fn assert_bench_plans_arrive_whole(sub: &mut Running, plans: u32, timeout: Duration) {
    let deadline = Instant::now() + timeout;
    for plan in 0..plans {
        let (_, head) = sub.wait_for(
            &format!("Benchmark plan {plan} completed, report:"),
            deadline.saturating_duration_since(Instant::now()),
        );
        assert!(head.contains("[BenchmarkSubscriberModule]"), "{head}");
        // The report's lines follow the head line, up to its blank last line.
        let mut report = std::collections::BTreeMap::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let (_, line) = sub.wait_for("", left);
            let Some((key, value)) = line.split_once(": ") else {
                break;
            };
            report.insert(key.trim().to_owned(), value.trim().to_owned());
        }
        let get = |k: &str| {
            report
                .get(k)
                .unwrap_or_else(|| panic!("plan {plan}: no '{k}' in the report {report:?}"))
                .as_str()
        };
        let sent: u64 = get("send count").parse().expect("send count");
        assert!(sent > 0, "plan {plan}: {report:?}");
        assert_eq!(
            get("recv count"),
            get("send count"),
            "plan {plan}: {report:?}"
        );
        assert_eq!(get("loss rate"), "0 %", "plan {plan}: {report:?}");
        for k in [
            "wrong size",
            "seq outside the plan",
            "received twice",
            "received before sent",
        ] {
            assert_eq!(get(k), "0", "plan {plan}, {k}: {report:?}");
        }
        for k in ["min latency", "p99 latency", "max latency"] {
            let us: f64 = get(k)
                .strip_suffix(" us")
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("plan {plan}, {k}: {report:?}"));
            assert!(us > 0.0, "plan {plan}, {k}: {report:?}");
        }
    }
}

/// AimRT's net_plugin channel example pair over `transport` (`http`, `tcp` or `udp`),
/// `config/pb_chn_<transport>_{sub,pub}.yaml` on a free port: the subscriber starts
/// first, then logs the publisher's first message with its context.
pub fn net_example_pair_exchanges_messages(transport: &str) {
    let wait = Duration::from_secs(30);
    let port = free_port(transport == "udp");
    let mut sub = Running::start(&net_example(&format!("pb_chn_{transport}_sub"), port));
    sub.wait_for("Module manager start completed.", wait);
    let mut publisher = Running::start(&net_example(&format!("pb_chn_{transport}_pub"), port));
    let (_, line) = sub.wait_for("Receive new pb event", wait);
    assert!(
        line.ends_with(r#"data: {"msg":"count: 1","num":1}"#),
        "{line}"
    );
    for kv in [
        r#"{"aimrt-serialization_type":"pb"}"#.to_owned(),
        r#"{"aimrt-pub_seq":"1"}"#.to_owned(),
        format!(r#"{{"aimrt-backend":"{transport}"}}"#),
    ] {
        assert!(line.contains(&kv), "{kv} not in {line}");
    }
    assert_eq!(publisher.interrupt(wait), Some(0), "{transport} publisher");
    assert_eq!(sub.interrupt(wait), Some(0), "{transport} subscriber");
}

/// AimRT's net_plugin channel benchmark pair over `transport` (`http`, `tcp` or `udp`),
/// `config/pb_chn_<transport>_benchmark_{sub,pub}.yaml` on a free port with the plans cut
/// short (and, over http, paced at a quarter of the rate): the subscriber starts first,
/// then every plan must arrive whole.
pub fn net_bench_pair_loses_nothing(transport: &str) {
    let wait = Duration::from_secs(60);
    let port = free_port(transport == "udp");
    let mut sub = Running::start(&net_example(
        &format!("pb_chn_{transport}_benchmark_sub"),
        port,
    ));
    sub.wait_for("Module manager start completed.", wait);
    let mut cfg = shorter_bench_plans(
        &net_example(&format!("pb_chn_{transport}_benchmark_pub"), port),
        10,
    );
    if transport == "http" {
        // A debug build's HTTP server spends about 200 µs of CPU a request; with other
        // tests on the same two cores it cannot take AimRT's 4 × 1 000 requests a second,
        // and the publisher refuses what exceeds its 1 024 requests in flight (reported
        // and counted, not lost silently). A quarter of the rate is what this test can
        // hold to "every message arrives".
        assert!(cfg.contains("channel_frq: 1000"), "{cfg}");
        cfg = cfg.replace("channel_frq: 1000", "channel_frq: 250");
    }
    let mut publisher = Running::start(&cfg);
    assert_bench_plans_arrive_whole(&mut sub, 3, wait);
    publisher.wait_for("Bench completed.", wait);
    assert_eq!(publisher.interrupt(wait), Some(0), "{transport} publisher");
    assert_eq!(sub.interrupt(wait), Some(0), "{transport} subscriber");
}

/// The error rate of each of the first `plans` reports (`Benchmark plan <i> completed,
/// report:`) of AimRT's RPC benchmark client, read after `Bench completed.`; fails the
/// test after `timeout` for any of them.
pub fn rpc_bench_error_rates(client: &mut Running, plans: usize, timeout: Duration) -> Vec<String> {
    let mut rates = Vec::new();
    for i in 0..plans {
        client.wait_for(&format!("Benchmark plan {i} completed, report:"), timeout);
        let (_, line) = client.wait_for("error rate: ", timeout);
        rates.push(line.trim_start_matches("error rate: ").to_owned());
    }
    client.wait_for("Bench completed.", timeout);
    rates
}

/// The drops for `reason` (`lost after publish`) that the shutdown stats lines of the
/// topics in `text` count, summed over the topics (0 where a line has none).
pub fn topics_dropped(text: &str, reason: &str) -> u64 {
    let key = format!("{reason}: ");
    text.lines()
        .filter(|l| l.contains("Channel topic '") && l.contains("': published "))
        .filter_map(|l| {
            let at = l.find(&key)? + key.len();
            l[at..]
                .split(|c: char| !c.is_ascii_digit())
                .next()?
                .parse::<u64>()
                .ok()
        })
        .sum()
}

/// What reached the subscribers of `test_topic` in `text`: delivered, or dropped there and
/// counted, from the topic's last stats line.
pub fn test_topic_received(text: &str) -> u64 {
    let line = text
        .lines()
        .rev()
        .find(|l| l.contains("Channel topic 'test_topic': published"))
        .unwrap_or_else(|| panic!("no stats of test_topic in:\n{text}"));
    number_after(line, "delivered") + number_after(line, "dropped")
}

/// The last `net_plugin <backend>: S messages sent, R refused, L lost after publish, …`
/// summary in `text`: `(S, R, L)`.
pub fn net_summary(text: &str, backend: &str) -> (u64, u64, u64) {
    let head = format!("net_plugin {backend}: ");
    let line = text
        .lines()
        .rev()
        .find(|l| l.contains(&head) && l.contains(" lost after publish,"))
        .unwrap_or_else(|| panic!("no {head}summary in:\n{text}"));
    let mut numbers = line
        .split(&head)
        .nth(1)
        .unwrap_or_default()
        .split(", ")
        .map(|part| part.split(' ').next().and_then(|n| n.parse().ok()));
    let mut next = || {
        numbers
            .next()
            .flatten()
            .unwrap_or_else(|| panic!("not a summary: {line}"))
    };
    (next(), next(), next())
}

/// Every `aimrt-pub_seq` that AimRT's example subscriber logged in `text`, in order.
pub fn received_seqs(text: &str) -> Vec<u64> {
    text.lines()
        .filter(|l| l.contains("Receive new pb event"))
        .filter_map(|l| {
            let rest = l.split_once(r#"{"aimrt-pub_seq":""#)?.1;
            rest.split('"').next()?.parse().ok()
        })
        .collect()
}

/// AimRT's example publisher config `cfg` publishing 64 KiB messages at `hz`: at 200 Hz,
/// 13 MB a second, far more than the sockets to a subscriber hold while it stands still.
pub fn fast_big_publisher(cfg: &str, hz: u32) -> String {
    let out = cfg.replace(
        "  channel_frq: 0.5",
        &format!("  channel_frq: {hz}\n  msg_size: 65536"),
    );
    assert_ne!(out, cfg, "not AimRT's example publisher config:\n{cfg}");
    out
}

/// Stops the process of `sub` (SIGSTOP) under `publisher` (AimRT's example pair, the
/// publisher made by [`fast_big_publisher`], both started) until the publisher has
/// published `n` more messages, then lets it go on.
///
/// Asserts that the publisher gets there without standing still: its log has no gap of
/// 2.5 s between two loops (zenoh's `block` congestion control holds a publisher up for
/// 5 s before it gives the link up), and that the subscriber, once going on, hears a message
/// published after that. Both are then interrupted (exit 0), and what the subscriber got
/// must be none twice, and in order where the transport keeps it (`ordered`;
/// net_plugin's `http` sends concurrent requests, as AimRT's).
pub fn stop_a_subscriber_under_its_publisher(
    sub: &mut Running,
    publisher: &mut Running,
    n: u64,
    ordered: bool,
) {
    let wait = Duration::from_secs(30);
    let loop_count = |line: &str| -> u64 {
        line.split("loop count : ")
            .nth(1)
            .and_then(|rest| rest.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no loop count in {line}"))
    };
    sub.wait_for("Receive new pb event", wait);
    sub.signal("STOP");
    let (_, line) = publisher.wait_for("loop count : ", wait);
    let target = loop_count(&line) + n;
    let from = publisher.seen.len();
    publisher.wait_for(&format!("loop count : {target} "), wait);
    sub.signal("CONT");
    let times: Vec<f64> = publisher.seen[from..]
        .iter()
        .filter(|(_, l)| l.contains("loop count : "))
        .map(|(_, l)| log_time_of_day(l))
        .collect();
    let longest = times
        .windows(2)
        .map(|w| (w[1] - w[0]).rem_euclid(86_400.0))
        .fold(0.0, f64::max);
    assert!(
        longest < 2.5,
        "the publisher stood still for {longest:.3} s while its subscriber did"
    );
    let (_, last) = publisher.wait_for("loop count : ", wait);
    let after = loop_count(&last);
    let deadline = Instant::now() + wait;
    while received_seqs(&sub.text()).iter().all(|s| *s <= after) {
        let left = deadline.saturating_duration_since(Instant::now());
        sub.wait_for("Receive new pb event", left.max(Duration::from_millis(1)));
    }
    assert_eq!(publisher.interrupt(wait), Some(0), "publisher");
    // What the publisher wrote before it stopped is read before the subscriber stops.
    sub.collect_for(Duration::from_secs(1), "");
    assert_eq!(sub.interrupt(wait), Some(0), "subscriber");
    let mut seen = received_seqs(&sub.text());
    if ordered {
        assert!(
            seen.windows(2).all(|w| w[0] < w[1]),
            "out of order or twice: {seen:?}"
        );
    }
    seen.sort_unstable();
    assert!(seen.windows(2).all(|w| w[0] < w[1]), "twice: {seen:?}");
}

/// The time of day, in seconds, of a log line (`[2026-11-28 08:37:55.123456][Info]…`).
pub fn log_time_of_day(line: &str) -> f64 {
    line.strip_prefix('[')
        .and_then(|rest| rest.split(']').next())
        .and_then(|stamp| stamp.split(' ').nth(1))
        .and_then(|time| {
            let mut parts = time.split(':');
            let (h, m, s) = (parts.next()?, parts.next()?, parts.next()?);
            Some(
                h.parse::<f64>().ok()? * 3600.0
                    + m.parse::<f64>().ok()? * 60.0
                    + s.parse::<f64>().ok()?,
            )
        })
        .unwrap_or_else(|| panic!("no time of day in {line}"))
}

/// net_plugin's publisher (summary `net_plugin <backend>: …` in `pub_text`) accounted for
/// every message it published on `test_topic` while its subscriber (`sub_text`) stood
/// still: each was sent, refused (its queue for the subscriber full) or lost after publish,
/// some were not sent, the topic's stats drop exactly those, and the subscriber got every
/// one sent (and, over `http`, perhaps some counted lost: a request whose answer came after
/// its 5 s deadline).
pub fn assert_net_accounts_for_every_message(pub_text: &str, sub_text: &str, backend: &str) {
    let stats = pub_text
        .lines()
        .rev()
        .find(|l| l.contains("Channel topic 'test_topic': published "))
        .unwrap_or_else(|| panic!("no stats of test_topic in:\n{pub_text}"));
    let (published, dropped) = (
        number_after(stats, ": published "),
        number_after(stats, ", dropped "),
    );
    let (sent, refused, lost) = net_summary(pub_text, backend);
    assert_eq!(published, sent + refused + lost, "{stats}\n{pub_text}");
    assert!(
        refused + lost > 0,
        "the subscriber stood still, yet every message was sent: {stats}"
    );
    assert_eq!(dropped, refused + lost, "{stats}");
    let received = received_seqs(sub_text).len() as u64;
    assert!(
        sent <= received && received <= sent + lost,
        "sent {sent} ({lost} lost after publish), the subscriber got {received}"
    );
}

/// `line`, the example subscriber's first `Receive new pb event` line from a publisher
/// that set `context_meta: {my-key: my-val}`, carries that pair, the serialization type,
/// the first sequence number and the name of `backend` across, and the first message.
pub fn assert_first_event_carries_context(line: &str, backend: &str) {
    let came_by = format!(r#"{{"aimrt-backend":"{backend}"}}"#);
    for kv in [
        came_by.as_str(),
        r#"{"my-key":"my-val"}"#,
        r#"{"aimrt-serialization_type":"pb"}"#,
        r#"{"aimrt-pub_seq":"1"}"#,
    ] {
        assert!(line.contains(kv), "{kv} not in {line}");
    }
    assert!(
        line.ends_with(r#"data: {"msg":"count: 1","num":1}"#),
        "{line}"
    );
}

/// The line AimRT's RPC example client logs for its first call answered by the example
/// server (`echo` of `hello world foo, count 1`).
pub const RPC_EXAMPLE_RSP: &str = r#"Client get rpc ret, status: suc, code 0, msg: OK, rsp: {"code":"0","msg":"echo hello world foo, count 1"}"#;

/// Runs the example client config `cfg` (`NormalRpcCoClientModule` calling every 2 s)
/// once per call style — Co, Sync, Async, Future — side by side for 3 s, and checks that
/// each got `rsp` for its one call and counted no error.
pub fn every_client_style_calls(cfg: &str, rsp: &str) {
    let styles = ["Co", "Sync", "Async", "Future"];
    let outs: Vec<Output> = std::thread::scope(|s| {
        let handles: Vec<_> = styles
            .iter()
            .map(|style| {
                let cfg = cfg.replace(
                    "NormalRpcCoClientModule",
                    &format!("NormalRpc{style}ClientModule"),
                );
                s.spawn(move || run_for(&cfg, 3))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for (style, out) in styles.iter().zip(&outs) {
        assert!(out.stdout.contains(rsp), "{style}:\n{}", out.stdout);
        assert!(
            out.stdout
                .contains("Module RPC: 1 calls, 0 answered with an error status"),
            "{style}:\n{}",
            out.stdout
        );
    }
}

/// Stops the process of `server` (SIGSTOP) under `client`: AimRT's example RPC pair, the
/// Co client calling in turn with a 3 s timeout, both started and a call answered. The
/// call in flight must end with 2 (`Timeout`) within 5 s of the stop, and once the server
/// goes on, the next be answered OK. Both are then interrupted (exit 0). Returns the
/// client's text.
pub fn stop_a_server_under_its_client(server: &mut Running, client: &mut Running) -> String {
    let wait = Duration::from_secs(30);
    server.signal("STOP");
    let stopped = Instant::now();
    let (at, line) = client.wait_for("Client get rpc error ret", wait);
    server.signal("CONT");
    assert!(line.contains("code 2, msg: Timeout"), "{line}");
    assert!(
        at.duration_since(stopped) < Duration::from_secs(5),
        "answered {:?} after the server stopped; the call's timeout is 3 s",
        at.duration_since(stopped)
    );
    let (_, line) = client.wait_for("Client get rpc", wait);
    assert!(line.contains("code 0, msg: OK"), "{line}");
    assert_eq!(client.interrupt(wait), Some(0), "client");
    assert_eq!(server.interrupt(wait), Some(0), "server");
    client.text()
}

/// The number after `prefix` (and any spaces) in the last line of `text` that has it:
/// `number_after(line, "published")` of `… published 218, …` is 218.
pub fn number_after(text: &str, prefix: &str) -> u64 {
    let line = text
        .lines()
        .rev()
        .find(|l| l.contains(prefix))
        .unwrap_or_else(|| panic!("no line with '{prefix}' in:\n{text}"));
    line.split_once(prefix)
        .and_then(|(_, rest)| {
            rest.trim_start()
                .split(|c: char| !c.is_ascii_digit())
                .next()
        })
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no number after '{prefix}' in {line}"))
}

/// Runs a runtime in this process for `running`, configured with `aimrt_section` (YAML
/// keys under `aimrt:`, indented two spaces) and INFO logging to a file; `setup` adds its
/// plugins and modules. Returns what was logged.
pub fn run_in_process(
    aimrt_section: &str,
    running: Duration,
    setup: impl FnOnce(&mut aimrt_runtime::Runtime),
) -> String {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let cfg = format!(
        "aimrt:\n  log:\n    core_lvl: INFO\n    backends:\n      - type: rotate_file\n        options:\n          path: {}\n          filename: run.log\n{aimrt_section}",
        dir.path().display()
    );
    let path = dir.path().join("cfg.yaml");
    std::fs::write(&path, cfg).expect("the config written");
    let mut runtime = aimrt_runtime::Runtime::new(aimrt_runtime::RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(running),
        ..Default::default()
    });
    setup(&mut runtime);
    runtime.run().expect("the runtime ran");
    std::fs::read_to_string(dir.path().join("run.log")).expect("the log")
}

/// A TCP proxy on a free loopback port to `upstream` that can cut its connections the way
/// a network that stops carrying does: [`cut`](Self::cut) leaves every open connection
/// open and silent for good (what either side sends is read and dropped; nothing is
/// closed), and connections made while cut are the same; after [`heal`](Self::heal), new
/// connections carry again. So a client that keeps writing into a connection it made
/// before the cut never hears back, and one that opens a new connection does.
pub struct BlackHoleProxy {
    addr: std::net::SocketAddr,
    cut: std::sync::Arc<std::sync::atomic::AtomicBool>,
    epoch: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl BlackHoleProxy {
    /// Listens on `127.0.0.1:0` and forwards to `upstream` (`host:port`).
    pub fn start(upstream: &str) -> BlackHoleProxy {
        use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
        use std::sync::Arc;
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port");
        let addr = listener.local_addr().expect("its address");
        let cut = Arc::new(AtomicBool::new(false));
        let epoch = Arc::new(AtomicU64::new(0));
        let upstream = upstream.to_owned();
        let (c, e) = (cut.clone(), epoch.clone());
        std::thread::spawn(move || {
            for client in listener.incoming().flatten() {
                let at = e.load(Ordering::SeqCst);
                let server = if c.load(Ordering::SeqCst) {
                    None
                } else {
                    std::net::TcpStream::connect(&upstream).ok()
                };
                let Some(server) = server else {
                    std::thread::spawn(move || swallow(client));
                    continue;
                };
                for (from, to) in [
                    (client.try_clone(), server.try_clone()),
                    (server.try_clone(), client.try_clone()),
                ] {
                    let (Ok(from), Ok(to)) = (from, to) else {
                        continue;
                    };
                    let e = e.clone();
                    std::thread::spawn(move || pipe(from, to, &e, at));
                }
            }
        });

        /// Copies `from` to `to` while the proxy's epoch is still `at`; after, drops.
        fn pipe(
            mut from: std::net::TcpStream,
            mut to: std::net::TcpStream,
            epoch: &AtomicU64,
            at: u64,
        ) {
            use std::io::Write;
            let mut buf = vec![0u8; 64 * 1024];
            loop {
                let n = match from.read(&mut buf) {
                    Ok(0) | Err(_) => {
                        let _ = to.shutdown(std::net::Shutdown::Write);
                        return;
                    }
                    Ok(n) => n,
                };
                if epoch.load(Ordering::SeqCst) != at {
                    // Cut: keep both sockets open and silent for good.
                    let _keep = to;
                    return swallow(from);
                }
                if to.write_all(&buf[..n]).is_err() {
                    return;
                }
            }
        }

        /// Reads and drops what `s` brings until its peer closes it.
        fn swallow(mut s: std::net::TcpStream) {
            let mut buf = vec![0u8; 64 * 1024];
            while matches!(s.read(&mut buf), Ok(n) if n > 0) {}
        }

        BlackHoleProxy { addr, cut, epoch }
    }

    /// Where clients connect.
    pub fn addr(&self) -> std::net::SocketAddr {
        self.addr
    }

    /// Every open connection goes silent for good, and new ones are silent until `heal`.
    pub fn cut(&self) {
        use std::sync::atomic::Ordering;
        self.cut.store(true, Ordering::SeqCst);
        self.epoch.fetch_add(1, Ordering::SeqCst);
    }

    /// New connections carry again (those cut stay silent).
    pub fn heal(&self) {
        self.cut.store(false, std::sync::atomic::Ordering::SeqCst);
    }
}
