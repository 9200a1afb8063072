//! End-to-end: `time_manipulator_plugin` and `net_plugin` loaded from their libraries by
//! the real `aimrt_main`, on AimRT's own config (only library paths and the module
//! changed), controlled over real HTTP. Each test listens on a port of its own (port 0,
//! read back from the log).

use std::time::{Duration, Instant};

use aimrt_e2e::{corpus, http, Running};

const SERVICE: &str = "/rpc/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService";
const JSON: (&str, &str) = ("content-type", "application/json");

/// `config/time_manipulator.yaml`, checked to be AimRT's config with only the library
/// paths and the module changed, listening on port 0.
fn config() -> String {
    let path = format!(
        "{}/../../config/time_manipulator.yaml",
        env!("CARGO_MANIFEST_DIR")
    );
    let ours = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let mut aimrt = corpus("examples_plugins_time_manipulator_plugin_cfg.yaml")
        .replace("ExecutorCoLoopModule", "TimeManipulatorModule");
    for lib in [
        "libaimrt_net_plugin.so",
        "libaimrt_time_manipulator_plugin.so",
        "libexecutor_pkg.so",
    ] {
        aimrt = aimrt.replace(
            &format!("path: ./{lib}"),
            &format!("path: ${{AIMRT_LIB_DIR:-./target/debug}}/{lib}"),
        );
    }
    let body: String = ours
        .lines()
        .skip_while(|l| !l.starts_with("# Copyright"))
        .map(|l| format!("{l}\n"))
        .collect();
    assert_eq!(
        body, aimrt,
        "{path} differs from AimRT's config beyond paths and the module"
    );
    aimrt_e2e::with_port(&ours, 0)
}

/// Starts `cfg` and returns it with the server's `ip:port`, once the runtime has started:
/// the server listens before, and answers a call of a module's function then with 503.
fn start(cfg: &str) -> (Running, String) {
    let mut running = Running::start(cfg);
    let addr = running.http_address(Duration::from_secs(30));
    running.wait_for("Module manager start completed.", Duration::from_secs(30));
    (running, addr)
}

fn post(addr: &str, method: &str, body: &str) -> (u16, String) {
    http(
        addr,
        "POST",
        &format!("{SERVICE}/{method}"),
        &[JSON],
        body.as_bytes(),
    )
}

/// The simulated time a `Loop count` line reports, in seconds since the epoch.
fn sim_secs(line: &str) -> f64 {
    line.rsplit('(')
        .next()
        .and_then(|s| s.trim_end_matches(')').parse().ok())
        .unwrap_or_else(|| panic!("no simulated time in {line}"))
}

