//! The `grpc` backend's client: module calls as unary gRPC calls to the `server_url` of the
//! first `clients_options` rule that matches the function (or the call's
//! `aimrt-to_addr`), one HTTP/2 connection per server, its calls multiplexed on it.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Duration;

use aimrt_net::header::{encode, name_without_prefix};
use aimrt_net::receiving;
use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall};
use aimrt_plugin_api::{meta_keys, Error, RateLimit, RpcStatus};
use bytes::Bytes;
use hyper::client::conn::http2::SendRequest;
use hyper::header::{self, HeaderMap, HeaderName, HeaderValue};
use hyper::{Method, Request, StatusCode};
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use regex::Regex;
use serde::{Deserialize, Serialize};

use crate::server::{GrpcBody, MAX_MESSAGE};
use crate::wire;

/// How long a call waits for its answer when the caller gave no timeout.
const DEFAULT_TIMEOUT: Duration = Duration::from_secs(5);

/// `clients_options[i]` of the `grpc` backend (AimRT's keys).
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ClientOption {
    func_name: String,
    server_url: String,
}

/// An `http://host:port` server address (or `grpc://host:port`, as a call's
/// `aimrt-to_addr` names the backend): `host:port`.
fn authority_of(url: &str) -> Option<String> {
    let rest = url
        .strip_prefix("http://")
        .or_else(|| url.strip_prefix("grpc://"))?;
    let authority = rest.split('/').next()?;
    let uri: hyper::Uri = format!("http://{authority}/").parse().ok()?;
    let host = uri.host().filter(|h| !h.is_empty())?;
    let port = uri.port_u16()?;
    Some(format!("{host}:{port}"))
}

/// One server's connection, once made.
type Slot = Arc<tokio::sync::Mutex<Option<Conn>>>;

/// A connection to a server, and how many answers it has brought: a call that times out
/// on a connection that brought none since the call went out finds it stalled (a network
/// that stopped carrying, where TCP may take minutes to give up), not a slow service.
#[derive(Clone)]
struct Conn {
    sender: SendRequest<GrpcBody>,
    answers: Arc<AtomicU64>,
}

/// The connection a call went out on, and its answers then.
type Sent = Option<(Arc<AtomicU64>, u64)>;

/// Where the calls of one function go.
#[derive(Debug)]
struct Target {
    authority: String,
    /// `http://host:port/Service/Method`.
    uri: hyper::Uri,
}

impl Target {
    fn new(authority: &str, func: &str) -> Option<Target> {
        Some(Target {
            authority: authority.to_owned(),
            uri: format!("http://{authority}{}", name_without_prefix(func))
                .parse()
                .ok()?,
        })
    }
}

/// The client: the rules, each registered function's target, and one connection per
/// server.
pub(crate) struct GrpcClient {
    rules: Vec<(Regex, String)>,
    targets: RwLock<HashMap<String, Arc<Target>>>,
    /// Per server, its connection; the slot is held across a connect, so that calls
    /// starting together share one new connection instead of each opening its own (and a
    /// server that is slow to connect to holds up only its own calls).
    connections: Mutex<HashMap<String, Slot>>,
    /// Limits the lines about connections given up.
    alarm: RateLimit,
}

impl GrpcClient {
    /// Compiles the rules; `where_` names the options for messages.
    pub(crate) fn new(options: Vec<ClientOption>, where_: &str) -> Result<GrpcClient, Error> {
        let mut rules = Vec::new();
        for (i, o) in options.into_iter().enumerate() {
            let bad = |message: String| Error::Options {
                what: format!("grpc backend options at {where_}"),
                message: format!("clients_options[{i}]: {message}"),
            };
            let pattern = aimrt_plugin_api::whole_match(&o.func_name).map_err(|e| {
                bad(format!(
                    "func_name '{}' is not a valid regular expression: {e}",
                    o.func_name
                ))
            })?;
            let authority = authority_of(&o.server_url).ok_or_else(|| {
                bad(format!(
                    "server_url '{}' is not an http://host:port address (gRPC without TLS), e.g. http://127.0.0.1:50050",
                    o.server_url
                ))
            })?;
            if authority.ends_with(":0") {
                return Err(bad(format!(
                    "server_url '{}' has port 0, where no server listens; give the server's listen_port",
                    o.server_url
                )));
            }
            rules.push((pattern, authority));
        }
        Ok(GrpcClient {
            rules,
            targets: RwLock::default(),
            connections: Mutex::default(),
            alarm: RateLimit::from_millis(1000),
        })
    }

