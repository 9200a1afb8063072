//! Log backends from a plugin (ABI 1.10, entries with their parts 1.11):
//! `config/log_backend_plugin.yaml` with `libexample_log_backend_plugin.so` — the lines
//! its `module_filter` admits reach the plugin's backend in its `pattern`, and with
//! `format: json` as their parts; the errors of an unknown type and of bad options name
//! their place and the types there are; plugin libraries of ABI 1.9 and 1.10 run on this
//! host.

use std::net::UdpSocket;
use std::time::Duration;

use aimrt_e2e::{assert_failure, repo_config, run_main, run_main_in, Output};

const LIMIT: Duration = Duration::from_secs(60);

/// The example sending to `address` (its `address:` line's value replaced).
fn example(address: &str) -> String {
    let cfg = repo_config("log_backend_plugin");
    let mut replaced = 0;
    let lines: Vec<String> = cfg
        .lines()
        .map(|l| match l.split_once("address: ") {
            Some((indent, _)) if indent.trim().is_empty() => {
                replaced += 1;
                format!("{indent}address: {address}")
            }
            _ => l.to_owned(),
        })
        .collect();
    assert_eq!(replaced, 1, "{cfg}");
    lines.join("\n") + "\n"
}

/// A loopback address of this test's own (bound to port 0, kept while the test runs).
fn own_address() -> (UdpSocket, String) {
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let address = socket.local_addr().unwrap().to_string();
    (socket, address)
}

/// Every datagram that arrives on `socket` until it is quiet for 300 ms.
fn received(socket: &UdpSocket) -> Vec<String> {
    socket
        .set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    let mut buf = vec![0u8; 70_000];
    let mut out = Vec::new();
    while let Ok(n) = socket.recv(&mut buf) {
        out.push(String::from_utf8_lossy(&buf[..n]).into_owned());
    }
    out
}

#[test]
fn the_plugins_backend_gets_the_lines_its_filter_admits_in_its_pattern() {
    let (socket, address) = own_address();
    let out = run_main(
        Some(&example(&address)),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=2"],
        LIMIT,
    );
    out.assert_exit(0, "the log backend example");
    let lines = received(&socket);
    // LoggerModule logs each level once a second from start: at least one round.
    for expected in [
        "[Info][LoggerModule] Init succeeded.",
        "[Trace][LoggerModule] Test trace log, loop count: 1",
        "[Error][LoggerModule] Test error log, loop count: 1",
    ] {
        assert!(
            lines.iter().any(|l| l == expected),
            "no {expected:?} in {lines:?}"
        );
    }
    // Only LoggerModule's lines: the runtime's (`core`) stay on the console.
    assert!(
        lines.iter().all(|l| l.contains("][LoggerModule] ")),
        "{lines:?}"
    );
    assert!(out.stdout.contains("][core]["), "{}", out.stdout);
    // The console got the module's lines too, in the default pattern.
    assert!(
        out.stdout.contains("[LoggerModule][")
            && out.stdout.contains("Test error log, loop count: 1"),
        "{}",
        out.stdout
    );
}

