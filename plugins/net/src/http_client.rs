//! The `http` backend's client side: module calls as `POST <server_url>/rpc/<Service>/<Method>`,
//! as AimRT's client sends them, over keep-alive connections with a cap per host.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall};
use aimrt_plugin_api::{meta_keys, Error, RpcStatus};
use bytes::Bytes;
use http_body_util::Full;
use hyper::body::Incoming;
use hyper::client::conn::http1::{self, SendRequest};
use hyper::header::{self, HeaderMap, HeaderValue};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::TokioIo;
use regex::Regex;
use serde::Deserialize;

use crate::header::STATUS_HEADER;
use crate::header::{content_type, encode, name_without_prefix, put_pair, FUNCTION_NAME, TIMEOUT};
use crate::http::MAX_BODY;
use crate::receiving;

/// `clients_options[i]` of the `http` backend's options.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ClientOption {
    func_name: String,
    server_url: String,
}

/// A compiled `clients_options` rule.
#[derive(Debug)]
struct Rule {
    pattern: Regex,
    url: Url,
}

/// An `http://host:port[/path]` address.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Url {
    /// `host:port`.
    authority: String,
    /// The host alone (AimRT's `Host` header has no port).
    host: String,
    /// The path, empty when the URL has none.
    path: String,
}

/// Where the calls of one function go: the request's path, `Host` header and function
/// name header, made once.
#[derive(Debug)]
struct Target {
    authority: String,
    /// The origin form (`/rpc/<Service>/<Method>`), as HTTP/1 sends it.
    path: hyper::Uri,
    host: HeaderValue,
    func: HeaderValue,
    /// The host's connections and call slots.
    pool: Arc<HostPool>,
}

impl Target {
    /// The target of `func` at `url`: the URL's own path, else `/rpc/<Service>/<Method>`.
    fn new(url: &Url, func: &str, pool: Arc<HostPool>) -> Option<Target> {
        let path = if url.path.is_empty() {
            format!("/rpc{}", name_without_prefix(func))
        } else {
            url.path.clone()
        };
        Some(Target {
            authority: url.authority.clone(),
            path: path.parse().ok()?,
            host: HeaderValue::from_str(&url.host).ok()?,
            func: HeaderValue::from_str(&encode(func)).ok()?,
            pool,
        })
    }
}

/// Bytes of channel messages in flight to one host at most: 1 024 requests of up to
/// 16 MiB would be 16 GiB held for a host that takes them and does not answer (each for
/// up to its 5 s deadline).
pub(crate) const PUBLISH_BYTES: usize = 256 << 20;

/// How long an idle keep-alive connection is reused at most (hyper's pooled client's
/// `pool_idle_timeout` as we had it).
const IDLE_FOR: Duration = Duration::from_secs(5);

/// One host's keep-alive HTTP/1 connections, for RPC calls and channel publishes alike:
/// the slots of requests in flight (a call waits for one, a publish is refused without
/// one) and the idle connections, reused newest first.
#[derive(Debug)]
pub(crate) struct HostPool {
    /// `host:port`, as `TcpStream::connect` takes it.
    authority: String,
    /// Requests in flight to the host at most.
    pub(crate) slots: Arc<tokio::sync::Semaphore>,
    /// Bytes of channel messages in flight to the host at most, a permit a byte
    /// ([`PUBLISH_BYTES`]); calls do not take them (their callers wait for the answers).
    pub(crate) publish_bytes: Arc<tokio::sync::Semaphore>,
    /// Idle connections kept at most, and for how long.
    keep_at_most: usize,
    idle_for: Duration,
    idle: Mutex<Vec<(SendRequest<Full<Bytes>>, Instant)>>,
}

/// The [`HostPool`]s of a client by `host:port`, and a task that closes their idle
/// connections once they are past [`IDLE_FOR`] (started with the first pool made on the
/// HTTP threads; it ends with the map).
#[derive(Debug)]
pub(crate) struct Pools {
    map: Arc<Mutex<HashMap<String, Arc<HostPool>>>>,
    reaping: std::sync::atomic::AtomicBool,
    idle_for: Duration,
}