    /// Resolves the server of `func` (the first rule matching the full name or the name
    /// without prefix); warns, as AimRT, when none does.
    pub(crate) fn register(&self, func: &str) {
        let short = name_without_prefix(func);
        let rule = self
            .rules
            .iter()
            .find(|(p, _)| p.is_match(func) || p.is_match(short));
        match rule.and_then(|(_, authority)| Target::new(authority, func)) {
            Some(target) => {
                self.targets
                    .write()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert(func.to_owned(), Arc::new(target));
            }
            None => {
                tracing::warn!(target: "aimrt", "Server url is not set for func: {func} (no clients_options rule of the grpc backend matches it); its calls need aimrt-to_addr");
            }
        }
    }

    /// Carries one call; every outcome is an answer, within the call's timeout.
    pub(crate) async fn call(&self, call: BackendCall) -> BackendAnswer {
        let to_addr = call.meta(meta_keys::TO_ADDR).unwrap_or("");
        let target = if to_addr.is_empty() {
            let found = self
                .targets
                .read()
                .unwrap_or_else(|e| e.into_inner())
                .get(&call.func)
                .cloned();
            match found {
                Some(t) => t,
                None => {
                    return BackendAnswer::fail(
                        RpcStatus::CLI_INVALID_ADDR,
                        format!("no server for '{}': give the grpc backend a clients_options rule with server_url, or set aimrt-to_addr", call.func),
                    )
                }
            }
        } else {
            match authority_of(to_addr).and_then(|a| Target::new(&a, &call.func)) {
                Some(t) => Arc::new(t),
                None => {
                    return BackendAnswer::fail(
                        RpcStatus::CLI_INVALID_ADDR,
                        format!("aimrt-to_addr '{to_addr}' is not a grpc://host:port address"),
                    )
                }
            }
        };
        let format = call.serialization_type().unwrap_or("pb");
        let Some(content_type) = wire::content_type_of(format) else {
            return BackendAnswer::fail(
                RpcStatus::CLI_INVALID_SERIALIZATION_TYPE,
                format!("the grpc backend carries pb, json and ros2, not '{format}'"),
            );
        };
        let timeout = call.timeout.unwrap_or(DEFAULT_TIMEOUT);
        let mut sent = None;
        let answered = tokio::time::timeout(
            timeout,
            self.send(&target, content_type, timeout, call, &mut sent),
        )
        .await;
        match answered {
            Ok(answer) => answer,
            Err(_) => {
                if let Some((answers, then)) = sent {
                    if answers.load(Ordering::SeqCst) == then {
                        self.give_up(&target.authority, &answers, timeout);
                    }
                }
                BackendAnswer::fail(
                    RpcStatus::TIMEOUT,
                    format!(
                        "no answer from {} within {} ms",
                        target.authority,
                        timeout.as_millis()
                    ),
                )
            }
        }
    }

    /// Stops giving new calls the connection to `authority` that `answers` counts: the
    /// next call opens a new one. The calls still on it end at their deadlines.
    fn give_up(&self, authority: &str, answers: &Arc<AtomicU64>, waited: Duration) {
        let slot = self
            .connections
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(authority)
            .cloned();
        // Busy: another call is connecting or taking the connection; a later timeout
        // gives it up if it is still stalled.
        let Some(mut slot) = slot.as_ref().and_then(|s| s.try_lock().ok()) else {
            return;
        };
        if slot
            .as_ref()
            .is_some_and(|c| Arc::ptr_eq(&c.answers, answers))
        {
            *slot = None;
            if let Some(held) = self.alarm.admit() {
                tracing::info!(target: "aimrt", "grpc_plugin: the connection to {authority} brought no answer while a call waited {} ms for one: the next call opens a new connection ({held} more such lines held back since the last)", waited.as_millis());
            }
        }
    }

