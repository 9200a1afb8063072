//! The bad-input corpus (`tests/e2e/corpus/`): configs, command lines, library files and
//! HTTP requests, each with its expected outcome. Every case is a real `aimrt_main`
//! process (one server for the HTTP cases) that must end within its timeout, without a
//! signal and without `panicked`; a refusal exits 255 with exactly one error line that
//! names what is wrong.
//!
//! Add a case by adding a file to `corpus/config/` or a line to `corpus/cli.txt` or
//! `corpus/http.txt`; each file says how it is read.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Duration;

use aimrt_e2e::{lib, run_main_args, Output};

const LIMIT: Duration = Duration::from_secs(60);

fn corpus_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("corpus")
}

/// What a case expects.
#[derive(Debug, Default)]
struct Expect {
    /// `true`: exit 255 with one failure line; `false`: exit 0.
    refused: bool,
    /// Texts the failure line (refused) or the whole output (accepted) contains.
    says: Vec<String>,
    /// Texts no output contains.
    lacks: Vec<String>,
}

/// Whether `output` reports a panic: Rust's own `panicked at`, or a contained panic's
/// `… panicked: …` line (the shutdown counters' `panicked 0` is neither).
fn panicked(output: &str) -> bool {
    output.contains("panicked at") || output.contains("panicked:")
}

/// Checks one finished run against `expect`; `Err` says why it does not match.
fn judge(out: &Output, expect: &Expect) -> Result<(), String> {
    let all = format!("{}\n{}", out.stdout, out.stderr);
    let Some(code) = out.code else {
        return Err("killed by a signal".to_owned());
    };
    if panicked(&all) {
        return Err("a panic in the output".to_owned());
    }
    if let Some(line) = out.stdout.lines().find(|l| {
        l.starts_with("AimRT run with exception and exit. ") && l.contains(".cargo/registry")
    }) {
        return Err(format!(
            "a dependency's source path in the failure line: {line}"
        ));
    }
    // The config snippet under an error echoes the file (`12 | key: value`), headers too.
    let said: String = all
        .lines()
        .filter(|l| {
            let t = l.trim_start();
            t.split_once(" | ")
                .is_none_or(|(n, _)| n.parse::<u32>().is_err())
        })
        .collect::<Vec<_>>()
        .join("\n");
    for lack in &expect.lacks {
        if said.contains(lack.as_str()) {
            return Err(format!("the output contains '{lack}'"));
        }
    }
    if expect.refused {
        if code != 255 {
            return Err(format!("exit code {code}, expected 255"));
        }
        let failures: Vec<&str> = out
            .stdout
            .lines()
            .filter(|l| l.starts_with("AimRT run with exception and exit. "))
            .collect();
        let errors = all
            .lines()
            .filter(|l| {
                l.contains("][Error][") || l.contains("][Fatal][") || l.starts_with("error")
            })
            .count();
        if failures.len() != 1 || errors != 0 {
            return Err(format!(
                "{} failure line(s) and {errors} other error line(s), expected exactly one error line",
                failures.len()
            ));
        }
        for say in &expect.says {
            if !failures[0].contains(say.as_str()) {
                return Err(format!("the failure line lacks '{say}': {}", failures[0]));
            }
        }
    } else {
        if code != 0 {
            return Err(format!("exit code {code}, expected 0"));
        }
        for say in &expect.says {
            if !all.contains(say.as_str()) {
                return Err(format!("the output lacks '{say}'"));
            }
        }
    }
    Ok(())
}

