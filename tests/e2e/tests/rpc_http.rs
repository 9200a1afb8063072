//! Module RPC over net_plugin's `http` backend, end to end: AimRT's
//! `pb_rpc_http_server` / `pb_rpc_http_client` configs as two `aimrt_main` processes in
//! every call style, our server against the bytes AimRT's server answered, our client
//! against the request AimRT's client sent, and plain HTTP clients (curl-style JSON,
//! malformed bodies, wrong content types, unknown functions), and a server whose process
//! stands still (SIGSTOP).

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::Duration;

use aimrt_e2e::{net_example, Running};

const LIMIT: Duration = Duration::from_secs(60);

fn server_config() -> String {
    net_example("pb_rpc_http_server", 0)
}

fn client_config(addr: &str) -> String {
    let port = addr
        .rsplit(':')
        .next()
        .and_then(|p| p.parse().ok())
        .expect("ip:port");
    net_example("pb_rpc_http_client", port)
}

/// The server process, and its address once it listens.
fn start_server() -> (Running, String) {
    let mut server = Running::start(&server_config());
    let addr = server.http_address(Duration::from_secs(20));
    // Calls are answered SVR_NOT_READY (503) until the modules have started.
    server.wait_for("Module manager start completed.", Duration::from_secs(20));
    (server, addr)
}

const RSP: &str = aimrt_e2e::RPC_EXAMPLE_RSP;

#[test]
fn two_processes_call_over_http_in_every_style() {
    let (mut server, addr) = start_server();
    aimrt_e2e::every_client_style_calls(&client_config(&addr), RSP);
    // The server saw the client's context: AimRT's keys restored from the headers.
    let (_, line) = server.wait_for("Server handle new rpc call. context: ", LIMIT);
    for kv in [
        r#"{"aimrt-function_name":"pb:/aimrt.protocols.example.ExampleService/GetFooData"}"#,
        r#"{"aimrt-serialization_type":"pb"}"#,
        r#"{"aimrt-backend":"http"}"#,
        r#"{"aimrt-request_id":"1"}"#,
        // As AimRT sets it for every backend: the caller's request id.
        r#"{"aimrt-response_id":"1"}"#,
    ] {
        assert!(line.contains(kv), "{kv} not in {line}");
    }
    assert!(line.contains("Server context, timeout: 3000ms"), "{line}");
}

/// An HTTP message split into its first line, headers (lowercased names) and body.
struct Message {
    first: String,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Message {
    fn parse(bytes: &[u8]) -> Message {
        let end = bytes
            .windows(4)
            .position(|w| w == b"\r\n\r\n")
            .expect("a header block");
        let head = String::from_utf8_lossy(&bytes[..end]).into_owned();
        let mut lines = head.split("\r\n");
        let first = lines.next().unwrap().to_owned();
        let headers = lines
            .map(|l| {
                let (k, v) = l.split_once(':').unwrap();
                (k.trim().to_ascii_lowercase(), v.trim().to_owned())
            })
            .collect();
        Message {
            first,
            headers,
            body: bytes[end + 4..].to_vec(),
        }
    }

    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }
}

/// A server process that stands still (SIGSTOP): the call in flight ends at its deadline
/// (3 s) with 2, the calls after the server goes on are answered, and the backend's own
/// timeout, a moment after the runtime's, is dropped without being counted as a late
/// answer: it repeats the timeout (and closes the call's connection, so the server's
/// answer finds no one).
#[test]
fn a_stopped_server_is_timed_out_and_the_backends_own_timeout_is_not_a_late_answer() {
    let (mut server, addr) = start_server();
    let cfg = client_config(&addr).replace("rpc_frq: 0.5", "rpc_frq: 5");
    let mut client = Running::start(&cfg);
    client.wait_for(RSP, LIMIT);
    let text = aimrt_e2e::stop_a_server_under_its_client(&mut server, &mut client);
    assert_eq!(
        aimrt_e2e::number_after(&text, " (1 timed out), "),
        0,
        "{text}"
    );
}