    /// The connection to `authority`: the open one, else a new one.
    async fn connection(&self, authority: &str) -> Result<Conn, String> {
        let slot = self
            .connections
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(authority.to_owned())
            .or_default()
            .clone();
        let mut slot = slot.lock().await;
        if let Some(conn) = slot.as_ref().filter(|c| !c.sender.is_closed()) {
            return Ok(conn.clone());
        }
        let stream = tokio::net::TcpStream::connect(authority)
            .await
            .map_err(|e| format!("cannot connect to {authority}: {e}"))?;
        let _ = stream.set_nodelay(true);
        let (sender, connection) = hyper::client::conn::http2::Builder::new(TokioExecutor::new())
            .timer(TokioTimer::new())
            .handshake(TokioIo::new(stream))
            .await
            .map_err(|e| format!("HTTP/2 handshake with {authority} failed: {e}"))?;
        tokio::spawn(async move {
            let _ = connection.await;
        });
        let conn = Conn {
            sender,
            answers: Arc::default(),
        };
        *slot = Some(conn.clone());
        Ok(conn)
    }

    async fn send(
        &self,
        target: &Target,
        content_type: &'static str,
        timeout: Duration,
        call: BackendCall,
        sent: &mut Sent,
    ) -> BackendAnswer {
        let mut headers = HeaderMap::with_capacity(6 + call.meta_len());
        headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
        headers.insert(header::TE, HeaderValue::from_static("trailers"));
        headers.insert(
            header::USER_AGENT,
            HeaderValue::from_static(concat!("grpc-rust-aimrt-rs/", env!("CARGO_PKG_VERSION"))),
        );
        headers.insert(wire::GRPC_TIMEOUT.clone(), wire::timeout_header(timeout));
        for (k, v) in call.meta_pairs() {
            put_meta(&mut headers, k, v);
        }
        let mut request = Request::new(GrpcBody::new(
            Some(Bytes::from(wire::frame(&call.body))),
            None,
        ));
        *request.method_mut() = Method::POST;
        *request.uri_mut() = target.uri.clone();
        *request.headers_mut() = headers;
        let Conn {
            mut sender,
            answers,
        } = match self.connection(&target.authority).await {
            Ok(c) => c,
            Err(why) => return BackendAnswer::fail(RpcStatus::CLI_SEND_REQ_FAILED, why),
        };
        *sent = Some((answers.clone(), answers.load(Ordering::SeqCst)));
        if let Err(e) = sender.ready().await {
            return BackendAnswer::fail(
                RpcStatus::CLI_SEND_REQ_FAILED,
                format!("the connection to {} closed: {e}", target.authority),
            );
        }
        let response = match sender.send_request(request).await {
            Ok(r) => {
                answers.fetch_add(1, Ordering::SeqCst);
                r
            }
            Err(e) if never_ran(&e) => {
                return BackendAnswer::fail(
                    RpcStatus::CLI_SEND_REQ_FAILED,
                    format!("the connection to {} closed before it took the call (the call was still queued, or the server's GOAWAY or REFUSED_STREAM left it out): it did not run", target.authority),
                )
            }
            Err(e) => {
                return BackendAnswer::fail(
                    RpcStatus::CLI_UNKNOWN,
                    format!("grpc call to {} failed: {e}", target.authority),
                )
            }
        };
        let (parts, body) = response.into_parts();
        if parts.status != StatusCode::OK {
            let status = match parts.status {
                StatusCode::NOT_FOUND => RpcStatus::SVR_NOT_FOUND,
                StatusCode::UNSUPPORTED_MEDIA_TYPE => RpcStatus::SVR_INVALID_DESERIALIZATION_TYPE,
                _ => RpcStatus::CLI_UNKNOWN,
            };
            return BackendAnswer::fail(
                status,
                format!(
                    "{} answered HTTP {} instead of a gRPC answer",
                    target.authority, parts.status
                ),
            );
        }
        let mut trailers = None;
        let read =
            receiving::collect_with_trailers(body, MAX_MESSAGE + wire::PREFIX, &mut trailers);
        let answer = match read.await {
            Ok(a) => a,
            Err(e) => {
                return BackendAnswer::fail(
                    RpcStatus::CLI_DESERIALIZATION_FAILED,
                    format!("cannot read the answer of {}: {e}", target.authority),
                )
            }
        };
        let trailers = trailers.unwrap_or_default();
        // The status: in the trailers, or in the headers of a trailers-only answer.
        let find = |name: &str| {
            trailers
                .get(name)
                .or_else(|| parts.headers.get(name))
                .and_then(|v| v.to_str().ok())
                .map(str::to_owned)
        };
        let Some(grpc) = find("grpc-status").and_then(|s| s.trim().parse::<u32>().ok()) else {
            return BackendAnswer::fail(
                RpcStatus::CLI_UNKNOWN,
                format!("the answer of {} has no grpc-status", target.authority),
            );
        };
        if grpc != wire::code::OK {
            let message = find("grpc-message")
                .map(|m| wire::decode_message(&m))
                .unwrap_or_default();
            let status = find(wire::AIMRT_STATUS)
                .and_then(|s| s.trim().parse::<u32>().ok())
                .filter(|c| *c != 0)
                .map_or_else(|| wire::status_of_grpc(grpc), RpcStatus::from_code);
            return BackendAnswer::fail(
                status,
                format!(
                    "{} answered grpc-status {grpc}: {message}",
                    target.authority
                ),
            );
        }
        match wire::unframe(&answer) {
            Ok(message) => BackendAnswer::ok(message.to_vec()),
            Err(e) => BackendAnswer::fail(
                RpcStatus::CLI_DESERIALIZATION_FAILED,
                format!("the answer of {}: {e}", target.authority),
            ),
        }
    }
}

