//! The `http` RPC backend: a hyper HTTP/1.1 server on its own tokio runtime.

use std::convert::Infallible;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Mutex, OnceLock};
use std::time::Duration;

use aimrt_plugin_api::{BackendOptions, Error, RpcBackend, ServiceError, ServiceHost};
use bytes::Bytes;
use http_body_util::{BodyExt, Full, Limited};
use hyper::body::Incoming;
use hyper::header::{self, HeaderValue};
use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};
use serde::Deserialize;

/// The largest request body, as AimRT's HTTP server (16 MiB).
pub(crate) const MAX_BODY: u64 = 16 * 1024 * 1024;

/// `net_plugin`'s `http_options`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct HttpOptions {
    #[serde(default = "loopback")]
    listen_ip: String,
    listen_port: u16,
    /// aimrt-rs: a request's headers must arrive within this long of its first byte
    /// (or of the connection's start), else the connection is closed.
    #[serde(default = "default_header_timeout_ms")]
    header_timeout_ms: u64,
    /// aimrt-rs: a request's whole body must arrive within this long of its headers,
    /// else the answer is 408 and the connection is closed.
    #[serde(default = "default_body_timeout_ms")]
    body_timeout_ms: u64,
    /// aimrt-rs: open connections at most; more wait in the kernel's accept queue.
    #[serde(default = "default_max_connections")]
    max_connections: u32,
}

fn loopback() -> String {
    "127.0.0.1".to_owned()
}
fn default_header_timeout_ms() -> u64 {
    10_000
}
fn default_body_timeout_ms() -> u64 {
    30_000
}
fn default_max_connections() -> u32 {
    4096
}

/// The most connections `max_connections` may allow (each is a file descriptor).
pub(crate) const MAX_CONNECTIONS: u32 = 1_000_000;

/// What the server enforces per connection.
#[derive(Debug, Clone, Copy)]
struct Limits {
    header_timeout: Duration,
    body_timeout: Duration,
    max_connections: usize,
}

/// `aimrt.rpc.backends[i].options` of `http`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct BackendConfig {
    #[serde(default)]
    clients_options: Vec<serde_json::Value>,
}

/// The backend: options from the plugin, the host from `init`, the server from `start`.
pub(crate) struct HttpBackend {
    threads: usize,
    options: Option<HttpOptions>,
    location: String,
    host: OnceLock<ServiceHost>,
    server: Mutex<Option<tokio::runtime::Runtime>>,
}

impl HttpBackend {
    pub(crate) fn new(threads: usize, options: Option<HttpOptions>, location: String) -> Self {
        HttpBackend {
            threads,
            options,
            location,
            host: OnceLock::new(),
            server: Mutex::new(None),
        }
    }

    fn address(&self) -> Result<(SocketAddr, Limits), Error> {
        let what = || format!("options of plugin 'net_plugin' at {}", self.location);
        let o = self.options.as_ref().ok_or_else(|| Error::Options {
            what: what(),
            message: "aimrt.rpc lists the http backend, so net_plugin needs http_options: {listen_ip: 127.0.0.1, listen_port: 50080}".into(),
        })?;
        for (key, ms) in [
            ("header_timeout_ms", o.header_timeout_ms),
            ("body_timeout_ms", o.body_timeout_ms),
        ] {
            if ms == 0 || ms > 3_600_000 {
                return Err(Error::Options {
                    what: what(),
                    message: format!(
                        "http_options.{key} must be in 1 ..= 3600000 (one hour), got {ms}"
                    ),
                });
            }
        }
        if o.max_connections == 0 || o.max_connections > MAX_CONNECTIONS {
            return Err(Error::Options {
                what: what(),
                message: format!(
                    "http_options.max_connections must be in 1 ..= {MAX_CONNECTIONS}, got {}",
                    o.max_connections
                ),
            });
        }
        let limits = Limits {
            header_timeout: Duration::from_millis(o.header_timeout_ms),
            body_timeout: Duration::from_millis(o.body_timeout_ms),
            max_connections: o.max_connections as usize,
        };
        let ip: IpAddr = o.listen_ip.parse().map_err(|_| Error::Options {
            what: what(),
            message: format!(
                "http_options.listen_ip '{}' is not an IP address; give one such as 127.0.0.1 (loopback) or 0.0.0.0 (every interface)",
                o.listen_ip
            ),
        })?;
        Ok((SocketAddr::new(ip, o.listen_port), limits))
    }
}

