//! `opentelemetry_plugin`: AimRT's trace and metrics filters. With
//! `trace_otlp_http_exporter_url` set, it registers the channel filters (publish and
//! subscribe) and the RPC filters (client and server) `otp_trace` and `otp_simple_trace`;
//! a message or call they see becomes a span, sent to an OpenTelemetry collector over
//! OTLP/HTTP (protobuf, [`otlp`]), with the trace carried in the context's meta
//! ([`trace`]) from publisher to subscriber and from client to server, also between
//! processes. With `metrics_otlp_http_exporter_url` set, it registers `otp_metrics`:
//! AimRT's counters and call-time histograms, sent every `metrics_export_interval_ms`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: opentelemetry_plugin
//!         path: ./target/debug/libaimrt_opentelemetry_plugin.so
//!         options:
//!           node_name: example_channel_node          # service.name of the spans
//!           trace_otlp_http_exporter_url: http://localhost:4318/v1/traces
//!           force_trace: true                         # every message and call is traced
//!           attributes: [{key: sn, val: 123456}]      # added to the resource
//!   channel:
//!     pub_topics_options:
//!       - topic_name: "(.*)"
//!         enable_backends: [local]
//!         enable_filters: [otp_trace]
//! ```
//!
//! `otp_trace` adds the message (or the request and the response) as JSON to the span;
//! `otp_simple_trace` does not. A filter starts a span when `force_trace` is set, when
//! the context says `aimrt_otp-start_new_trace: true`, or when the context carries a
//! trace (`aimrt_otp-traceparent`); otherwise it passes the message on untouched.
#![deny(unsafe_code)]

pub mod exporter;
mod metrics;
pub mod otlp;
pub mod trace;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::{FilterSide, Next, Publication};
use aimrt_plugin_api::ffi::{formats_of, type_name_of, RawMessage};
use aimrt_plugin_api::rpc::{CallFilterSide, CallNext, FilterCall};
use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar};
use serde::Deserialize;

use crate::exporter::{Endpoint, Exporter};
use crate::metrics::{Def, Labels, Meter, MetricsExporter};
use crate::otlp::{KeyValue, Span, SpanKind, Status};
use crate::trace::{
    new_span_id, new_trace_id, now_ns, TraceParent, KEY_START_NEW_TRACE, KEY_TRACEPARENT,
    KEY_TRACESTATE,
};

/// `attributes[i]`: added to every span's resource.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Attribute {
    key: String,
    /// Text, or a number or boolean written as text (AimRT's examples write `val: 123456`).
    #[serde(deserialize_with = "scalar_text")]
    val: String,
}

fn scalar_text<'de, D: serde::Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Scalar {
        Text(String),
        Int(i64),
        Float(f64),
        Bool(bool),
    }
    Ok(match Scalar::deserialize(d)? {
        Scalar::Text(s) => s,
        Scalar::Int(i) => i.to_string(),
        Scalar::Float(f) => f.to_string(),
        Scalar::Bool(b) => b.to_string(),
    })
}

/// The plugin's options (AimRT's keys).
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    node_name: String,
    #[serde(default)]
    trace_otlp_http_exporter_url: String,
    #[serde(default)]
    force_trace: bool,
    #[serde(default)]
    metrics_otlp_http_exporter_url: String,
    #[serde(default)]
    metrics_export_interval_ms: Option<u32>,
    #[serde(default)]
    metrics_export_timeout_ms: Option<u32>,
    /// The call-time histograms' bucket bounds, in µs (a later AimRT's key).
    #[serde(default)]
    rpc_time_cost_histogram_boundaries: Option<Vec<f64>>,
    #[serde(default)]
    attributes: Vec<Attribute>,
}

struct OtelPlugin {
    exporter: Mutex<Option<Arc<Exporter>>>,
    /// The metrics exporter and its export timeout.
    metrics: Mutex<Option<(MetricsExporter, Duration)>>,
}

impl OtelPlugin {
    /// Starts the exporters of the halves that are on and registers their filters.
    fn start_exporters(
        &self,
        registrar: &mut Registrar<'_>,
        o: &Options,
        resource: Vec<KeyValue>,
        traces: Option<Endpoint>,
        metrics: Option<(Endpoint, Meter, Duration, Duration)>,
    ) -> Result<(), Error> {
        if let Some(endpoint) = traces {
            let exporter = Arc::new(
                Exporter::start(endpoint, resource.clone(), o.node_name.clone())
                    .map_err(Error::msg)?,
            );
            *lock(&self.exporter) = Some(exporter.clone());
            let tracer = Arc::new(Tracer {
                exporter,
                force: o.force_trace,
            });
            register_trace_filters(registrar, &tracer)?;
        }
        if let Some((endpoint, meter, interval, timeout)) = metrics {
            let meter = Arc::new(meter);
            let exporter = MetricsExporter::start(
                meter.clone(),
                endpoint,
                resource,
                o.node_name.clone(),
                interval,
                timeout,
            )
            .map_err(Error::msg)?;
            *lock(&self.metrics) = Some((exporter, timeout));
            register_metrics_filters(registrar, &meter)?;
        }
        Ok(())
    }
}