/// The framework's meta keys that travel under their own names, made once (parsing a
/// name copies it).
static KNOWN: [HeaderName; 6] = [
    HeaderName::from_static(meta_keys::FUNCTION_NAME),
    HeaderName::from_static(meta_keys::REQUEST_ID),
    HeaderName::from_static(meta_keys::RESPONSE_ID),
    HeaderName::from_static(meta_keys::BACKEND),
    HeaderName::from_static(meta_keys::FROM_PKG),
    HeaderName::from_static(meta_keys::FROM_MODULE),
];

/// Adds one meta pair as a header: under its own name when that is a valid HTTP/2 name
/// (lowercase), as AimRT's grpc client sends it, else in net_plugin's encoding (HTTP
/// lowercases names: `Trace-Id` arrives as `trace-id`); never under a name of the
/// protocol's.
fn put_meta(headers: &mut HeaderMap, key: &str, value: &str) {
    if key == meta_keys::SERIALIZATION_TYPE || key == meta_keys::TO_ADDR {
        return;
    }
    let name = KNOWN
        .iter()
        .find(|n| n.as_str() == key)
        .cloned()
        .or_else(|| {
            HeaderName::from_bytes(key.as_bytes())
                .ok()
                .filter(|n| n.as_str() == key)
        })
        .or_else(|| HeaderName::from_bytes(encode(key).as_bytes()).ok());
    let Some(name) = name else { return };
    if name == header::CONTENT_TYPE
        || name == header::TE
        || name == header::USER_AGENT
        || name == header::HOST
        || name == header::CONTENT_LENGTH
        || name.as_str().starts_with("grpc-")
    {
        return;
    }
    // As is when it can be (AimRT's server reads values as they come), else encoded (ours
    // decodes `%XX`, so a `%` is always encoded).
    let value = match HeaderValue::from_str(value) {
        Ok(v) if !value.contains('%') => Ok(v),
        _ => HeaderValue::from_str(&encode(value)),
    };
    if let Ok(v) = value {
        headers.insert(name, v);
    }
}

