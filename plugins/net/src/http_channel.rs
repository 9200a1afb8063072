//! The `http` channel backend: each message is `POST /channel/<UrlEncode(topic)>/<UrlEncode(type)>`
//! with the encoded message as the body and the context as headers (AimRT's request) to
//! every address of the topic's `server_url_list` (or the `http://` entries of
//! `aimrt-to_addr`); subscribers receive through net_plugin's HTTP server.
//!
//! Publishing never blocks: each request is a task on the shared HTTP threads, at most
//! [`IN_FLIGHT`] and [`PUBLISH_BYTES`] of bodies per host (more are refused and counted),
//! each with a 5 s deadline. A
//! request that fails, and one still in flight [`SETTLE`](crate::channel::SETTLE) after
//! shutdown began, is counted as lost.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use aimrt_plugin_api::channel::{ChannelBackend, Publication, PublisherInfo, Subscription};
use aimrt_plugin_api::ffi::type_name_of;
use aimrt_plugin_api::{BackendOptions, Error};
use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper::header::{self, HeaderMap, HeaderValue};
use hyper::{Method, Request, StatusCode};

use crate::channel::{encoded, Routes};
use crate::header::{content_type, put_meta};
use crate::http::HttpShared;
use crate::http_client::{HostPool, Pools, SendError, PUBLISH_BYTES};
use crate::wire::channel_uri;

/// Requests in flight to one host at most; more are refused (never queued).
pub(crate) const IN_FLIGHT: usize = 1024;

/// The most of a subscriber's answer read: AimRT's is empty, ours a line (a 404 says which
/// uri was meant).
const MAX_ANSWER: usize = 64 << 10;

/// A subscriber's answer, up to [`MAX_ANSWER`] bytes, and whether that was all of it.
async fn read_answer(mut body: hyper::body::Incoming) -> (Vec<u8>, bool) {
    let mut got = Vec::new();
    while let Some(frame) = body.frame().await {
        let Ok(frame) = frame else {
            return (got, false);
        };
        if let Some(data) = frame.data_ref() {
            if got.len() + data.len() > MAX_ANSWER {
                got.extend_from_slice(&data[..MAX_ANSWER - got.len()]);
                return (got, false);
            }
            got.extend_from_slice(data);
        }
    }
    (got, true)
}

/// An answer's body for a warning: ` ("…")`, its first 300 bytes on one line; nothing
/// for an empty one.
fn quoted(answer: &[u8]) -> String {
    if answer.is_empty() {
        return String::new();
    }
    let text =
        String::from_utf8_lossy(&answer[..answer.len().min(300)]).replace(char::is_control, " ");
    let more = if answer.len() > 300 { "…" } else { "" };
    format!(" (\"{}{more}\")", text.trim())
}

/// The backend.
pub(crate) struct HttpChannel {
    shared: Arc<HttpShared>,
    routes: OnceLock<Routes>,
    handle: Mutex<Option<tokio::runtime::Handle>>,
    /// Each address's keep-alive connections and [`IN_FLIGHT`] slots.
    pools: Pools,
}

impl HttpChannel {
    pub(crate) fn new(shared: Arc<HttpShared>) -> HttpChannel {
        HttpChannel {
            shared,
            routes: OnceLock::new(),
            handle: Mutex::new(None),
            pools: Pools::default(),
        }
    }

    fn pool(&self, addr: SocketAddr, rt: &tokio::runtime::Handle) -> Arc<HostPool> {
        self.pools.get(&addr.to_string(), IN_FLIGHT, Some(rt))
    }
}

impl ChannelBackend for HttpChannel {
    fn type_name(&self) -> &str {
        "http"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let _ = self.routes.set(Routes::parse(options, "http")?);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        let handle = self.shared.acquire()?;
        *self.handle.lock().unwrap_or_else(|e| e.into_inner()) = Some(handle);
        Ok(())
    }

    fn shutdown(&self) {
        let handle = self.handle.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(handle) = handle {
            // Requests in flight get a little time to be answered; the rest count as lost
            // when the runtime lets their tasks go.
            self.shared.channels.settle(&handle);
            self.shared.release();
        }
        tracing::info!(target: "aimrt", "net_plugin http channel: {}{}", self.shared.channels.stats.line(), self.shared.receiving.refused_part());
    }

    fn register_publish_type(&self, publisher: &PublisherInfo<'_>) -> Result<(), Error> {
        match self.routes.get() {
            Some(r) => r.register(publisher, "http"),
            None => Err(Error::msg("the http channel backend was not initialized")),
        }
    }