/// Runs `cases` on a few threads; fails listing every case that did not hold.
fn run_all<C: Sync>(kind: &str, cases: &[C], run: impl Fn(&C) -> Result<(), String> + Sync) {
    let failed = Mutex::new(Vec::new());
    let next = Mutex::new(0);
    std::thread::scope(|s| {
        for _ in 0..4 {
            s.spawn(|| loop {
                let i = {
                    let mut n = next.lock().unwrap();
                    *n += 1;
                    *n - 1
                };
                let Some(case) = cases.get(i) else { break };
                if let Err(e) = run(case) {
                    failed.lock().unwrap().push(format!("case {}: {e}", i + 1));
                }
            });
        }
    });
    let failed = failed.into_inner().unwrap();
    assert!(
        failed.is_empty(),
        "{} of {} {kind} cases failed:\n{}",
        failed.len(),
        cases.len(),
        failed.join("\n")
    );
}

/// `\xNN`, `\n`, `\r`, `\t` and `\\` in corpus text, as bytes.
fn unescape(text: &str) -> Vec<u8> {
    let b = text.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let next = b.get(i + 1).copied();
        let hex = b
            .get(i + 2..i + 4)
            .and_then(|h| std::str::from_utf8(h).ok())
            .and_then(|h| u8::from_str_radix(h, 16).ok());
        let (byte, used) = match (b[i], next, hex) {
            (b'\\', Some(b'x'), Some(v)) => (v, 4),
            (b'\\', Some(b'n'), _) => (b'\n', 2),
            (b'\\', Some(b'r'), _) => (b'\r', 2),
            (b'\\', Some(b't'), _) => (b'\t', 2),
            (b'\\', Some(b'\\'), _) => (b'\\', 2),
            (other, _, _) => (other, 1),
        };
        out.push(byte);
        i += used;
    }
    out
}

/// The `# key: value` header lines of a config case.
fn header(text: &str, key: &str) -> Vec<String> {
    let prefix = format!("# {key}: ");
    text.lines()
        .take_while(|l| l.starts_with('#'))
        .filter_map(|l| l.strip_prefix(&prefix))
        .map(|v| v.trim_end_matches('\r').to_owned())
        .collect()
}

#[test]
fn config_corpus() {
    let mut files: Vec<PathBuf> = std::fs::read_dir(corpus_dir().join("config"))
        .expect("corpus/config")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml"))
        .collect();
    files.sort();
    assert!(files.len() >= 100, "only {} config cases", files.len());
    run_all("config", &files, |path| {
        let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
        let text = String::from_utf8_lossy(&bytes);
        let name = path.file_name().unwrap_or_default().to_string_lossy();
        let outcome = header(&text, "outcome");
        let expect = Expect {
            refused: match outcome.first().map(String::as_str) {
                Some("refused") => true,
                Some("accepted") => false,
                other => {
                    return Err(format!(
                        "{name}: outcome {other:?} is not refused or accepted"
                    ))
                }
            },
            says: header(&text, "says"),
            lacks: header(&text, "lacks"),
        };
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        std::fs::write(dir.path().join("cfg.yaml"), &bytes).map_err(|e| e.to_string())?;
        let out = run_main_args(
            dir.path(),
            &[
                "--cfg_file_path=./cfg.yaml".into(),
                "--running_duration=1".into(),
            ],
            LIMIT,
        );
        judge(&out, &expect).map_err(|e| {
            format!(
                "{name} ({}): {e}\n{}",
                header(&text, "what").join(""),
                out.stdout
            )
        })
    });
}

#[test]
fn command_line_corpus() {
    let text = std::fs::read_to_string(corpus_dir().join("cli.txt")).expect("corpus/cli.txt");
    let cases: Vec<&str> = text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .collect();
    assert!(cases.len() >= 30, "only {} command-line cases", cases.len());
    run_all("command-line", &cases, |line| {
        let fields: Vec<&str> = line.split(" | ").collect();
        let [args, outcome, says] = fields[..] else {
            return Err(format!("'{line}' does not have three fields"));
        };
        let expect = Expect {
            refused: outcome == "refused",
            says: says.split(" && ").map(str::to_owned).collect(),
            lacks: Vec::new(),
        };
        let args: Vec<std::ffi::OsString> = args
            .split(' ')
            .map(|a| {
                use std::os::unix::ffi::OsStringExt;
                std::ffi::OsString::from_vec(unescape(a))
            })
            .collect();
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        std::fs::write(
            dir.path().join("cfg.yaml"),
            "aimrt:\n  log:\n    core_lvl: Info\n",
        )
        .map_err(|e| e.to_string())?;
        let out = run_main_args(dir.path(), &args, LIMIT);
        judge(&out, &expect).map_err(|e| format!("'{line}': {e}\n{}", out.stdout))
    });
}