/// Whether the call never reached the server: hyper gave it up before it went out (the
/// connection closed while it waited for a stream), or the server said it did not take
/// it (a `GOAWAY` whose last stream is below the call's, or `REFUSED_STREAM`, which
/// HTTP/2 guarantees did not run).
fn never_ran(e: &hyper::Error) -> bool {
    if e.is_canceled() {
        return true;
    }
    let mut source = std::error::Error::source(e);
    while let Some(s) = source {
        if let Some(h2) = s.downcast_ref::<h2::Error>() {
            return h2.is_remote()
                && (h2.is_go_away() || h2.reason() == Some(h2::Reason::REFUSED_STREAM));
        }
        source = s.source();
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn server_urls_are_http_host_port() {
        assert_eq!(
            authority_of("http://127.0.0.1:50050").as_deref(),
            Some("127.0.0.1:50050")
        );
        assert_eq!(
            authority_of("http://localhost:1/x").as_deref(),
            Some("localhost:1")
        );
        assert_eq!(
            authority_of("grpc://10.0.0.7:50050").as_deref(),
            Some("10.0.0.7:50050")
        );
        assert_eq!(authority_of("https://127.0.0.1:50050"), None);
        assert_eq!(authority_of("127.0.0.1:50050"), None);
        assert_eq!(authority_of("http://127.0.0.1"), None, "a port is needed");
        let err = GrpcClient::new(
            vec![ClientOption {
                func_name: "(.*)".into(),
                server_url: "127.0.0.1:50050".into(),
            }],
            "cfg.yaml:3:5",
        )
        .err()
        .unwrap()
        .to_string();
        assert!(
            err.contains("clients_options[0]") && err.contains("http://127.0.0.1:50050"),
            "{err}"
        );
    }

    fn two_threads() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap()
    }

    #[test]
    fn calls_starting_together_share_one_new_connection() {
        two_threads().block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            let authority = listener.local_addr().unwrap().to_string();
            let accepted = Arc::new(std::sync::atomic::AtomicUsize::new(0));
            let counter = accepted.clone();
            tokio::spawn(async move {
                let mut open = Vec::new();
                while let Ok((stream, _)) = listener.accept().await {
                    counter.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                    open.push(stream);
                }
            });
            let client = Arc::new(GrpcClient::new(Vec::new(), "test").unwrap());
            let tasks: Vec<_> = (0..20)
                .map(|_| {
                    let (client, authority) = (client.clone(), authority.clone());
                    tokio::spawn(async move { client.connection(&authority).await.is_ok() })
                })
                .collect();
            for t in tasks {
                assert!(t.await.unwrap());
            }
            assert_eq!(accepted.load(std::sync::atomic::Ordering::SeqCst), 1);
        });
    }

    #[test]
    fn aimrt_to_addr_names_the_server_of_one_call() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        // A port nobody listens on: free now, closed again.
        let closed = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap();
        let client = GrpcClient::new(Vec::new(), "test").unwrap();
        let func = "pb:/a.B/C";
        client.register(func);
        let call = |to_addr: Option<&str>| {
            let mut call = BackendCall::new(func);
            if let Some(a) = to_addr {
                call.set_meta(meta_keys::TO_ADDR, a);
            }
            call.timeout = Some(Duration::from_secs(5));
            rt.block_on(client.call(call))
        };
        // No rule and no aimrt-to_addr: no server.
        let a = call(None);
        assert_eq!(a.status, RpcStatus::CLI_INVALID_ADDR, "{}", a.detail);
        // aimrt-to_addr is used: the call goes to that address (nobody there).
        let a = call(Some(&format!("grpc://{closed}")));
        assert_eq!(a.status, RpcStatus::CLI_SEND_REQ_FAILED, "{}", a.detail);
        assert!(a.detail.contains(&closed.to_string()), "{}", a.detail);
        // One that is not grpc://host:port.
        let a = call(Some("grpc://no-port-here"));
        assert_eq!(a.status, RpcStatus::CLI_INVALID_ADDR, "{}", a.detail);
        assert!(a.detail.contains("grpc://host:port"), "{}", a.detail);
    }

    /// A call whose stream an HTTP/2 server resets with `reason`, as answered.
    fn answer_of_a_reset(reason: h2::Reason) -> BackendAnswer {
        two_threads().block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            let authority = listener.local_addr().unwrap().to_string();
            tokio::spawn(async move {
                let (stream, _) = listener.accept().await.unwrap();
                let mut conn = h2::server::handshake(stream).await.unwrap();
                if let Some(Ok((_, mut respond))) = conn.accept().await {
                    respond.send_reset(reason);
                }
                // Serve the connection on until the client has read the reset.
                while conn.accept().await.is_some() {}
            });
            let client = GrpcClient::new(Vec::new(), "test").unwrap();
            let mut call = BackendCall::new("pb:/a.B/C");
            call.set_meta(meta_keys::TO_ADDR, &format!("grpc://{authority}"));
            call.timeout = Some(Duration::from_secs(5));
            client.call(call).await
        })
    }

    #[test]
    fn a_call_the_server_refused_is_known_not_to_have_run() {
        let a = answer_of_a_reset(h2::Reason::REFUSED_STREAM);
        assert_eq!(a.status, RpcStatus::CLI_SEND_REQ_FAILED, "{}", a.detail);
        assert!(a.detail.contains("it did not run"), "{}", a.detail);
        // Another reset may come after the service ran: nobody knows.
        let a = answer_of_a_reset(h2::Reason::INTERNAL_ERROR);
        assert_eq!(a.status, RpcStatus::CLI_UNKNOWN, "{}", a.detail);
    }

    #[test]
    fn a_call_still_queued_when_the_connection_closes_did_not_run() {
        two_threads().block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            let authority = listener.local_addr().unwrap().to_string();
            let (took, taken) = tokio::sync::oneshot::channel();
            tokio::spawn(async move {
                let (stream, _) = listener.accept().await.unwrap();
                // One stream at a time: the second call waits in hyper for its stream to
                // open, the third in hyper's queue.
                let mut conn = h2::server::Builder::new()
                    .max_concurrent_streams(1)
                    .handshake::<_, Bytes>(stream)
                    .await
                    .unwrap();
                // h2 lets a client open any number of streams until it has read the
                // server's SETTINGS. An answer comes after them on the connection, so
                // once the client has the warm-up call's answer it keeps to one stream.
                let (request, mut warm_up) = conn.accept().await.unwrap().unwrap();
                let not_found = hyper::Response::builder().status(404).body(()).unwrap();
                warm_up.send_response(not_found, true).unwrap();
                drop(request);
                let first = conn.accept().await;
                let _ = took.send(());
                // The others are queued by now; then the server goes away.
                tokio::time::sleep(Duration::from_millis(200)).await;
                drop((first, conn));
            });
            let client = Arc::new(GrpcClient::new(Vec::new(), "test").unwrap());
            let call = |client: Arc<GrpcClient>| {
                let mut call = BackendCall::new("pb:/a.B/C");
                call.set_meta(meta_keys::TO_ADDR, &format!("grpc://{authority}"));
                call.timeout = Some(Duration::from_secs(5));
                tokio::spawn(async move { client.call(call).await })
            };
            let warm_up = call(client.clone()).await.unwrap();
            assert_eq!(
                warm_up.status,
                RpcStatus::SVR_NOT_FOUND,
                "{}",
                warm_up.detail
            );
            let first = call(client.clone());
            taken.await.unwrap();
            let second = call(client.clone());
            tokio::time::sleep(Duration::from_millis(50)).await;
            let third = call(client);
            // The server had the first: nobody knows whether it ran.
            let a = first.await.unwrap();
            assert_eq!(a.status, RpcStatus::CLI_UNKNOWN, "{}", a.detail);
            // The second had its stream opened in h2 but not sent; hyper only says that
            // its task is gone, which it also says of calls that were sent: unknown.
            let _ = second.await.unwrap();
            // The third never left hyper's queue.
            let a = third.await.unwrap();
            assert_eq!(a.status, RpcStatus::CLI_SEND_REQ_FAILED, "{}", a.detail);
            assert!(a.detail.contains("it did not run"), "{}", a.detail);
        });
    }

    #[test]
    fn meta_goes_out_under_its_own_name_when_it_can() {
        let mut h = HeaderMap::new();
        put_meta(&mut h, "aimrt-function_name", "pb:/a.B/C");
        put_meta(&mut h, "Trace-Id", "x y");
        put_meta(&mut h, "content-type", "text/plain");
        put_meta(&mut h, "grpc-timeout", "1S");
        put_meta(&mut h, meta_keys::TO_ADDR, "http://1.2.3.4:5");
        assert_eq!(h.get("aimrt-function_name").unwrap(), "pb:/a.B/C");
        assert_eq!(h.len(), 2, "{h:?}");
        assert!(h.keys().any(|k| k.as_str() != "aimrt-function_name"));
        // The framework's keys made once are the names parsing would give.
        for name in &KNOWN {
            assert_eq!(
                *name,
                HeaderName::from_bytes(name.as_str().as_bytes()).unwrap()
            );
            let mut h = HeaderMap::new();
            put_meta(&mut h, name.as_str(), "v");
            assert_eq!(h.get(name.as_str()).unwrap(), "v");
        }
    }
}
