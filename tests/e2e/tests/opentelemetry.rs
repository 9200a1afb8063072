//! opentelemetry_plugin's trace filters under `aimrt_main`, AimRT's two examples
//! (`config/opentelemetry_plugin_pb_<chn|rpc>.yaml`), sending to a collector of the test's
//! own (an HTTP server that keeps each OTLP request): the spans, their parents across the
//! publisher and the subscriber, the client and the server, their attributes; a collector
//! that refuses or is not there; an `https://` collector, trusted or not; bad options.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_e2e::{repo_config, run_main, Output, Running};
use aimrt_mqtt::test_broker::{TlsFiles, TlsFront};
use aimrt_opentelemetry::otlp::{
    ExportMetricsServiceRequest, ExportTraceServiceRequest, Metric, MetricData, Span,
};
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
    /// Where it takes spans (`/v1/traces`); `/v1/metrics` takes metrics.
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

    fn metrics_url(&self) -> String {
        self.url.replace("/v1/traces", "/v1/metrics")
    }

    /// The metrics of the last metrics request.
    fn last_metrics(&self) -> Vec<Metric> {
        let got = self.got.lock().unwrap();
        let (_, ct, body) = got
            .iter()
            .rev()
            .find(|(path, _, _)| path == "/v1/metrics")
            .expect("a metrics request");
        assert_eq!(ct, "application/x-protobuf");
        let req = ExportMetricsServiceRequest::decode(&body[..]).expect("an OTLP metrics request");
        req.resource_metrics
            .into_iter()
            .flat_map(|r| r.scope_metrics)
            .flat_map(|s| s.metrics)
            .collect()
    }

    /// Every span received, with its request's resource attributes.
    fn spans(&self) -> Vec<(Vec<(String, String)>, Span)> {
        let mut out = Vec::new();
        for (path, ct, body) in self.got.lock().unwrap().iter() {
            if path != "/v1/traces" {
                continue;
            }
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

/// `cfg` with every collector URL (traces or metrics) made `url`: no port of the example
/// configs is kept.
fn with_collector(cfg: &str, url: &str) -> String {
    cfg.lines()
        .map(|l| {
            let indent = &l[..l.len() - l.trim_start().len()];
            match l.trim_start().split_once(':') {
                Some((
                    key @ ("trace_otlp_http_exporter_url" | "metrics_otlp_http_exporter_url"),
                    _,
                )) => {
                    format!("{indent}{key}: {url}\n")
                }
                _ => format!("{l}\n"),
            }
        })
        .collect()
}

/// `config/<name>.yaml` sending to `url` (spans or metrics), run for `secs` seconds.
fn run(name: &str, url: &str, edit: impl FnOnce(String) -> String, secs: u32) -> Output {
    let cfg = with_collector(&edit(repo_config(name)), url);
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
    // Every case stops before a span is sent; the URL names a free port all the same.
    let url = format!("http://127.0.0.1:{}/v1/traces", aimrt_e2e::free_port(false));
    let cases = [
        (
            "node_name: example_channel_node",
            "node_name: \"\"",
            "node_name is empty",
        ),
        (
            url.as_str(),
            "grpc://collector:4317",
            "is not an http:// or https:// URL",
        ),
        (
            "force_trace: true",
            "force_trace: true\n          rpc_time_cost_histogram_boundaries: [10, 5]",
            "must be finite numbers in strictly increasing order",
        ),
        (
            "force_trace: true",
            "force_trace: true\n          metrics_otlp_http_exporter_url: http://collector/v1/metrics\n          metrics_export_interval_ms: 0",
            "metrics_export_interval_ms must be at least 1",
        ),
    ];
    for (from, to, expected) in cases {
        let cfg =
            with_collector(&repo_config("opentelemetry_plugin_pb_chn"), &url).replace(from, to);
        assert!(cfg.contains(to), "{from} not in the config");
        let out = run_main(Some(&cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        aimrt_e2e::assert_failure(&out, &[expected, "cfg.yaml:"]);
    }
}

/// The integer value of `name`'s point whose labels include every one of `labels`.
fn sum_of(metrics: &[Metric], name: &str, labels: &[(&str, &str)]) -> Option<i64> {
    let m = metrics.iter().find(|m| m.name == name)?;
    let Some(MetricData::Sum(sum)) = &m.data else {
        panic!("{name} is not a sum: {m:?}")
    };
    assert!(
        sum.is_monotonic && sum.aggregation_temporality == 2,
        "{m:?}"
    );
    sum.data_points
        .iter()
        .find(|p| {
            labels.iter().all(|(k, v)| {
                p.attributes
                    .iter()
                    .any(|kv| kv.key == *k && kv.as_text() == Some(v))
            })
        })
        .map(|p| p.as_int)
}

#[test]
fn channel_metrics_count_every_message_and_its_bytes_by_topic_and_module() {
    let collector = Collector::start(200);
    let out = run(
        "opentelemetry_plugin_pb_chn_metrics",
        &collector.metrics_url(),
        |c| {
            c.replace("channel_frq: 0.5", "channel_frq: 10").replace(
                "          attributes:",
                "          metrics_export_interval_ms: 500\n          attributes:",
            )
        },
        3,
    );
    // The last export comes at shutdown, after every message.
    let published = aimrt_e2e::number_after(&out.stdout, "Channel topic 'test_topic': published ");
    let delivered = aimrt_e2e::number_after(&out.stdout, "delivered ");
    assert!(published >= 10, "{}", out.stdout);
    let metrics = collector.last_metrics();
    let topic = [
        ("topic_name", "test_topic"),
        ("msg_type", "pb:aimrt.protocols.example.ExampleEventMsg"),
    ];
    let pub_labels = [topic[0], topic[1], ("module_name", "NormalPublisherModule")];
    let sub_labels = [
        topic[0],
        topic[1],
        ("module_name", "NormalSubscriberModule"),
    ];
    assert_eq!(
        sum_of(&metrics, "chn.pub.msg_num", &pub_labels),
        Some(published as i64)
    );
    assert_eq!(
        sum_of(&metrics, "chn.sub.msg_num", &sub_labels),
        Some(delivered as i64)
    );
    let bytes = sum_of(
        &metrics,
        "chn.pub.msg_size",
        &[pub_labels[2], ("serialization_type", "pb")],
    )
    .expect("the published bytes");
    // ExampleEventMsg{msg: "count: n", num: n}: at least 12 bytes each.
    assert!(
        bytes >= 12 * published as i64,
        "{bytes} bytes for {published} messages"
    );
    let size = metrics
        .iter()
        .find(|m| m.name == "chn.pub.msg_size")
        .unwrap();
    assert_eq!(size.unit, "bytes");
    assert!(
        out.stdout.contains("opentelemetry_plugin: ")
            && out.stdout.contains(" metrics exports sent, 0 failed"),
        "{}",
        out.stdout
    );
}

#[test]
fn rpc_metrics_count_calls_by_status_and_time_them_in_the_configured_buckets() {
    let collector = Collector::start(200);
    let out = run(
        "opentelemetry_plugin_pb_rpc_metrics",
        &collector.metrics_url(),
        |c| c.replace("rpc_frq: 0.5", "rpc_frq: 5"),
        3,
    );
    let calls = out
        .stdout
        .matches("Client get rpc ret, status: suc")
        .count() as i64;
    assert!(calls >= 5, "{}", out.stdout);
    let metrics = collector.last_metrics();
    let func = (
        "func_name",
        "pb:/aimrt.protocols.example.ExampleService/GetFooData",
    );
    let client = [
        ("module_name", "NormalRpcCoClientModule"),
        func,
        ("status", "OK"),
    ];
    let server = [
        ("module_name", "NormalRpcCoServerModule"),
        func,
        ("status", "OK"),
    ];
    assert_eq!(
        sum_of(&metrics, "rpc.client.invoke_num", &client),
        Some(calls)
    );
    assert_eq!(
        sum_of(&metrics, "rpc.server.invoke_num", &server),
        Some(calls)
    );
    assert!(sum_of(&metrics, "rpc.client.req_size", &client).unwrap() > 0);
    assert!(sum_of(&metrics, "rpc.server.rsp_size", &server).unwrap() > 0);
    let time = metrics
        .iter()
        .find(|m| m.name == "rpc.client.time_cost")
        .unwrap();
    assert_eq!(time.unit, "us");
    let Some(MetricData::Histogram(h)) = &time.data else {
        panic!("{time:?}")
    };
    let p = &h.data_points[0];
    assert_eq!(p.count as i64, calls);
    assert_eq!(p.explicit_bounds, [0.0, 50.0, 150.0, 350.0, 750.0, 1350.0]);
    assert_eq!(p.bucket_counts.iter().sum::<u64>(), p.count);
    assert!(p.min.unwrap() > 0.0 && p.max.unwrap() >= p.min.unwrap());
}

/// `cfg` (a net_plugin example) with opentelemetry_plugin as `node` sending to `url`, and
/// `otp_trace` on its topics.
fn traced(cfg: &str, node: &str, url: &str) -> String {
    let plugin = format!(
        "    plugins:\n      - name: opentelemetry_plugin\n        path: ${{AIMRT_LIB_DIR}}/libaimrt_opentelemetry_plugin.so\n        options:\n          node_name: {node}\n          trace_otlp_http_exporter_url: {url}\n          force_trace: true\n"
    );
    let out = cfg.replacen("    plugins:\n", &plugin, 1).replace(
        "        enable_backends: [tcp]\n",
        "        enable_backends: [tcp]\n        enable_filters: [otp_trace]\n",
    );
    assert!(out.contains("enable_filters: [otp_trace]"), "{out}");
    out
}

/// The trace crosses processes in the context's meta (net_plugin's tcp carries it): the
/// subscriber process's consumer span is the child of the publisher process's producer
/// span, in the same trace.
#[test]
fn a_trace_crosses_from_a_publisher_process_to_a_subscriber_process() {
    let collector = Collector::start(200);
    let port = aimrt_e2e::free_port(false);
    let wait = Duration::from_secs(30);
    let mut sub = aimrt_e2e::Running::start(&traced(
        &aimrt_e2e::net_example("pb_chn_tcp_sub", port),
        "sub_node",
        &collector.url,
    ));
    sub.wait_for("Module manager start completed.", wait);
    let mut publisher = aimrt_e2e::Running::start(&traced(
        &aimrt_e2e::net_example("pb_chn_tcp_pub", port)
            .replace("channel_frq: 0.5", "channel_frq: 5"),
        "pub_node",
        &collector.url,
    ));
    sub.wait_for(r#""num":3}"#, wait);
    assert_eq!(publisher.interrupt(wait), Some(0));
    assert_eq!(sub.interrupt(wait), Some(0));
    let spans = collector.spans();
    let service = |resource: &[(String, String)]| {
        resource
            .iter()
            .find(|(k, _)| k == "service.name")
            .map(|(_, v)| v.clone())
            .unwrap_or_default()
    };
    let producers: Vec<&Span> = spans
        .iter()
        .filter(|(r, s)| service(r) == "pub_node" && s.kind == 4)
        .map(|(_, s)| s)
        .collect();
    let consumers: Vec<&Span> = spans
        .iter()
        .filter(|(r, s)| service(r) == "sub_node" && s.kind == 5)
        .map(|(_, s)| s)
        .collect();
    assert!(consumers.len() >= 3, "{} consumer spans", consumers.len());
    for c in &consumers {
        let parent = producers
            .iter()
            .find(|p| p.span_id == c.parent_span_id)
            .unwrap_or_else(|| panic!("no producer span is the parent of {c:?}"));
        assert_eq!(parent.trace_id, c.trace_id);
    }
}

/// The channel example sending spans to `url`, trusting the CAs of `cas` (as the
/// system's, through `SSL_CERT_FILE`), for about 2 s; its output.
fn run_trusting(url: &str, cas: &str) -> String {
    let cfg = with_collector(
        &repo_config("opentelemetry_plugin_pb_chn").replace("channel_frq: 0.5", "channel_frq: 5"),
        url,
    );
    // `SSL_CERT_DIR` emptied: the machine's own CAs (some set it) stay out of the test.
    let env = [
        ("SSL_CERT_FILE".to_owned(), aimrt_e2e::tls_file(cas)),
        ("SSL_CERT_DIR".to_owned(), String::new()),
    ];
    let mut running = Running::start_env(&cfg, &env);
    running.wait_for("Module manager start completed.", LIMIT);
    std::thread::sleep(Duration::from_millis(2500));
    assert_eq!(running.interrupt(LIMIT), Some(0));
    running.text()
}

#[test]
fn spans_reach_an_https_collector_and_one_whose_certificate_no_trusted_ca_signed_gets_none() {
    let collector = Collector::start(200);
    let plain: std::net::SocketAddr = collector.url["http://".len()..]
        .split('/')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let files = TlsFiles {
        cert: aimrt_e2e::tls_file("broker.pem"),
        key: aimrt_e2e::tls_file("broker.key"),
        client_ca: String::new(),
    };
    let front = TlsFront::start("127.0.0.1:0", &files, plain).unwrap();
    let url = format!("https://{}/v1/traces", front.addr());
    let text = run_trusting(&url, "ca.pem");
    let spans = collector.spans();
    assert!(spans.len() >= 5, "{} spans\n{text}", spans.len());
    assert!(
        text.contains(" 0 dropped at a full queue, 0 in requests that failed"),
        "{text}"
    );
    // Another CA: the handshake fails, nothing is sent, every span is counted.
    let before = collector.got.lock().unwrap().len();
    let text = run_trusting(&url, "other_ca.pem");
    assert!(
        text.contains(&format!(
            "not exported to {url}: TLS handshake failed: invalid peer certificate: UnknownIssuer"
        )),
        "{text}"
    );
    assert!(text.contains(" 0 exported,"), "{text}");
    assert_eq!(collector.got.lock().unwrap().len(), before);
    // No CA at all (a file without a certificate): start-up stops, saying what to do.
    let dir = tempfile::tempdir().unwrap();
    let cfg = with_collector(&repo_config("opentelemetry_plugin_pb_chn"), &url);
    std::fs::write(dir.path().join("cfg.yaml"), cfg).unwrap();
    let out = aimrt_e2e::run_main_after(
        dir.path(),
        &format!(
            "export SSL_CERT_FILE='{}' SSL_CERT_DIR=",
            aimrt_e2e::tls_file("ca.key")
        ),
        &["--cfg_file_path=./cfg.yaml"],
        LIMIT,
    );
    aimrt_e2e::assert_failure(
        &out,
        &[
            "trace_otlp_http_exporter_url",
            "no CA certificate found on this system",
            "SSL_CERT_FILE",
            "cfg.yaml:",
        ],
    );
}
