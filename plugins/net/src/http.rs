//! The `http` RPC backend: a hyper HTTP/1.1 server (module and plugin services at
//! `POST /rpc/<Service>/<Method>`) and client (`http_client`), on one tokio runtime.

use std::borrow::Cow;
use std::collections::HashMap;
use std::convert::Infallible;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex, OnceLock, RwLock};
use std::time::Duration;

use aimrt_plugin_api::ffi::{lossy, meta_of};
use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall, BackendReply, CallView};
use aimrt_plugin_api::{
    meta_keys, BackendOptions, Error, RpcBackend, RpcStatus, ServiceError, ServiceHost,
};
use bytes::Bytes;
use http_body_util::Full;
use hyper::body::Incoming;
use hyper::header::{self, HeaderValue};
use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};
use serde::Deserialize;
use smallvec::SmallVec;

use crate::channel::Inbox;
use crate::close::{Closer, Closing, CLOSE_WAIT};
use crate::header::{
    decode, is_standard_name, meta_key, name_without_prefix, REMOTE_ENDPOINT, REMOTE_ENDPOINT_KEY,
    STATUS_HEADER, TIMEOUT,
};
use crate::http_client::{ClientOption, HttpClient};
use crate::receiving::{self, BodyError, Claim, Full as FullBudget, Receiving, RECEIVING_BYTES};

/// The largest request body, as AimRT's HTTP server (16 MiB).
pub(crate) const MAX_BODY: u64 = 16 * 1024 * 1024;

/// `net_plugin`'s `http_options`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
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
#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct BackendConfig {
    #[serde(default)]
    clients_options: Vec<ClientOption>,
    /// AimRT decodes it and never uses it: accepted with a warning.
    #[serde(default)]
    servers_options: Vec<serde_json::Value>,
    /// aimrt-rs: calls in flight to one host at most (each holds a connection); more
    /// queue until one ends.
    #[serde(default = "default_max_connections_per_host")]
    max_connections_per_host: u32,
}

fn default_max_connections_per_host() -> u32 {
    100
}

/// A module service this backend serves: its function name, and that name as AimRT's
/// client sends it in `aimrt-function_name` (so a request that says so needs no decoding).
#[derive(Debug)]
struct Route {
    func: String,
    encoded: String,
}

/// Exact paths of the module services this backend serves.
type Routes = Arc<RwLock<HashMap<String, Arc<Route>, foldhash::fast::RandomState>>>;

/// The HTTP side of net_plugin that the `http` RPC and channel backends share: one tokio
/// runtime (the client's and the server's threads) and, with `http_options`, one server
/// for both RPC routes and channel routes. Started by the first backend that starts,
/// stopped when the last one stops.
pub(crate) struct HttpShared {
    threads: usize,
    options: Option<HttpOptions>,
    location: String,
    /// The runtime's handle to RPC services (set by the RPC backend's `init`).
    host: OnceLock<ServiceHost>,
    routes: Routes,
    /// Channel subscribers, by uri.
    pub(crate) channels: Arc<Inbox>,
    /// What the server's connections hold of request bodies on their way, and what it
    /// refused.
    pub(crate) receiving: Arc<Receiving>,
    state: Mutex<SharedState>,
}

#[derive(Default)]
struct SharedState {
    runtime: Option<tokio::runtime::Runtime>,
    /// Closes the server gracefully before the runtime stops (with `http_options`).
    closer: Option<Closer>,
    users: usize,
}

/// The RPC backend: the shared server and runtime, and the client from `init`.
pub(crate) struct HttpBackend {
    shared: Arc<HttpShared>,
    client: OnceLock<Arc<HttpClient>>,
    handle: Mutex<Option<tokio::runtime::Handle>>,
}

/// What each connection of the server needs.
#[derive(Clone)]
struct Server {
    host: Option<ServiceHost>,
    limits: Limits,
    routes: Routes,
    channels: Arc<Inbox>,
    /// The bytes of request bodies arriving on all connections.
    receiving: Arc<Receiving>,
    /// The connections' permits (`limits.max_connections`) and the signal to close.
    closing: Closing,
}

impl HttpShared {
    pub(crate) fn new(threads: usize, options: Option<HttpOptions>, location: String) -> Arc<Self> {
        Arc::new(HttpShared {
            threads,
            options,
            location,
            host: OnceLock::new(),
            routes: Routes::default(),
            channels: Arc::new(Inbox::new("http")),
            receiving: Receiving::new(RECEIVING_BYTES, "net_plugin http"),
            state: Mutex::default(),
        })
    }

    /// Whether the server has `http_options` to listen on.
    pub(crate) fn serves(&self) -> bool {
        self.options.is_some()
    }

