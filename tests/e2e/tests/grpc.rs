//! Module RPC over grpc_plugin's `grpc` backend, end to end: the example pair as two
//! `aimrt_main` processes in every call style; a plain HTTP/2 gRPC client (as grpcurl or a
//! Python client calls) against our server, answers and failures; our client against a
//! plain gRPC server that answers with gRPC's own statuses; garbage on the port.

use std::collections::HashMap;
use std::time::Duration;

use aimrt_e2e::{repo_config, Running};
use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper::header::HeaderMap;
use hyper::{Request, Response, StatusCode};
use hyper_util::rt::{TokioExecutor, TokioIo};

const LIMIT: Duration = Duration::from_secs(60);

/// `config/<name>.yaml` with its `listen_port` made 0 (the server picks a free port and
/// logs it) and its clients' `server_url` made `http://<server>`: no port of the example
/// configs is kept.
fn example(name: &str, server: &str) -> String {
    repo_config(name)
        .lines()
        .map(|l| {
            let indent = &l[..l.len() - l.trim_start().len()];
            if l.trim_start().starts_with("listen_port:") {
                format!("{indent}listen_port: 0\n")
            } else if l.trim_start().starts_with("server_url:") {
                format!("{indent}server_url: http://{server}\n")
            } else {
                format!("{l}\n")
            }
        })
        .collect()
}

/// The example server on a free port, and its address once it listens and serves.
fn start_server() -> (Running, String) {
    let cfg = example("grpc_pb_rpc_server", "");
    let mut server = Running::start(&cfg);
    let (_, line) = server.wait_for("gRPC server listening on ", Duration::from_secs(20));
    let addr = line
        .split("listening on ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .unwrap_or_else(|| panic!("no address in {line}"))
        .to_owned();
    // Calls are answered SVR_NOT_READY until the modules have started.
    server.wait_for("Module manager start completed.", Duration::from_secs(20));
    (server, addr)
}

fn client_config(addr: &str) -> String {
    example("grpc_pb_rpc_client", addr)
}

const RSP: &str = aimrt_e2e::RPC_EXAMPLE_RSP;

#[test]
fn two_processes_call_over_grpc_in_every_style() {
    let (mut server, addr) = start_server();
    aimrt_e2e::every_client_style_calls(&client_config(&addr), RSP);
    // The server saw the client's context, its deadline and where the call came from.
    let (_, line) = server.wait_for("Server handle new rpc call. context: ", LIMIT);
    for kv in [
        r#"{"aimrt-function_name":"pb:/aimrt.protocols.example.ExampleService/GetFooData"}"#,
        r#"{"aimrt-serialization_type":"pb"}"#,
        r#"{"aimrt-backend":"grpc"}"#,
        r#"{"Remote-Endpoint":"127.0.0.1:"#,
    ] {
        assert!(line.contains(kv), "{kv} not in {line}");
    }
    assert!(line.contains("Server context, timeout: 3000ms"), "{line}");
}

/// An answer as a plain HTTP/2 client sees it.
struct Answer {
    status: StatusCode,
    headers: HeaderMap,
    trailers: HeaderMap,
    body: Bytes,
}

impl Answer {
    /// `name` from the trailers, or from the headers of a trailers-only answer.
    fn get(&self, name: &str) -> Option<&str> {
        self.trailers
            .get(name)
            .or_else(|| self.headers.get(name))
            .and_then(|v| v.to_str().ok())
    }
}

/// One call as a plain gRPC client makes it: `POST http://addr<path>` over h2c.
fn call(addr: &str, method: &str, path: &str, headers: &[(&str, &str)], body: Vec<u8>) -> Answer {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let stream = tokio::net::TcpStream::connect(addr).await.unwrap();
        let (mut sender, connection) =
            hyper::client::conn::http2::handshake(TokioExecutor::new(), TokioIo::new(stream))
                .await
                .unwrap();
        tokio::spawn(connection);
        let mut req = Request::builder()
            .method(method)
            .uri(format!("http://{addr}{path}"));
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        let req = req.body(Full::new(Bytes::from(body))).unwrap();
        let rsp = tokio::time::timeout(Duration::from_secs(20), sender.send_request(req))
            .await
            .expect("an answer within 20 s")
            .unwrap();
        let (parts, body) = rsp.into_parts();
        let collected = body.collect().await.unwrap();
        Answer {
            status: parts.status,
            headers: parts.headers,
            trailers: collected.trailers().cloned().unwrap_or_default(),
            body: collected.to_bytes(),
        }
    })
}