impl Plugin for OtelPlugin {
    fn name(&self) -> &str {
        "opentelemetry_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: Options = registrar.read_options(options)?;
        if o.node_name.is_empty() {
            return Err(options.invalid(
                "node_name is empty: it names this process in the collector (service.name)",
            ));
        }
        // Every option is checked, also those of a half that is off.
        let ms = |v: Option<u32>, default: u32, key: &str| match v.unwrap_or(default) {
            0 => Err(options.invalid(format!("{key} must be at least 1"))),
            n => Ok(Duration::from_millis(n.into())),
        };
        let interval = ms(
            o.metrics_export_interval_ms,
            15_000,
            "metrics_export_interval_ms",
        )?;
        let timeout = ms(
            o.metrics_export_timeout_ms,
            5_000,
            "metrics_export_timeout_ms",
        )?;
        let bounds = o
            .rpc_time_cost_histogram_boundaries
            .clone()
            .unwrap_or_else(|| metrics::BOUNDS.to_vec());
        let meter = Meter::new(bounds)
            .map_err(|e| options.invalid(format!("rpc_time_cost_histogram_boundaries {e}")))?;
        let endpoint = |url: &str, key: &str| {
            let e = Endpoint::parse(url).map_err(|e| options.invalid(format!("{key} {e}")))?;
            if e.tls {
                // The CAs are read now: a system without them stops start-up, not every request.
                exporter::tls().map_err(|why| options.invalid(format!("{key} '{url}': {why}")))?;
            }
            Ok(e)
        };
        let traces = (!o.trace_otlp_http_exporter_url.is_empty())
            .then(|| {
                endpoint(
                    &o.trace_otlp_http_exporter_url,
                    "trace_otlp_http_exporter_url",
                )
            })
            .transpose()?;
        let metrics = (!o.metrics_otlp_http_exporter_url.is_empty())
            .then(|| {
                endpoint(
                    &o.metrics_otlp_http_exporter_url,
                    "metrics_otlp_http_exporter_url",
                )
            })
            .transpose()?;
        if traces.is_none() && metrics.is_none() {
            tracing::warn!(target: "aimrt", "opentelemetry_plugin: neither trace_otlp_http_exporter_url nor metrics_otlp_http_exporter_url is set: no filter is registered");
            return Ok(());
        }
        let mut resource = vec![KeyValue::text("service.name", &o.node_name)];
        resource.extend(o.attributes.iter().map(|a| KeyValue::text(&a.key, &a.val)));
        let registered = self.start_exporters(
            registrar,
            &o,
            resource,
            traces,
            metrics.map(|e| (e, meter, interval, timeout)),
        );
        if registered.is_err() {
            self.shutdown();
        }
        registered
    }

    fn shutdown(&mut self) {
        if let Some(exporter) = lock(&self.exporter).take() {
            exporter.close();
        }
        if let Some((exporter, timeout)) = lock(&self.metrics).take() {
            exporter.close(timeout);
        }
    }
}

/// The plugin, as `libaimrt_opentelemetry_plugin.so` exports it (`plugins/opentelemetry/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(OtelPlugin {
        exporter: Mutex::new(None),
        metrics: Mutex::new(None),
    })
}

/// The guard of `m`, also after a thread panicked holding it.
pub(crate) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// What the filters share.
struct Tracer {
    exporter: Arc<Exporter>,
    force: bool,
}

/// The span a filter starts, once it knows it traces.
struct Started {
    trace: TraceParent,
    parent: Option<[u8; 8]>,
    trace_state: String,
    start: u64,
}