    /// Starts the runtime (and the server) for one more user; its handle.
    pub(crate) fn acquire(&self) -> Result<tokio::runtime::Handle, Error> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(handle) = state.runtime.as_ref().map(|rt| rt.handle().clone()) {
            state.users += 1;
            return Ok(handle);
        }
        let runtime = crate::start_runtime(self.threads, "aimrt_http", "HTTP")?;
        if self.options.is_some() {
            let (addr, limits) = self.address()?;
            let listener = crate::listen_tcp(addr)
                .map_err(|e| crate::cannot_listen("http", &addr, &e, &self.location))?;
            let bound = listener.local_addr().unwrap_or(addr);
            let listener = {
                let _in_runtime = runtime.enter();
                tokio::net::TcpListener::from_std(listener)
                    .map_err(|e| Error::msg(format!("cannot serve on {bound}: {e}")))?
            };
            let closer = Closer::new(limits.max_connections);
            let server = Server {
                host: self.host.get().copied(),
                limits,
                routes: self.routes.clone(),
                channels: self.channels.clone(),
                receiving: self.receiving.clone(),
                closing: closer.closing(),
            };
            runtime.spawn(accept(closer.listener(listener), server));
            state.closer = Some(closer);
            tracing::info!(target: "aimrt", "net_plugin: http server listening on {bound}; services at POST http://{bound}/rpc/<Service>/<Method>, channels at POST http://{bound}/channel/<topic>/<type>");
        }
        let handle = runtime.handle().clone();
        state.runtime = Some(runtime);
        state.users = 1;
        Ok(handle)
    }

    /// One user fewer; the last one stops the server and the runtime.
    pub(crate) fn release(&self) {
        let (runtime, closer) = {
            let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
            state.users = state.users.saturating_sub(1);
            if state.users > 0 {
                return;
            }
            (state.runtime.take(), state.closer.take())
        };
        if let Some(rt) = runtime {
            // The listener stops; for LAST_REQUESTS each connection still answers what
            // comes (with `Connection: close`, which ends it), then an idle one closes
            // and a busy one after its answer. What is left after a second is cut off.
            if let Some(closer) = closer {
                closer.close(CLOSE_WAIT);
            }
            // Cancels what is left and client calls (their replies are dropped, which
            // answers them) and waits for the threads.
            rt.shutdown_timeout(Duration::from_secs(2));
            tracing::info!(target: "aimrt", "net_plugin: http stopped{}", self.receiving.refused_part());
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

impl HttpBackend {
    pub(crate) fn new(shared: Arc<HttpShared>) -> Self {
        HttpBackend {
            shared,
            client: OnceLock::new(),
            handle: Mutex::new(None),
        }
    }
}

impl RpcBackend for HttpBackend {
    fn type_name(&self) -> &str {
        "http"
    }

    fn init(&self, options: &BackendOptions, host: ServiceHost) -> Result<(), Error> {
        let config: BackendConfig = options.read()?;
        if !config.servers_options.is_empty() {
            tracing::warn!(target: "aimrt", "http backend at {}: servers_options is accepted but unused (as in AimRT): which functions http serves is decided by aimrt.rpc.servers_options", options.location());
        }
        if config.max_connections_per_host == 0 || config.max_connections_per_host > MAX_CONNECTIONS
        {
            return Err(Error::Options {
                what: format!("http backend options at {}", options.location()),
                message: format!(
                    "max_connections_per_host must be in 1 ..= {MAX_CONNECTIONS}, got {}",
                    config.max_connections_per_host
                ),
            });
        }
        if self.shared.options.is_some() {
            self.shared.address()?;
        }
        let client = HttpClient::new(
            config.clients_options,
            config.max_connections_per_host as usize,
            options.location(),
        )?;
        let _ = self.client.set(Arc::new(client));
        let _ = self.shared.host.set(host);
        Ok(())
    }

    fn register_service_func(&self, func: &str) -> Result<(), Error> {
        if self.shared.options.is_none() {
            return Err(Error::msg(
                "Failed to register service function: please set http listen IP and port in the configuration (net_plugin options: http_options: {listen_ip: 127.0.0.1, listen_port: 50080})",
            ));
        }
        let path = format!("/rpc{}", name_without_prefix(func));
        tracing::info!(target: "aimrt", "Register http handle for rpc, uri '{path}'");
        self.shared
            .routes
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(
                path,
                Arc::new(Route {
                    func: func.to_owned(),
                    encoded: crate::header::encode(func).into_owned(),
                }),
            );
        Ok(())
    }

    fn register_client_func(&self, func: &str) -> Result<(), Error> {
        if let Some(client) = self.client.get() {
            client.register(func);
        }
        Ok(())
    }

    fn invoke(&self, call: BackendCall, reply: BackendReply) {
        let handle = self
            .handle
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let (Some(handle), Some(client)) = (handle, self.client.get().cloned()) else {
            return reply.send(BackendAnswer::fail(
                RpcStatus::CLI_BACKEND_INTERNAL_ERROR,
                "the http backend is not running",
            ));
        };
        handle.spawn(async move { reply.send(client.call(call).await) });
    }

    fn start(&self) -> Result<(), Error> {
        if self.shared.host.get().is_none() {
            return Err(Error::msg("the http backend was started before init"));
        }
        let handle = self.shared.acquire()?;
        *self.handle.lock().unwrap_or_else(|e| e.into_inner()) = Some(handle);
        Ok(())
    }

    fn shutdown(&self) {
        if self
            .handle
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
            .is_some()
        {
            self.shared.release();
        }
    }
}

/// Accepts connections until the server closes or the runtime stops.
async fn accept(listener: crate::close::Listener, server: Server) {
    let closing = server.closing.clone();
    let what = (
        "net_plugin",
        "raise the open-file limit (ulimit -n) or lower http_options.max_connections",
    );
    crate::close::accept(listener, closing, what, move |stream, remote| {
        serve_connection(stream, Some(remote), server.clone())
    })
    .await;
}

/// How long a closing server still takes requests on the connections it has. HTTP/1.1
/// cannot tell a client that a connection is closing but by closing it, and a request
/// the client sends as the close crosses it on the wire is lost without an answer (2000:
/// the client cannot tell whether it ran). A connection in use meanwhile gets an answer,
/// with `Connection: close`; only one idle for all of this time is closed unasked.
const LAST_REQUESTS: Duration = Duration::from_millis(100);

/// Serves HTTP/1.1 requests on one connection from `remote` until it closes.
async fn serve_connection<S>(stream: S, remote: Option<SocketAddr>, server: Server)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    serve(stream, remote, server, LAST_REQUESTS).await;
}

/// [`serve_connection`], taking requests for `last_requests` once the server closes.
async fn serve<S>(stream: S, remote: Option<SocketAddr>, server: Server, last_requests: Duration)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    let limits = server.limits;
    let closing = server.closing.clone();
    // AimRT's `ip:port` (`[::1]:port` for IPv6), made once for the connection.
    let remote: Option<Arc<str>> = remote.map(|r| r.to_string().into());
    let service = service_fn(move |req| {
        let (server, remote) = (server.clone(), remote.clone());
        async move {
            let mut answer = route(req, remote.as_deref(), &server)
                .await
                .unwrap_or_else(|e| e);
            if server.closing.is_closing() {
                // hyper closes the connection once this answer is out.
                answer
                    .headers_mut()
                    .insert(header::CONNECTION, HeaderValue::from_static("close"));
            }
            Ok::<_, Infallible>(answer)
        }
    });
    // half_close: a client that shuts down its sending side after the request (as
    // `nc -N` does) still gets its answer.
    let connection = http1::Builder::new()
        .timer(TokioTimer::new())
        .half_close(true)
        .header_read_timeout(limits.header_timeout)
        .serve_connection(TokioIo::new(stream), service);
    tokio::pin!(connection);
    let served = tokio::select! {
        served = connection.as_mut() => served,
        () = closing.closed() => {
            // For `last_requests` every request is still answered (refused by then, as the
            // runtime is stopping) with `Connection: close`, which ends the connection;
            // then an idle connection closes and a busy one after its answer.
            match tokio::time::timeout(last_requests, connection.as_mut()).await {
                Ok(served) => served,
                Err(_) => {
                    connection.as_mut().graceful_shutdown();
                    connection.await
                }
            }
        }
    };
    if let Err(e) = served {
        tracing::debug!(target: "aimrt", "net_plugin: connection ended: {e}");
    }
}