/// Sends `request` as is on a fresh connection and reads one response.
fn exchange(addr: &str, request: &[u8]) -> Message {
    let mut stream = TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    stream.write_all(request).unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        let n = stream.read(&mut buf).unwrap();
        assert!(n > 0, "the server closed before answering");
        got.extend_from_slice(&buf[..n]);
        if let Some(end) = got.windows(4).position(|w| w == b"\r\n\r\n") {
            let m = Message::parse(&got);
            let len: usize = m.header("content-length").map_or(0, |v| v.parse().unwrap());
            if got.len() >= end + 4 + len {
                return m;
            }
        }
    }
}

#[test]
fn our_server_answers_aimrts_requests_as_aimrt_does() {
    let (_server, addr) = start_server();
    let f = aimrt_e2e::wire_fixture("http_rpc_server_rsp.txt");
    for case in ["replay_of_request_1", "min_pb", "json"] {
        let ours = exchange(&addr, &f[&format!("sent_{case}")]);
        let aimrts = Message::parse(&f[&format!("recv_{case}")]);
        assert_eq!(ours.first, aimrts.first, "{case}");
        assert_eq!(ours.body, aimrts.body, "{case}: the response body");
        for h in ["content-type", "access-control-allow-origin"] {
            assert_eq!(ours.header(h), aimrts.header(h), "{case}: {h}");
        }
        assert_eq!(ours.header("aimrt-rs-status"), Some("0"), "{case}");
    }
    // An undecodable body: AimRT answers 500; we say 400 and the code.
    let bad = exchange(&addr, &f["sent_bad_pb"]);
    assert!(bad.first.starts_with("HTTP/1.1 400"), "{}", bad.first);
    assert_eq!(bad.header("aimrt-rs-status"), Some("1007"));
    assert!(String::from_utf8_lossy(&bad.body).contains("cannot be deserialized (pb)"));
    let options = exchange(&addr, &f["sent_options"]);
    assert!(
        options.first.starts_with("HTTP/1.1 200"),
        "{}",
        options.first
    );
}