fn gaps(ticks: &[(Instant, String)]) -> Vec<(f64, f64)> {
    ticks
        .windows(2)
        .map(|w| {
            (
                w[1].0.duration_since(w[0].0).as_secs_f64(),
                sim_secs(&w[1].1) - sim_secs(&w[0].1),
            )
        })
        .collect()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
fn speed_up_slow_down_pause_and_resume_over_http() {
    let (mut app, addr) = start(&config());
    let tick = "Loop count";

    // init_ratio 2: one simulated second every half real second.
    let mut ticks = vec![app.wait_for(tick, Duration::from_secs(10))];
    for _ in 0..4 {
        ticks.push(app.wait_for(tick, Duration::from_secs(5)));
    }
    let g = gaps(&ticks);
    let real = median(g.iter().map(|x| x.0).collect());
    assert!((0.3..0.8).contains(&real), "ratio 2: {g:?}\n{}", app.text());
    for (_, sim) in &g {
        assert!((0.95..1.5).contains(sim), "simulated gaps {g:?}");
    }

    // Slow down to 0.5: one simulated second every two real seconds.
    let (code, body) = post(
        &addr,
        "SetTimeRatio",
        r#"{"executor_name": "time_schedule_executor", "time_ratio": 0.5}"#,
    );
    assert_eq!(
        (code, body.as_str()),
        (200, r#"{"time_ratio":0.5,"code":0,"msg":""}"#)
    );
    app.wait_for(tick, Duration::from_secs(5));
    let slow = vec![
        app.wait_for(tick, Duration::from_secs(6)),
        app.wait_for(tick, Duration::from_secs(6)),
    ];
    let g = gaps(&slow);
    assert!((1.5..3.0).contains(&g[0].0), "ratio 0.5: {g:?}");
    assert!((0.95..1.5).contains(&g[0].1), "simulated gap {g:?}");

    // Pause: no ticks, and simulated time stands still.
    let (code, body) = post(
        &addr,
        "Pause",
        r#"{"executor_name": "time_schedule_executor"}"#,
    );
    assert_eq!(
        (code, body.as_str()),
        (200, r#"{"time_ratio":0,"code":0,"msg":""}"#)
    );
    let last_before = sim_secs(&slow[1].1);
    let paused_at = Instant::now();
    let during = app.collect_for(Duration::from_millis(2500), tick);
    assert!(
        during
            .iter()
            .all(|(at, _)| at.duration_since(paused_at) < Duration::from_millis(100)),
        "ticks while paused: {during:?}"
    );
    let (code, body) = post(
        &addr,
        "GetTimeRatio",
        r#"{"executor_name": "time_schedule_executor"}"#,
    );
    assert_eq!(
        (code, body.as_str()),
        (200, r#"{"time_ratio":0,"code":0,"msg":""}"#)
    );

    // Resume at 2: ticks come back, and the simulated clock went on from where it stood.
    let (code, body) = post(
        &addr,
        "SetTimeRatio",
        r#"{"executor_name": "time_schedule_executor", "time_ratio": 2}"#,
    );
    assert_eq!(
        (code, body.as_str()),
        (200, r#"{"time_ratio":2,"code":0,"msg":""}"#)
    );
    let (_, first) = app.wait_for(tick, Duration::from_secs(3));
    let jump = sim_secs(&first) - last_before;
    let ticks_in_pause = during.len() as f64;
    assert!(
        jump < 1.5 * (1.0 + ticks_in_pause),
        "the simulated clock moved {jump} s across a 2.5 s pause"
    );
    assert_eq!(app.interrupt(Duration::from_secs(20)), Some(0));
}

/// Method, path, headers, body, expected status, and a piece of the expected body.
type Case<'a> = (
    &'a str,
    String,
    Vec<(&'a str, &'a str)>,
    Vec<u8>,
    u16,
    &'a str,
);

#[test]
fn bad_requests_get_clear_http_errors_and_never_a_crash() {
    // Only SetTimeRatio and GetTimeRatio are enabled for http.
    let cfg = config().replace(
        r#""(pb:/aimrt.protocols.time_manipulator_plugin.*)""#,
        r#""pb:/.*/(SetTimeRatio|GetTimeRatio)""#,
    );
    let (mut app, addr) = start(&cfg);
    let set = format!("{SERVICE}/SetTimeRatio");
    let ok = br#"{"executor_name": "time_schedule_executor", "time_ratio": 1.5}"#;
    let cases: Vec<Case> = vec![
        (
            "POST",
            set.clone(),
            vec![JSON],
            ok.to_vec(),
            200,
            r#""time_ratio":1.5"#,
        ),
        (
            "POST",
            set.clone(),
            vec![("content-type", "application/json; charset=utf-8")],
            ok.to_vec(),
            200,
            r#""code":0"#,
        ),
        (
            "POST",
            set.clone(),
            vec![("content-type", "application/json charset=utf-8")],
            ok.to_vec(),
            200,
            r#""code":0"#,
        ),
        (
            "POST",
            set.clone(),
            vec![JSON],
            b"{not json".to_vec(),
            400,
            "not valid JSON",
        ),
        (
            "POST",
            set.clone(),
            vec![JSON],
            br#"{"executor_name": "time_schedule_executor"}"#.to_vec(),
            400,
            "missing field 'time_ratio'",
        ),
        (
            "POST",
            set.clone(),
            vec![JSON],
            br#"{"executor_name": "time_schedule_executor", "time_ratio": "NaN"}"#.to_vec(),
            200,
            r#""code":2"#,
        ),
        (
            "POST",
            set.clone(),
            vec![JSON],
            br#"{"executor_name": "nope", "time_ratio": 1}"#.to_vec(),
            200,
            r#"{"time_ratio":0,"code":1,"msg":"INVALID_EXECUTOR_NAME: no time_manipulator executor is named 'nope'; the time_manipulator executors: time_schedule_executor"}"#,
        ),
        (
            "POST",
            set.clone(),
            vec![JSON],
            br#"{"executor_name": "time_schedule_executr", "time_ratio": 1}"#.to_vec(),
            200,
            "did you mean 'time_schedule_executor'?",
        ),
        (
            "POST",
            "/rpc/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService/Paus".to_owned(),
            vec![JSON],
            br#"{"executor_name": "time_schedule_executor"}"#.to_vec(),
            404,
            "did you mean 'pb:/aimrt.protocols.time_manipulator_plugin.TimeManipulatorService/Pause'?",
        ),
        (
            "POST",
            set.clone(),
            vec![],
            ok.to_vec(),
            415,
            "no Content-Type",
        ),
        (
            "POST",
            set.clone(),
            vec![("content-type", "text/plain")],
            ok.to_vec(),
            415,
            "text/plain",
        ),
        (
            "POST",
            set.clone(),
            vec![("content-type", "application/x-www-form-urlencoded")],
            ok.to_vec(),
            415,
            "application/json",
        ),
        ("GET", set.clone(), vec![JSON], ok.to_vec(), 405, "POST"),
        (
            "POST",
            format!("{SERVICE}/Pause"),
            vec![JSON],
            br#"{"executor_name": "time_schedule_executor"}"#.to_vec(),
            404,
            "not enabled for the 'http' backend",
        ),
        (
            "POST",
            format!("{SERVICE}/Rewind"),
            vec![JSON],
            b"{}".to_vec(),
            404,
            "no service function",
        ),
        (
            "POST",
            "/rpc/".to_owned(),
            vec![JSON],
            b"{}".to_vec(),
            404,
            "no route",
        ),
        (
            "POST",
            "/elsewhere".to_owned(),
            vec![JSON],
            b"{}".to_vec(),
            404,
            "no route",
        ),
        (
            "POST",
            set.clone(),
            vec![JSON],
            vec![b' '; 16 * 1024 * 1024 + 1],
            413,
            "larger than the limit",
        ),
    ];
    for (method, path, headers, body, status, says) in &cases {
        let (code, text) = http(&addr, method, path, headers, body);
        assert_eq!(code, *status, "{method} {path}: {text}");
        assert!(text.contains(says), "{method} {path}: {text}");
        if *status != 200 {
            let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
            assert!(
                v["error"].is_string(),
                "errors are JSON {{\"error\": …}}: {text}"
            );
        }
    }
    // Random bodies: always an HTTP answer, never a crash, and the ratio stays valid.
    let pieces: [&[u8]; 12] = [
        b"{",
        b"}",
        b"\"executor_name\"",
        b":",
        b"\"time_schedule_executor\"",
        b",",
        b"\"time_ratio\"",
        b"1e999",
        b"\"Infinity\"",
        b"[",
        b"\xff",
        b"0.25",
    ];
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    for _ in 0..300 {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        let mut s = seed;
        let mut body = Vec::new();
        for _ in 0..(s % 10) {
            body.extend_from_slice(pieces[(s % 12) as usize]);
            s /= 12;
        }
        let (code, text) = http(&addr, "POST", &set, &[JSON], &body);
        assert!(
            code == 200 || code == 400,
            "{code} {text} for {:?}",
            String::from_utf8_lossy(&body)
        );
    }
    let (code, text) = post(
        &addr,
        "GetTimeRatio",
        r#"{"executor_name": "time_schedule_executor"}"#,
    );
    assert_eq!(code, 200, "{text}");
    app.wait_for("Loop count", Duration::from_secs(10));
    assert_eq!(app.interrupt(Duration::from_secs(20)), Some(0));
}

#[test]
fn a_backend_the_config_does_not_list_is_not_started() {
    let cfg = "aimrt:\n  log:\n    backends:\n      - type: console\n  plugin:\n    plugins:\n      - name: net_plugin\n        path: ${AIMRT_LIB_DIR}/libaimrt_net_plugin.so\n        options: {http_options: {listen_port: 0}}\n";
    let out = aimrt_e2e::run_main(
        Some(cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        Duration::from_secs(30),
    );
    assert_eq!(out.code, Some(0), "{}\n{}", out.stdout, out.stderr);
    assert!(
        out.stdout
            .contains("rpc backend 'http' of 'net_plugin' is not started"),
        "{}",
        out.stdout
    );
    assert!(!out.stdout.contains("listening on"), "{}", out.stdout);
}

#[test]
fn service_name_replaces_the_service_part_of_the_function_names() {
    let cfg = config()
        .replace(
            "libaimrt_time_manipulator_plugin.so\n",
            "libaimrt_time_manipulator_plugin.so\n        options:\n          service_name: SimClock\n",
        )
        .replace(
            r#""(pb:/aimrt.protocols.time_manipulator_plugin.*)""#,
            r#""pb:/SimClock/.*""#,
        );
    let (mut app, addr) = start(&cfg);
    let body = br#"{"executor_name": "time_schedule_executor"}"#;
    let (code, text) = http(&addr, "POST", "/rpc/SimClock/GetTimeRatio", &[JSON], body);
    assert_eq!(
        (code, text.as_str()),
        (200, r#"{"time_ratio":2,"code":0,"msg":""}"#)
    );
    let (code, _) = http(
        &addr,
        "POST",
        &format!("{SERVICE}/GetTimeRatio"),
        &[JSON],
        body,
    );
    assert_eq!(code, 404);
    assert_eq!(app.interrupt(Duration::from_secs(20)), Some(0));
}

/// 1 000 clients that send headers and then trickle nothing of their body do not stop
/// the service: a valid request is answered while they are connected, and each of them
/// is answered 408 once `body_timeout_ms` has passed.
#[test]
fn slow_clients_neither_exhaust_the_server_nor_stay_forever() {
    use std::io::{Read, Write};
    aimrt_runtime::raise_open_file_limit().expect("raise the open-file limit");
    let cfg = config().replace(
        "listen_port: 0",
        "listen_port: 0\n            body_timeout_ms: 6000",
    );
    let (app, addr) = start(&cfg);
    let head = format!(
        "POST {SERVICE}/GetTimeRatio HTTP/1.1\r\nHost: {addr}\r\ncontent-type: application/json\r\nContent-Length: 100\r\n\r\n{{"
    );
    let mut slow = Vec::new();
    for i in 0..1000 {
        let mut s = std::net::TcpStream::connect(&addr)
            .unwrap_or_else(|e| panic!("slow client {i} cannot connect: {e}"));
        s.write_all(head.as_bytes()).expect("send head");
        slow.push(s);
    }
    let (code, body) = post(
        &addr,
        "GetTimeRatio",
        r#"{"executor_name": "time_schedule_executor"}"#,
    );
    assert_eq!(code, 200, "{body}");
    // The last slow client has had no answer yet: the valid call was served while all
    // of them were connected and waiting.
    let last = slow.last().expect("slow clients");
    last.set_nonblocking(true).expect("nonblocking");
    let mut byte = [0u8; 1];
    assert!(
        matches!(last.peek(&mut byte), Err(e) if e.kind() == std::io::ErrorKind::WouldBlock),
        "the last slow client was answered before its body timeout"
    );
    last.set_nonblocking(false).expect("blocking");
    // Every slow client gets its 408 within the timeout plus slack.
    for s in slow.iter_mut().take(20) {
        s.set_read_timeout(Some(Duration::from_secs(30)))
            .expect("timeout");
        let mut answer = Vec::new();
        let _ = s.read_to_end(&mut answer);
        let text = String::from_utf8_lossy(&answer);
        assert!(
            text.starts_with("HTTP/1.1 408"),
            "a slow client got {text:?}"
        );
    }
    drop(app);
}