/// A host whose every service echoes the request, and fails on a request of `fail`: the
/// services of the servers' fuzz targets (made once, kept for the process).
pub fn echo_host() -> ServiceHost {
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
    *HOST.get_or_init(|| ServiceHost::new(std::sync::Arc::new(Echo)))
}

/// Feeds `input` as one connection's bytes to the server (with a service that echoes
/// JSON bodies and fails on a body of `fail`) and returns what it answered. For fuzzing:
/// whatever the bytes, this must return, not panic or hang.
pub fn serve_bytes(input: &[u8]) -> Vec<u8> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let host = echo_host();
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
        let server_side = Server {
            host: Some(host),
            limits,
            routes: Routes::default(),
            channels: Arc::new(Inbox::new("http")),
            receiving: Receiving::new(RECEIVING_BYTES, "net_plugin http"),
            closing: Closing::never(1),
        };
        let served = tokio::spawn(serve_connection(server, None, server_side));
        let _ = client.write_all(input).await;
        let _ = client.shutdown().await;
        let mut out = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(2), client.read_to_end(&mut out)).await;
        served.abort();
        out
    })
}

type Reply = Response<Full<Bytes>>;

fn reply(status: StatusCode, content_type: &'static str, body: Vec<u8>) -> Reply {
    let mut r = Response::new(Full::new(Bytes::from(body)));
    *r.status_mut() = status;
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(
        header::ACCESS_CONTROL_ALLOW_ORIGIN,
        HeaderValue::from_static("*"),
    );
    r
}

