//! opentelemetry_plugin's trace filters under `aimrt_main`, AimRT's two examples
//! (`config/opentelemetry_plugin_pb_<chn|rpc>.yaml`), sending to a collector of the test's
//! own (an HTTP server that keeps each OTLP request): the spans, their parents across the
//! publisher and the subscriber, the client and the server, their attributes; a collector
//! that refuses or is not there; bad options.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::{repo_config, run_main, Output};
use aimrt_opentelemetry::otlp::{ExportTraceServiceRequest, Span};
use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper_util::rt::TokioIo;
use prost::Message;

const LIMIT: Duration = Duration::from_secs(60);

/// What the collector kept of each request: its path, content type and body.
type Requests = Arc<Mutex<Vec<(String, String, Vec<u8>)>>>;

/// An OTLP/HTTP collector on a free port: keeps every request's path, content type and
/// body, and answers `status`.
struct Collector {
    url: String,
    got: Requests,
}

impl Collector {
    fn start(status: u16) -> Collector {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let url = format!("http://{}/v1/traces", listener.local_addr().unwrap());
        let got: Requests = Arc::default();
        let keep = got.clone();
        std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .unwrap();
            rt.block_on(async move {
                let listener = tokio::net::TcpListener::from_std(listener).unwrap();
                loop {
                    let Ok((stream, _)) = listener.accept().await else {
                        continue;
                    };
                    let keep = keep.clone();
                    tokio::spawn(async move {
                        let service = hyper::service::service_fn(
                            move |req: hyper::Request<hyper::body::Incoming>| {
                                let keep = keep.clone();
                                async move {
                                    let path = req.uri().path().to_owned();
                                    let ct = req
                                        .headers()
                                        .get("content-type")
                                        .and_then(|v| v.to_str().ok())
                                        .unwrap_or("")
                                        .to_owned();
                                    let body = req.into_body().collect().await.unwrap().to_bytes();
                                    keep.lock().unwrap().push((path, ct, body.to_vec()));
                                    let mut rsp = hyper::Response::new(Full::new(Bytes::new()));
                                    *rsp.status_mut() =
                                        hyper::StatusCode::from_u16(status).unwrap();
                                    Ok::<_, std::convert::Infallible>(rsp)
                                }
                            },
                        );
                        let _ = hyper::server::conn::http1::Builder::new()
                            .serve_connection(TokioIo::new(stream), service)
                            .await;
                    });
                }
            });
        });
        Collector { url, got }
    }

    /// Every span received, with its request's resource attributes.
    fn spans(&self) -> Vec<(Vec<(String, String)>, Span)> {
        let mut out = Vec::new();
        for (path, ct, body) in self.got.lock().unwrap().iter() {
            assert_eq!(path, "/v1/traces");
            assert_eq!(ct, "application/x-protobuf");
            let req = ExportTraceServiceRequest::decode(&body[..]).expect("an OTLP request");
            for rs in req.resource_spans {
                let resource: Vec<(String, String)> = rs
                    .resource
                    .map(|r| r.attributes)
                    .unwrap_or_default()
                    .iter()
                    .map(|kv| (kv.key.clone(), kv.as_text().unwrap_or("").to_owned()))
                    .collect();
                for ss in rs.scope_spans {
                    for s in ss.spans {
                        out.push((resource.clone(), s));
                    }
                }
            }
        }
        out
    }
}

fn attr<'a>(span: &'a Span, key: &str) -> Option<&'a str> {
    span.attributes
        .iter()
        .find(|kv| kv.key == key)
        .and_then(|kv| kv.as_text())
}

/// `config/<name>.yaml` sending to `url`, run for `secs` seconds.
fn run(name: &str, url: &str, edit: impl FnOnce(String) -> String, secs: u32) -> Output {
    let cfg = edit(repo_config(name)).replace(
        "${AIMRT_OTLP_TRACES_URL:-http://localhost:4318/v1/traces}",
        url,
    );
    let out = run_main(
        Some(&cfg),
        &[
            "--cfg_file_path=./cfg.yaml",
            &format!("--running_duration={secs}"),
        ],
        LIMIT,
    );
    out.assert_exit(0, name);
    out
}

#[test]
fn a_published_message_and_its_delivery_are_a_producer_span_and_its_consumer_child() {
    let collector = Collector::start(200);
    let out = run(
        "opentelemetry_plugin_pb_chn",
        &collector.url,
        |c| c.replace("channel_frq: 0.5", "channel_frq: 5"),
        3,
    );
    let spans = collector.spans();
    let producers: Vec<&Span> = spans
        .iter()
        .map(|(_, s)| s)
        .filter(|s| s.kind == 4)
        .collect();
    assert!(
        producers.len() >= 5,
        "{} producer spans\n{}",
        producers.len(),
        out.stdout
    );
    let (resource, _) = &spans[0];
    assert!(resource.contains(&("service.name".into(), "example_channel_node".into())));
    assert!(
        resource.contains(&("sn".into(), "123456".into())),
        "{resource:?}"
    );
    let first = producers
        .iter()
        .find(|s| attr(s, "msg_data").is_some_and(|d| d.contains("count: 1")))
        .expect("the first message's producer span");
    assert_eq!(
        first.name,
        "test_topic/pb:aimrt.protocols.example.ExampleEventMsg"
    );
    assert_eq!(attr(first, "module_name"), Some("NormalPublisherModule"));
    assert_eq!(first.trace_id.len(), 16);
    assert_eq!(first.span_id.len(), 8);
    assert!(first.parent_span_id.is_empty(), "a new trace: no parent");
    assert!(first.end_time_unix_nano >= first.start_time_unix_nano);
    // Its subscriber's span: the same trace, the producer its parent.
    let consumer = spans
        .iter()
        .map(|(_, s)| s)
        .find(|s| s.kind == 5 && s.parent_span_id == first.span_id)
        .expect("the consumer span of the first message");
    assert_eq!(consumer.trace_id, first.trace_id);
    assert_eq!(
        attr(consumer, "module_name"),
        Some("NormalSubscriberModule")
    );
    assert!(attr(consumer, "msg_data").is_some_and(|d| d.contains("count: 1")));
    let traceparent = attr(consumer, "aimrt_otp-traceparent").expect("the context's traceparent");
    assert!(traceparent.starts_with("00-"), "{traceparent}");
    assert!(
        out.stdout
            .contains(" 0 dropped at a full queue, 0 in requests that failed"),
        "{}",
        out.stdout
    );
}