/// With `format: json` each datagram is one line's parts, as the runtime handed them to
/// the backend: the logger, level, call site, thread and time, and the message alone.
#[test]
fn the_plugins_backend_gets_each_lines_parts() {
    let (socket, address) = own_address();
    let cfg = example(&address).replace(
        "          pattern: \"[%l][%n] %v\"\n",
        "          pattern: \"[%l][%n] %v\"\n          format: json\n",
    );
    assert!(cfg.contains("format: json"), "{cfg}");
    let before = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64;
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=2"],
        LIMIT,
    );
    out.assert_exit(0, "the log backend example with format: json");
    let after = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64;
    let entries: Vec<serde_json::Value> = received(&socket)
        .iter()
        .map(|d| serde_json::from_str(d).unwrap_or_else(|e| panic!("{d:?} is not JSON: {e}")))
        .collect();
    let error = entries
        .iter()
        .find(|e| e["message"] == "Test error log, loop count: 1")
        .unwrap_or_else(|| panic!("no error line of loop 1 in {entries:?}"));
    assert_eq!(error["level"], "Error", "{error}");
    assert_eq!(error["module"], "LoggerModule", "{error}");
    let file = error["file"].as_str().unwrap();
    assert!(file.ends_with(".rs") && file.contains("logger"), "{error}");
    assert!(error["line"].as_u64().unwrap() > 0, "{error}");
    assert!(error["thread_id"].as_i64().unwrap() > 0, "{error}");
    let time = error["time_ns"].as_u64().unwrap();
    assert!(
        (before..=after).contains(&time),
        "{before} ≤ {time} ≤ {after}"
    );
    // Every entry is LoggerModule's, and none is the formatted line.
    assert!(
        entries
            .iter()
            .all(|e| e["module"] == "LoggerModule"
                && !e["message"].as_str().unwrap().starts_with('[')),
        "{entries:?}"
    );
}

/// `--dump_cfg_file` writes a plugin's backend options as its factory read them (`format`
/// filled in), with the keys the runtime reads, and the dump runs to the same dump.
#[test]
fn the_dump_has_the_plugins_backend_options_as_read() {
    let (_socket, address) = own_address();
    let dir = tempfile::tempdir().unwrap();
    let args = [
        "--cfg_file_path=./cfg.yaml",
        "--running_duration=1",
        "--dump_cfg_file=true",
    ];
    let out = run_main_in(dir.path(), Some(&example(&address)), &args, LIMIT);
    out.assert_exit(0, "the log backend example with --dump_cfg_file");
    let dump = std::fs::read_to_string(dir.path().join("dump_cfg.yaml")).unwrap();
    let entry = dump
        .split_once("- type: udp_lines\n")
        .unwrap_or_else(|| panic!("no udp_lines in:\n{dump}"))
        .1;
    let options: Vec<&str> = entry.lines().take(5).map(str::trim).collect();
    assert_eq!(
        options,
        [
            "options:",
            &format!("address: {address}"),
            "format: line",
            "module_filter: LoggerModule",
            "pattern: \"[%l][%n] %v\"",
        ],
        "{dump}"
    );
    let again = run_main_in(dir.path(), Some(&dump), &args, LIMIT);
    again.assert_exit(0, "the dump");
    let dump_again = std::fs::read_to_string(dir.path().join("dump_cfg.yaml")).unwrap();
    assert_eq!(dump_again, dump);
}

#[test]
fn an_unknown_type_and_bad_options_are_errors_at_their_place() {
    let (_socket, address) = own_address();
    let cfg = example(&address).replace("- type: udp_lines", "- type: udp_line");
    let line = 1 + cfg
        .lines()
        .position(|l| l.ends_with("- type: udp_line"))
        .unwrap();
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            &format!("cfg.yaml:{line}:"),
            "unknown log backend type 'udp_line'",
            "did you mean 'udp_lines'",
            "console, rotate_file, udp_lines",
        ],
    );

    let cfg = example(&address).replace("          address:", "          adress:");
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(&out, &["log backend 'udp_lines'", "adress", "address"]);

    let cfg = example(&address).replace(
        "          pattern: \"[%l][%n] %v\"\n",
        "          pattern: \"[%l][%n] %v\"\n          format: yaml\n",
    );
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(&out, &["log backend 'udp_lines'", "yaml", "line", "json"]);

    let cfg = example("nowhere");
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(&out, &["address 'nowhere' is not ip:port"]);

    // Without the plugin the type is unknown.
    let cfg = example(&address).replace(
        "  plugin:\n    plugins:\n      - name: example_log_backend\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_log_backend_plugin.so\n",
        "",
    );
    assert!(!cfg.contains("name: example_log_backend"), "{cfg}");
    let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &[
            "unknown log backend type 'udp_lines'",
            "the types are console, rotate_file",
        ],
    );
}