fn error(status: StatusCode, message: &str) -> Reply {
    reply(
        status,
        "application/json",
        serde_json::json!({ "error": message })
            .to_string()
            .into_bytes(),
    )
}

/// The HTTP status of a failed call: 4xx for what the caller got wrong, 5xx otherwise.
fn http_status(status: RpcStatus) -> StatusCode {
    match status.code() {
        1003 => StatusCode::NOT_FOUND,
        1004 | 1006 | 2005 | 2007 => StatusCode::UNSUPPORTED_MEDIA_TYPE,
        1007 | 2008 => StatusCode::BAD_REQUEST,
        2 => StatusCode::GATEWAY_TIMEOUT,
        1009 | 2011 => StatusCode::SERVICE_UNAVAILABLE,
        _ => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

/// The answer to a call as HTTP, with the status code in [`STATUS_HEADER`].
fn answer_reply(answer: BackendAnswer, content_type: &'static str) -> Reply {
    let mut r = if answer.status.is_ok() {
        reply(StatusCode::OK, content_type, answer.body)
    } else {
        let message = if answer.detail.is_empty() {
            format!(
                "Handle rpc failed, code: {} ({})",
                answer.status.code(),
                answer.status.text()
            )
        } else {
            answer.detail
        };
        error(http_status(answer.status), &message)
    };
    let code = match answer.status.code() {
        0 => HeaderValue::from_static("0"),
        c => HeaderValue::from(c),
    };
    r.headers_mut().insert(STATUS_HEADER, code);
    r
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

/// The serialization type of a request's `Content-Type` and the `Content-Type` of its
/// answer.
fn format_of(content_type: &str) -> Option<(&'static str, &'static str)> {
    // What AimRT's clients and ours send, before the general parse.
    match content_type {
        "application/protobuf" => return Some(("pb", "application/protobuf")),
        "application/json" => return Some(("json", "application/json")),
        _ => {}
    }
    if is_json(content_type) {
        return Some(("json", "application/json"));
    }
    let media = content_type.split(';').next().unwrap_or("").trim();
    if media.eq_ignore_ascii_case("application/protobuf") {
        Some(("pb", "application/protobuf"))
    } else if media.eq_ignore_ascii_case("application/ros2") {
        Some(("ros2", "application/ros2"))
    } else {
        None
    }
}

/// A request's meta: borrowed from its headers where nothing is escaped.
type Pairs<'a> = SmallVec<[(Cow<'a, str>, Cow<'a, str>); 8]>;

/// Sets `key` in `meta`: in place when it is there, else last.
fn set<'a>(meta: &mut Pairs<'a>, key: Cow<'a, str>, value: Cow<'a, str>) {
    match meta.iter_mut().find(|(k, _)| *k == key) {
        Some(slot) => slot.1 = value,
        None => meta.push((key, value)),
    }
}

/// Answers one request from `remote` (the peer's address, where known).
async fn route(
    req: Request<Incoming>,
    remote: Option<&str>,
    server: &Server,
) -> Result<Reply, Reply> {
    // A clone of the parsed URI shares its bytes; the path is borrowed from it.
    let uri = req.uri().clone();
    let path = uri.path();
    let channel = path.starts_with("/channel/");
    let registered = server
        .routes
        .read()
        .unwrap_or_else(|e| e.into_inner())
        .get(path)
        .cloned();
    let (func, route): (Cow<'_, str>, _) = match &registered {
        Some(r) => (Cow::Borrowed(r.func.as_str()), Some(r)),
        None if channel => (Cow::Borrowed(""), None),
        // A plugin's service (or none: the runtime answers 404).
        None => match path.strip_prefix("/rpc/").filter(|n| !n.is_empty()) {
            Some(name) => (Cow::Owned(format!("pb:/{name}")), None),
            None => {
                return Err(error(
                    StatusCode::NOT_FOUND,
                    &format!("no route for '{path}'; services are at POST /rpc/<Service>/<Method>, channels at POST /channel/<topic>/<type>"),
                ))
            }
        },
    };
    if req.method() == Method::OPTIONS {
        let mut r = reply(StatusCode::OK, "application/json", Vec::new());
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
        .map(|v| lossy(v.as_bytes()));
    let (format, answer_type) = match content_type.as_deref().map(format_of) {
        Some(Some(f)) => f,
        Some(None) => {
            return Err(error(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                &format!(
                    "Content-Type '{}' is not supported; send application/json (with or without charset=utf-8) or application/protobuf",
                    content_type.unwrap_or_default()
                ),
            ))
        }
        None => {
            return Err(error(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "the request has no Content-Type; send application/json or application/protobuf",
            ))
        }
    };
    // The context: every header that is not HTTP's own, decoded as AimRT encodes meta
    // (borrowed where nothing is escaped; a repeated name keeps its last value);
    // `Timeout` in whole seconds (0 or absent: none).
    // Split first: `meta` borrows the headers, so they must outlive it.
    let (parts, incoming) = req.into_parts();
    let mut meta: Pairs<'_> = SmallVec::new();
    let (mut timeout, mut declared) = (None, None);
    for (name, value) in &parts.headers {
        // The first of each, as `HeaderMap::get` reads them.
        if name == TIMEOUT {
            timeout = timeout.or(Some(value));
            continue;
        }
        if name == header::CONTENT_LENGTH {
            declared = declared.or(Some(value));
            continue;
        }
        // The server's own `Remote-Endpoint` replaces the client's, as in AimRT.
        if is_standard_name(name) || name == REMOTE_ENDPOINT {
            continue;
        }
        let key = meta_key(name.as_str());
        match route {
            // The route's own name, as AimRT's client spells it.
            Some(r)
                if key == meta_keys::FUNCTION_NAME && r.encoded.as_bytes() == value.as_bytes() =>
            {
                set(&mut meta, key, Cow::Borrowed(r.func.as_str()));
                continue;
            }
            _ => {}
        }
        set(&mut meta, key, decode(value.as_bytes()));
    }
    if let Some(remote) = remote {
        // The caller's address, under AimRT's name, for a service or subscriber to trace
        // where a request came from.
        set(
            &mut meta,
            Cow::Borrowed(REMOTE_ENDPOINT_KEY),
            Cow::Borrowed(remote),
        );
    }
    set(
        &mut meta,
        Cow::Borrowed(meta_keys::SERIALIZATION_TYPE),
        Cow::Borrowed(format),
    );
    let call_timeout = timeout
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok())
        .filter(|s| *s > 0)
        .map(Duration::from_secs);
    let declared = declared
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
    // A declared length is held before a byte of the body is read.
    let mut claim = Claim::new(&server.receiving);
    // 503 (1009) with `Connection: close`: the rest of the body is not read.
    let busy = |full: FullBudget| {
        server.receiving.refuse(format_args!(
            "a request for '{path}' was answered 503: {full}"
        ));
        let mut r = answer_reply(
            BackendAnswer::fail(RpcStatus::SVR_NOT_READY, format!("{full}; try again")),
            "application/json",
        );
        r.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
        r
    };
    if let Some(n) = declared {
        claim.hold(n as usize).map_err(busy)?;
    }
    let limits = server.limits;
    let body = receiving::collect(incoming, MAX_BODY as usize, &mut claim);
    let body: Bytes = match tokio::time::timeout(limits.body_timeout, body).await {
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
        Ok(Ok(b)) => b,
        Ok(Err(BodyError::TooLarge(_))) => return Err(too_large()),
        Ok(Err(BodyError::Full(full))) => return Err(busy(full)),
        Ok(Err(e)) => {
            return Err(error(
                StatusCode::BAD_REQUEST,
                &format!("cannot read the body: {e}"),
            ))
        }
    };
    if channel {
        // A channel message: the body is the encoded message; nothing is answered but
        // whether somebody here takes it.
        let body = crate::wire::Body {
            uri: path,
            serialization_type: format,
            meta: meta
                .iter()
                .filter(|(k, _)| k != meta_keys::SERIALIZATION_TYPE)
                .map(|(k, v)| (k.as_ref(), v.as_ref()))
                .collect(),
            payload: &body,
        };
        let uri = body.uri;
        return if server.channels.deliver(body, &"an http client") {
            Ok(reply(StatusCode::OK, answer_type, Vec::new()))
        } else {
            Err(error(
                StatusCode::NOT_FOUND,
                &format!(
                    "nobody here subscribes to '{uri}'{}",
                    server.channels.hint(uri)
                ),
            ))
        };
    }
    let Some(host) = server.host else {
        return Err(error(
            StatusCode::NOT_FOUND,
            "this process serves no RPC over http (aimrt.rpc does not list the http backend)",
        ));
    };
    let (tx, rx) = tokio::sync::oneshot::channel();
    {
        let pairs = meta_of(meta.iter().map(|(k, v)| (k.as_ref(), v.as_ref())));
        let call = CallView::new(&func, &pairs, call_timeout, &body);
        host.call_view(call, move |answer| {
            let _ = tx.send(answer);
        });
    }
    match rx.await {
        Ok(answer) if answer.status.is_ok() => Ok(answer_reply(answer, answer_type)),
        Ok(answer) => Err(answer_reply(answer, answer_type)),
        Err(_) => Err(error(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the service dropped the call without an answer",
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The meta a module service's route hands the runtime for a request whose
    /// `aimrt-function_name` header is `func_header`.
    fn served_meta(func_header: &str) -> Vec<(String, String)> {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        struct Capture(Mutex<Vec<(String, String)>>);
        impl aimrt_plugin_api::HostServices for Capture {
            fn invoke(&self, _: &str, _: &str, _: &[u8], r: aimrt_plugin_api::Responder) {
                r.respond(Ok(Vec::new()));
            }
            fn call_view(&self, call: aimrt_plugin_api::rpc::CallView<'_>, reply: BackendReply) {
                *self.0.lock().unwrap() = call
                    .meta_pairs()
                    .map(|(k, v)| (k.to_owned(), v.to_owned()))
                    .collect();
                reply.send(BackendAnswer::ok(Vec::new()));
            }
        }
        let capture = Arc::new(Capture(Mutex::default()));
        let func = "pb:/aimrt.protocols.example.ExampleService/GetFooData";
        let routes = Routes::default();
        routes.write().unwrap().insert(
            "/rpc/aimrt.protocols.example.ExampleService/GetFooData".into(),
            Arc::new(Route {
                func: func.into(),
                encoded: crate::header::encode(func).into_owned(),
            }),
        );
        let server = Server {
            host: Some(ServiceHost::new(capture.clone())),
            limits: Limits {
                header_timeout: Duration::from_secs(2),
                body_timeout: Duration::from_secs(2),
                max_connections: 1,
            },
            routes,
            channels: Arc::new(Inbox::new("http")),
            receiving: Receiving::new(RECEIVING_BYTES, "net_plugin http"),
            closing: Closing::never(1),
        };
        let request = format!(
            "POST /rpc/aimrt.protocols.example.ExampleService/GetFooData HTTP/1.1\r\nhost: x\r\ncontent-type: application/protobuf\r\naimrt-function%5Fname: {func_header}\r\naimrt-request%5Fid: 7\r\nmy%20key: a%2Fb\r\ncontent-length: 0\r\n\r\n"
        );
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let answer = rt.block_on(async move {
            let (mut client, side) = tokio::io::duplex(1 << 16);
            let served = tokio::spawn(serve_connection(side, None, server));
            client.write_all(request.as_bytes()).await.unwrap();
            client.shutdown().await.unwrap();
            let mut out = Vec::new();
            let _ =
                tokio::time::timeout(Duration::from_secs(2), client.read_to_end(&mut out)).await;
            served.abort();
            out
        });
        assert!(
            answer.starts_with(b"HTTP/1.1 200"),
            "{}",
            String::from_utf8_lossy(&answer)
        );
        let captured = capture.0.lock().unwrap();
        captured.clone()
    }

    /// A request the server took when it stops is answered, with `Connection: close`,
    /// before the connection closes; an idle connection is closed.
    #[test]
    fn stopping_answers_the_request_taken_then_closes() {
        use std::io::{Read, Write};
        /// Answers each call after 300 ms, from another thread.
        struct Slow;
        impl aimrt_plugin_api::HostServices for Slow {
            fn invoke(&self, _: &str, _: &str, _: &[u8], r: aimrt_plugin_api::Responder) {
                r.respond(Ok(Vec::new()));
            }
            fn call_view(&self, _: aimrt_plugin_api::rpc::CallView<'_>, reply: BackendReply) {
                std::thread::spawn(move || {
                    std::thread::sleep(Duration::from_millis(300));
                    reply.send(BackendAnswer::ok(b"done".to_vec()));
                });
            }
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .unwrap()
            .port();
        let options = HttpOptions {
            listen_ip: loopback(),
            listen_port: port,
            header_timeout_ms: default_header_timeout_ms(),
            body_timeout_ms: default_body_timeout_ms(),
            max_connections: default_max_connections(),
        };
        let shared = HttpShared::new(1, Some(options), "test".into());
        let _ = shared.host.set(ServiceHost::new(Arc::new(Slow)));
        shared.routes.write().unwrap().insert(
            "/rpc/a.B/C".into(),
            Arc::new(Route {
                func: "pb:/a.B/C".into(),
                encoded: crate::header::encode("pb:/a.B/C").into_owned(),
            }),
        );
        shared.acquire().unwrap();
        let connect = || {
            let c = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
            c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
            c
        };
        const REQUEST: &[u8] = b"POST /rpc/a.B/C HTTP/1.1\r\nhost: x\r\ncontent-type: application/protobuf\r\ncontent-length: 0\r\n\r\n";
        let (mut busy, mut idle) = (connect(), connect());
        busy.write_all(REQUEST).unwrap();
        let busy = std::thread::spawn(move || {
            let mut out = Vec::new();
            busy.read_to_end(&mut out).map(|_| out)
        });
        // The request is with the service when the server stops.
        std::thread::sleep(Duration::from_millis(100));
        shared.release();
        let answer = busy.join().unwrap().expect("the answer, not a reset");
        let answer = String::from_utf8_lossy(&answer).to_ascii_lowercase();
        assert!(answer.starts_with("http/1.1 200"), "{answer}");
        assert!(answer.contains("connection: close"), "{answer}");
        assert!(answer.ends_with("done"), "{answer}");
        let mut rest = Vec::new();
        assert_eq!(idle.read_to_end(&mut rest).unwrap(), 0, "{rest:?}");
        // Nothing listens any more.
        assert!(std::net::TcpStream::connect(("127.0.0.1", port)).is_err());
    }

    /// A request on a kept connection while the server closes is answered, with
    /// `Connection: close`; a connection that stays idle as long is closed.
    #[test]
    fn a_closing_server_answers_requests_for_a_while_then_closes_what_is_idle() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async {
            let closer = Closer::new(2);
            let server = || Server {
                host: Some(echo_host()),
                limits: Limits {
                    header_timeout: Duration::from_secs(10),
                    body_timeout: Duration::from_secs(10),
                    max_connections: 2,
                },
                routes: Routes::default(),
                channels: Arc::new(Inbox::new("http")),
                receiving: Receiving::new(RECEIVING_BYTES, "net_plugin http"),
                closing: closer.closing(),
            };
            let (mut kept, side) = tokio::io::duplex(1 << 16);
            let kept_served = tokio::spawn(serve(side, None, server(), Duration::from_secs(30)));
            let idle_for = Duration::from_millis(50);
            let (mut idle, side) = tokio::io::duplex(1 << 16);
            let idle_served = tokio::spawn(serve(side, None, server(), idle_for));
            tokio::task::yield_now().await;
            // Told to close; no connection holds a permit here, so this returns at once.
            let t0 = std::time::Instant::now();
            assert!(closer.close(Duration::ZERO));
            tokio::time::sleep(Duration::from_millis(20)).await;
            kept.write_all(b"POST /rpc/a.B/C HTTP/1.1\r\nhost: x\r\ncontent-type: application/json\r\ncontent-length: 2\r\n\r\n{}").await.unwrap();
            let mut answer = Vec::new();
            let read = tokio::time::timeout(Duration::from_secs(10), kept.read_to_end(&mut answer));
            read.await.expect("the connection closes after its answer").unwrap();
            let answer = String::from_utf8_lossy(&answer).to_ascii_lowercase();
            assert!(answer.starts_with("http/1.1 200"), "{answer}");
            assert!(answer.contains("connection: close"), "{answer}");
            assert!(answer.ends_with("{}"), "{answer}");
            kept_served.await.unwrap();
            let mut rest = Vec::new();
            let read = tokio::time::timeout(Duration::from_secs(10), idle.read_to_end(&mut rest));
            assert_eq!(read.await.expect("the idle connection is closed").unwrap(), 0);
            assert!(t0.elapsed() >= idle_for);
            idle_served.await.unwrap();
        });
    }

    /// Request bodies arriving on all connections hold at most the server's budget: with
    /// one request in the middle of a 2 MiB body, another of 2 MiB is answered 503 (1009),
    /// at once when it declares its length and part way when it is chunked; small
    /// requests are answered meanwhile, and the first completes.
    #[test]
    fn request_bodies_arriving_on_all_connections_hold_at_most_the_servers_budget() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async {
            let budget = Receiving::new(3 << 20, "net_plugin http");
            let channels = Arc::new(Inbox::new("http"));
            let server = || Server {
                host: Some(echo_host()),
                limits: Limits {
                    header_timeout: Duration::from_secs(10),
                    body_timeout: Duration::from_secs(10),
                    max_connections: 8,
                },
                routes: Routes::default(),
                channels: channels.clone(),
                receiving: budget.clone(),
                closing: Closing::never(8),
            };
            let connect = || {
                let (ours, side) = tokio::io::duplex(4 << 20);
                tokio::spawn(serve_connection(side, None, server()));
                ours
            };
            let head = |length: &str| {
                format!("POST /rpc/a.B/C HTTP/1.1\r\nhost: x\r\ncontent-type: application/json\r\n{length}\r\n\r\n")
            };
            let answer = |mut c: tokio::io::DuplexStream| async move {
                let mut out = Vec::new();
                let read = tokio::time::timeout(Duration::from_secs(10), c.read_to_end(&mut out));
                read.await.expect("an answer, and the connection closed").unwrap();
                String::from_utf8_lossy(&out).to_ascii_lowercase()
            };
            let large = vec![b'x'; 2 << 20];
            // Half of a 2 MiB body, then nothing yet: its declared length is held.
            let mut first = connect();
            first.write_all(head("content-length: 2097152").as_bytes()).await.unwrap();
            first.write_all(&large[..1 << 20]).await.unwrap();
            let whole = (2 << 20) - crate::receiving::UNCOUNTED;
            let by = std::time::Instant::now() + Duration::from_secs(10);
            while budget.held() < whole {
                assert!(std::time::Instant::now() < by, "the first body was held");
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
            // Another 2 MiB, declared: refused before its body is read.
            let mut declared = connect();
            declared.write_all(head("content-length: 2097152").as_bytes()).await.unwrap();
            let refused = answer(declared).await;
            assert!(refused.starts_with("http/1.1 503"), "{refused}");
            assert!(refused.contains("aimrt-rs-status: 1009"), "{refused}");
            assert!(refused.contains("connection: close"), "{refused}");
            assert!(refused.contains("bytes of messages are arriving on this server's connections"), "{refused}");
            // Another 2 MiB, chunked: refused part way.
            let mut chunked = connect();
            chunked.write_all(head("transfer-encoding: chunked").as_bytes()).await.unwrap();
            for part in large.chunks(256 << 10) {
                let chunk = [format!("{:x}\r\n", part.len()).as_bytes(), part, b"\r\n"].concat();
                if chunked.write_all(&chunk).await.is_err() {
                    break;
                }
            }
            let _ = chunked.write_all(b"0\r\n\r\n").await;
            let refused = answer(chunked).await;
            assert!(refused.starts_with("http/1.1 503"), "{refused}");
            // A small request is answered however full the budget is.
            let mut small = connect();
            small.write_all(format!("{}{{}}", head("content-length: 2\r\nconnection: close")).as_bytes()).await.unwrap();
            let echoed = answer(small).await;
            assert!(echoed.starts_with("http/1.1 200") && echoed.ends_with("{}"), "{echoed}");
            // The first body completes and is answered; the budget is given back.
            first.write_all(&large[1 << 20..]).await.unwrap();
            let mut out = vec![0u8; 64];
            let n = tokio::time::timeout(Duration::from_secs(10), first.read(&mut out)).await.unwrap().unwrap();
            assert!(out[..n].starts_with(b"HTTP/1.1 200"), "{:?}", String::from_utf8_lossy(&out[..n]));
            assert_eq!(budget.held(), 0);
            assert_eq!(budget.refused(), 2);
        });
    }

    #[test]
    fn a_route_reads_the_function_name_however_it_is_spelled() {
        let func = "pb:/aimrt.protocols.example.ExampleService/GetFooData";
        // AimRT's spelling (uppercase hex, as the route keeps it), lowercase hex, and a
        // name that is not the route's: each arrives decoded, the framework keys too.
        for (header, want) in [
            (
                "pb%3A%2Faimrt%2Eprotocols%2Eexample%2EExampleService%2FGetFooData",
                func,
            ),
            (
                "pb%3a%2faimrt%2eprotocols%2eexample%2eExampleService%2fGetFooData",
                func,
            ),
            ("pb%3A%2FOther%2FName", "pb:/Other/Name"),
        ] {
            let meta = served_meta(header);
            let get = |k: &str| {
                meta.iter()
                    .find(|(key, _)| key == k)
                    .map(|(_, v)| v.as_str())
            };
            assert_eq!(get("aimrt-function_name"), Some(want), "{header}: {meta:?}");
            assert_eq!(get("aimrt-request_id"), Some("7"), "{meta:?}");
            assert_eq!(get("my key"), Some("a/b"), "{meta:?}");
            assert_eq!(get("aimrt-serialization_type"), Some("pb"), "{meta:?}");
            assert_eq!(get("host"), None, "{meta:?}");
        }
    }

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