/// `message` as one gRPC message (uncompressed).
fn framed(message: &[u8]) -> Vec<u8> {
    let mut out = vec![0];
    out.extend_from_slice(&(message.len() as u32).to_be_bytes());
    out.extend_from_slice(message);
    out
}

const GRPC: [(&str, &str); 2] = [("content-type", "application/grpc"), ("te", "trailers")];
const GET_FOO: &str = "/aimrt.protocols.example.ExampleService/GetFooData";

#[test]
fn plain_grpc_clients_get_grpc_answers_and_statuses() {
    let (mut server, addr) = start_server();
    // GetFooDataReq { msg: "hello" } in pb, as grpcurl sends it.
    let mut req = vec![0x0a, 5];
    req.extend_from_slice(b"hello");
    let a = call(&addr, "POST", GET_FOO, &GRPC, framed(&req));
    assert_eq!(a.status, StatusCode::OK);
    assert_eq!(a.headers.get("content-type").unwrap(), "application/grpc");
    assert_eq!(a.get("grpc-status"), Some("0"), "{:?}", a.trailers);
    // GetFooDataRsp { msg: "echo hello" }: one message with its prefix.
    let mut rsp = vec![0x12, 10];
    rsp.extend_from_slice(b"echo hello");
    assert_eq!(&a.body[..], &framed(&rsp)[..]);
    // The deadline and the caller's meta reach the service.
    let a = call(
        &addr,
        "POST",
        GET_FOO,
        &[
            GRPC[0],
            GRPC[1],
            ("grpc-timeout", "1500m"),
            ("trace-id", "t-42"),
        ],
        framed(&req),
    );
    assert_eq!(a.get("grpc-status"), Some("0"));
    let (_, line) = server.wait_for(r#"{"trace-id":"t-42"}"#, LIMIT);
    assert!(line.contains("Server context, timeout: 1500ms"), "{line}");
    // JSON, as application/grpc+json.
    let a = call(
        &addr,
        "POST",
        GET_FOO,
        &[("content-type", "application/grpc+json"), GRPC[1]],
        framed(br#"{"msg": "json"}"#),
    );
    assert_eq!(a.get("grpc-status"), Some("0"));
    assert_eq!(
        a.headers.get("content-type").unwrap(),
        "application/grpc+json"
    );
    assert!(
        String::from_utf8_lossy(&a.body).contains(r#""msg":"echo json""#),
        "{:?}",
        a.body
    );
    // Failures: a gRPC status, AimRT's code, and why; never a call left unanswered.
    let cases: [(&str, Vec<u8>, &str, &str, &str); 5] = [
        (
            "/aimrt.protocols.example.ExampleService/Nope",
            framed(&req),
            "12",
            "1003",
            "no service function at '/aimrt.protocols.example.ExampleService/Nope'",
        ),
        (
            GET_FOO,
            vec![0, 0, 0, 0, 9, 1],
            "3",
            "1007",
            "the gRPC prefix says 9 bytes and 1 follow",
        ),
        (
            GET_FOO,
            vec![0, 0],
            "3",
            "1007",
            "fewer than a gRPC message's 5-byte prefix",
        ),
        (GET_FOO, framed(&[0xff, 0xff, 0xff]), "3", "1007", ""),
        (GET_FOO, vec![1, 0, 0, 0, 0], "12", "1007", "compressed"),
    ];
    for (path, body, grpc, aimrt, why) in cases {
        let a = call(&addr, "POST", path, &GRPC, body.clone());
        assert_eq!(a.status, StatusCode::OK, "{path} {body:?}");
        assert_eq!(
            a.get("grpc-status"),
            Some(grpc),
            "{path} {body:?}: {:?}",
            a.headers
        );
        assert_eq!(a.get("aimrt-rs-status"), Some(aimrt), "{path} {body:?}");
        let message = a.get("grpc-message").unwrap_or("");
        assert!(message.contains(why), "{path} {body:?}: {message}");
        assert!(a.body.is_empty(), "trailers only");
    }
    // A compressed call (`grpc-encoding` other than identity) is refused; identity is read.
    for (encoding, grpc) in [("gzip", "12"), ("identity", "0")] {
        let headers = [GRPC[0], GRPC[1], ("grpc-encoding", encoding)];
        let a = call(&addr, "POST", GET_FOO, &headers, framed(&req));
        assert_eq!(
            a.get("grpc-status"),
            Some(grpc),
            "{encoding}: {:?}",
            a.headers
        );
    }
    // What is not gRPC gets HTTP's answer, as gRPC's rules say.
    assert_eq!(
        call(&addr, "GET", GET_FOO, &GRPC, Vec::new()).status,
        StatusCode::METHOD_NOT_ALLOWED
    );
    assert_eq!(
        call(
            &addr,
            "POST",
            GET_FOO,
            &[("content-type", "application/json")],
            framed(&req)
        )
        .status,
        StatusCode::UNSUPPORTED_MEDIA_TYPE
    );
    // Garbage on the port: the connection is dropped, the server serves on.
    {
        use std::io::Write;
        let mut raw = std::net::TcpStream::connect(&addr).unwrap();
        let _ = raw.write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n\x00\x01\x02garbage");
    }
    let a = call(&addr, "POST", GET_FOO, &GRPC, framed(&req));
    assert_eq!(a.get("grpc-status"), Some("0"));
}

/// A plain gRPC server (not aimrt-rs) on a free port that answers every call with
/// `grpc-status` `code` and records the requests' headers.
fn plain_server(
    code: &'static str,
) -> (String, std::sync::mpsc::Receiver<HashMap<String, String>>) {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.set_nonblocking(true).unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::from_std(listener).unwrap();
            loop {
                let Ok((stream, _)) = listener.accept().await else {
                    return;
                };
                let tx = tx.clone();
                let service =
                    hyper::service::service_fn(move |req: Request<hyper::body::Incoming>| {
                        let tx = tx.clone();
                        async move {
                            let mut seen: HashMap<String, String> = req
                                .headers()
                                .iter()
                                .map(|(k, v)| (k.to_string(), v.to_str().unwrap_or("").to_owned()))
                                .collect();
                            seen.insert(":path".into(), req.uri().path().to_owned());
                            let _ = tx.send(seen);
                            let rsp = Response::builder()
                                .header("content-type", "application/grpc")
                                .header("grpc-status", code)
                                .header("grpc-message", "not%20allowed")
                                .body(Full::new(Bytes::new()))
                                .unwrap();
                            Ok::<_, std::convert::Infallible>(rsp)
                        }
                    });
                tokio::spawn(
                    hyper::server::conn::http2::Builder::new(TokioExecutor::new())
                        .serve_connection(TokioIo::new(stream), service),
                );
            }
        });
    });
    (addr, rx)
}