/// A library file made broken from a built one, and what the refusal must say.
struct BrokenLib {
    what: &'static str,
    bytes: Vec<u8>,
    says: &'static str,
}

fn broken_libraries() -> Vec<BrokenLib> {
    let good = std::fs::read(lib("libaimrt_std_executors_plugin.so")).expect("read the plugin");
    let patched = |at: usize, value: &[u8]| {
        let mut b = good.clone();
        b[at..at + value.len()].copy_from_slice(value);
        b
    };
    let mut cases = vec![
        BrokenLib {
            what: "zero bytes",
            bytes: Vec::new(),
            says: "the file is empty (0 bytes)",
        },
        BrokenLib {
            what: "text",
            bytes: b"#!/bin/sh\necho hi\n".to_vec(),
            says: "starts with '#!/b'",
        },
        BrokenLib {
            what: "three bytes",
            bytes: good[..3].to_vec(),
            says: "not an ELF header",
        },
        BrokenLib {
            what: "cut in the ELF header",
            bytes: good[..40].to_vec(),
            says: "ends inside its ELF header",
        },
        BrokenLib {
            what: "cut after the ELF header",
            bytes: good[..64].to_vec(),
            says: "program headers lie past the end",
        },
        BrokenLib {
            what: "32-bit class",
            bytes: patched(4, &[1]),
            says: "32-bit",
        },
        BrokenLib {
            what: "unknown class",
            bytes: patched(4, &[9]),
            says: "unknown class",
        },
        BrokenLib {
            what: "built for AArch64",
            bytes: patched(18, &183u16.to_le_bytes()),
            says: "was built for AArch64",
        },
        BrokenLib {
            what: "built for 32-bit ARM",
            bytes: patched(18, &40u16.to_le_bytes()),
            says: "was built for ARM (32-bit)",
        },
        BrokenLib {
            what: "an executable, not a library",
            bytes: patched(16, &2u16.to_le_bytes()),
            says: "not a shared library",
        },
        BrokenLib {
            what: "random bytes",
            bytes: (0..4096u32)
                .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
                .collect(),
            says: "not an ELF header",
        },
    ];
    // Cut inside what the loader maps (past it come only sections dlopen never reads).
    let mapped = loaded_end(&good);
    for cut in [mapped - 1, mapped * 3 / 4, mapped / 2, mapped / 4, 4096] {
        cases.push(BrokenLib {
            what: "truncated inside its code",
            bytes: good[..cut].to_vec(),
            says: "is truncated: a loadable segment ends at byte",
        });
    }
    cases
}

/// Where the last loadable segment of a 64-bit little-endian ELF file ends.
fn loaded_end(elf: &[u8]) -> usize {
    let u16_at = |at: usize| u16::from_le_bytes([elf[at], elf[at + 1]]) as usize;
    let u64_at =
        |at: usize| u64::from_le_bytes(elf[at..at + 8].try_into().expect("8 bytes")) as usize;
    let (phoff, phentsize, phnum) = (u64_at(32), u16_at(54), u16_at(56));
    (0..phnum)
        .map(|i| phoff + i * phentsize)
        .filter(|&ph| elf[ph..ph + 4] == 1u32.to_le_bytes()) // PT_LOAD
        .map(|ph| u64_at(ph + 8) + u64_at(ph + 32))
        .max()
        .expect("a loadable segment")
}