#[test]
fn plain_http_clients_get_precise_answers() {
    let (mut server, addr) = start_server();
    let path = "/rpc/aimrt.protocols.example.ExampleService/GetFooData";
    // The service sees where the call came from under AimRT's `Remote-Endpoint` (a
    // client's own is replaced), and an empty `aimrt-response_id` for a call without a
    // request id, as on AimRT.
    let (status, _) = aimrt_e2e::http(
        &addr,
        "POST",
        path,
        &[
            ("Content-Type", "application/json"),
            ("Remote-Endpoint", "6.6.6.6:1"),
        ],
        br#"{"msg":"traced"}"#,
    );
    assert_eq!(status, 200);
    let (_, line) = server.wait_for("Server handle new rpc call. context: ", LIMIT);
    assert!(line.contains(r#"{"Remote-Endpoint":"127.0.0.1:"#), "{line}");
    assert!(line.contains(r#"{"aimrt-response_id":""}"#), "{line}");
    assert!(line.contains("Server context, timeout: 0ms"), "{line}");
    assert!(!line.contains("6.6.6.6"), "{line}");
    // curl -H 'Content-Type: application/json' -d '{"msg":"hi"}'
    let (status, body) = aimrt_e2e::http(
        &addr,
        "POST",
        path,
        &[("Content-Type", "application/json")],
        br#"{"msg":"hi"}"#,
    );
    assert_eq!(
        (status, body.as_str()),
        (200, r#"{"code":"0","msg":"echo hi"}"#)
    );
    // GetBarData answers too (the server module registers every method).
    let (status, body) = aimrt_e2e::http(
        &addr,
        "POST",
        "/rpc/aimrt.protocols.example.ExampleService/GetBarData",
        &[("Content-Type", "application/json")],
        br#"{"msg":"bar"}"#,
    );
    assert_eq!(
        (status, body.as_str()),
        (200, r#"{"code":"0","msg":"echo bar"}"#)
    );
    for (ct, payload, want, text) in [
        (
            "application/json",
            &b"{\"msg\":"[..],
            400,
            "cannot be deserialized (json)",
        ),
        (
            "application/json",
            &b""[..],
            400,
            "cannot be deserialized (json)",
        ),
        (
            "application/json",
            &b"{\"nope\":1}"[..],
            400,
            "cannot be deserialized",
        ),
        (
            "text/plain",
            &b"hi"[..],
            415,
            "'text/plain' is not supported",
        ),
        (
            "application/protobuf",
            &b"\xff\xff"[..],
            400,
            "cannot be deserialized (pb)",
        ),
    ] {
        let (status, body) = aimrt_e2e::http(&addr, "POST", path, &[("Content-Type", ct)], payload);
        assert_eq!(status, want, "{ct} {payload:?}: {body}");
        assert!(body.contains(text), "{ct} {payload:?}: {body}");
    }
    let (status, body) = aimrt_e2e::http(
        &addr,
        "POST",
        "/rpc/aimrt.protocols.example.ExampleService/NoSuchMethod",
        &[("Content-Type", "application/json")],
        b"{}",
    );
    assert_eq!(status, 404, "{body}");
    assert!(body.contains("no service function"), "{body}");
    // A near miss names the function meant.
    let (status, body) = aimrt_e2e::http(
        &addr,
        "POST",
        "/rpc/aimrt.protocols.example.ExampleService/GetFoData",
        &[("Content-Type", "application/json")],
        b"{}",
    );
    assert_eq!(status, 404, "{body}");
    assert!(
        body.contains("did you mean 'pb:/aimrt.protocols.example.ExampleService/GetFooData'?"),
        "{body}"
    );
}

#[test]
fn our_client_sends_what_aimrts_client_sends() {
    let f = aimrt_e2e::wire_fixture("http_rpc_req.txt");
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let response = f["python_response_1"].clone();
    let captured = std::thread::spawn(move || {
        let (mut stream, _) = listener.accept().unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        loop {
            let n = stream.read(&mut buf).unwrap();
            assert!(n > 0, "the client closed before sending a request");
            got.extend_from_slice(&buf[..n]);
            if let Some(end) = got.windows(4).position(|w| w == b"\r\n\r\n") {
                let m = Message::parse(&got);
                let len: usize = m.header("content-length").map_or(0, |v| v.parse().unwrap());
                if got.len() >= end + 4 + len {
                    break;
                }
            }
        }
        stream.write_all(&response).unwrap();
        got
    });
    let out = aimrt_e2e::run_for(&client_config(&addr), 3);
    let sent = Message::parse(&captured.join().unwrap());
    let aimrts = Message::parse(&f["request_1"]);
    assert_eq!(sent.first, aimrts.first);
    assert_eq!(sent.body, aimrts.body);
    // Header order after Content-Type is unspecified (AimRT's meta is a hash map): as sets.
    let mut ours = sent.headers.clone();
    let mut theirs = aimrts.headers.clone();
    ours.sort();
    theirs.sort();
    assert_eq!(ours, theirs);
    // Host, User-Agent, Timeout and Content-Type come first, as AimRT sends them.
    let names: Vec<&str> = sent.headers.iter().map(|(k, _)| k.as_str()).collect();
    assert_eq!(
        names[..4],
        ["host", "user-agent", "timeout", "content-type"]
    );
    // The client accepted AimRT's recorded answer.
    let answered = Message::parse(&f["python_response_1"]);
    let rsp = String::from_utf8_lossy(&answered.body[2..]).into_owned();
    assert!(
        out.stdout.contains(&format!(
            r#"Client get rpc ret, status: suc, code 0, msg: OK, rsp: {{"code":"0","msg":"{rsp}"}}"#
        )),
        "{}",
        out.stdout
    );
}

/// AimRT's http RPC benchmark client (its own listener moved to a free port) against the
/// server, with the plans cut short: every call of both plans succeeds.
#[test]
fn aimrts_benchmark_client_calls_over_http_without_error() {
    let (mut server, addr) = start_server();
    let port: u16 = addr
        .rsplit(':')
        .next()
        .and_then(|p| p.parse().ok())
        .expect("ip:port");
    let cfg = aimrt_e2e::shorter_bench_plans(
        &net_example("pb_rpc_http_benchmark_client", port)
            .replace("listen_port: 50081", "listen_port: 0"),
        20,
    );
    let mut client = Running::start(&cfg);
    let rates = aimrt_e2e::rpc_bench_error_rates(&mut client, 2, LIMIT);
    assert_eq!(rates, ["0 %", "0 %"], "{}", client.text());
    assert_eq!(client.interrupt(LIMIT), Some(0));
    assert_eq!(server.interrupt(LIMIT), Some(0));
}