#[test]
fn a_call_is_a_client_span_and_its_server_child_with_the_request_and_the_response() {
    let collector = Collector::start(200);
    let out = run(
        "opentelemetry_plugin_pb_rpc",
        &collector.url,
        |c| c.replace("rpc_frq: 0.5", "rpc_frq: 5"),
        3,
    );
    let spans: Vec<Span> = collector.spans().into_iter().map(|(_, s)| s).collect();
    let client = spans
        .iter()
        .find(|s| s.kind == 3)
        .unwrap_or_else(|| panic!("no client span\n{}", out.stdout));
    assert_eq!(
        client.name,
        "pb:/aimrt.protocols.example.ExampleService/GetFooData"
    );
    assert_eq!(client.status.as_ref().map(|s| s.code), Some(1));
    assert!(attr(client, "req_data").is_some_and(|d| d.contains("hello world foo")));
    assert!(attr(client, "rsp_data").is_some_and(|d| d.contains("echo hello world foo")));
    let server = spans
        .iter()
        .find(|s| s.kind == 2 && s.parent_span_id == client.span_id)
        .expect("the server span of the client's call");
    assert_eq!(server.trace_id, client.trace_id);
    assert_eq!(attr(server, "module_name"), Some("NormalRpcCoServerModule"));
    assert_eq!(server.status.as_ref().map(|s| s.code), Some(1));
}

#[test]
fn spans_a_collector_refuses_or_cannot_take_are_counted_and_the_process_ends_well() {
    let refusing = Collector::start(500);
    let out = run(
        "opentelemetry_plugin_pb_chn",
        &refusing.url,
        |c| c.replace("channel_frq: 0.5", "channel_frq: 5"),
        2,
    );
    assert!(
        out.stdout.contains("the collector answered 500"),
        "{}",
        out.stdout
    );
    assert!(
        !out.stdout.contains(" 0 in requests that failed"),
        "{}",
        out.stdout
    );
    // Nothing listens there.
    let port = aimrt_e2e::free_port(false);
    let out = run(
        "opentelemetry_plugin_pb_chn",
        &format!("http://127.0.0.1:{port}/v1/traces"),
        |c| c.replace("channel_frq: 0.5", "channel_frq: 5"),
        2,
    );
    assert!(out.stdout.contains("cannot connect"), "{}", out.stdout);
    assert!(
        !out.stdout.contains(" 0 in requests that failed"),
        "{}",
        out.stdout
    );
}

#[test]
fn messages_without_a_trace_pass_untouched_unless_the_context_asks() {
    let collector = Collector::start(200);
    // force_trace off, and no context asks: no span at all.
    let out = run(
        "opentelemetry_plugin_pb_chn",
        &collector.url,
        |c| {
            c.replace("force_trace: true", "force_trace: false")
                .replace("channel_frq: 0.5", "channel_frq: 5")
        },
        2,
    );
    assert!(
        out.stdout.contains("Receive new pb event"),
        "{}",
        out.stdout
    );
    assert!(collector.spans().is_empty());
    // The publisher's context asks for a trace.
    let out = run(
        "opentelemetry_plugin_pb_chn",
        &collector.url,
        |c| {
            c.replace("force_trace: true", "force_trace: false")
                .replace(
                    "  channel_frq: 0.5",
                    "  channel_frq: 5\n  context_meta:\n    aimrt_otp-start_new_trace: \"TRUE\"",
                )
        },
        2,
    );
    assert!(
        out.stdout.contains("Receive new pb event"),
        "{}",
        out.stdout
    );
    let spans = collector.spans();
    assert!(spans.iter().any(|(_, s)| s.kind == 4), "{}", out.stdout);
    assert!(spans.iter().any(|(_, s)| s.kind == 5), "{}", out.stdout);
}

#[test]
fn bad_options_stop_start_up_with_a_message_naming_them() {
    for (from, to, expected) in [
        (
            "node_name: example_channel_node",
            "node_name: \"\"",
            "node_name is empty",
        ),
        (
            "${AIMRT_OTLP_TRACES_URL:-http://localhost:4318/v1/traces}",
            "https://collector:4318/v1/traces",
            "https is not supported",
        ),
        (
            "force_trace: true",
            "force_trace: true\n          metrics_otlp_http_exporter_url: http://localhost:4318/v1/metrics",
            "exports traces only",
        ),
    ] {
        let cfg = repo_config("opentelemetry_plugin_pb_chn").replace(from, to);
        let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        aimrt_e2e::assert_failure(&out, &[expected, "cfg.yaml:"]);
    }
}