impl Tracer {
    /// Whether to trace, from the options and the context: the span to start (a child of
    /// the context's trace, or a new trace), or `None`.
    fn begin<'a>(&self, get: impl Fn(&str) -> Option<&'a str>) -> Option<Started> {
        let parent = get(KEY_TRACEPARENT).and_then(TraceParent::parse);
        let asked = get(KEY_START_NEW_TRACE).is_some_and(|v| v.eq_ignore_ascii_case("true"));
        if !(self.force || asked || parent.is_some()) {
            return None;
        }
        Some(Started {
            trace: TraceParent {
                trace_id: parent.map_or_else(new_trace_id, |p| p.trace_id),
                span_id: new_span_id(),
                flags: parent.map_or(1, |p| p.flags),
            },
            parent: parent.map(|p| p.span_id),
            trace_state: get(KEY_TRACESTATE).unwrap_or("").to_owned(),
            start: now_ns(),
        })
    }

    /// Ends `s` now and queues it.
    fn end(
        &self,
        s: &Started,
        name: String,
        kind: SpanKind,
        attributes: Vec<KeyValue>,
        status: Option<Status>,
    ) {
        self.exporter.record(Span {
            trace_id: s.trace.trace_id.to_vec(),
            span_id: s.trace.span_id.to_vec(),
            trace_state: s.trace_state.clone(),
            parent_span_id: s.parent.map(|p| p.to_vec()).unwrap_or_default(),
            name,
            kind: kind as i32,
            start_time_unix_nano: s.start,
            end_time_unix_nano: now_ns(),
            attributes,
            status,
            flags: u32::from(s.trace.flags),
        });
    }
}

/// `module_name` and every pair of the context, as AimRT puts them on a span.
fn attributes<'a>(module: &str, meta: impl Iterator<Item = (&'a str, &'a str)>) -> Vec<KeyValue> {
    let mut out = vec![KeyValue::text("module_name", module)];
    out.extend(meta.map(|(k, v)| KeyValue::text(k, v)));
    out
}

/// A message or request as JSON text, for `otp_trace` (`None`: it has no JSON form).
fn json_of(message: &aimrt_plugin_api::ffi::RawMessage) -> Option<String> {
    let mut out = Vec::new();
    message.encode_into("json", &mut out).ok()?;
    String::from_utf8(out).ok().filter(|s| !s.is_empty())
}

fn error_status(why: String) -> Status {
    Status {
        message: why,
        code: 2,
    }
}

fn register_trace_filters(
    registrar: &mut Registrar<'_>,
    tracer: &Arc<Tracer>,
) -> Result<(), Error> {
    for (name, upload) in [("otp_trace", true), ("otp_simple_trace", false)] {
        for side in [FilterSide::Publish, FilterSide::Subscribe] {
            let t = tracer.clone();
            registrar.register_channel_filter(
                name,
                side,
                move |msg: &Publication<'_>, next: Next<'_>| {
                    trace_message(&t, side, upload, msg, next)
                },
            )?;
        }
        for side in [CallFilterSide::Client, CallFilterSide::Server] {
            let t = tracer.clone();
            registrar.register_rpc_filter(
                name,
                side,
                move |call: &FilterCall<'_>, next: CallNext<'_>| {
                    trace_call(&t, side, upload, call, next)
                },
            )?;
        }
    }
    Ok(())
}

/// A channel message: its span covers passing it on (to the backends, or to the
/// subscriber); the context passed on names it as the parent of what follows.
fn trace_message(
    t: &Tracer,
    side: FilterSide,
    upload: bool,
    msg: &Publication<'_>,
    next: Next<'_>,
) -> Result<(), String> {
    let Some(s) = t.begin(|k| msg.get(k)) else {
        return next.pass();
    };
    let mut ctx = next.context();
    if t.force {
        ctx.set(KEY_START_NEW_TRACE, "true");
    }
    ctx.set(KEY_TRACEPARENT, &s.trace.to_string());
    let mut attrs = attributes(msg.module(), ctx.iter());
    if upload {
        if let Some(json) = json_of(msg.message()) {
            attrs.push(KeyValue::text("msg_data", &json));
        }
    }
    let result = next.pass_with(&ctx);
    let kind = match side {
        FilterSide::Publish => SpanKind::Producer,
        FilterSide::Subscribe => SpanKind::Consumer,
    };
    let name = format!(
        "{}/{}",
        msg.topic(),
        type_name_of(msg.message().type_support())
    );
    let status = result.as_ref().err().map(|e| error_status(e.clone()));
    t.end(&s, name, kind, attrs, status);
    result
}