impl RpcBackend for HttpBackend {
    fn type_name(&self) -> &str {
        "http"
    }

    fn init(&self, options: &BackendOptions, host: ServiceHost) -> Result<(), Error> {
        let config: BackendConfig = options.get()?;
        if !config.clients_options.is_empty() {
            tracing::warn!(target: "aimrt", "http backend at {}: clients_options is accepted but unused: this runtime has no RPC client API yet", options.location());
        }
        self.address()?;
        let _ = self.host.set(host);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        let (addr, limits) = self.address()?;
        let host = *self
            .host
            .get()
            .ok_or_else(|| Error::msg("the http backend was started before init"))?;
        let listener = std::net::TcpListener::bind(addr)
            .and_then(|l| l.set_nonblocking(true).map(|()| l))
            .map_err(|e| {
                let fix = match e.kind() {
                    std::io::ErrorKind::AddrInUse => "choose another http_options.listen_port (0 picks a free one)",
                    std::io::ErrorKind::AddrNotAvailable => "http_options.listen_ip is not an address of this machine; use 127.0.0.1 (loopback), 0.0.0.0 (every interface) or one of this machine's addresses",
                    std::io::ErrorKind::PermissionDenied => "ports below 1024 need privileges; choose a http_options.listen_port of 1024 or more",
                    _ => "check http_options.listen_ip and listen_port",
                };
                Error::msg(format!(
                    "cannot listen on {addr}: {e}; {fix}, in the options of net_plugin at {}",
                    self.location
                ))
            })?;
        let bound = listener.local_addr().unwrap_or(addr);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(self.threads)
            .thread_name("aimrt_http")
            .enable_io()
            .enable_time()
            .build()
            .map_err(|e| Error::msg(format!("cannot start the HTTP server threads: {e}")))?;
        let listener = {
            let _in_runtime = runtime.enter();
            tokio::net::TcpListener::from_std(listener)
                .map_err(|e| Error::msg(format!("cannot serve on {bound}: {e}")))?
        };
        runtime.spawn(accept(listener, host, limits));
        *self.server.lock().unwrap_or_else(|e| e.into_inner()) = Some(runtime);
        tracing::info!(target: "aimrt", "net_plugin: http server listening on {bound}; services at POST http://{bound}/rpc/<Service>/<Method>");
        Ok(())
    }

    fn shutdown(&self) {
        let runtime = self.server.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(rt) = runtime {
            // Stops accepting, cancels open connections and waits for their threads.
            rt.shutdown_timeout(Duration::from_secs(2));
            tracing::info!(target: "aimrt", "net_plugin: http server stopped");
        }
    }
}

async fn accept(listener: tokio::net::TcpListener, host: ServiceHost, limits: Limits) {
    let slots = std::sync::Arc::new(tokio::sync::Semaphore::new(limits.max_connections));
    let accept_alarm = aimrt_plugin_api::RateLimit::from_millis(1000);
    loop {
        // At max_connections, wait for one to close before accepting the next: further
        // clients wait in the kernel's accept queue instead of failing.
        let Ok(slot) = slots.clone().acquire_owned().await else {
            return;
        };
        let stream = match listener.accept().await {
            Ok((stream, _)) => stream,
            Err(e) => {
                // Out of file descriptors and the like: wait a little rather than spin,
                // and say so at most once a second.
                if let Some(held) = accept_alarm.admit() {
                    tracing::warn!(target: "aimrt", "net_plugin: accepting a connection failed: {e} ({} failure(s) since the last report); raise the open-file limit (ulimit -n) or lower http_options.max_connections", held + 1);
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        tokio::spawn(async move {
            let _slot = slot;
            serve_connection(stream, host, limits).await;
        });
    }
}

/// Serves HTTP/1.1 requests on one connection until it closes.
async fn serve_connection<S>(stream: S, host: ServiceHost, limits: Limits)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    let service = service_fn(move |req| async move {
        Ok::<_, Infallible>(route(req, host, limits).await.unwrap_or_else(|e| e))
    });
    // half_close: a client that shuts down its sending side after the request (as
    // `nc -N` does) still gets its answer.
    let served = http1::Builder::new()
        .timer(TokioTimer::new())
        .half_close(true)
        .header_read_timeout(limits.header_timeout)
        .serve_connection(TokioIo::new(stream), service)
        .await;
    if let Err(e) = served {
        tracing::debug!(target: "aimrt", "net_plugin: connection ended: {e}");
    }
}

/// Feeds `input` as one connection's bytes to the server (with a service that echoes
/// JSON bodies and fails on a body of `fail`) and returns what it answered. For fuzzing:
/// whatever the bytes, this must return, not panic or hang.
pub fn serve_bytes(input: &[u8]) -> Vec<u8> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    struct Echo;
    impl aimrt_plugin_api::HostServices for Echo {
        fn invoke(
            &self,
            _func: &str,
            _format: &str,
            request: &[u8],
            responder: aimrt_plugin_api::Responder,
        ) {
            if request == b"fail" {
                responder.respond(Err(ServiceError::Failed("fail".into())));
            } else {
                responder.respond(Ok(request.to_vec()));
            }
        }
    }
    static HOST: OnceLock<ServiceHost> = OnceLock::new();
    let host = *HOST.get_or_init(|| ServiceHost::new(std::sync::Arc::new(Echo)));
    let limits = Limits {
        header_timeout: Duration::from_millis(200),
        body_timeout: Duration::from_millis(200),
        max_connections: 1,
    };
    let Ok(runtime) = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    else {
        return Vec::new();
    };
    runtime.block_on(async move {
        let (mut client, server) = tokio::io::duplex(1 << 20);
        let served = tokio::spawn(serve_connection(server, host, limits));
        let _ = client.write_all(input).await;
        let _ = client.shutdown().await;
        let mut out = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(2), client.read_to_end(&mut out)).await;
        served.abort();
        out
    })
}