#[test]
fn our_client_speaks_grpc_and_reads_grpcs_statuses() {
    // PERMISSION_DENIED from a server that is not aimrt-rs: the service failed (1008).
    let (addr, seen) = plain_server("7");
    let out = aimrt_e2e::run_for(&client_config(&addr), 3);
    assert!(
        out.stdout.contains(
            "Client get rpc error ret, status: fail, code 1008, msg: Server handle failed"
        ),
        "{}",
        out.stdout
    );
    let headers = seen.recv_timeout(LIMIT).expect("the server got a call");
    assert_eq!(headers[":path"], GET_FOO);
    assert_eq!(headers["content-type"], "application/grpc");
    assert_eq!(headers["te"], "trailers");
    assert_eq!(headers["aimrt-function_name"], format!("pb:{GET_FOO}"));
    // The client's 3 s (rpc examples' timeout) in at most 8 digits.
    assert_eq!(headers["grpc-timeout"], "3000000u");
    // DEADLINE_EXCEEDED: AimRT's timeout.
    let (addr, _seen) = plain_server("4");
    let out = aimrt_e2e::run_for(&client_config(&addr), 3);
    assert!(
        out.stdout
            .contains("Client get rpc error ret, status: fail, code 2, msg: Timeout"),
        "{}",
        out.stdout
    );
    // Nobody at the address: the call fails at once with CLI_SEND_REQ_FAILED.
    let port = aimrt_e2e::free_port(false);
    let out = aimrt_e2e::run_for(&client_config(&format!("127.0.0.1:{port}")), 3);
    assert!(
        out.stdout
            .contains("Client get rpc error ret, status: fail, code 2010"),
        "{}",
        out.stdout
    );
}