impl Default for Pools {
    fn default() -> Pools {
        Pools::new(IDLE_FOR)
    }
}

impl Pools {
    /// Pools whose idle connections are reused for `idle_for` at most.
    pub(crate) fn new(idle_for: Duration) -> Pools {
        Pools {
            map: Arc::default(),
            reaping: std::sync::atomic::AtomicBool::new(false),
            idle_for,
        }
    }

    /// The pool of `authority`, made with `slots` when it is new. `rt` runs the reaper
    /// (default: the runtime this is called on, if any).
    pub(crate) fn get(
        &self,
        authority: &str,
        slots: usize,
        rt: Option<&tokio::runtime::Handle>,
    ) -> Arc<HostPool> {
        let pool = self
            .map
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(authority.to_owned())
            .or_insert_with(|| Arc::new(HostPool::new(authority, slots, self.idle_for)))
            .clone();
        // Looked up per call: the handle only until the reaper runs.
        if !self.reaping.load(std::sync::atomic::Ordering::Relaxed) {
            let rt = rt
                .cloned()
                .or_else(|| tokio::runtime::Handle::try_current().ok());
            if let Some(rt) = rt {
                self.start_reaper(&rt);
            }
        }
        pool
    }

    /// Starts the task that closes idle connections past their time, once, on `rt`.
    fn start_reaper(&self, rt: &tokio::runtime::Handle) {
        use std::sync::atomic::Ordering;
        if self.reaping.swap(true, Ordering::Relaxed) {
            return;
        }
        let (map, every) = (Arc::downgrade(&self.map), self.idle_for / 2);
        rt.spawn(async move {
            loop {
                tokio::time::sleep(every).await;
                let Some(map) = map.upgrade() else { return };
                let pools: Vec<_> = map
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .values()
                    .cloned()
                    .collect();
                for p in pools {
                    p.reap();
                }
            }
        });
    }
}

/// Why a request got no response.
#[derive(Debug)]
pub(crate) enum SendError {
    /// No connection could be made.
    Connect(String),
    /// The connection failed while the request was on it.
    Failed(String),
}

impl HostPool {
    /// A pool of `slots` requests in flight, keeping up to `slots` idle connections for
    /// `idle_for` each.
    fn new(authority: &str, slots: usize, idle_for: Duration) -> HostPool {
        HostPool {
            authority: authority.to_owned(),
            slots: Arc::new(tokio::sync::Semaphore::new(slots)),
            publish_bytes: Arc::new(tokio::sync::Semaphore::new(PUBLISH_BYTES)),
            keep_at_most: slots,
            idle_for,
            idle: Mutex::default(),
        }
    }

    /// The newest kept connection that is still open (it may still be finishing its last
    /// answer: wait for [`SendRequest::ready`]).
    fn reuse(&self) -> Option<SendRequest<Full<Bytes>>> {
        let mut idle = self.idle.lock().unwrap_or_else(|e| e.into_inner());
        while let Some((sender, since)) = idle.pop() {
            if since.elapsed() < self.idle_for && !sender.is_closed() {
                return Some(sender);
            }
        }
        None
    }

    /// Closes the idle connections past their time.
    fn reap(&self) {
        self.idle
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .retain(|(sender, since)| since.elapsed() < self.idle_for && !sender.is_closed());
    }

    /// Keeps `sender` for the next request once its answer was read whole (when it is
    /// open and the pool has room).
    pub(crate) fn keep(&self, sender: SendRequest<Full<Bytes>>) {
        if sender.is_closed() {
            return;
        }
        let mut idle = self.idle.lock().unwrap_or_else(|e| e.into_inner());
        if idle.len() < self.keep_at_most {
            idle.push((sender, Instant::now()));
        }
    }