/// An RPC call: its span covers the call until its answer; the context passed on names
/// it as the server's parent.
fn trace_call(
    t: &Arc<Tracer>,
    side: CallFilterSide,
    upload: bool,
    call: &FilterCall<'_>,
    next: CallNext<'_>,
) -> Result<(), String> {
    let Some(s) = t.begin(|k| call.get(k)) else {
        return next.pass();
    };
    let mut ctx = next.context();
    if t.force {
        ctx.set_meta(KEY_START_NEW_TRACE, "true");
    }
    ctx.set_meta(KEY_TRACEPARENT, &s.trace.to_string());
    let mut attrs = attributes(call.module(), ctx.meta_pairs());
    if upload {
        if let Some(json) = json_of(call.request()) {
            attrs.push(KeyValue::text("req_data", &json));
        }
    }
    let kind = match side {
        CallFilterSide::Client => SpanKind::Client,
        CallFilterSide::Server => SpanKind::Server,
    };
    let name = call.func().to_owned();
    let tracer = t.clone();
    next.on_reply(move |reply| {
        let status = reply.status();
        let mut attrs = attrs;
        if upload {
            if let Some(json) = reply.response().and_then(json_of) {
                attrs.push(KeyValue::text("rsp_data", &json));
            }
        }
        let span_status = if status.is_ok() {
            Status {
                message: String::new(),
                code: 1,
            }
        } else {
            error_status(status.to_string())
        };
        tracer.end(&s, name, kind, attrs, Some(span_status));
    })
    .pass_with(&ctx)
}

/// The message's encoded size in its context's serialization type (else its type's
/// first), and that type; 0 when it cannot be encoded.
fn size_of(message: &RawMessage, format: Option<&str>) -> (u64, String) {
    let format = format
        .map(str::to_owned)
        .or_else(|| formats_of(message.type_support()).into_iter().next())
        .unwrap_or_default();
    let size = message.encode(&format).map_or(0, |b| b.len() as u64);
    (size, format)
}

fn register_metrics_filters(
    registrar: &mut Registrar<'_>,
    meter: &Arc<Meter>,
) -> Result<(), Error> {
    use crate::metrics::*;
    for (side, num, size) in [
        (FilterSide::Publish, CHN_PUB_NUM, CHN_PUB_SIZE),
        (FilterSide::Subscribe, CHN_SUB_NUM, CHN_SUB_SIZE),
    ] {
        let m = meter.clone();
        registrar.register_channel_filter(
            "otp_metrics",
            side,
            move |msg: &Publication<'_>, next: Next<'_>| {
                let result = next.pass();
                count_message(&m, (num, size), msg);
                result
            },
        )?;
    }
    for (side, defs) in [
        (
            CallFilterSide::Client,
            [
                RPC_CLI_NUM,
                RPC_CLI_REQ_SIZE,
                RPC_CLI_RSP_SIZE,
                RPC_CLI_TIME,
            ],
        ),
        (
            CallFilterSide::Server,
            [
                RPC_SVR_NUM,
                RPC_SVR_REQ_SIZE,
                RPC_SVR_RSP_SIZE,
                RPC_SVR_TIME,
            ],
        ),
    ] {
        let m = meter.clone();
        registrar.register_rpc_filter(
            "otp_metrics",
            side,
            move |call: &FilterCall<'_>, next: CallNext<'_>| count_call(&m, defs, call, next),
        )?;
    }
    Ok(())
}

/// One message: counted, and its size added, by topic, type and module.
fn count_message(m: &Meter, (num, size): (Def, Def), msg: &Publication<'_>) {
    let ts = msg.message().type_support();
    let mut labels: Labels = vec![
        ("topic_name", msg.topic().to_owned()),
        ("msg_type", type_name_of(ts).to_owned()),
        ("module_name", msg.module().to_owned()),
    ];
    m.add(num, labels.clone(), 1);
    let (bytes, format) = size_of(msg.message(), msg.get("aimrt-serialization_type"));
    labels.push(("serialization_type", format));
    m.add(size, labels, bytes);
}

/// One call: when answered, counted with its status, its sizes added and its time
/// (from this filter to the answer) recorded.
fn count_call(
    m: &Arc<Meter>,
    [num, req_size, rsp_size, time]: [Def; 4],
    call: &FilterCall<'_>,
    next: CallNext<'_>,
) -> Result<(), String> {
    let began = Instant::now();
    let format = call.get("aimrt-serialization_type").map(str::to_owned);
    let (req_bytes, _) = size_of(call.request(), format.as_deref());
    let module = call.module().to_owned();
    let func = call.func().to_owned();
    let meter = m.clone();
    next.on_reply(move |reply| {
        let us = began.elapsed().as_secs_f64() * 1e6;
        let labels: Labels = vec![
            ("module_name", module),
            ("func_name", func),
            ("status", reply.status().text().to_owned()),
        ];
        let rsp_bytes = reply
            .response()
            .map_or(0, |r| size_of(r, format.as_deref()).0);
        meter.record(time, labels.clone(), us);
        meter.add(num, labels.clone(), 1);
        meter.add(req_size, labels.clone(), req_bytes);
        meter.add(rsp_size, labels, rsp_bytes);
    })
    .pass()
}