/// A server whose process stands still (SIGSTOP) under a calling client: the call in
/// flight ends with `Timeout` within its 3 s, and once the server goes on, the next call
/// on the same HTTP/2 connection is answered.
#[test]
fn a_stopped_server_is_timed_out_and_the_next_call_answered() {
    let (mut server, addr) = start_server();
    let cfg = client_config(&addr).replace("rpc_frq: 0.5", "rpc_frq: 5");
    let mut client = Running::start(&cfg);
    client.wait_for(RSP, LIMIT);
    let text = aimrt_e2e::stop_a_server_under_its_client(&mut server, &mut client);
    assert!(
        aimrt_e2e::number_after(&text, "answered with an error status (") >= 1,
        "the timed-out call is counted:\n{text}"
    );
}

/// The network between client and server stops carrying (a black-hole proxy: the HTTP/2
/// connection stays open and silent, as over a cut link before TCP gives up, which can
/// take minutes): the call in flight ends with `Timeout`, and once the network carries
/// again the next call is answered on a new connection. Before, every later call went
/// into the stalled connection and timed out too.
#[test]
fn a_connection_that_stops_carrying_is_given_up_after_a_timeout() {
    let (mut server, addr) = start_server();
    let proxy = aimrt_e2e::BlackHoleProxy::start(&addr);
    let cfg = client_config(&proxy.addr().to_string()).replace("rpc_frq: 0.5", "rpc_frq: 5");
    let mut client = Running::start(&cfg);
    client.wait_for(RSP, LIMIT);
    proxy.cut();
    let (_, line) = client.wait_for("Client get rpc", LIMIT);
    assert!(line.contains("code 2, msg: Timeout"), "{line}");
    proxy.heal();
    let (_, line) = client.wait_for("Client get rpc", LIMIT);
    assert!(line.contains("code 0, msg: OK"), "{line}");
    assert_eq!(client.interrupt(LIMIT), Some(0));
    assert_eq!(server.interrupt(LIMIT), Some(0));
    let text = client.text();
    assert!(
        text.contains("grpc_plugin: the connection to 127.0.0.1:"),
        "{text}"
    );
}

/// The benchmark client's two plans over grpc (shortened), every call answered OK.
#[test]
fn the_benchmark_client_calls_over_grpc_without_error() {
    let (mut server, addr) = start_server();
    let cfg = aimrt_e2e::shorter_bench_plans(&example("grpc_pb_rpc_benchmark_client", &addr), 20);
    let mut client = Running::start(&cfg);
    let rates = aimrt_e2e::rpc_bench_error_rates(&mut client, 2, LIMIT);
    assert_eq!(rates, ["0 %", "0 %"], "{}", client.text());
    assert_eq!(client.interrupt(LIMIT), Some(0));
    assert_eq!(server.interrupt(LIMIT), Some(0));
}