    fn subscribe(&self, subscription: Subscription) -> Result<(), Error> {
        if !self.shared.serves() {
            return Err(Error::msg(
                "Failed to subscribe: please set http listen IP and port in the configuration (net_plugin options: http_options: {listen_ip: 127.0.0.1, listen_port: 50080})",
            ));
        }
        let uri = channel_uri(&subscription.topic, subscription.sink.type_name());
        tracing::info!(target: "aimrt", "Register http handle for channel, uri '{uri}'");
        self.shared.channels.subscribe(subscription);
        Ok(())
    }

    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error> {
        let refuse = |why: String| self.shared.channels.refuse(why);
        let handle = self
            .handle
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let (Some(routes), Some(handle)) = (self.routes.get(), handle) else {
            return refuse("the http channel backend is not running".into());
        };
        let (targets, uri) = match routes.targets(publication, "http") {
            Ok(r) => (r.addrs, r.uri),
            Err(why) => return refuse(why),
        };
        if targets.is_empty() {
            return Ok(0);
        }
        let (format, payload) = match encoded(publication) {
            Ok((f, p)) => (f, Bytes::from(p)),
            Err(why) => return refuse(why),
        };
        let path = uri.map_or_else(
            || {
                channel_uri(
                    publication.topic(),
                    type_name_of(publication.message().type_support()),
                )
            },
            |u| u.to_string(),
        );
        let ct = content_type(&format)
            .map(str::to_owned)
            .unwrap_or_else(|| format!("application/{format}"));
        let mut headers = HeaderMap::new();
        put_meta(&mut headers, publication.ctx());
        let topic = publication.loss_reporter();
        let mut full = Vec::new();
        let path: hyper::Uri = match path.parse() {
            Ok(p) => p,
            Err(e) => return refuse(format!("'{path}' is not a request path: {e}")),
        };
        let ct = match HeaderValue::from_str(&ct) {
            Ok(v) => v,
            Err(e) => return refuse(format!("'{ct}' is not a header value: {e}")),
        };
        for &addr in targets.iter() {
            let pool = self.pool(addr, &handle);
            let Ok(permit) = pool.slots.clone().try_acquire_owned() else {
                full.push(addr);
                continue;
            };
            // A body larger than the whole allowance is refused too.
            let Some(bytes) = u32::try_from(payload.len())
                .ok()
                .and_then(|n| pool.publish_bytes.clone().try_acquire_many_owned(n).ok())
            else {
                full.push(addr);
                continue;
            };
            let host = match addr {
                SocketAddr::V4(a) => a.ip().to_string(),
                SocketAddr::V6(a) => format!("[{}]", a.ip()),
            };
            let Ok(host) = HeaderValue::from_str(&host) else {
                self.shared.channels.lose(
                    &topic,
                    format_args!("'{host}' is not a Host header; the message to {addr} is lost"),
                );
                continue;
            };
            let mut request = Request::new(Full::new(payload.clone()));
            *request.method_mut() = Method::POST;
            *request.uri_mut() = path.clone();
            let h = request.headers_mut();
            h.reserve(headers.len() + 3);
            h.insert(header::HOST, host);
            h.insert(header::USER_AGENT, HeaderValue::from_static("aimrt"));
            h.insert(header::CONTENT_TYPE, ct.clone());
            for (n, v) in &headers {
                h.append(n, v.clone());
            }
            let taken = self.shared.channels.take(&topic);
            // A task the runtime drops at shutdown drops `taken`, which counts it lost.
            handle.spawn(async move {
                let _permits = (permit, bytes);
                let sent = async {
                    let (sender, rsp) = pool.send(request).await?;
                    let status = rsp.status();
                    // Read whole, so the connection can take the next request; an answer
                    // over the limit closes the connection instead.
                    let (answer, whole) = read_answer(rsp.into_body()).await;
                    if whole {
                        pool.keep(sender);
                    }
                    Ok::<_, SendError>((status, answer))
                };
                match tokio::time::timeout(Duration::from_secs(5), sent).await {
                    Ok(Ok((StatusCode::OK, _))) => taken.sent(),
                    Ok(Ok((status, answer))) => taken.lost(format_args!(
                        "http channel publish to {addr} got {status}{}; the message is lost",
                        quoted(&answer)
                    )),
                    Ok(Err(SendError::Connect(why) | SendError::Failed(why))) => taken.lost(
                        format_args!("http channel publish to {addr} failed: {why}; the message is lost"),
                    ),
                    Err(_) => taken.lost(format_args!(
                        "http channel publish to {addr} got no answer within 5 s; the message is lost"
                    )),
                }
            });
        }
        if !full.is_empty() {
            return refuse(format!(
                "{IN_FLIGHT} requests or {} MiB of messages are already in flight to {}",
                PUBLISH_BYTES >> 20,
                full.iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        Ok(aimrt_plugin_api::channel::RECEIVERS_UNKNOWN)
    }
}