type Reply = Response<Full<Bytes>>;

fn reply(status: StatusCode, body: Vec<u8>) -> Reply {
    let mut r = Response::new(Full::new(Bytes::from(body)));
    *r.status_mut() = status;
    let h = r.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    h.insert(
        header::ACCESS_CONTROL_ALLOW_ORIGIN,
        HeaderValue::from_static("*"),
    );
    r
}

fn error(status: StatusCode, message: &str) -> Reply {
    reply(
        status,
        serde_json::json!({ "error": message })
            .to_string()
            .into_bytes(),
    )
}

/// Whether `content_type` is JSON: `application/json`, with or without a charset
/// (`; charset=utf-8`, or AimRT's own `application/json charset=utf-8`).
pub(crate) fn is_json(content_type: &str) -> bool {
    let mut parts = content_type
        .split([';', ' ', '\t'])
        .filter(|p| !p.is_empty());
    let media = parts.next().unwrap_or_default();
    if !media.eq_ignore_ascii_case("application/json") {
        return false;
    }
    parts.all(|p| {
        let (key, value) = p.split_once('=').unwrap_or((p, ""));
        !key.trim().eq_ignore_ascii_case("charset")
            || value.trim().trim_matches('"').eq_ignore_ascii_case("utf-8")
    })
}