#[test]
fn library_file_corpus() {
    let cases = broken_libraries();
    let mut runs = Vec::new();
    for case in &cases {
        for as_plugin in [true, false] {
            runs.push((case, as_plugin));
        }
    }
    run_all("library", &runs, |(case, as_plugin)| {
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        std::fs::write(dir.path().join("libbroken.so"), &case.bytes).map_err(|e| e.to_string())?;
        let cfg = if *as_plugin {
            "aimrt:\n  plugin:\n    plugins:\n      - name: broken\n        path: ./libbroken.so\n"
        } else {
            "aimrt:\n  module:\n    pkgs:\n      - path: ./libbroken.so\n"
        };
        std::fs::write(dir.path().join("cfg.yaml"), cfg).map_err(|e| e.to_string())?;
        let out = run_main_args(dir.path(), &["--cfg_file_path=./cfg.yaml".into()], LIMIT);
        let expect = Expect {
            refused: true,
            says: vec!["libbroken.so".to_owned(), case.says.to_owned()],
            lacks: Vec::new(),
        };
        let role = if *as_plugin { "plugin" } else { "pkg" };
        judge(&out, &expect).map_err(|e| format!("{} as a {role}: {e}\n{}", case.what, out.stdout))
    });
    // Libraries that are ELF and complete but not aimrt-rs libraries.
    let no_entry = lib("libfixture_no_entry.so");
    let exe = aimrt_e2e::aimrt_main();
    for (path, says) in [
        (no_entry.as_path(), "no aimrt-rs entry symbol"),
        (exe.as_path(), "cannot load the library"),
        (Path::new("/"), "is a directory, not a library file"),
        (Path::new("/dev/null"), "is not a regular file"),
    ] {
        let dir = tempfile::tempdir().expect("tempdir");
        let cfg = format!(
            "aimrt:\n  plugin:\n    plugins:\n      - name: p\n        path: {}\n",
            path.display()
        );
        std::fs::write(dir.path().join("cfg.yaml"), cfg).expect("write");
        let out = run_main_args(dir.path(), &["--cfg_file_path=./cfg.yaml".into()], LIMIT);
        let expect = Expect {
            refused: true,
            says: vec![says.to_owned()],
            lacks: Vec::new(),
        };
        if let Err(e) = judge(&out, &expect) {
            panic!("{}: {e}\n{}", path.display(), out.stdout);
        }
    }
}