    /// A new connection; its driver runs as a task until either side closes it.
    async fn connect(&self) -> Result<SendRequest<Full<Bytes>>, String> {
        let stream = tokio::net::TcpStream::connect(&self.authority)
            .await
            .map_err(|e| format!("cannot connect: {e}"))?;
        let _ = stream.set_nodelay(true);
        let (sender, connection) = http1::handshake(TokioIo::new(stream))
            .await
            .map_err(|e| format!("HTTP/1 handshake failed: {e}"))?;
        tokio::spawn(async move {
            let _ = connection.await;
        });
        Ok(sender)
    }

    /// Sends `request` (origin-form URI, `Host` set) on a kept connection, newest first,
    /// else a new one. A kept connection the server closed meanwhile hands the request
    /// back unsent, and it goes on the next (as hyper's pooled client retries); a new
    /// connection gets one try. Read the answer whole, then [`keep`](Self::keep) the
    /// sender. Dropping the future before the answer closes the connection.
    pub(crate) async fn send(
        &self,
        mut request: Request<Full<Bytes>>,
    ) -> Result<(SendRequest<Full<Bytes>>, Response<Incoming>), SendError> {
        loop {
            let (mut sender, fresh) = match self.reuse() {
                Some(mut s) => match s.ready().await {
                    Ok(()) => (s, false),
                    Err(_) => continue,
                },
                None => (self.connect().await.map_err(SendError::Connect)?, true),
            };
            match sender.try_send_request(request).await {
                Ok(r) => return Ok((sender, r)),
                Err(mut e) => match e.take_message() {
                    Some(back) if !fresh => request = back,
                    _ => {
                        use std::error::Error as _;
                        let e = e.into_error();
                        return Err(SendError::Failed(
                            e.source()
                                .map_or_else(|| e.to_string(), |s| format!("{e}: {s}")),
                        ));
                    }
                },
            }
        }
    }
}

impl Url {
    /// Parses `http://host[:port][/path]`; `None` when it is not such a URL.
    pub(crate) fn parse(text: &str) -> Option<Url> {
        let rest = text.strip_prefix("http://")?;
        let (authority, path) = match rest.find('/') {
            Some(i) => (&rest[..i], &rest[i..]),
            None => (rest, ""),
        };
        let uri: hyper::Uri = format!("http://{authority}/").parse().ok()?;
        let host = uri.host()?.to_owned();
        if host.is_empty() {
            return None;
        }
        let port = uri.port_u16().unwrap_or(80);
        let bare = host.trim_start_matches('[').trim_end_matches(']');
        let authority = if bare.contains(':') {
            format!("[{bare}]:{port}")
        } else {
            format!("{host}:{port}")
        };
        Some(Url {
            authority,
            host,
            path: path.to_owned(),
        })
    }
}

/// `secs` as a header value: a static one up to a minute (no allocation per call), else
/// formatted.
fn seconds(secs: u64) -> HeaderValue {
    const TEXT: [&str; 61] = [
        "0", "1", "2", "3", "4", "5", "6", "7", "8", "9", "10", "11", "12", "13", "14", "15", "16",
        "17", "18", "19", "20", "21", "22", "23", "24", "25", "26", "27", "28", "29", "30", "31",
        "32", "33", "34", "35", "36", "37", "38", "39", "40", "41", "42", "43", "44", "45", "46",
        "47", "48", "49", "50", "51", "52", "53", "54", "55", "56", "57", "58", "59", "60",
    ];
    match usize::try_from(secs).ok().and_then(|i| TEXT.get(i)) {
        Some(text) => HeaderValue::from_static(text),
        None => HeaderValue::from(secs),
    }
}

/// The client: rules from the options, the URL of each registered function, and the
/// keep-alive connections of each host with its cap of calls in flight.
pub(crate) struct HttpClient {
    rules: Vec<Rule>,
    /// By function name (a fast hash: looked up on every call).
    targets: RwLock<HashMap<String, Arc<Target>, foldhash::fast::RandomState>>,
    per_host: usize,
    hosts: Pools,
}