/// A plugin library of ABI 1.9 (`plugins/fixtures/abi_1_9`) on this host of 1.10: its
/// client RPC filter runs around every call of the local RPC example and its context key
/// reaches the server.
#[test]
fn a_plugin_library_of_abi_1_9_filters_every_call_on_this_host() {
    let cfg = repo_config("rpc_filter_plugin")
        .replace(
            "      - name: example_filters\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_filters_plugin.so\n",
            &format!(
                "      - name: abi_1_9_plugin\n        path: {}\n",
                aimrt_e2e::lib("libfixture_abi_1_9.so").display()
            ),
        )
        .replace("enable_filters: [debug_log, trace_id]", "enable_filters: [abi_1_9_stamp]")
        .replace("        enable_filters: [require_trace_id]\n", "")
        .replace("rpc_frq: 2\n", "rpc_frq: 20\n");
    assert!(
        cfg.contains("enable_filters: [abi_1_9_stamp]") && !cfg.contains("name: example_filters"),
        "{cfg}"
    );
    let dir = tempfile::tempdir().unwrap();
    let out: Output = run_main_in(
        dir.path(),
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    out.assert_exit(0, "the ABI 1.9 fixture");
    let handled: Vec<&str> = out
        .stdout
        .lines()
        .filter(|l| l.contains("]Server handle new rpc call. context: "))
        .collect();
    assert!(handled.len() >= 4, "{}", out.stdout);
    assert!(
        handled.iter().all(|l| l.contains(r#"{"abi-1-9":"yes"}"#)),
        "{handled:?}"
    );
    let n = handled.len();
    let line = format!(
        "]ABI 1.9 plugin shut down: its filter passed {n} calls on and heard {n} answered OK"
    );
    assert!(
        out.stdout.contains(&line),
        "no {line:?} in:\n{}",
        out.stdout
    );
}

/// `config/log_backend_plugin.yaml` with its log backend from the fixture of ABI
/// `1.<minor>` (`plugins/fixtures/abi_1_<minor>`, log backend type `backend`, writing to
/// the file `path` in the run's directory), run for a second with `extra` arguments: the
/// file's lines, which must include each of `expected`, and the config it dumped (empty
/// without `--dump_cfg_file=true`).
fn run_with_fixture_backend(
    minor: u32,
    backend: &str,
    extra: &[&str],
    expected: [&str; 2],
) -> (String, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("fixture.log");
    let cfg = repo_config("log_backend_plugin")
        .replace(
            "      - name: example_log_backend\n        path: ${AIMRT_LIB_DIR:-./target/debug}/libexample_log_backend_plugin.so\n",
            &format!(
                "      - name: abi_1_{minor}_plugin\n        path: {}\n",
                aimrt_e2e::lib(&format!("libfixture_abi_1_{minor}.so")).display()
            ),
        )
        .replace("- type: udp_lines", &format!("- type: {backend}"))
        .lines()
        .map(|l| match l.split_once("address: ") {
            // The UDP address option becomes the fixture's file: no socket is involved.
            Some((indent, _)) if indent.trim().is_empty() => {
                format!("{indent}path: {}\n", path.display())
            }
            _ => format!("{l}\n"),
        })
        .collect::<String>();
    assert!(
        cfg.contains(&format!("- type: {backend}")) && !cfg.contains("address:"),
        "{cfg}"
    );
    let mut args = vec!["--cfg_file_path=./cfg.yaml", "--running_duration=1"];
    args.extend_from_slice(extra);
    let out = run_main_in(dir.path(), Some(&cfg), &args, LIMIT);
    out.assert_exit(0, &format!("the ABI 1.{minor} fixture"));
    let written = std::fs::read_to_string(&path).unwrap();
    for line in expected {
        assert!(
            written.lines().any(|l| l == line),
            "no {line:?} in:\n{written}"
        );
    }
    let dump = std::fs::read_to_string(dir.path().join("dump_cfg.yaml")).unwrap_or_default();
    (written, dump)
}

/// A plugin library of ABI 1.10 (`plugins/fixtures/abi_1_10`) on this host: its log
/// backend type writes every line its entry admits, in the entry's pattern.
#[test]
fn a_plugin_library_of_abi_1_10_writes_log_lines_on_this_host() {
    let expected = [
        "[Info][LoggerModule] Init succeeded.",
        "[Error][LoggerModule] Test error log, loop count: 1",
    ];
    let (written, _) = run_with_fixture_backend(10, "abi_1_10_file", &[], expected);
    assert!(
        written.lines().all(|l| l.contains("][LoggerModule] ")),
        "{written}"
    );
}

/// A plugin library of ABI 1.11 (`plugins/fixtures/abi_1_11`) on this host of 1.12: its
/// log backend type gets every line's parts, and its options are dumped as it read them.
#[test]
fn a_plugin_library_of_abi_1_11_gets_log_entries_with_their_parts_on_this_host() {
    let expected = [
        "Info | LoggerModule | Init succeeded.",
        "Error | LoggerModule | Test error log, loop count: 1",
    ];
    let dump_too = ["--dump_cfg_file=true"];
    let (_, dump) = run_with_fixture_backend(11, "abi_1_11_parts", &dump_too, expected);
    assert!(dump.contains(r#"separator: " | ""#), "{dump}");
}

/// A plugin's backend that logs from its own `write` (a line that would come back to it).
struct Chatty(std::sync::Arc<std::sync::atomic::AtomicUsize>);

impl aimrt_plugin_api::LogBackend for Chatty {
    fn write(&mut self, _: &aimrt_plugin_api::LogEntry<'_>) -> Result<(), String> {
        self.0.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        tracing::info!(target: "aimrt", "chatty wrote a line");
        Ok(())
    }
}

struct ChattyPlugin(std::sync::Arc<std::sync::atomic::AtomicUsize>);

impl aimrt_plugin_api::Plugin for ChattyPlugin {
    fn name(&self) -> &str {
        "chatty"
    }
    fn initialize(
        &mut self,
        registrar: &mut aimrt_plugin_api::Registrar<'_>,
        _: &aimrt_plugin_api::PluginOptions,
    ) -> Result<(), aimrt_plugin_api::Error> {
        let writes = self.0.clone();
        registrar
            .register_log_backend_type("chatty", move |_: &aimrt_plugin_api::BackendOptions| {
                Ok(Chatty(writes.clone()))
            })?;
        // Taken: the built-in types and a type already registered (by whom is said).
        for (name, says) in [
            ("console", "is built into the runtime"),
            ("chatty", "is already registered by 'chatty'"),
        ] {
            let err = registrar
                .register_log_backend_type(name, |_: &aimrt_plugin_api::BackendOptions| {
                    Ok(Chatty(Default::default()))
                })
                .unwrap_err()
                .to_string();
            assert!(err.contains(&format!("'{name}' {says}")), "{err}");
        }
        Ok(())
    }
}

/// What a backend logs while it writes is not handed back to it: one write per line the
/// runtime logs, not a loop.
#[test]
fn a_backend_that_logs_while_it_writes_does_not_feed_itself() {
    let writes = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let mut runtime = aimrt_runtime::Runtime::new(aimrt_runtime::RuntimeOptions {
        cfg_yaml: Some(
            "aimrt:\n  log:\n    core_lvl: INFO\n    backends:\n      - type: chatty\n".into(),
        ),
        running_duration: Some(Duration::from_secs(1)),
        ..Default::default()
    });
    runtime.builtin_plugin(Box::new(ChattyPlugin(writes.clone())));
    runtime.run().unwrap();
    let n = writes.load(std::sync::atomic::Ordering::SeqCst);
    // The runtime's own start and shutdown lines: a few dozen.
    assert!((5..200).contains(&n), "{n} writes");
}