#[test]
fn http_request_corpus() {
    use std::io::{Read, Write};
    const SERVICE: &str = "/rpc/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService";
    let text = std::fs::read_to_string(corpus_dir().join("http.txt")).expect("corpus/http.txt");
    let cases: Vec<&str> = text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .collect();
    assert!(cases.len() >= 40, "only {} HTTP cases", cases.len());
    let cfg = "aimrt:\n  plugin:\n    plugins:\n      - name: net_plugin\n        path: ${AIMRT_LIB_DIR}/libaimrt_net_plugin.so\n        options: {http_options: {listen_port: 0}}\n      - name: time_manipulator_plugin\n        path: ${AIMRT_LIB_DIR}/libaimrt_time_manipulator_plugin.so\n  log:\n    backends:\n      - type: console\n  executor:\n    executors:\n      - name: pool\n        type: asio_thread\n      - name: time_schedule_executor\n        type: time_manipulator\n        options: {bind_executor: pool}\n  rpc:\n    backends:\n      - type: http\n    servers_options:\n      - func_name: \"(pb:/aimrt.protocols.time_manipulator_plugin.*)\"\n        enable_backends: [http]\n";
    let mut server = aimrt_e2e::Running::start(cfg);
    let addr = server.http_address(LIMIT);
    // Until the runtime has started, a call of no plugin service is answered 503.
    server.wait_for("Module manager start completed.", LIMIT);
    let send = |request: &[u8]| -> Result<(u16, String), String> {
        let mut stream = std::net::TcpStream::connect(&addr).map_err(|e| e.to_string())?;
        stream
            .set_read_timeout(Some(Duration::from_secs(20)))
            .map_err(|e| e.to_string())?;
        // The server may answer and close before it has read everything.
        let _ = stream.write_all(request);
        let mut answer = Vec::new();
        let mut buf = [0u8; 65536];
        // Read one response: up to the end of the body its Content-Length announces.
        loop {
            match stream.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => answer.extend_from_slice(&buf[..n]),
                Err(e) if answer.is_empty() => return Err(format!("no answer: {e}")),
                Err(_) => break,
            }
            let text = String::from_utf8_lossy(&answer);
            if let Some((head, body)) = text.split_once("\r\n\r\n") {
                let length = head.lines().find_map(|l| {
                    l.to_ascii_lowercase()
                        .strip_prefix("content-length:")
                        .map(|v| v.trim().parse::<usize>().unwrap_or(0))
                });
                if length.is_some_and(|n| body.len() >= n) {
                    break;
                }
            }
        }
        let text = String::from_utf8_lossy(&answer).into_owned();
        let status = text
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| format!("not an HTTP response: {text:?}"))?;
        Ok((status, text))
    };
    run_all("HTTP", &cases, |line| {
        let fields: Vec<&str> = line.split(" | ").collect();
        let (request, status, says) = match fields[..] {
            ["raw", raw, status, says] => (unescape(&raw.replace("$S", SERVICE)), status, says),
            [start, content_type, body, status, says] => {
                let body = unescape(body);
                let mut head = format!(
                    "{} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n",
                    start.replace("$S", SERVICE),
                    body.len()
                );
                if content_type != "-" {
                    head.push_str(&format!("Content-Type: {content_type}\r\n"));
                }
                head.push_str("\r\n");
                let mut request = head.into_bytes();
                request.extend_from_slice(&body);
                (request, status, says)
            }
            _ => return Err(format!("'{line}' has neither 4 (raw) nor 5 fields")),
        };
        let (got, answer) = send(&request).map_err(|e| format!("'{line}': {e}"))?;
        if got.to_string() != status {
            return Err(format!(
                "'{line}': status {got}, expected {status}\n{answer}"
            ));
        }
        for say in says.split(" && ").filter(|s| *s != "-") {
            if !answer.contains(say) {
                return Err(format!("'{line}': the answer lacks '{say}'\n{answer}"));
            }
        }
        Ok(())
    });
    // Still serving, and nothing panicked.
    let (status, answer) = send(
        format!(
            "POST {SERVICE}/GetTimeRatio HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: application/json\r\nContent-Length: 43\r\n\r\n{{\"executor_name\": \"time_schedule_executor\"}}"
        )
        .as_bytes(),
    )
    .expect("a valid call after the corpus");
    assert_eq!(status, 200, "{answer}");
    let code = server.interrupt(LIMIT);
    assert_eq!(code, Some(0), "{}", server.text());
    assert!(!panicked(&server.text()), "{}", server.text());
}

/// A module section of 300 000 values (more than the YAML parser's default budget of
/// 250 000 nodes, which refused it with a Rust type name) is a legitimate config.
#[test]
fn a_large_module_section_is_accepted() {
    let mut cfg = String::from("aimrt:\n  log:\n    core_lvl: Info\nBigTable:\n  values:\n");
    for i in 0..300_000 {
        cfg.push_str(&format!("    - {i}\n"));
    }
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("cfg.yaml"), cfg).expect("write");
    let out = run_main_args(
        dir.path(),
        &[
            "--cfg_file_path=./cfg.yaml".into(),
            "--running_duration=1".into(),
        ],
        LIMIT,
    );
    let expect = Expect {
        refused: false,
        says: vec!["root node 'BigTable' configures no loaded module".to_owned()],
        lacks: vec!["budget".to_owned()],
    };
    if let Err(e) = judge(&out, &expect) {
        panic!("{e}\n{}", out.stdout);
    }
}