impl HttpClient {
    /// Compiles the rules; `where_` names the options for messages.
    pub(crate) fn new(
        options: Vec<ClientOption>,
        per_host: usize,
        where_: &str,
    ) -> Result<HttpClient, Error> {
        let mut rules = Vec::new();
        for (i, o) in options.into_iter().enumerate() {
            let bad = |message: String| Error::Options {
                what: format!("http backend options at {where_}"),
                message: format!("clients_options[{i}]: {message}"),
            };
            let pattern = aimrt_plugin_api::whole_match(&o.func_name).map_err(|e| {
                bad(format!(
                    "func_name '{}' is not a valid regular expression: {e}",
                    o.func_name
                ))
            })?;
            let url = Url::parse(&o.server_url).ok_or_else(|| {
                bad(format!(
                    "server_url '{}' is not an http://host:port address, e.g. http://127.0.0.1:50080",
                    o.server_url
                ))
            })?;
            if url.authority.ends_with(":0") {
                return Err(bad(format!(
                    "server_url '{}' has port 0, where no server listens; give the port of the server's listen_port",
                    o.server_url
                )));
            }
            rules.push(Rule { pattern, url });
        }
        Ok(HttpClient {
            rules,
            targets: RwLock::default(),
            per_host,
            hosts: Pools::default(),
        })
    }

    /// Resolves the server URL of `func` (first rule matching the full name or the name
    /// without prefix); warns, as AimRT, when none does.
    pub(crate) fn register(&self, func: &str) {
        let short = name_without_prefix(func);
        match self
            .rules
            .iter()
            .find(|r| r.pattern.is_match(func) || r.pattern.is_match(short))
        {
            Some(rule) => match Target::new(&rule.url, func, self.pool(&rule.url.authority)) {
                Some(target) => {
                    self.targets
                        .write()
                        .unwrap_or_else(|e| e.into_inner())
                        .insert(func.to_owned(), Arc::new(target));
                }
                None => {
                    tracing::warn!(target: "aimrt", "the http backend cannot call '{func}' at {}: it makes no valid URI; its calls need aimrt-to_addr", rule.url.authority);
                }
            },
            None => {
                tracing::warn!(target: "aimrt", "Server url is not set for func: {func} (no clients_options rule of the http backend matches it); its calls need aimrt-to_addr");
            }
        }
    }

    fn pool(&self, authority: &str) -> Arc<HostPool> {
        self.hosts.get(authority, self.per_host, None)
    }

    /// Carries one call; every outcome is an answer.
    pub(crate) async fn call(&self, call: BackendCall) -> BackendAnswer {
        let to_addr = call.meta(meta_keys::TO_ADDR).unwrap_or("");
        let target = if to_addr.is_empty() {
            let targets = self.targets.read().unwrap_or_else(|e| e.into_inner());
            match targets.get(&call.func) {
                Some(t) => t.clone(),
                None => {
                    return BackendAnswer::fail(
                        RpcStatus::CLI_INVALID_ADDR,
                        format!("no server URL for '{}': give the http backend a clients_options rule with server_url, or set aimrt-to_addr", call.func),
                    )
                }
            }
        } else {
            match Url::parse(to_addr)
                .and_then(|u| Target::new(&u, &call.func, self.pool(&u.authority)))
            {
                Some(t) => Arc::new(t),
                None => {
                    return BackendAnswer::fail(
                        RpcStatus::CLI_INVALID_ADDR,
                        format!("aimrt-to_addr '{to_addr}' is not an http://host:port address"),
                    )
                }
            }
        };
        let format = call.serialization_type().unwrap_or("pb");
        let Some(ct) = content_type(format) else {
            return BackendAnswer::fail(
                RpcStatus::CLI_INVALID_SERIALIZATION_TYPE,
                format!("the http backend carries pb, json and ros2, not '{format}'"),
            );
        };
        let timeout = call.timeout.unwrap_or(Duration::from_secs(5));
        match tokio::time::timeout(timeout, self.send(&target, ct, call)).await {
            Ok(answer) => answer,
            Err(_) => BackendAnswer::fail(
                RpcStatus::TIMEOUT,
                format!(
                    "no answer from {} within {} ms",
                    target.authority,
                    timeout.as_millis()
                ),
            ),
        }
    }

