//! `opentelemetry_plugin`: AimRT's trace filters. With `trace_otlp_http_exporter_url` set,
//! it registers the channel filters (publish and subscribe) and the RPC filters (client
//! and server) `otp_trace` and `otp_simple_trace`; a message or call they see becomes a
//! span, sent to an OpenTelemetry collector over OTLP/HTTP (protobuf,
//! [`otlp`]), with the trace carried in the context's meta ([`trace`]) from publisher to
//! subscriber and from client to server, also between processes.
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
pub mod otlp;
pub mod trace;

use std::sync::{Arc, Mutex};

use aimrt_plugin_api::channel::{FilterSide, Next, Publication};
use aimrt_plugin_api::ffi::type_name_of;
use aimrt_plugin_api::rpc::{CallFilterSide, CallNext, FilterCall};
use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar};
use serde::Deserialize;

use crate::exporter::{Endpoint, Exporter};
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
    #[serde(default)]
    attributes: Vec<Attribute>,
}

struct OtelPlugin {
    exporter: Mutex<Option<Arc<Exporter>>>,
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
        if !o.metrics_otlp_http_exporter_url.is_empty() {
            return Err(options.invalid(
                "metrics_otlp_http_exporter_url is set, but this opentelemetry_plugin exports traces only (no otp_metrics filter); leave it out",
            ));
        }
        if o.trace_otlp_http_exporter_url.is_empty() {
            tracing::warn!(target: "aimrt", "opentelemetry_plugin: trace_otlp_http_exporter_url is not set: no filter is registered and nothing is traced");
            return Ok(());
        }
        let endpoint = Endpoint::parse(&o.trace_otlp_http_exporter_url)
            .map_err(|e| options.invalid(format!("trace_otlp_http_exporter_url {e}")))?;
        let mut resource = vec![KeyValue::text("service.name", &o.node_name)];
        resource.extend(o.attributes.iter().map(|a| KeyValue::text(&a.key, &a.val)));
        let exporter =
            Arc::new(Exporter::start(endpoint, resource, o.node_name.clone()).map_err(Error::msg)?);
        *lock(&self.exporter) = Some(exporter.clone());
        let tracer = Arc::new(Tracer {
            exporter,
            force: o.force_trace,
        });
        let registered = register_filters(registrar, &tracer);
        if registered.is_err() {
            self.shutdown();
        }
        registered
    }

    fn shutdown(&mut self) {
        if let Some(exporter) = lock(&self.exporter).take() {
            exporter.close();
        }
    }
}

/// The plugin, as `libaimrt_opentelemetry_plugin.so` exports it (`plugins/opentelemetry/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(OtelPlugin {
        exporter: Mutex::new(None),
    })
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
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

fn register_filters(registrar: &mut Registrar<'_>, tracer: &Arc<Tracer>) -> Result<(), Error> {
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