async fn route(req: Request<Incoming>, host: ServiceHost, limits: Limits) -> Result<Reply, Reply> {
    let path = req.uri().path().to_owned();
    let Some(name) = path.strip_prefix("/rpc/").filter(|n| !n.is_empty()) else {
        return Err(error(
            StatusCode::NOT_FOUND,
            &format!("no route for '{path}'; services are at POST /rpc/<Service>/<Method>"),
        ));
    };
    if req.method() == Method::OPTIONS {
        let mut r = reply(StatusCode::OK, Vec::new());
        let h = r.headers_mut();
        h.insert(
            header::ACCESS_CONTROL_ALLOW_METHODS,
            HeaderValue::from_static("POST, OPTIONS"),
        );
        h.insert(
            header::ACCESS_CONTROL_ALLOW_HEADERS,
            HeaderValue::from_static("Content-Type, Authorization, X-Requested-With"),
        );
        h.insert(
            header::ACCESS_CONTROL_MAX_AGE,
            HeaderValue::from_static("86400"),
        );
        return Ok(r);
    }
    if req.method() != Method::POST {
        let mut r = error(
            StatusCode::METHOD_NOT_ALLOWED,
            &format!("{} is not supported; call services with POST", req.method()),
        );
        r.headers_mut()
            .insert(header::ALLOW, HeaderValue::from_static("POST, OPTIONS"));
        return Err(r);
    }
    let content_type = req
        .headers()
        .get(header::CONTENT_TYPE)
        .map(|v| String::from_utf8_lossy(v.as_bytes()).into_owned());
    match &content_type {
        Some(ct) if is_json(ct) => {}
        Some(ct) => {
            return Err(error(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                &format!("Content-Type '{ct}' is not supported; send the body as application/json (with or without charset=utf-8)"),
            ))
        }
        None => {
            return Err(error(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "the request has no Content-Type; send the body as application/json",
            ))
        }
    }
    let declared = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    let too_large = || {
        error(
            StatusCode::PAYLOAD_TOO_LARGE,
            &format!("the body is larger than the limit of {MAX_BODY} bytes"),
        )
    };
    if declared.is_some_and(|n| n > MAX_BODY) {
        return Err(too_large());
    }
    let body = Limited::new(req.into_body(), MAX_BODY as usize).collect();
    let body = match tokio::time::timeout(limits.body_timeout, body).await {
        Err(_) => {
            let mut r = error(
                StatusCode::REQUEST_TIMEOUT,
                &format!(
                    "the body did not arrive within http_options.body_timeout_ms ({} ms)",
                    limits.body_timeout.as_millis()
                ),
            );
            r.headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
            return Err(r);
        }
        Ok(Ok(b)) => b.to_bytes(),
        Ok(Err(e)) if e.is::<http_body_util::LengthLimitError>() => return Err(too_large()),
        Ok(Err(e)) => {
            return Err(error(
                StatusCode::BAD_REQUEST,
                &format!("cannot read the body: {e}"),
            ))
        }
    };
    let func = format!("pb:/{name}");
    let (tx, rx) = tokio::sync::oneshot::channel();
    host.invoke(&func, "json", &body, move |r| {
        let _ = tx.send(r);
    });
    match rx.await {
        Ok(Ok(answer)) => Ok(reply(StatusCode::OK, answer)),
        Ok(Err(e)) => {
            let status = match &e {
                ServiceError::BadRequest(_) => StatusCode::BAD_REQUEST,
                ServiceError::NotFound(_) => StatusCode::NOT_FOUND,
                ServiceError::UnsupportedFormat(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
                ServiceError::Failed(_) => StatusCode::INTERNAL_SERVER_ERROR,
            };
            Err(error(status, e.message()))
        }
        Err(_) => Err(error(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the service dropped the call without an answer",
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_content_types() {
        for ok in [
            "application/json",
            "Application/JSON",
            "application/json; charset=utf-8",
            "application/json;charset=UTF-8",
            "application/json charset=utf-8",
            "application/json; charset=\"utf-8\"",
        ] {
            assert!(is_json(ok), "{ok}");
        }
        for bad in [
            "",
            "text/plain",
            "application/jsonx",
            "application/x-www-form-urlencoded",
            "application/protobuf",
            "application/json; charset=latin1",
        ] {
            assert!(!is_json(bad), "{bad}");
        }
    }

    #[test]
    fn raw_bytes_get_an_answer_never_a_panic() {
        let ok = serve_bytes(
            b"POST /rpc/a.B/C HTTP/1.1\r\nHost: x\r\ncontent-type: application/json\r\nContent-Length: 2\r\n\r\n{}",
        );
        let text = String::from_utf8_lossy(&ok);
        assert!(text.starts_with("HTTP/1.1 200 OK"), "{text:?}");
        assert!(text.ends_with("{}"), "{text}");
        let failed = serve_bytes(
            b"POST /rpc/a.B/C HTTP/1.1\r\nHost: x\r\ncontent-type: application/json\r\nContent-Length: 4\r\n\r\nfail",
        );
        assert!(String::from_utf8_lossy(&failed).starts_with("HTTP/1.1 500"));
        let garbage = serve_bytes(b"\x00\xff GET / HTTP/1.1\r\n\r\n");
        assert!(String::from_utf8_lossy(&garbage).starts_with("HTTP/1.1 400"));
        // A body cut short by the client closing its side is a bad request.
        let cut = serve_bytes(
            b"POST /rpc/a.B/C HTTP/1.1\r\nHost: x\r\ncontent-type: application/json\r\nContent-Length: 10\r\n\r\n{",
        );
        let cut = String::from_utf8_lossy(&cut);
        assert!(
            cut.starts_with("HTTP/1.1 400") && cut.contains("cannot read the body"),
            "{cut:?}"
        );
    }
}