    async fn send(&self, target: &Target, ct: &'static str, call: BackendCall) -> BackendAnswer {
        let timeout = call.timeout.unwrap_or(Duration::from_secs(5));
        // Whole seconds, rounded up (AimRT truncates, so 500 ms would say 0: none).
        let secs = timeout.as_secs() + u64::from(timeout.subsec_nanos() > 0);
        let mut headers = HeaderMap::with_capacity(8 + call.meta_len());
        headers.insert(header::HOST, target.host.clone());
        headers.insert(header::USER_AGENT, HeaderValue::from_static("aimrt"));
        headers.insert(TIMEOUT, seconds(secs));
        headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
        for (k, v) in call.meta_pairs() {
            if k == meta_keys::FUNCTION_NAME && v == call.func {
                headers.insert(FUNCTION_NAME, target.func.clone());
            } else {
                put_pair(&mut headers, k, v);
            }
        }
        let mut request = Request::new(Full::new(Bytes::from(call.body)));
        *request.method_mut() = Method::POST;
        *request.uri_mut() = target.path.clone();
        *request.headers_mut() = headers;
        let pool = &target.pool;
        let Ok(_slot) = pool.slots.acquire().await else {
            return BackendAnswer::fail(
                RpcStatus::CLI_BACKEND_INTERNAL_ERROR,
                "the http client is shut down",
            );
        };
        let (sender, response) = match pool.send(request).await {
            Ok(r) => r,
            Err(e) => {
                let (status, why) = match e {
                    SendError::Connect(why) => (RpcStatus::CLI_SEND_REQ_FAILED, why),
                    SendError::Failed(why) => (RpcStatus::CLI_UNKNOWN, why),
                };
                return BackendAnswer::fail(
                    status,
                    format!("http call to {} failed: {why}", target.authority),
                );
            }
        };
        let status = response.status();
        let code = response
            .headers()
            .get(STATUS_HEADER)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.trim().parse::<u32>().ok());
        let body = match receiving::collect_within(response.into_body(), MAX_BODY as usize).await {
            Ok(b) => Vec::from(b),
            Err(e) => {
                return BackendAnswer::fail(
                    RpcStatus::CLI_DESERIALIZATION_FAILED,
                    format!("cannot read the answer of {}: {e}", target.authority),
                )
            }
        };
        // The answer is read whole: the connection can take the next call.
        pool.keep(sender);
        if status == StatusCode::OK {
            return BackendAnswer::ok(body);
        }
        let text = String::from_utf8_lossy(&body[..body.len().min(512)]).into_owned();
        match code {
            Some(c) if c != 0 => BackendAnswer::fail(RpcStatus::from_code(c), text),
            // AimRT's server says nothing more: 1003, as AimRT's client.
            _ => BackendAnswer::fail(
                RpcStatus::SVR_NOT_FOUND,
                format!("{} answered HTTP {status}: {text}", target.authority),
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use http_body_util::BodyExt;

    /// A server on a free port answering every POST with 200 and its body, closing each
    /// connection after one answer when `close_each`; counts the connections it accepts.
    async fn echo_server(close_each: bool) -> (String, Arc<[std::sync::atomic::AtomicUsize; 2]>) {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        // Accepted and closed connections.
        let counts = Arc::new([AtomicUsize::new(0), AtomicUsize::new(0)]);
        let count = counts.clone();
        tokio::spawn(async move {
            while let Ok((stream, _)) = listener.accept().await {
                count[0].fetch_add(1, Ordering::SeqCst);
                let count = count.clone();
                tokio::spawn(async move {
                    let service = hyper::service::service_fn(
                        |req: Request<hyper::body::Incoming>| async move {
                            let body = req.into_body().collect().await?.to_bytes();
                            Ok::<_, hyper::Error>(hyper::Response::new(Full::new(body)))
                        },
                    );
                    let _ = hyper::server::conn::http1::Builder::new()
                        .keep_alive(!close_each)
                        .serve_connection(TokioIo::new(stream), service)
                        .await;
                    count[1].fetch_add(1, Ordering::SeqCst);
                });
            }
        });
        (addr, counts)
    }

    /// The HTTP threads of a test: two workers, as net_plugin's default.
    fn runtime() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap()
    }

    fn client_of(addr: &str) -> HttpClient {
        let rule = ClientOption {
            func_name: ".*".into(),
            server_url: format!("http://{addr}"),
        };
        let client = HttpClient::new(vec![rule], 2, "test").unwrap();
        client.register("pb:/x/Y");
        client
    }

    fn call_of(body: &[u8]) -> BackendCall {
        let mut call = BackendCall::new("pb:/x/Y");
        call.set_meta(meta_keys::SERIALIZATION_TYPE, "pb");
        call.timeout = Some(Duration::from_secs(5));
        call.body = body.to_vec();
        call
    }

    /// Calls one after another share one kept connection; when the server closes each
    /// connection after its answer, every call still gets its answer on a new one.
    #[test]
    fn kept_connections_are_reused_and_closed_ones_replaced() {
        use std::sync::atomic::Ordering;
        let rt = runtime();
        rt.block_on(async {
            for close_each in [false, true] {
                let (addr, counts) = echo_server(close_each).await;
                let client = client_of(&addr);
                for i in 0..5u8 {
                    let answer = client.call(call_of(&[i; 3])).await;
                    assert_eq!(answer.status, RpcStatus::OK, "{}", answer.detail);
                    assert_eq!(answer.body, [i; 3]);
                    // Give a closing server's end time to reach the client.
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                let expected = if close_each { 5 } else { 1 };
                assert_eq!(
                    counts[0].load(Ordering::SeqCst),
                    expected,
                    "close_each {close_each}"
                );
            }
        });
    }

    /// A kept connection idle past its time is closed by the reaper, not left open.
    #[test]
    fn idle_connections_are_closed_after_their_time() {
        use std::sync::atomic::Ordering;
        let rt = runtime();
        rt.block_on(async {
            let (addr, counts) = echo_server(false).await;
            let pools = Pools::new(Duration::from_millis(200));
            let pool = pools.get(&addr, 2, None);
            let mut request = Request::new(Full::new(Bytes::from_static(b"x")));
            *request.method_mut() = Method::POST;
            *request.uri_mut() = "/rpc/x/Y".parse().unwrap();
            request
                .headers_mut()
                .insert(header::HOST, HeaderValue::from_static("127.0.0.1"));
            let (sender, response) = pool.send(request).await.unwrap();
            response.into_body().collect().await.unwrap();
            pool.keep(sender);
            assert_eq!(pool.idle.lock().unwrap().len(), 1);
            let deadline = Instant::now() + Duration::from_secs(5);
            while counts[1].load(Ordering::SeqCst) == 0 {
                assert!(
                    Instant::now() < deadline,
                    "the idle connection was never closed"
                );
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            assert!(pool.idle.lock().unwrap().is_empty());
            assert_eq!(counts[0].load(Ordering::SeqCst), 1);
        });
    }

    /// A server on a free port that answers each connection's first request with `parts`,
    /// 20 ms apart (so they arrive as pieces), then holds the connection open.
    async fn raw_server(parts: Vec<Vec<u8>>) -> String {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        tokio::spawn(async move {
            while let Ok((mut stream, _)) = listener.accept().await {
                let parts = parts.clone();
                tokio::spawn(async move {
                    let (mut head, mut buf) = (Vec::new(), [0u8; 4096]);
                    while !head.windows(4).any(|w| w == b"\r\n\r\n") {
                        match stream.read(&mut buf).await {
                            Ok(0) | Err(_) => return,
                            Ok(n) => head.extend_from_slice(&buf[..n]),
                        }
                    }
                    for part in parts {
                        tokio::time::sleep(Duration::from_millis(20)).await;
                        if stream.write_all(&part).await.is_err() {
                            return;
                        }
                    }
                    tokio::time::sleep(Duration::from_secs(30)).await;
                });
            }
        });
        addr
    }

    /// An answer is read whole, also when it arrives in pieces; one that declares more
    /// than AimRT's 16 MiB is refused at once, without waiting for its body (which this
    /// server never sends: the call would wait out its 5 s timeout).
    #[test]
    fn answers_are_read_whole_and_one_declared_too_large_is_refused_at_once() {
        let rt = runtime();
        rt.block_on(async {
            let parts = vec![
                b"HTTP/1.1 200 OK\r\nContent-Length: 6\r\n\r\nabc".to_vec(),
                b"de".to_vec(),
                b"f".to_vec(),
            ];
            let answer = client_of(&raw_server(parts).await)
                .call(call_of(b"x"))
                .await;
            assert_eq!(answer.status, RpcStatus::OK, "{}", answer.detail);
            assert_eq!(answer.body, b"abcdef");

            let head = format!(
                "HTTP/1.1 200 OK\r\nContent-Length: {}\r\n\r\n",
                MAX_BODY + 1
            );
            let client = client_of(&raw_server(vec![head.into_bytes()]).await);
            let started = Instant::now();
            let answer = client.call(call_of(b"x")).await;
            assert_eq!(
                answer.status,
                RpcStatus::CLI_DESERIALIZATION_FAILED,
                "{}",
                answer.detail
            );
            assert!(
                answer
                    .detail
                    .contains("larger than the limit of 16777216 bytes"),
                "{}",
                answer.detail
            );
            assert!(started.elapsed() < Duration::from_secs(4), "not at once");
        });
    }

    /// Nobody listening: 2010 (the server cannot be reached), at once.
    #[test]
    fn an_unreachable_server_is_2010() {
        let rt = runtime();
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let answer = rt.block_on(client_of(&format!("127.0.0.1:{port}")).call(call_of(b"x")));
        assert_eq!(
            answer.status,
            RpcStatus::CLI_SEND_REQ_FAILED,
            "{}",
            answer.detail
        );
        assert!(
            answer.detail.contains("cannot connect"),
            "{}",
            answer.detail
        );
    }

    #[test]
    fn timeouts_are_whole_seconds_in_decimal() {
        for secs in [0, 1, 9, 10, 59, 60, 61, 3600, u64::MAX] {
            assert_eq!(seconds(secs).to_str().unwrap(), secs.to_string());
        }
    }

    #[test]
    fn urls_parse_as_aimrt_writes_them() {
        let u = Url::parse("http://127.0.0.1:50080").unwrap();
        assert_eq!(
            (u.authority.as_str(), u.host.as_str(), u.path.as_str()),
            ("127.0.0.1:50080", "127.0.0.1", "")
        );
        let u = Url::parse("http://localhost/custom/path").unwrap();
        assert_eq!(
            (u.authority.as_str(), u.path.as_str()),
            ("localhost:80", "/custom/path")
        );
        let u = Url::parse("http://[::1]:8080").unwrap();
        assert_eq!(u.authority, "[::1]:8080");
        for bad in [
            "127.0.0.1:50080",
            "https://x:1",
            "http://",
            "http://:80",
            "http://a b:1",
        ] {
            assert_eq!(Url::parse(bad), None, "{bad}");
        }
    }
}
